//! `token-probe`: where ChatSplat's view tokens lose "how many" and "which colours" (issue 38,
//! section 3). On scenes that `vqa-bench` already trained (its `seed*` directories), every
//! unambiguous view (training and held-out) is asked "How many objects are there?" and "What
//! colors are there?" from token grids that mix the teacher's tokens of the ground-truth image
//! with ChatSplat's, region by region of the view's 8x8 patch grid (by the ground-truth mask):
//!
//! * `background`: no object pixel in the patch; `inside`: one object fills it; `edge`: one
//!   object and background; `contact`: two objects or more.
//!
//! A region whose ChatSplat tokens break the ground truth's answers (or whose teacher tokens
//! repair ChatSplat's) is where the answer is lost. Also prints the token L1 per region and the
//! signed count error of each source. Writes probe.json beside the report.
//!
//! cargo run --release -p eval --bin token-probe -- out/vqa-bench/seed30000 [more seeds] [--out DIR]
#![allow(deprecated)]

use burn::tensor::{Device, Tensor, TensorData};
use clap::Parser;
use eval::compare::{exact, greedy};
use eval::probe::{REGIONS, Region, count_answer, regions, token_l1, view_truth};
use model::chat::{ChatSession, Target, answer};
use model::data::synth::scene::Scene;
use model::data::{LoadOptions, load_any};
use model::run::GeometryRun;
use model::splats::host;
use model::vlm::{LlavaOnevision, RgbImage};
use model::{Backend, Result, catch_backend};
use std::collections::BTreeMap;
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "token-probe", about = "Which regions of ChatSplat's view tokens lose count and colours")]
struct Args {
    /// Scene directories written by vqa-bench (each holds data/ and run/).
    #[arg(required = true)]
    scenes: Vec<PathBuf>,
    /// LLaVA-OneVision directory (default: the built-in model).
    #[arg(long)]
    vlm: Option<PathBuf>,
    /// Use every Gaussian (default: the run's compaction, as chat and vqa-bench's (c) do).
    #[arg(long)]
    full: bool,
    /// The language run inside each scene's run/ (default: run/language).
    #[arg(long)]
    language: Option<String>,
    #[arg(long, default_value = "out/token-probe")]
    out: PathBuf,
    #[arg(long, default_value_t = Backend::Ndarray)]
    backend: Backend,
}

/// The token grid a variant asks from: `base`'s tokens with `other`'s in `regions`.
struct Variant {
    name: &'static str,
    base_is_gt: bool,
    regions: &'static [Region],
}

const VARIANTS: [Variant; 10] = [
    Variant { name: "ground truth", base_is_gt: true, regions: &[] },
    Variant { name: "ChatSplat", base_is_gt: false, regions: &[] },
    Variant { name: "truth, ChatSplat background", base_is_gt: true, regions: &[Region::Background] },
    Variant { name: "truth, ChatSplat inside", base_is_gt: true, regions: &[Region::Inside] },
    Variant { name: "truth, ChatSplat edges", base_is_gt: true, regions: &[Region::Edge] },
    Variant { name: "truth, ChatSplat contacts", base_is_gt: true, regions: &[Region::Contact] },
    Variant {
        name: "truth, ChatSplat on objects",
        base_is_gt: true,
        regions: &[Region::Inside, Region::Edge, Region::Contact],
    },
    Variant { name: "ChatSplat, truth background", base_is_gt: false, regions: &[Region::Background] },
    Variant { name: "ChatSplat, truth edges+contacts", base_is_gt: false, regions: &[Region::Edge, Region::Contact] },
    Variant {
        name: "ChatSplat, truth on objects",
        base_is_gt: false,
        regions: &[Region::Inside, Region::Edge, Region::Contact],
    },
];

#[derive(Default, Clone, serde::Serialize)]
struct Score {
    count_right: usize,
    colors_right: usize,
    asked: usize,
    /// Sum of (answered - true) over count answers that were numbers, and how many were.
    count_bias: i64,
    numeric: usize,
    under: usize,
    over: usize,
}

fn main() -> std::process::ExitCode {
    model::alloc::keep_freed_memory();
    let a = Args::parse();
    match catch_backend("token-probe", || probe(&a)).and_then(|r| r) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn probe(a: &Args) -> Result<()> {
    let device: Device = a.backend.device();
    let vlm_dir = match &a.vlm {
        Some(d) => d.clone(),
        None => model::vlm::default_model_dir()?,
    };
    let vlm = LlavaOnevision::load(&vlm_dir, &device)?;
    let (d, p) = (vlm.cfg.vision.hidden_size, vlm.cfg.vision.patch_size);
    let opts = greedy();
    // per variant: every view, and the held-out views alone
    let mut scores: Vec<Score> = vec![Score::default(); VARIANTS.len()];
    let mut held: Vec<Score> = vec![Score::default(); VARIANTS.len()];
    let mut held_views = 0usize;
    // token L1 of ChatSplat against the truth per region: (sum, tokens)
    let mut l1: BTreeMap<Region, (f64, usize)> = BTreeMap::new();
    let mut l1_held: BTreeMap<Region, (f64, usize)> = BTreeMap::new();
    let mut views_seen = 0usize;
    let mut rows = Vec::new();
    for dir in &a.scenes {
        let data = dir.join("data");
        let scene: Scene = model::io::read_json(&data.join("scene.json"))?;
        let ds = load_any(&data, &LoadOptions::default())?;
        let run = GeometryRun::new(dir.join("run"));
        let lang = a.language.as_ref().map(|l| run.dir.join(l));
        let session = if a.full {
            ChatSession::open_full(&run, lang.as_deref(), &vlm_dir, &device)?
        } else {
            ChatSession::open(&run, lang.as_deref(), &vlm_dir, &device)?
        };
        let split = ds.train.iter().map(|v| (v, false)).chain(ds.test.iter().map(|v| (v, true)));
        for (v, held_out) in split {
            let name = v.image_path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            let Some(index) = session.images.iter().position(|i| *i == name) else { continue };
            let Some(ids) = v.instance_ids.as_ref() else { continue };
            let (w, h) = (v.camera.width as usize, v.camera.height as usize);
            let Some((truth_count, truth_colors)) = view_truth(&scene, ids, w, h) else { continue };
            views_seen += 1;
            held_views += held_out as usize;
            let gt = host(vlm.teacher_tokens(&RgbImage::from_f32(w, h, &v.rgb)));
            let cam = *session.camera(index)?;
            let cs = host(session.tokens(&Target::View(cam))?.remove(0));
            let reg = regions(ids, w, h, p);
            if reg.len() * d != gt.len() || gt.len() != cs.len() {
                return Err(model::Error::input(format!(
                    "{name}: {} patches of {p} px but {} tokens (the probe needs the view at the tower's size)",
                    reg.len(),
                    gt.len() / d
                )));
            }
            for (t, r) in reg.iter().enumerate() {
                let err = token_l1(&gt, &cs, t, d);
                let add = |m: &mut BTreeMap<Region, (f64, usize)>| {
                    let e = m.entry(*r).or_default();
                    e.0 += err;
                    e.1 += 1;
                };
                add(&mut l1);
                if held_out {
                    add(&mut l1_held);
                }
            }
            let mut row = serde_json::json!({
                "scene": dir.display().to_string(), "view": name, "held_out": held_out,
                "count": truth_count, "colors": truth_colors,
                "regions": REGIONS.iter().map(|r| (format!("{r:?}"), reg.iter().filter(|x| *x == r).count()))
                    .collect::<BTreeMap<_, _>>(),
            });
            for (vi, var) in VARIANTS.iter().enumerate() {
                let (base, other) = if var.base_is_gt { (&gt, &cs) } else { (&cs, &gt) };
                let mut mixed = base.clone();
                for (t, r) in reg.iter().enumerate() {
                    if var.regions.contains(r) {
                        mixed[t * d..(t + 1) * d].copy_from_slice(&other[t * d..(t + 1) * d]);
                    }
                }
                let tokens = Tensor::<2>::from_data(TensorData::new(mixed, [reg.len(), d]), &device);
                let count = answer(&vlm, std::slice::from_ref(&tokens), "How many objects are there?", &opts, |_| {})?;
                let cols = answer(&vlm, &[tokens], "What colors are there?", &opts, |_| {})?;
                let number = count_answer(&count.text);
                for s in std::iter::once(&mut scores[vi]).chain(held_out.then_some(&mut held[vi])) {
                    s.asked += 1;
                    s.count_right += exact(&count.text, &truth_count.to_string()) as usize;
                    s.colors_right += exact(&cols.text, &truth_colors) as usize;
                    if let Some(n) = number {
                        let e = n - truth_count as i64;
                        s.count_bias += e;
                        s.numeric += 1;
                        s.under += (e < 0) as usize;
                        s.over += (e > 0) as usize;
                    }
                }
                row[var.name] = serde_json::json!({"count": count.text, "colors": cols.text});
            }
            rows.push(row);
            eprint!("\rtoken-probe: {views_seen} views");
        }
    }
    eprintln!();
    println!(
        "token-probe: {views_seen} views of {} scenes, {held_views} of them held out (count and colours asked on \
         each)\n",
        a.scenes.len()
    );
    println!(
        "| tokens | count right % | under / over | mean count error | colours right % | held out: count / colours % |"
    );
    println!("|---|---|---|---|---|---|");
    for ((var, s), h) in VARIANTS.iter().zip(&scores).zip(&held) {
        let pc = |r: usize, s: &Score| 100.0 * r as f64 / s.asked.max(1) as f64;
        println!(
            "| {} | {:.1} | {} / {} | {:+.2} | {:.1} | {:.1} / {:.1} |",
            var.name,
            pc(s.count_right, s),
            s.under,
            s.over,
            s.count_bias as f64 / s.numeric.max(1) as f64,
            pc(s.colors_right, s),
            pc(h.count_right, h),
            pc(h.colors_right, h)
        );
    }
    println!("\n| region | tokens | share | ChatSplat token L1 vs truth | held out: tokens / L1 |");
    println!("|---|---|---|---|---|");
    let all: usize = l1.values().map(|e| e.1).sum();
    for (r, (s, n)) in &l1 {
        let (hs, hn) = l1_held.get(r).copied().unwrap_or_default();
        println!(
            "| {r:?} | {n} | {:.1} % | {:.3} | {hn} / {:.3} |",
            100.0 * *n as f64 / all.max(1) as f64,
            s / (*n).max(1) as f64,
            hs / hn.max(1) as f64
        );
    }
    model::io::create_dir(&a.out)?;
    let means = |m: &BTreeMap<Region, (f64, usize)>| -> BTreeMap<String, f64> {
        m.iter().map(|(r, (s, n))| (format!("{r:?}"), s / (*n).max(1) as f64)).collect()
    };
    let summary = serde_json::json!({
        "scenes": a.scenes.iter().map(|s| s.display().to_string()).collect::<Vec<_>>(),
        "variants": VARIANTS.iter().zip(&scores).map(|(v, s)| (v.name, s.clone())).collect::<BTreeMap<_, _>>(),
        "held_out": VARIANTS.iter().zip(&held).map(|(v, s)| (v.name, s.clone())).collect::<BTreeMap<_, _>>(),
        "l1_by_region": means(&l1),
        "l1_by_region_held_out": means(&l1_held),
        "views": rows,
    });
    model::io::write_json(&a.out.join("probe.json"), &summary)?;
    Ok(())
}
