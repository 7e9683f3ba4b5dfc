//! `vqa-bench`: the paper's comparison reproduced offline on held-out synthetic scenes. For each
//! seed: `synth` -> geometry -> teacher tokens (the given VLM) -> language field, then every
//! question of the scene's question file (view and object level on the held-out, novel views;
//! scene level on training views) answered three ways: (a) the VLM on the ground-truth image,
//! (b) the VLM on the rendered RGB (object level: the rendered crop cut by the ground-truth mask),
//! (c) ChatSplat's tokens (object level: by click). Prints accuracy per level and question type,
//! views/s and objects/s of each path, and token L1 / cosine against teacher(ground truth).
//! `--sweep` adds speed against error on answers: other fields of each scene (channels, Gaussians
//! kept, map resolution, iterations), each scored on ChatSplat's answers, with a plot of exact
//! match against views/s and its Pareto front.
//!
//! cargo run --release -p eval --bin vqa-bench -- [--vlm DIR] [--seeds 5] [--sweep] [--out out/vqa-bench]
#![allow(deprecated)]

use burn::tensor::Device;
use clap::Parser;
use eval::compare::{Answered, Source, Tally, answer_file};
use eval::plot::{Chart, Series};
use eval::progress::Progress;
use model::chat::{ChatSession, DEFAULT_SCENE_VIEWS};
use model::data::synth::{SynthOptions, write_dataset};
use model::data::{LoadOptions, load_any};
use model::run::{GeometryRun, LanguageRun, TeacherDir};
use model::splats::host;
use model::vlm::{LlavaOnevision, RgbImage};
use model::vqa::{Level, load_questions, scene_view, target_of};
use model::{Backend, Result, catch_backend};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;
use train::geometry::GeometryConfig;
use train::language::LanguageTrainConfig;

#[derive(Parser)]
#[command(name = "vqa-bench", about = "ChatSplat vs the VLM on ground-truth and rendered images, offline")]
struct Args {
    /// LLaVA-OneVision directory (default: the built-in model).
    #[arg(long)]
    vlm: Option<PathBuf>,
    /// Held-out scenes (seeds `first-seed..first-seed + seeds`; training never uses seeds below 1e6).
    #[arg(long, default_value_t = 5)]
    seeds: u64,
    #[arg(long, default_value_t = 30_000)]
    first_seed: u64,
    /// Views per scene (every 8th is held out) and their side.
    #[arg(long, default_value_t = 32)]
    views: usize,
    #[arg(long, default_value_t = 96)]
    resolution: u32,
    #[arg(long, default_value_t = 1500)]
    geometry_iters: usize,
    /// Language-stage iterations (without `--language-config`, the first tenth warm up).
    #[arg(long, default_value_t = 600)]
    language_iters: usize,
    /// A language-stage config.json (any `LanguageTrainConfig` fields, e.g. `{"lr_final": 1.0}`
    /// for the paper's constant rate); `--language-iters` sets its iterations.
    #[arg(long)]
    language_config: Option<PathBuf>,
    /// Work directory (datasets, runs) and bench.json.
    #[arg(long, default_value = "out/vqa-bench")]
    out: PathBuf,
    #[arg(long, default_value_t = Backend::Ndarray)]
    backend: Backend,
    /// Also sweep speed against error on ChatSplat's answers: language channels (8/16/64 beside
    /// the config's), Gaussians kept by language contribution (50/25/10 %), a coarser map, half
    /// the language iterations and a quarter of the geometry's. Writes sweep.png (accuracy against
    /// views/s, the Pareto front marked) beside bench.json.
    #[arg(long)]
    sweep: bool,
}

/// One way to make a scene's field in the sweep, scored by ChatSplat's answers.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Variant {
    /// The field as configured (the reference point).
    Configured,
    /// Language features of this many channels per level.
    Channels(usize),
    /// The configured field with only this percentage of its Gaussians, those with the largest
    /// accumulated language gradient (no retraining).
    Kept(usize),
    /// Maps rendered at this many pixels per token (the configured: the views' resolution).
    Patch(usize),
    /// The language stage with 1/this of its iterations.
    LanguageIters(usize),
    /// Geometry trained with 1/this of its iterations, then the configured language stage.
    GeometryIters(usize),
}

const SWEEP: [Variant; 9] = [
    Variant::Configured,
    Variant::Channels(8),
    Variant::Channels(16),
    Variant::Channels(64),
    Variant::Kept(50),
    Variant::Kept(25),
    Variant::Kept(10),
    Variant::Patch(6),
    Variant::LanguageIters(2),
];

/// Geometry iterations are swept on their own (a second geometry run per scene).
const GEOMETRY_SWEEP: Variant = Variant::GeometryIters(4);

impl Variant {
    fn name(self, a: &Args, channels: usize) -> String {
        match self {
            Variant::Configured => format!("configured ({channels} ch, all Gaussians)"),
            Variant::Channels(c) => format!("{c} channels"),
            Variant::Kept(p) => format!("{p} % of the Gaussians kept"),
            Variant::Patch(p) => format!("map at {p} px per token"),
            Variant::LanguageIters(d) => format!("language {} iterations", a.language_iters / d),
            Variant::GeometryIters(d) => format!("geometry {} iterations", a.geometry_iters / d),
        }
    }

    /// The plot series a point belongs to.
    fn axis(self) -> &'static str {
        match self {
            Variant::Configured | Variant::Channels(_) => "channels",
            Variant::Kept(_) => "Gaussians kept",
            Variant::Patch(_) => "map resolution",
            Variant::LanguageIters(_) | Variant::GeometryIters(_) => "iterations",
        }
    }
}

/// A sweep point summed over the scenes.
#[derive(Clone, Debug, Default, serde::Serialize)]
struct Point {
    name: String,
    axis: &'static str,
    tally: Tally,
    token_seconds: eval::compare::TokenSeconds,
    /// Language-stage seconds per iteration, summed over the scenes that trained one.
    train_seconds: f64,
    trained: usize,
    gaussians: usize,
    field_bytes: usize,
    scenes: usize,
}

impl Point {
    fn rate(&self, level: Level) -> f64 {
        self.token_seconds.get(&level).map(|(t, n)| *n as f64 / t.max(1e-9)).unwrap_or(f64::NAN)
    }
    fn kind(&self, kind: &str) -> String {
        self.tally
            .by_kind
            .get(kind)
            .map(|(r, n)| format!("{:.1}", 100.0 * *r as f64 / (*n).max(1) as f64))
            .unwrap_or("-".into())
    }
}

/// Bytes of a scene's language field (features and encoder) as f32.
fn field_bytes(session: &ChatSession) -> usize {
    session.scene.field.named().iter().map(|(_, t)| 4 * t.dims().iter().product::<usize>()).sum()
}

fn main() -> std::process::ExitCode {
    model::alloc::keep_freed_memory();
    let a = Args::parse();
    match catch_backend("vqa-bench", || bench(&a)).and_then(|r| r) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Mean L1 and cosine of token grids against the teacher's.
#[derive(Default, Clone, Copy, serde::Serialize)]
struct Fidelity {
    l1: f64,
    cos: f64,
    n: usize,
}

impl Fidelity {
    fn add(&mut self, a: &[f32], b: &[f32], d: usize) {
        for (x, y) in a.chunks(d).zip(b.chunks(d)) {
            let l1 = x.iter().zip(y).map(|(p, q)| (p - q).abs() as f64).sum::<f64>() / d as f64;
            let dot: f64 = x.iter().zip(y).map(|(p, q)| *p as f64 * *q as f64).sum();
            let nx = x.iter().map(|p| (*p as f64).powi(2)).sum::<f64>().sqrt();
            let ny = y.iter().map(|p| (*p as f64).powi(2)).sum::<f64>().sqrt();
            self.l1 += l1;
            self.cos += dot / (nx * ny).max(1e-12);
            self.n += 1;
        }
    }
    fn mean(self) -> Self {
        let n = self.n.max(1) as f64;
        Self { l1: self.l1 / n, cos: self.cos / n, n: self.n }
    }
}

fn bench(a: &Args) -> Result<()> {
    let device: Device = a.backend.device();
    let vlm_dir = match &a.vlm {
        Some(d) => d.clone(),
        None => model::vlm::default_model_dir()?,
    };
    let vlm = LlavaOnevision::load(&vlm_dir, &device)?;
    let mut language_config = match &a.language_config {
        Some(p) => {
            let c: LanguageTrainConfig = model::io::read_config(p)?;
            c.validate().map_err(|e| model::Error::invalid(p, e.to_string()))?;
            c
        }
        None => {
            let mut c = LanguageTrainConfig::default();
            c.field.patch = 0; // maps at the views' own resolution
            c.warmup_iters = (a.language_iters / 10).max(1);
            c
        }
    };
    language_config.iters = a.language_iters;
    language_config.checkpoint_every = 0;
    model::io::create_dir(&a.out)?;
    let mut tallies: BTreeMap<Source, Tally> = BTreeMap::new();
    let mut points: Vec<Point> = Vec::new();
    let mut seconds: BTreeMap<(Source, Level), (f64, usize)> = BTreeMap::new();
    let (mut fid_rgb, mut fid_cs) = (Fidelity::default(), Fidelity::default());
    let d = vlm.cfg.vision.hidden_size;
    for seed in a.first_seed..a.first_seed + a.seeds {
        let dir = a.out.join(format!("seed{seed}"));
        let data = dir.join("data");
        let opts =
            SynthOptions { seed, views: a.views, width: a.resolution, height: a.resolution, ..Default::default() };
        write_dataset(&data, &opts, |_, _| {})?;
        let load = LoadOptions::default();
        let ds = load_any(&data, &load)?;
        let run = GeometryRun::new(dir.join("run"));
        let gcfg = GeometryConfig::short(a.geometry_iters);
        let bar = Progress::new(format!("seed {seed} geometry"), "it");
        let g = train::geometry::run(&ds, None, &data, &load, &run, gcfg, &device, false, |p| {
            if p.iter % 20 == 0 || p.iter == p.iters {
                bar.update_with(p.iter, p.iters, &format!("psnr {:.2}", p.psnr))
            }
        })?;
        let teacher = TeacherDir::new(data.join("teacher"));
        train::teacher::extract(&vlm, &data, &teacher, &Default::default(), |_| {}, |_, _| {})?;
        let lang = LanguageRun::new(run.dir.join("language"));
        let lcfg = language_config.clone();
        let bar = Progress::new(format!("seed {seed} language"), "it");
        let l = train::language::run(&run, &teacher.dir, &lang, lcfg, &device, false, &train::dist::Solo, |p| {
            if p.iter % 10 == 0 || p.iter == p.iters {
                bar.update_with(p.iter, p.iters, &format!("loss {:.4}", p.step.loss))
            }
        })?;
        eprintln!(
            "seed {seed}: geometry held-out PSNR {:.2} dB, mIoU {:.3}; language token L1 view {:.3} object {:.3}",
            g.eval.psnr,
            g.eval.miou.unwrap_or(0.0),
            l.after.0,
            l.after.1
        );
        let session = ChatSession::open(&run, None, &vlm_dir, &device)?;
        let qf = load_questions(&data.join("questions.json"))?;
        let mut configured = None;
        for source in Source::ALL {
            let answered = answer_file(&vlm, &qf, &ds, Some(&session), source, 0.1)?;
            tallies.entry(source).or_default().merge(&answered.tally);
            if source == Source::ChatSplat {
                configured = Some(answered);
            }
        }
        // speed of each path's tokens and their fidelity to teacher(ground truth), per question target
        for q in &qf.questions {
            if q.level == Level::Scene {
                continue;
            }
            let target = target_of(&qf, q, &session, DEFAULT_SCENE_VIEWS)?;
            let view = scene_view(&qf, &session.images, q.view.unwrap_or(0))?;
            let obj = q.object.filter(|_| q.level == Level::Object).map(|[x, y]| (x as usize, y as usize));
            let cam = session.camera(view)?;
            let frame = &ds.train.iter().chain(&ds.test).find(|v| {
                v.image_path.file_name().map(|n| n.to_string_lossy().into_owned()).as_deref()
                    == Some(&session.images[view])
            });
            let Some(gt_view) = frame else { continue };
            let (w, h) = (cam.width as usize, cam.height as usize);
            let gt_img = RgbImage::from_f32(w, h, &gt_view.rgb);
            let crop = |img: &RgbImage| -> Option<RgbImage> {
                let (x, y) = obj?;
                let ids = gt_view.instance_ids.as_ref()?;
                let id = ids[y * w + x];
                model::language::ObjectCrop::of(ids, w, h, id, 0.1).map(|c| c.masked_image(img, ids, id))
            };
            let level = q.level;
            let gt_tokens = host(vlm.teacher_tokens(&if obj.is_some() {
                crop(&gt_img).unwrap_or(gt_img.clone())
            } else {
                gt_img.clone()
            }));
            // (b): render RGB, (crop), vision tower
            let t0 = Instant::now();
            let r = session.scene.render(cam)?;
            let rgb: Vec<f32> = r.rgb.iter().map(|c| c.clamp(0.0, 1.0)).collect();
            let img = RgbImage::from_f32(w, h, &rgb);
            let img = if obj.is_some() { crop(&img).unwrap_or(img) } else { img };
            let b = host(vlm.teacher_tokens(&img));
            let e = seconds.entry((Source::RenderedRgb, level)).or_default();
            e.0 += t0.elapsed().as_secs_f64();
            e.1 += 1;
            // (c): ChatSplat tokens
            let t0 = Instant::now();
            let c = host(session.tokens(&target)?.remove(0));
            let e = seconds.entry((Source::ChatSplat, level)).or_default();
            e.0 += t0.elapsed().as_secs_f64();
            e.1 += 1;
            if level == Level::View {
                fid_rgb.add(&b, &gt_tokens, d);
                fid_cs.add(&c, &gt_tokens, d);
            }
        }
        if !a.sweep {
            continue;
        }
        // speed against error: other fields of the same scene, each scored on ChatSplat's answers
        let channels = language_config.field.view_channels;
        let mut record = |v: Variant, session: &ChatSession, ans: Answered, seconds_per_iter: Option<f64>| {
            let name = v.name(a, channels);
            let i = points.iter().position(|p| p.name == name).unwrap_or_else(|| {
                points.push(Point { name: name.clone(), axis: v.axis(), ..Default::default() });
                points.len() - 1
            });
            let p = &mut points[i];
            p.tally.merge(&ans.tally);
            for (level, (t, n)) in ans.token_seconds {
                let e = p.token_seconds.entry(level).or_default();
                e.0 += t;
                e.1 += n;
            }
            if let Some(s) = seconds_per_iter {
                p.train_seconds += s;
                p.trained += 1;
            }
            p.gaussians += session.scene.splats.len();
            p.field_bytes += field_bytes(session);
            p.scenes += 1;
        };
        let train_field = |run: &GeometryRun, tag: &str, cfg: LanguageTrainConfig| -> Result<(ChatSession, f64)> {
            let lang = LanguageRun::new(run.dir.join(format!("language-{tag}")));
            let bar = Progress::new(format!("seed {seed} sweep: language {tag}"), "it");
            let l = train::language::run(run, &teacher.dir, &lang, cfg, &device, false, &train::dist::Solo, |p| {
                if p.iter % 10 == 0 || p.iter == p.iters {
                    bar.update_with(p.iter, p.iters, &format!("loss {:.4}", p.step.loss))
                }
            })?;
            Ok((ChatSession::open(run, Some(&lang.dir), &vlm_dir, &device)?, l.seconds_per_iter))
        };
        for v in SWEEP.into_iter().chain([GEOMETRY_SWEEP]) {
            let mut cfg = language_config.clone();
            let (field, seconds_per_iter) = match v {
                Variant::Configured => {
                    let ans = configured.take().expect("ChatSplat's answers of the configured field");
                    record(v, &session, ans, Some(l.seconds_per_iter));
                    continue;
                }
                Variant::Kept(pct) => {
                    let c = lang.read_contribution()?;
                    let mut order: Vec<usize> = (0..c.len()).collect();
                    order.sort_by(|&i, &j| c[j].total_cmp(&c[i]));
                    let mut keep = order[..(c.len() * pct).div_ceil(100)].to_vec();
                    keep.sort_unstable();
                    let mut s = ChatSession::open(&run, None, &vlm_dir, &device)?;
                    s.scene = s.scene.subset(&keep);
                    (s, None)
                }
                Variant::Channels(c) => {
                    cfg.field.view_channels = c;
                    cfg.field.object_channels = c;
                    let (s, t) = train_field(&run, &format!("ch{c}"), cfg)?;
                    (s, Some(t))
                }
                Variant::Patch(p) => {
                    cfg.field.patch = p;
                    let (s, t) = train_field(&run, &format!("patch{p}"), cfg)?;
                    (s, Some(t))
                }
                Variant::LanguageIters(k) => {
                    cfg.iters = (cfg.iters / k).max(1);
                    cfg.warmup_iters /= k;
                    let (s, t) = train_field(&run, &format!("iters{}", cfg.iters), cfg)?;
                    (s, Some(t))
                }
                Variant::GeometryIters(k) => {
                    let small = GeometryRun::new(dir.join(format!("run-geometry-{k}")));
                    let bar = Progress::new(format!("seed {seed} sweep: geometry 1/{k}"), "it");
                    let gcfg = GeometryConfig::short((a.geometry_iters / k).max(1));
                    train::geometry::run(&ds, None, &data, &load, &small, gcfg, &device, false, |p| {
                        if p.iter % 20 == 0 || p.iter == p.iters {
                            bar.update_with(p.iter, p.iters, &format!("psnr {:.2}", p.psnr))
                        }
                    })?;
                    let (s, t) = train_field(&small, "configured", cfg)?;
                    (s, Some(t))
                }
            };
            let ans = answer_file(&vlm, &qf, &ds, Some(&field), Source::ChatSplat, 0.1)?;
            eprintln!("seed {seed} sweep: {}: {:.1} %", v.name(a, channels), ans.tally.overall());
            record(v, &field, ans, seconds_per_iter);
        }
    }
    println!(
        "\n## ChatSplat vs the VLM on images ({} held-out seeds from {}, {} views of {}px)\n",
        a.seeds, a.first_seed, a.views, a.resolution
    );
    println!("| path | view | object | scene | overall | questions |\n|---|---|---|---|---|---|");
    for source in Source::ALL {
        let t = &tallies[&source];
        let f = |l: Level| t.level(l).map(|v| format!("{v:.1}")).unwrap_or_else(|| "-".into());
        let n: usize = t.by_level.values().map(|(_, n)| n).sum();
        println!(
            "| {} | {} | {} | {} | {:.1} | {n} |",
            source.label(),
            f(Level::View),
            f(Level::Object),
            f(Level::Scene),
            t.overall()
        );
    }
    let kinds: Vec<String> = tallies[&Source::GroundTruth].by_kind.keys().cloned().collect();
    println!(
        "\n| question type | (a) ground truth | (b) rendered RGB | (c) ChatSplat | asked |\n|---|---|---|---|---|"
    );
    for k in &kinds {
        let pct = |s: Source| {
            tallies[&s]
                .by_kind
                .get(k)
                .map(|(r, n)| format!("{:.1}", 100.0 * *r as f64 / (*n).max(1) as f64))
                .unwrap_or("-".into())
        };
        let n = tallies[&Source::GroundTruth].by_kind[k].1;
        println!(
            "| {k} | {} | {} | {} | {n} |",
            pct(Source::GroundTruth),
            pct(Source::RenderedRgb),
            pct(Source::ChatSplat)
        );
    }
    println!("\n| tokens of | views/s | objects/s | view token L1 vs teacher(GT) | cosine |\n|---|---|---|---|---|");
    let rate = |s: Source, l: Level| seconds.get(&(s, l)).map(|(t, n)| *n as f64 / t.max(1e-9)).unwrap_or(0.0);
    let (fr, fc) = (fid_rgb.mean(), fid_cs.mean());
    for (name, s, f) in [
        ("(b) render RGB + vision tower", Source::RenderedRgb, &fr),
        ("(c) ChatSplat: render language map + encoder", Source::ChatSplat, &fc),
    ] {
        println!(
            "| {name} | {:.1} | {:.1} | {:.4} | {:.4} |",
            rate(s, Level::View),
            rate(s, Level::Object),
            f.l1,
            f.cos
        );
    }
    let baseline = (rate(Source::RenderedRgb, Level::View), tallies[&Source::RenderedRgb].overall());
    if a.sweep {
        sweep_report(&points, baseline, a)?;
    }
    let json = serde_json::json!({
        "seeds": [a.first_seed, a.first_seed + a.seeds], "views": a.views, "resolution": a.resolution,
        "geometry_iters": a.geometry_iters, "language_iters": a.language_iters,
        "language_config": language_config, "backend": a.backend.to_string(),
        "tallies": tallies
            .iter()
            .map(|(s, t)| (format!("{s:?}"), serde_json::to_value(t).unwrap()))
            .collect::<serde_json::Map<_, _>>(),
        "fidelity_rendered_rgb": fr, "fidelity_chatsplat": fc, "sweep": points,
    });
    model::io::write_json(&a.out.join("bench.json"), &json)?;
    println!("\nfigures -> {}", a.out.join("bench.json").display());
    Ok(())
}

/// Prints the sweep's table and writes its plot: ChatSplat's exact match against views/s, one
/// series per axis through the configured field, the Pareto front, and the rendered-RGB baseline
/// (`baseline`: its views/s and exact match).
fn sweep_report(points: &[Point], baseline: (f64, f64), a: &Args) -> Result<()> {
    println!("\n## Speed against error on ChatSplat's answers ({} held-out seeds from {})\n", a.seeds, a.first_seed);
    println!(
        "| field | Gaussians | field MB | view | object | scene | overall | count | colors | left_of | views/s \
         | objects/s | train s/iter |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for p in points {
        let n = p.scenes.max(1);
        let lv = |l: Level| p.tally.level(l).map(|v| format!("{v:.1}")).unwrap_or_else(|| "-".into());
        let train = if p.trained > 0 { format!("{:.3}", p.train_seconds / p.trained as f64) } else { "-".into() };
        println!(
            "| {} | {} | {:.2} | {} | {} | {} | {:.1} | {} | {} | {} | {:.1} | {:.1} | {train} |",
            p.name,
            p.gaussians / n,
            p.field_bytes as f64 / n as f64 / 1e6,
            lv(Level::View),
            lv(Level::Object),
            lv(Level::Scene),
            p.tally.overall(),
            p.kind("count"),
            p.kind("colors"),
            p.kind("left_of"),
            p.rate(Level::View),
            p.rate(Level::Object),
        );
    }
    let xy = |p: &Point| (p.rate(Level::View), p.tally.overall());
    let all: Vec<(f64, f64)> = points.iter().map(xy).collect();
    let front = eval::plot::pareto_front(&all);
    println!(
        "\nPareto front (views/s against exact match): {}",
        front.iter().map(|&i| points[i].name.as_str()).collect::<Vec<_>>().join(" -> ")
    );
    let colors = [[31, 119, 180], [214, 39, 40], [44, 160, 44], [148, 103, 189]];
    let mut series = Vec::new();
    for (k, axis) in ["channels", "Gaussians kept", "map resolution", "iterations"].into_iter().enumerate() {
        let mut pts: Vec<(f64, f64)> =
            points.iter().filter(|p| p.axis == axis || p.name.starts_with("configured")).map(xy).collect();
        pts.sort_by(|p, q| p.0.total_cmp(&q.0));
        series.push(Series { label: axis.into(), points: pts, color: colors[k] });
    }
    series.push(Series {
        label: "Pareto front".into(),
        points: front.iter().map(|&i| all[i]).collect(),
        color: [0; 3],
    });
    series.push(Series { label: "LLaVA-OV on rendered RGB".into(), points: vec![baseline], color: [120; 3] });
    let chart = Chart {
        title: format!("ChatSplat answers: speed against exact match ({} seeds)", a.seeds),
        x_label: "views per second (view tokens)".into(),
        y_label: "exact match (%)".into(),
        log_x: true,
        series,
    };
    let png = a.out.join("sweep.png");
    chart.write_png(&png, 900, 600)?;
    println!("plot -> {}", png.display());
    Ok(())
}
