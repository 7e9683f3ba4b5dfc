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
use eval::harness::{HeldOutSeeds, ModelArgs, TokenFidelity};
use eval::plot::{Chart, Series};
use eval::progress::Progress;
use model::Result;
use model::chat::{ChatSession, DEFAULT_SCENE_VIEWS};
use model::data::synth::{SynthOptions, write_dataset};
use model::data::{LoadOptions, load_any};
use model::language::CROP_MARGIN;
use model::run::{GeometryRun, LanguageRun};
use model::splats::host;
use model::vlm::{LlavaOnevision, RgbImage};
use model::vqa::{Level, load_questions, scene_view, target_of};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;
use train::geometry::GeometryConfig;
use train::language::LanguageTrainConfig;
use train::pipeline::{Observer, Recipe, SceneDirs, Stage, TeacherModel, train_scene};
use train::teacher::{ExtractOptions, NovelViews};

/// One seed's progress bars: geometry (PSNR) and language (loss).
struct SeedBars {
    seed: u64,
    bar: Option<Progress>,
}

impl Observer for SeedBars {
    fn start(&mut self, stage: Stage, _resumed_from: Option<usize>) {
        self.bar =
            (stage != Stage::Teacher).then(|| Progress::new(format!("seed {} {}", self.seed, stage.name()), "it"));
    }
    fn geometry(&mut self, p: &train::geometry::Progress) {
        if let Some(bar) = self.bar.as_ref().filter(|_| p.iter.is_multiple_of(20) || p.iter == p.iters) {
            bar.update_with(p.iter, p.iters, &format!("psnr {:.2}", p.psnr))
        }
    }
    fn language(&mut self, p: &train::language::LangProgress) {
        if let Some(bar) = self.bar.as_ref().filter(|_| p.iter.is_multiple_of(10) || p.iter == p.iters) {
            bar.update_with(p.iter, p.iters, &format!("loss {:.4}", p.step.loss))
        }
    }
}

#[derive(Parser)]
#[command(name = "vqa-bench", about = "ChatSplat vs the VLM on ground-truth and rendered images, offline")]
struct Args {
    #[command(flatten)]
    model: ModelArgs,
    #[command(flatten)]
    held_out: HeldOutSeeds,
    /// Views per scene (every 8th is held out) and their side.
    #[arg(long, default_value_t = 32)]
    views: usize,
    /// Default: the side the model reads (the built-in model's image size).
    #[arg(long)]
    resolution: Option<u32>,
    #[arg(long, default_value_t = 1500)]
    geometry_iters: usize,
    /// Language-stage iterations (without `--language-config`, the first tenth warm up).
    #[arg(long, default_value_t = 600)]
    language_iters: usize,
    /// A language-stage config.json (any `LanguageTrainConfig` fields, e.g. `{"lr_final": 1.0}`
    /// for the paper's constant rate); `--language-iters` sets its iterations.
    #[arg(long)]
    language_config: Option<PathBuf>,
    /// Also teach the language stage this many novel views per scene: the scene's geometry
    /// rendered between its training cameras (`chatsplat extract --novel-views`).
    #[arg(long, default_value_t = 0)]
    novel_views: usize,
    /// The tower's last K layers left to the tower (`chatsplat extract --tower-tail`; 0 is the
    /// paper's field).
    #[arg(long, default_value_t = train::teacher::DEFAULT_TOWER_TAIL, value_name = "K")]
    tower_tail: usize,
    /// Work directory (datasets, runs) and bench.json.
    #[arg(long, default_value = "out/vqa-bench")]
    out: PathBuf,
    /// Also sweep speed against error on ChatSplat's answers: language channels (8/16/64 beside
    /// the config's), Gaussians kept by language contribution (50/25/10 %), a coarser map, half
    /// the language iterations and a quarter of the geometry's. Writes sweep.png (accuracy against
    /// views/s, the Pareto front marked) beside bench.json.
    #[arg(long)]
    sweep: bool,
    /// Instead of running, add up the bench.json of earlier runs (tallies, token seconds and sweep
    /// points of their scenes) and print, plot and write them as one run into `--out`.
    #[arg(long, num_args = 1.., value_name = "BENCH_JSON")]
    merge: Vec<PathBuf>,
}

/// One way to make a scene's field in the sweep, scored by ChatSplat's answers.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Variant {
    /// The field as configured, every Gaussian (the reference point).
    Configured,
    /// The field as `train-language` leaves it by default: compacted (compact.json), the
    /// comparison's (c).
    Compacted,
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

const SWEEP: [Variant; 10] = [
    Variant::Configured,
    Variant::Compacted,
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
            Variant::Compacted => "compacted (the default: compact.json)".into(),
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
            Variant::Kept(_) | Variant::Compacted => "Gaussians kept",
            Variant::Patch(_) => "map resolution",
            Variant::LanguageIters(_) | Variant::GeometryIters(_) => "iterations",
        }
    }
}

/// A sweep point summed over the scenes.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize)]
struct Point {
    name: String,
    axis: String,
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
    fn add(&mut self, o: &Point) {
        self.tally.merge(&o.tally);
        for (level, (t, n)) in &o.token_seconds {
            let e = self.token_seconds.entry(*level).or_default();
            e.0 += t;
            e.1 += n;
        }
        self.train_seconds += o.train_seconds;
        self.trained += o.trained;
        self.gaussians += o.gaussians;
        self.field_bytes += o.field_bytes;
        self.scenes += o.scenes;
    }
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

eval::bench_main!("vqa-bench", bench);

/// Adds `p` to the point of its name in `points`, or appends it (the sweep's order).
fn add_point(points: &mut Vec<Point>, p: &Point) {
    match points.iter_mut().find(|q| q.name == p.name) {
        Some(q) => q.add(p),
        None => points.push(p.clone()),
    }
}

/// What a run adds up over its scenes; `--merge` adds the bench.json of several runs.
#[derive(Default)]
struct Totals {
    tallies: BTreeMap<Source, Tally>,
    /// Seconds spent making tokens and how many, per path and level.
    seconds: BTreeMap<(Source, Level), (f64, usize)>,
    fid_rgb: TokenFidelity,
    fid_cs: TokenFidelity,
    points: Vec<Point>,
    /// Held-out seeds, ranges `[first, end)`.
    seeds: Vec<[u64; 2]>,
}

/// The parts of a bench.json that `--merge` adds (older files lack `token_seconds`).
#[derive(serde::Deserialize)]
struct BenchJson {
    #[serde(default)]
    seeds: Option<[u64; 2]>,
    #[serde(default)]
    seed_ranges: Vec<[u64; 2]>,
    tallies: BTreeMap<Source, Tally>,
    /// `None` in files written before the runs stored it.
    #[serde(default)]
    token_seconds: Option<Vec<(Source, Level, f64, usize)>>,
    fidelity_rendered_rgb: TokenFidelity,
    fidelity_chatsplat: TokenFidelity,
    #[serde(default)]
    sweep: Vec<Point>,
}

impl Totals {
    fn add(&mut self, b: &BenchJson) {
        for (s, t) in &b.tallies {
            self.tallies.entry(*s).or_default().merge(t);
        }
        for &(s, l, t, n) in b.token_seconds.iter().flatten() {
            let e = self.seconds.entry((s, l)).or_default();
            e.0 += t;
            e.1 += n;
        }
        self.fid_rgb.add_mean(b.fidelity_rendered_rgb);
        self.fid_cs.add_mean(b.fidelity_chatsplat);
        for p in &b.sweep {
            add_point(&mut self.points, p);
        }
        self.seeds.extend(b.seeds.iter().chain(&b.seed_ranges));
    }

    fn scenes(&self) -> u64 {
        self.seeds.iter().map(|[a, b]| b - a).sum()
    }

    /// "5 held-out seeds: 30000-30002, 30003, 30004".
    fn label(&self) -> String {
        let ranges: Vec<String> = self
            .seeds
            .iter()
            .map(|&[a, b]| if b == a + 1 { a.to_string() } else { format!("{a}-{}", b - 1) })
            .collect();
        format!("{} held-out seeds: {}", self.scenes(), ranges.join(", "))
    }
}

fn bench(a: &Args) -> Result<()> {
    if !a.merge.is_empty() {
        return merge(a);
    }
    let device: Device = a.model.device();
    let vlm_dir = a.model.vlm_dir()?;
    let vlm = LlavaOnevision::load(&vlm_dir, &device)?;
    let side = a.resolution.unwrap_or(vlm.cfg.vision.image_size as u32);
    let mut language_config = match &a.language_config {
        Some(p) => {
            let c: LanguageTrainConfig = model::io::read_config(p)?;
            c.validate().map_err(|e| model::Error::invalid(p, e.to_string()))?;
            c
        }
        None => LanguageTrainConfig::short(a.language_iters),
    };
    language_config.iters = a.language_iters;
    language_config.checkpoint_every = 0;
    model::io::create_dir(&a.out)?;
    let mut totals = Totals { seeds: vec![[a.held_out.first_seed, a.held_out.range().end]], ..Default::default() };
    let Totals { tallies, seconds, fid_rgb, fid_cs, points, .. } = &mut totals;
    let d = vlm.cfg.vision.hidden_size;
    for seed in a.held_out.range() {
        let dir = a.out.join(format!("seed{seed}"));
        let data = dir.join("data");
        let opts = SynthOptions { seed, views: a.views, width: side, height: side, ..Default::default() };
        write_dataset(&data, &opts, |_, _| {})?;
        let dirs = SceneDirs::beside(&data, &dir.join("run"));
        let (run, teacher) = (dirs.run.clone(), dirs.teacher.clone());
        let novel = (a.novel_views > 0).then(|| NovelViews { run: run.clone(), count: a.novel_views, seed });
        let recipe = Recipe {
            geometry: GeometryConfig::short(a.geometry_iters),
            teacher: ExtractOptions { novel, tower_tail: a.tower_tail, ..Default::default() },
            language: language_config.clone(),
        };
        let mut bars = SeedBars { seed, bar: None };
        let trained = train_scene(TeacherModel::Loaded(&vlm), &dirs, &recipe, &device, false, &mut bars)?;
        let (Some(g), Some(l)) = (trained.geometry, trained.language) else {
            unreachable!("every stage runs without resume")
        };
        let load = LoadOptions::default();
        let ds = load_any(&data, &load)?;
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
            let answered = answer_file(&vlm, &qf, &ds, Some(&session), source, CROP_MARGIN)?;
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
                model::language::ObjectCrop::of(ids, w, h, id, CROP_MARGIN).map(|c| c.masked_image(img, ids, id))
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
            let scene = Point {
                name: v.name(a, channels),
                axis: v.axis().into(),
                tally: ans.tally,
                token_seconds: ans.token_seconds,
                train_seconds: seconds_per_iter.unwrap_or(0.0),
                trained: seconds_per_iter.is_some() as usize,
                gaussians: session.scene.splats.len(),
                field_bytes: field_bytes(session),
                scenes: 1,
            };
            add_point(points, &scene);
        };
        let train_field = |run: &GeometryRun, tag: &str, cfg: LanguageTrainConfig| -> Result<(ChatSession, f64)> {
            let lang = LanguageRun::new(run.dir.join(format!("language-{tag}")));
            let bar = Progress::new(format!("seed {seed} sweep: language {tag}"), "it");
            let l = train::language::fit(run, &teacher.dir, &lang, cfg, &device, false, &train::dist::Solo, |p| {
                if p.iter.is_multiple_of(10) || p.iter == p.iters {
                    bar.update_with(p.iter, p.iters, &format!("loss {:.4}", p.step.loss))
                }
            })?;
            Ok((ChatSession::open_full(run, Some(&lang.dir), &vlm_dir, &device)?, l.seconds_per_iter))
        };
        for v in SWEEP.into_iter().chain([GEOMETRY_SWEEP]) {
            // the sweep's fields are compared with every Gaussian (the configured one's compaction
            // is a point of its own)
            let mut cfg = LanguageTrainConfig { compact_tolerance: 0.0, ..language_config.clone() };
            let (field, seconds_per_iter) = match v {
                Variant::Configured => {
                    (ChatSession::open_full(&run, None, &vlm_dir, &device)?, Some(l.seconds_per_iter))
                }
                Variant::Compacted => {
                    let ans = configured.take().expect("ChatSplat's answers of the default field");
                    record(v, &session, ans, Some(l.seconds_per_iter));
                    continue;
                }
                Variant::Kept(pct) => {
                    let c = dirs.language.read_contribution()?;
                    let keep = model::scene::top_contributors(&c, (c.len() * pct).div_ceil(100));
                    let mut s = ChatSession::open_full(&run, None, &vlm_dir, &device)?;
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
                    train::geometry::fit(&ds, None, &data, &load, &small, gcfg, &device, false, |p| {
                        if p.iter.is_multiple_of(20) || p.iter == p.iters {
                            bar.update_with(p.iter, p.iters, &format!("psnr {:.2}", p.psnr))
                        }
                    })?;
                    let (s, t) = train_field(&small, "configured", cfg)?;
                    (s, Some(t))
                }
            };
            let ans = answer_file(&vlm, &qf, &ds, Some(&field), Source::ChatSplat, CROP_MARGIN)?;
            eprintln!("seed {seed} sweep: {}: {:.1} %", v.name(a, channels), ans.tally.overall());
            record(v, &field, ans, seconds_per_iter);
        }
    }
    let settings = serde_json::json!({
        "seeds": [a.held_out.first_seed, a.held_out.range().end], "views": a.views, "resolution": side,
        "geometry_iters": a.geometry_iters, "language_iters": a.language_iters, "novel_views": a.novel_views,
        "tower_tail": a.tower_tail,
        "language_config": language_config, "backend": a.model.backend.to_string(),
    });
    report(&totals, &format!("{} views of {side}px", a.views), settings, &a.out)
}

/// `--merge`: the bench.json of earlier runs added up and reported as one.
fn merge(a: &Args) -> Result<()> {
    let mut totals = Totals::default();
    let mut missing = 0;
    for f in &a.merge {
        let b: BenchJson = model::io::read_json(f)?;
        missing += b.token_seconds.is_none() as usize;
        if b.seeds.is_none() && b.seed_ranges.is_empty() {
            return Err(model::Error::invalid(f, "names no seeds: not a vqa-bench bench.json"));
        }
        if let Some(dup) =
            totals.seeds.iter().find(|r| b.seeds.iter().chain(&b.seed_ranges).any(|s| s[0] < r[1] && r[0] < s[1]))
        {
            return Err(model::Error::invalid(
                f,
                format!("its seeds overlap seeds {}..{} of an earlier file: a scene would count twice", dup[0], dup[1]),
            ));
        }
        totals.add(&b);
    }
    if missing > 0 {
        eprintln!(
            "note: {missing} of {} files predate token_seconds: the views/s and objects/s of the three paths {} \
                (the sweep's rates are in every file)",
            a.merge.len(),
            if missing == a.merge.len() { "are not known" } else { "come from the others" }
        );
    }
    model::io::create_dir(&a.out)?;
    let settings = serde_json::json!({
        "seed_ranges": totals.seeds, "merged_from": a.merge,
    });
    report(&totals, "merged", settings, &a.out)
}

/// Prints the comparison (and the sweep, when there is one) and writes bench.json (`settings`
/// first) and sweep.png into `out`.
fn report(t: &Totals, what: &str, settings: serde_json::Value, out: &std::path::Path) -> Result<()> {
    let empty = Tally::default();
    let tally = |s: Source| t.tallies.get(&s).unwrap_or(&empty);
    println!("\n## ChatSplat vs the VLM on images ({}, {what})\n", t.label());
    println!("| path | view | object | scene | overall | questions |\n|---|---|---|---|---|---|");
    for source in Source::ALL {
        let t = tally(source);
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
    let kinds: Vec<String> = tally(Source::GroundTruth).by_kind.keys().cloned().collect();
    println!(
        "\n| question type | (a) ground truth | (b) rendered RGB | (c) ChatSplat | asked |\n|---|---|---|---|---|"
    );
    for k in &kinds {
        let pct = |s: Source| {
            tally(s)
                .by_kind
                .get(k)
                .map(|(r, n)| format!("{:.1}", 100.0 * *r as f64 / (*n).max(1) as f64))
                .unwrap_or("-".into())
        };
        let n = tally(Source::GroundTruth).by_kind.get(k).map_or(0, |e| e.1);
        println!(
            "| {k} | {} | {} | {} | {n} |",
            pct(Source::GroundTruth),
            pct(Source::RenderedRgb),
            pct(Source::ChatSplat)
        );
    }
    println!("\n| tokens of | views/s | objects/s | view token L1 vs teacher(GT) | cosine |\n|---|---|---|---|---|");
    let rate = |s: Source, l: Level| t.seconds.get(&(s, l)).map(|(t, n)| *n as f64 / t.max(1e-9));
    let fmt = |r: Option<f64>| r.map_or("-".into(), |r| format!("{r:.1}"));
    let (fr, fc) = (t.fid_rgb.mean(), t.fid_cs.mean());
    for (name, s, f) in [
        ("(b) render RGB + vision tower", Source::RenderedRgb, &fr),
        ("(c) ChatSplat: render language map + encoder", Source::ChatSplat, &fc),
    ] {
        println!(
            "| {name} | {} | {} | {:.4} | {:.4} |",
            fmt(rate(s, Level::View)),
            fmt(rate(s, Level::Object)),
            f.l1,
            f.cos
        );
    }
    let baseline = rate(Source::RenderedRgb, Level::View).map(|r| (r, tally(Source::RenderedRgb).overall()));
    if !t.points.is_empty() {
        sweep_report(&t.points, baseline, t, out)?;
    }
    let mut json = settings;
    let figures = serde_json::json!({
        "tallies": t.tallies
            .iter()
            .map(|(s, t)| (format!("{s:?}"), serde_json::to_value(t).unwrap()))
            .collect::<serde_json::Map<_, _>>(),
        "token_seconds": t.seconds.iter().map(|(&(s, l), &(secs, n))| (s, l, secs, n)).collect::<Vec<_>>(),
        "fidelity_rendered_rgb": fr, "fidelity_chatsplat": fc, "sweep": t.points,
    });
    if let (Some(j), serde_json::Value::Object(f)) = (json.as_object_mut(), figures) {
        j.extend(f);
    }
    model::io::write_json(&out.join("bench.json"), &json)?;
    println!("\nfigures -> {}", out.join("bench.json").display());
    Ok(())
}

/// Prints the sweep's table and writes its plot: ChatSplat's exact match against views/s, one
/// series per axis through the configured field, the Pareto front, and the rendered-RGB baseline
/// (`baseline`: its views/s and exact match, when the runs timed it).
fn sweep_report(points: &[Point], baseline: Option<(f64, f64)>, t: &Totals, out: &std::path::Path) -> Result<()> {
    println!("\n## Speed against error on ChatSplat's answers ({})\n", t.label());
    println!(
        "| field | Gaussians | field MB | view | object | scene | overall | count | colors | left_of | views/s \
         | objects/s | train s/iter |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    );
    for p in points {
        let n = p.scenes.max(1);
        let lv = |l: Level| p.tally.level(l).map(|v| format!("{v:.1}")).unwrap_or_else(|| "-".into());
        let (right, asked) = p.tally.by_level.values().fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        let train = if p.trained > 0 { format!("{:.3}", p.train_seconds / p.trained as f64) } else { "-".into() };
        println!(
            "| {} | {} | {:.2} | {} | {} | {} | {:.1} ({right}/{asked}) | {} | {} | {} | {:.1} | {:.1} | {train} |",
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
    if let Some(b) = baseline {
        series.push(Series { label: "LLaVA-OV on rendered RGB".into(), points: vec![b], color: [120; 3] });
    }
    let chart = Chart {
        title: format!("ChatSplat answers: speed against exact match ({} held-out scenes)", t.scenes()),
        x_label: "views per second (view tokens)".into(),
        y_label: "exact match (%)".into(),
        log_x: true,
        series,
    };
    let png = out.join("sweep.png");
    chart.write_png(&png, 900, 600)?;
    println!("plot -> {}", png.display());
    Ok(())
}
