//! `token-probe`: where ChatSplat's view tokens lose "how many" and "which colours".
//! On scenes that `vqa-bench` already trained (its `seed*` directories), every
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
//! `--novel N` also asks at N poses per scene that no view of the dataset has (random orbit
//! cameras, the same N for every scene and every field): the synthetic scene is ray-cast there
//! for the ground-truth image and mask, so the held-out questions are not limited to the six
//! held-out views of a 48-view capture. `--no-swaps` asks only the two sources themselves.
//!
//! cargo run --release -p eval --bin token-probe -- out/vqa-bench/seed30000 [more seeds] [--out DIR]
#![allow(deprecated)]

use burn::tensor::{Device, Tensor, TensorData};
use clap::Parser;
use eval::harness::ModelArgs;
use eval::probe::{REGIONS, Region, count_answer, regions, token_l1, view_truth};
use model::ObjectId;
use model::Result;
use model::chat::{ChatSession, Target, answer};
use model::data::synth::raycast::render_view;
use model::data::synth::scene::SynthScene;
use model::data::synth::{FOV_DEG, SynthOptions, random_camera, view_camera};
use model::data::{LoadOptions, load_any};
use model::rng::Rng;
use model::run::GeometryRun;
use model::splats::host;
use model::vlm::{LlavaOnevision, RgbImage};
use scoring::compare::{exact, greedy};
use splat_kernels::Camera;
use std::collections::BTreeMap;
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "token-probe", about = "Which regions of ChatSplat's view tokens lose count and colours")]
struct Args {
    /// SynthScene directories written by vqa-bench (each holds data/ and run/).
    #[arg(required = true)]
    scenes: Vec<PathBuf>,
    #[command(flatten)]
    model: ModelArgs,
    /// Use every Gaussian (default: the run's compaction, as chat and vqa-bench's (c) do).
    #[arg(long)]
    full: bool,
    /// The language run inside each scene's run/ (default: run/language).
    #[arg(long)]
    language: Option<String>,
    /// Also ask at this many new poses per scene (random orbit cameras, ray-cast ground truth).
    #[arg(long, default_value_t = 0)]
    novel: usize,
    /// Ask only the ground truth's and ChatSplat's own tokens (no region swaps): 5x fewer answers.
    #[arg(long)]
    no_swaps: bool,
    #[arg(long, default_value = "out/token-probe")]
    out: PathBuf,
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

/// Which views a tally holds.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Debug, serde::Serialize)]
#[serde(rename_all = "snake_case")]
enum Split {
    Training,
    HeldOut,
    /// Poses no view of the dataset has (`--novel`).
    Novel,
}

/// One view to ask about: its ground-truth image and mask, and the camera ChatSplat renders.
struct ProbeView {
    name: String,
    split: Split,
    rgb: Vec<f32>,
    ids: Vec<ObjectId>,
    camera: Camera,
}

/// Seed of the `--novel` cameras (the same poses for every scene and field).
const NOVEL_SEED: u64 = 0x6e6f_7665_6c00;

/// `n` random orbit cameras of `scene` with its dataset's image size, ray-cast for the truth.
/// Fails when the dataset's first camera is not the synthetic frame's (a capture that is not
/// `synth`'s, or one moved after writing), where the ray-cast truth would be of other poses.
fn novel_views(scene: &SynthScene, ds: &model::data::Dataset, n: usize) -> Result<Vec<ProbeView>> {
    if n == 0 {
        return Ok(Vec::new()); // without --novel, any dataset the probe read before still works
    }
    let Some(first) = ds.train.iter().chain(&ds.test).find(|v| v.image_path.ends_with("frame_0000.png")) else {
        return Err(model::Error::input("--novel needs a synth dataset (no frame_0000.png)"));
    };
    let (w, h) = (first.camera.width, first.camera.height);
    let opts =
        SynthOptions { seed: scene.seed, views: ds.train.len() + ds.test.len(), width: w, height: h, fov_deg: FOV_DEG };
    let expect = view_camera(0, &opts).world_to_cam.to_cols_array();
    let got = first.camera.world_to_cam.to_cols_array();
    if expect.iter().zip(&got).any(|(a, b)| (a - b).abs() > 1e-3) {
        return Err(model::Error::input(format!(
            "{}: the dataset's cameras are not the synthetic scene's (is it `chatsplat synth`'s?)",
            first.image_path.display()
        )));
    }
    let mut rng = Rng::new(NOVEL_SEED);
    Ok((0..n)
        .map(|i| {
            let camera = random_camera(&mut rng, FOV_DEG, w, h);
            let v = render_view(&camera, scene);
            ProbeView { name: format!("novel_{i:04}"), split: Split::Novel, rgb: v.rgb, ids: v.ids, camera }
        })
        .collect())
}

eval::bench_main!("token-probe", probe);

fn probe(a: &Args) -> Result<()> {
    let device: Device = a.model.device()?;
    let vlm_dir = a.model.vlm_dir()?;
    let vlm = LlavaOnevision::load(&vlm_dir, &device)?;
    let (d, p) = (vlm.cfg.vision.hidden_size, vlm.cfg.vision.patch_size);
    let opts = greedy();
    let variants = if a.no_swaps { &VARIANTS[..2] } else { &VARIANTS[..] };
    // per split, per variant
    let mut scores: BTreeMap<Split, Vec<Score>> = BTreeMap::new();
    // token L1 of ChatSplat against the truth per split and region: (sum, tokens)
    let mut l1: BTreeMap<(Split, Region), (f64, usize)> = BTreeMap::new();
    let mut views_seen: BTreeMap<Split, usize> = BTreeMap::new();
    let mut rows = Vec::new();
    for dir in &a.scenes {
        let data = dir.join("data");
        let scene: SynthScene = model::io::read_json(&data.join("scene.json"))?;
        let ds = load_any(&data, &LoadOptions::default())?;
        let run = GeometryRun::new(dir.join("run"));
        let lang = a.language.as_ref().map(|l| run.dir.join(l));
        let session = if a.full {
            ChatSession::open_full(&run, lang.as_deref(), &vlm_dir, &device)?
        } else {
            ChatSession::open(&run, lang.as_deref(), &vlm_dir, &device)?
        };
        let split = ds.train.iter().map(|v| (v, Split::Training)).chain(ds.test.iter().map(|v| (v, Split::HeldOut)));
        let mut views = Vec::new();
        for (v, split) in split {
            let name = v.image_path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            let Some(index) = session.images.iter().position(|i| *i == name) else { continue };
            let Some(ids) = v.instance_ids.clone() else { continue };
            views.push(ProbeView { name, split, rgb: v.rgb.clone(), ids, camera: *session.camera(index)? });
        }
        views.extend(novel_views(&scene, &ds, a.novel)?);
        for v in views {
            let (w, h) = (v.camera.width as usize, v.camera.height as usize);
            let Some((truth_count, truth_colors)) = view_truth(&scene, &v.ids, w, h) else { continue };
            *views_seen.entry(v.split).or_default() += 1;
            let gt = host(vlm.teacher_tokens(&RgbImage::from_f32(w, h, &v.rgb)));
            let cs = host(session.tokens(&Target::View(v.camera))?.remove(0));
            let reg = regions(&v.ids, w, h, p);
            if reg.len() * d != gt.len() || gt.len() != cs.len() {
                return Err(model::Error::input(format!(
                    "{}: {} patches of {p} px but {} tokens (the probe needs the view at the tower's size)",
                    v.name,
                    reg.len(),
                    gt.len() / d
                )));
            }
            for (t, r) in reg.iter().enumerate() {
                let e = l1.entry((v.split, *r)).or_default();
                e.0 += token_l1(&gt, &cs, t, d);
                e.1 += 1;
            }
            let mut row = serde_json::json!({
                "scene": dir.display().to_string(), "view": v.name, "split": v.split,
                "count": truth_count, "colors": truth_colors,
                "regions": REGIONS.iter().map(|r| (format!("{r:?}"), reg.iter().filter(|x| *x == r).count()))
                    .collect::<BTreeMap<_, _>>(),
            });
            let tally = scores.entry(v.split).or_insert_with(|| vec![Score::default(); variants.len()]);
            for (var, s) in variants.iter().zip(tally.iter_mut()) {
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
                s.asked += 1;
                s.count_right += exact(&count.text, &truth_count.to_string()) as usize;
                s.colors_right += exact(&cols.text, &truth_colors) as usize;
                if let Some(n) = count_answer(&count.text) {
                    let e = n - truth_count as i64;
                    s.count_bias += e;
                    s.numeric += 1;
                    s.under += (e < 0) as usize;
                    s.over += (e > 0) as usize;
                }
                row[var.name] = serde_json::json!({"count": count.text, "colors": cols.text});
            }
            rows.push(row);
            eprint!("\rtoken-probe: {} views", views_seen.values().sum::<usize>());
        }
    }
    eprintln!();
    let seen = |s: Split| views_seen.get(&s).copied().unwrap_or(0);
    println!(
        "token-probe: {} views of {} scenes: {} training, {} held out, {} new poses (count and colours asked on \
         each)\n",
        views_seen.values().sum::<usize>(),
        a.scenes.len(),
        seen(Split::Training),
        seen(Split::HeldOut),
        seen(Split::Novel)
    );
    let none = vec![Score::default(); variants.len()];
    let of = |s: Split| scores.get(&s).unwrap_or(&none);
    let pc = |r: usize, s: &Score| 100.0 * r as f64 / s.asked.max(1) as f64;
    println!(
        "| tokens | dataset views: count right % | under / over | mean count error | colours right % | held out: \
         count / colours % | new poses: count / colours % | new poses: under / over |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for (i, var) in variants.iter().enumerate() {
        let (t, h, n) = (&of(Split::Training)[i], &of(Split::HeldOut)[i], &of(Split::Novel)[i]);
        let all = Score {
            count_right: t.count_right + h.count_right,
            colors_right: t.colors_right + h.colors_right,
            asked: t.asked + h.asked,
            count_bias: t.count_bias + h.count_bias,
            numeric: t.numeric + h.numeric,
            under: t.under + h.under,
            over: t.over + h.over,
        };
        println!(
            "| {} | {:.1} | {} / {} | {:+.2} | {:.1} | {:.1} / {:.1} | {:.1} / {:.1} | {} / {} |",
            var.name,
            pc(all.count_right, &all),
            all.under,
            all.over,
            all.count_bias as f64 / all.numeric.max(1) as f64,
            pc(all.colors_right, &all),
            pc(h.count_right, h),
            pc(h.colors_right, h),
            pc(n.count_right, n),
            pc(n.colors_right, n),
            n.under,
            n.over
        );
    }
    println!("\n| region | split | tokens | ChatSplat token L1 vs truth |");
    println!("|---|---|---|---|");
    for ((split, r), (s, n)) in &l1 {
        println!("| {r:?} | {split:?} | {n} | {:.3} |", s / (*n).max(1) as f64);
    }
    model::io::create_dir(&a.out)?;
    let mut l1_means: BTreeMap<String, BTreeMap<String, f64>> = BTreeMap::new();
    for ((split, r), (sum, n)) in &l1 {
        l1_means.entry(format!("{split:?}")).or_default().insert(format!("{r:?}"), sum / (*n).max(1) as f64);
    }
    let summary = serde_json::json!({
        "scenes": a.scenes.iter().map(|s| s.display().to_string()).collect::<Vec<_>>(),
        "novel_poses_per_scene": a.novel,
        "scores": scores.iter().map(|(s, v)| {
            (format!("{s:?}"), variants.iter().zip(v).map(|(var, x)| (var.name, x.clone())).collect::<BTreeMap<_, _>>())
        }).collect::<BTreeMap<_, _>>(),
        "l1_by_region": l1_means,
        "views": rows,
    });
    model::io::write_json(&a.out.join("probe.json"), &summary)?;
    Ok(())
}
