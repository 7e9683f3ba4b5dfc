//! `splat-bench`: milliseconds per forward and per forward+backward of the splatting op for
//! N in {10k, 100k, 1M}, C in {3, 32, 64}, at 384x384 and 1280x720, on ndarray, wgpu and the
//! dense burn-ops baseline, with speed-up ratios. Prints a Markdown table.
//!
//! The dense baseline is timed on as many pixel chunks as fit in `--dense-budget` seconds and
//! extrapolated linearly to the whole image (its cost is exactly linear in the number of chunks);
//! such cells are marked `~`.
#![allow(deprecated)]

use burn::tensor::{Device, Tensor, TensorData};
use clap::Parser;
use model::rng::Rng;
use model::{Backend, catch_backend};
use splat_kernels::api::{SplatOptions, splat};
use splat_kernels::{Camera, FloatAdd, Gaussians, GradReduce, RasterConfig, TileSort, dense};
use std::time::Instant;

#[derive(Parser)]
#[command(about = "Benchmark the splatting op against a dense burn-ops implementation")]
struct Args {
    /// Gaussian counts.
    #[arg(long, value_delimiter = ',', default_values_t = [10_000usize, 100_000, 1_000_000])]
    n: Vec<usize>,
    /// Channel counts.
    #[arg(long, value_delimiter = ',', default_values_t = [3usize, 32, 64])]
    c: Vec<usize>,
    /// Resolutions as WxH.
    #[arg(long, value_delimiter = ',', default_values_t = ["384x384".to_string(), "1280x720".to_string()])]
    res: Vec<String>,
    /// Backends to time (the dense baseline always runs on ndarray).
    #[arg(long, value_delimiter = ',', default_values = ["ndarray", "wgpu", "dense"])]
    impls: Vec<String>,
    /// Seconds of dense-baseline work per cell before extrapolating.
    #[arg(long, default_value_t = 3.0)]
    dense_budget: f64,
    /// Skip a backend for the remaining (larger) N of a row once one run took longer than this.
    #[arg(long, default_value_t = 60.0)]
    max_secs: f64,
    /// Instead of timing, print each implementation's error against the f64 reference.
    #[arg(long)]
    accuracy: bool,
    /// How the wgpu backward adds a tile's gradients: auto (plane sums where the adapter has
    /// plane operations), atomic (one atomic per pixel) or plane.
    #[arg(long, value_enum, default_value_t = Reduce::Auto)]
    grad_reduce: Reduce,
    /// Which atomic add the wgpu backward uses: auto (native where the adapter has it), native or
    /// cas (a compare-and-swap loop).
    #[arg(long, value_enum, default_value_t = Add::Auto)]
    float_add: Add,
    /// How the wgpu forward orders each tile's Gaussians: auto (radix), radix (two global radix
    /// sorts) or bitonic (a bitonic sort per tile).
    #[arg(long, value_enum, default_value_t = Sort::Auto)]
    tile_sort: Sort,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum Sort {
    Auto,
    Radix,
    Bitonic,
}

impl From<Sort> for TileSort {
    fn from(s: Sort) -> Self {
        match s {
            Sort::Auto => TileSort::Auto,
            Sort::Radix => TileSort::Radix,
            Sort::Bitonic => TileSort::Bitonic,
        }
    }
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum Add {
    Auto,
    Native,
    Cas,
}

impl From<Add> for FloatAdd {
    fn from(a: Add) -> Self {
        match a {
            Add::Auto => FloatAdd::Auto,
            Add::Native => FloatAdd::Native,
            Add::Cas => FloatAdd::Cas,
        }
    }
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum Reduce {
    Auto,
    Atomic,
    Plane,
}

impl From<Reduce> for GradReduce {
    fn from(r: Reduce) -> Self {
        match r {
            Reduce::Auto => GradReduce::Auto,
            Reduce::Atomic => GradReduce::Atomic,
            Reduce::Plane => GradReduce::Plane,
        }
    }
}

/// Max abs error of every implementation against the dense f64 reference on a small scene
/// (the reference is O(pixels x N)), for the speed-against-error table.
fn accuracy() {
    use splat_kernels::{cpu::SplatInputsRef, reference};
    println!("| scene | impl | max abs error (features) | max abs error (alpha) | mean abs error (features) |");
    println!("|---|---|---|---|---|");
    for (n, c, w, h) in [(2000usize, 32usize, 160u32, 120u32), (20000, 3, 160, 120)] {
        let cam = Camera::look_at(glam::Vec3::ZERO, glam::Vec3::Z, -glam::Vec3::Y, 50.0, w, h);
        let host = scene(n, c);
        let zeros = vec![0.0f32; n * 2];
        let bg = vec![0.0f32; c];
        let inp = SplatInputsRef {
            means: &host[0],
            log_scales: &host[1],
            quats: &host[2],
            opacity_logits: &host[3],
            features: &host[4],
            background: &bg,
            screen_offsets: &zeros,
        };
        let cfg = RasterConfig::default();
        let r = reference::render(&inp, &cam, &cfg);
        let amb = r.ambiguous.iter().filter(|&&a| a).count();
        let mut rows: Vec<(&str, Vec<f32>, Vec<f32>)> = vec![];
        let mut devices = vec![("ndarray", Device::ndarray())];
        devices.extend(Backend::Wgpu.device().ok().map(|d| ("wgpu", d)));
        for (name, dev) in devices {
            let got = catch_backend(name, || {
                let (g, bgt) = tensors(&host, n, c, &dev, false);
                let out = splat(&g, &cam, bgt, &SplatOptions::default()).expect("valid");
                (
                    out.features.into_data().to_vec::<f32>().expect("f32"),
                    out.alpha.into_data().to_vec::<f32>().expect("f32"),
                )
            });
            if let Ok((f, a)) = got {
                rows.push((name, f, a));
            }
        }
        let (g, bgt) = tensors(&host, n, c, &Device::ndarray(), false);
        let proj = dense::project(&g, &cam, &cfg);
        let (f, a, _) = dense::composite(&proj, &cam, &cfg, bgt, 0, (w * h) as usize);
        rows.push((
            "dense burn ops",
            f.into_data().to_vec::<f32>().expect("f32"),
            a.into_data().to_vec::<f32>().expect("f32"),
        ));
        for (name, f, a) in rows {
            // Threshold-ambiguous pixels (f32 rounding may flip a 1/255 or 1e-4 test) are excluded.
            let mut fmax = 0.0f64;
            let mut fsum = 0.0f64;
            let mut cnt = 0usize;
            let mut amax = 0.0f64;
            for o in 0..(w * h) as usize {
                if r.ambiguous[o] {
                    continue;
                }
                for ch in 0..c {
                    let e = (f[o * c + ch] as f64 - r.image[o * c + ch]).abs();
                    fmax = fmax.max(e);
                    fsum += e;
                    cnt += 1;
                }
                amax = amax.max((a[o] as f64 - r.alpha[o]).abs());
            }
            println!(
                "| N={n}, C={c}, {w}x{h} ({amb} ambiguous px excluded) | {name} | {fmax:.2e} | {amax:.2e} | {:.2e} |",
                fsum / cnt.max(1) as f64
            );
        }
    }
}

/// The backward's error on wgpu, per way of adding a tile's gradients, against ndarray's
/// deterministic backward: max abs difference over the largest gradient, per parameter, on the
/// smooth configuration (no alpha threshold whose rounding could flip between backends) with
/// the usual early stop (without it the transmittance recovered back to front from 1e-30 is noise).
fn grad_accuracy() {
    println!();
    println!("| scene (smooth config) | wgpu backward | means | log_scales | quats | opacity | features |");
    println!("|---|---|---|---|---|---|---|");
    // From few Gaussians per tile to many (the last two overlap hundreds per tile).
    for (n, c, w, h) in [(40usize, 32usize, 45u32, 37u32), (300, 32, 64, 48), (2000, 3, 64, 48), (2000, 32, 160, 120)] {
        grad_errors(n, c, w, h);
    }
}

fn grad_errors(n: usize, c: usize, w: u32, h: u32) {
    let cam = Camera::look_at(glam::Vec3::ZERO, glam::Vec3::Z, -glam::Vec3::Y, 50.0, w, h);
    let host = scene(n, c);
    let grads = |device: &Device, (grad_reduce, float_add): (GradReduce, FloatAdd)| -> Vec<Vec<f32>> {
        let device = device.clone().autodiff();
        let (g, bg) = tensors(&host, n, c, &device, true);
        let config = RasterConfig { grad_reduce, float_add, t_min: 1e-4, ..RasterConfig::smooth() };
        let out = splat(&g, &cam, bg, &SplatOptions { config, ..Default::default() }).expect("valid");
        let loss = (out.features.clone() * out.features).sum() + out.alpha.sum() + out.depth.sum();
        let gr = loss.backward();
        let get = |t: burn::tensor::Tensor<2>| t.grad(&gr).expect("gradient").into_data().to_vec::<f32>().expect("f32");
        vec![
            get(g.means),
            get(g.log_scales),
            get(g.quats),
            g.opacity_logits.grad(&gr).expect("gradient").into_data().to_vec::<f32>().expect("f32"),
            get(g.features),
        ]
    };
    let want = grads(&Device::ndarray(), (GradReduce::Atomic, FloatAdd::Auto));
    let wgpu = match Backend::Wgpu.device() {
        Ok(d) => d,
        Err(e) => return println!("| N={n}, C={c}, {w}x{h} | {e} | | | | | |"),
    };
    let mut ways = vec![
        ("atomic, cas", (GradReduce::Atomic, FloatAdd::Cas)),
        ("plane, cas", (GradReduce::Plane, FloatAdd::Cas)),
        ("auto", (GradReduce::Auto, FloatAdd::Auto)),
    ];
    if catch_backend("wgpu", || splat_kernels::cube::native_float_add_on(&wgpu)).ok().flatten() == Some(true) {
        ways.push(("atomic, native", (GradReduce::Atomic, FloatAdd::Native)));
        ways.push(("plane, native", (GradReduce::Plane, FloatAdd::Native)));
    }
    for (name, way) in ways {
        let Ok(got) = catch_backend("wgpu", || grads(&wgpu, way)) else { continue };
        let cells: Vec<String> = got
            .iter()
            .zip(&want)
            .map(|(a, b)| {
                let scale = b.iter().fold(1e-30f32, |m, v| m.max(v.abs()));
                let err = a.iter().zip(b).fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
                format!("{:.2e}", err / scale)
            })
            .collect();
        println!("| N={n}, C={c}, {w}x{h} | {name} | {} |", cells.join(" | "));
    }
}

/// A cloud of `n` Gaussians filling a box in front of the camera; sizes shrink as n^(-1/3) so the
/// depth complexity stays comparable across n.
fn scene(n: usize, c: usize) -> Vec<Vec<f32>> {
    let mut r = Rng::new(n as u64 * 31 + c as u64);
    let sigma = 0.8 * (8.0 / n as f32).cbrt();
    let mut means = Vec::with_capacity(n * 3);
    let mut scales = Vec::with_capacity(n * 3);
    let mut quats = Vec::with_capacity(n * 4);
    let mut logits = Vec::with_capacity(n);
    let mut feats = Vec::with_capacity(n * c);
    for _ in 0..n {
        means.extend([r.f() * 3.0 - 1.5, r.f() * 2.0 - 1.0, 3.0 + r.f() * 2.0]);
        for _ in 0..3 {
            scales.push((sigma * (0.3 + r.f())).ln());
        }
        quats.extend([r.f() - 0.5, r.f() - 0.5, r.f() - 0.5, r.f() - 0.5]);
        logits.push(r.f() * 4.0 - 2.0);
        for _ in 0..c {
            feats.push(r.f());
        }
    }
    vec![means, scales, quats, logits, feats]
}

fn tensors(host: &[Vec<f32>], n: usize, c: usize, device: &Device, grad: bool) -> (Gaussians, Tensor<1>) {
    let t2 = |v: &Vec<f32>, w: usize| {
        let t = Tensor::<2>::from_data(TensorData::new(v.clone(), [n, w]), device);
        if grad { t.require_grad() } else { t }
    };
    let logits = Tensor::<1>::from_data(TensorData::new(host[3].clone(), [n]), device);
    let bg = Tensor::<1>::zeros([c], device);
    (
        Gaussians {
            means: t2(&host[0], 3),
            log_scales: t2(&host[1], 3),
            quats: t2(&host[2], 4),
            opacity_logits: if grad { logits.require_grad() } else { logits },
            features: t2(&host[4], c),
        },
        if grad { bg.require_grad() } else { bg },
    )
}

/// Median of up to `reps` runs (fewer when a run is slow); each run ends with a device sync.
fn time_runs(mut f: impl FnMut()) -> f64 {
    f(); // warm-up (kernel compilation on wgpu)
    let mut times = vec![];
    let start = Instant::now();
    while times.len() < 5 && (times.is_empty() || start.elapsed().as_secs_f64() < 1.5) {
        let t = Instant::now();
        f();
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(|a, b| a.total_cmp(b));
    times[times.len() / 2]
}

fn op_fwd(host: &[Vec<f32>], n: usize, c: usize, cam: &Camera, device: &Device) -> f64 {
    let (g, bg) = tensors(host, n, c, device, false);
    let opts = SplatOptions { validate: false, ..Default::default() };
    time_runs(|| {
        let out = splat(&g, cam, bg.clone(), &opts).expect("valid");
        let _ = out.alpha.sum().into_data().to_vec::<f32>();
    })
}

fn op_fwd_bwd(host: &[Vec<f32>], n: usize, c: usize, cam: &Camera, device: &Device, config: RasterConfig) -> f64 {
    let device = device.clone().autodiff();
    let (g, bg) = tensors(host, n, c, &device, true);
    let opts = SplatOptions { validate: false, config, ..Default::default() };
    time_runs(|| {
        let out = splat(&g, cam, bg.clone(), &opts).expect("valid");
        let loss = out.features.sum() + out.alpha.sum();
        let grads = loss.backward();
        let _ = bg.grad(&grads).map(|t| t.into_data().to_vec::<f32>());
    })
}

/// Dense baseline: (projection time + per-chunk time x chunks, fraction of chunks measured).
fn dense_time(host: &[Vec<f32>], n: usize, c: usize, cam: &Camera, backward: bool, budget: f64) -> (f64, f64) {
    let cfg = RasterConfig::default();
    let device = if backward { Device::ndarray().autodiff() } else { Device::ndarray() };
    let (g, bg) = tensors(host, n, c, &device, backward);
    let t = Instant::now();
    let proj = dense::project(&g, cam, &cfg);
    let t_proj = t.elapsed().as_secs_f64();
    let hw = (cam.width * cam.height) as usize;
    let chunk = dense::chunk_pixels(n);
    let chunks = hw.div_ceil(chunk);
    let start = Instant::now();
    let mut done = 0;
    while done < chunks && (done == 0 || start.elapsed().as_secs_f64() < budget) {
        let first = done * chunk;
        let count = chunk.min(hw - first);
        let (f, a, _) = dense::composite(&proj, cam, &cfg, bg.clone(), first, count);
        if backward {
            let grads = (f.sum() + a.sum()).backward();
            let _ = bg.grad(&grads).map(|t| t.into_data().to_vec::<f32>());
        } else {
            let _ = f.sum().into_data().to_vec::<f32>();
        }
        done += 1;
    }
    let per_chunk = start.elapsed().as_secs_f64() / done as f64;
    ((t_proj + per_chunk * chunks as f64) * 1e3, done as f64 / chunks as f64)
}

fn fmt_ms(v: Option<f64>) -> String {
    match v {
        Some(ms) if ms >= 100.0 => format!("{ms:.0}"),
        Some(ms) => format!("{ms:.1}"),
        None => "—".into(),
    }
}

eval::bench_main!("splat-bench", bench);

fn bench(a: &Args) -> model::Result<()> {
    if a.accuracy {
        accuracy();
        grad_accuracy();
        return Ok(());
    }
    let want = |s: &str| a.impls.iter().any(|x| x == s);
    let config = RasterConfig {
        grad_reduce: GradReduce::from(a.grad_reduce),
        float_add: FloatAdd::from(a.float_add),
        tile_sort: TileSort::from(a.tile_sort),
        ..Default::default()
    };
    if want("wgpu") {
        match Backend::Wgpu.device().and_then(|d| catch_backend("wgpu", || splat_kernels::cube::adapter_report(&d))) {
            Ok(Some(line)) => println!("{line}"),
            Ok(None) => println!("wgpu: no adapter"),
            Err(e) => println!("{e}"),
        }
        if let Ok(Some(line)) =
            Backend::Wgpu.device().and_then(|d| catch_backend("wgpu", || splat_kernels::cube::paths(&d, &config)))
        {
            println!("wgpu: {line}");
        }
    }
    println!(
        "| res | N | C | ndarray fwd | ndarray f+b | wgpu fwd | wgpu f+b | dense fwd | dense f+b | ndarray vs \
            dense (fwd / f+b) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for res in &a.res {
        let Some((w, h)) =
            res.split_once('x').and_then(|(w, h)| Some((w.parse::<u32>().ok()?, h.parse::<u32>().ok()?)))
        else {
            return Err(model::Error::input(format!("--res expects WxH, got `{res}`")));
        };
        let cam = Camera::look_at(glam::Vec3::ZERO, glam::Vec3::Z, -glam::Vec3::Y, 50.0, w, h);
        for &c in &a.c {
            let mut slow: [bool; 4] = [false; 4];
            for &n in &a.n {
                let host = scene(n, c);
                let mut run = |slot: usize, enabled: bool, f: &mut dyn FnMut() -> f64| -> Option<f64> {
                    if !enabled || slow[slot] {
                        return None;
                    }
                    let v = f();
                    if v > a.max_secs * 1e3 {
                        slow[slot] = true;
                    }
                    Some(v)
                };
                let nd = Device::ndarray();
                let ndf = run(0, want("ndarray"), &mut || op_fwd(&host, n, c, &cam, &nd));
                let ndb = run(1, want("ndarray"), &mut || op_fwd_bwd(&host, n, c, &cam, &nd, config));
                // no usable adapter: the wgpu columns stay empty (the line above the table says why)
                let wg = if want("wgpu") { Backend::Wgpu.device().ok() } else { None };
                let wgf = run(2, wg.is_some(), &mut || {
                    wg.as_ref().map_or(f64::NAN, |d| {
                        catch_backend("wgpu", || op_fwd(&host, n, c, &cam, d)).unwrap_or(f64::NAN)
                    })
                });
                let wgb = run(3, wg.is_some(), &mut || {
                    let fb = |d| catch_backend("wgpu", || op_fwd_bwd(&host, n, c, &cam, d, config)).unwrap_or(f64::NAN);
                    wg.as_ref().map_or(f64::NAN, fb)
                });
                let (mut df, mut db) = (None, None);
                let (mut cf, mut cb) = (1.0, 1.0);
                if want("dense") {
                    let (t, cov) = dense_time(&host, n, c, &cam, false, a.dense_budget);
                    df = Some(t);
                    cf = cov;
                    let (t, cov) = dense_time(&host, n, c, &cam, true, a.dense_budget);
                    db = Some(t);
                    cb = cov;
                }
                let mark = |v: Option<f64>, cov: f64| {
                    let s = fmt_ms(v);
                    if v.is_some() && cov < 1.0 { format!("~{s}") } else { s }
                };
                let ratio = |d: Option<f64>, o: Option<f64>| match (d, o) {
                    (Some(d), Some(o)) if o > 0.0 => format!("{:.0}x", d / o),
                    _ => "—".into(),
                };
                println!(
                    "| {res} | {n} | {c} | {} | {} | {} | {} | {} | {} | {} / {} |",
                    fmt_ms(ndf),
                    fmt_ms(ndb),
                    fmt_ms(wgf),
                    fmt_ms(wgb),
                    mark(df, cf),
                    mark(db, cb),
                    ratio(df, ndf),
                    ratio(db, ndb),
                );
            }
        }
    }
    Ok(())
}
