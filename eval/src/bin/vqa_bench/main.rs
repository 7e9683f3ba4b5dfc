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

mod sweep;
mod totals;

use burn::tensor::Device;
use clap::Parser;
use eval::harness::{HeldOutSeeds, ModelArgs};
use model::chat::{ChatSession, DEFAULT_SCENE_VIEWS};
use model::data::synth::{SynthOptions, write_dataset};
use model::data::{LoadOptions, load_any};
use model::language::CROP_MARGIN;
use model::run::{GeometryRun, LanguageRun};
use model::splats::host;
use model::vlm::{LlavaOnevision, RgbImage};
use model::vqa::{FindOptions, Level, load_questions, scene_view, target_of};
use model::{ObjectId, Result};
use scoring::compare::{Answered, Source, answer_file, find_file_as};
use scoring::progress::Progress;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;
use sweep::{GEOMETRY_SWEEP, Point, SWEEP, Variant, add_point};
use totals::{BenchJson, Totals, add_find, report};
use train::geometry::GeometryConfig;
use train::language::LanguageTrainConfig;
use train::pipeline::{Observer, PerViewMasks, Recipe, SceneDirs, Stage, TeacherModel, train_scene};
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
    /// Only ChatSplat's find phrases (the scene's `find` questions): no answers of the three
    /// paths, no token speed or fidelity.
    #[arg(long, conflicts_with = "sweep")]
    find_only: bool,
    /// Where each scene's objects come from: `truth`, the capture's own masks; `matched`, issue
    /// 84's flow on a capture without labels: its true masks corrupted the way segmenters err
    /// (ids shuffled per view, masks split, merged, missing, fragments, edges moved), the geometry
    /// trained without them, the masks matched across views (`chatsplat masks`) and the identity
    /// fitted from them. The questions and the scoring are the same either way.
    #[arg(long, value_enum, default_value_t = Objects::Truth)]
    objects: Objects,
    /// Only ChatSplat's answers and find phrases: not the ground-truth and rendered-RGB paths, no
    /// token speed or fidelity.
    #[arg(long, conflicts_with = "sweep")]
    chatsplat_only: bool,
    /// Keep what an earlier run left in `--out`: a seed's capture is not written again and its
    /// finished stages are not trained again (to score the same fields again).
    #[arg(long, conflicts_with = "sweep")]
    resume: bool,
    /// Instead of running, add up the bench.json of earlier runs (tallies, token seconds and sweep
    /// points of their scenes) and print, plot and write them as one run into `--out`.
    #[arg(long, num_args = 1.., value_name = "BENCH_JSON")]
    merge: Vec<PathBuf>,
}

#[derive(Clone, Copy, Debug, PartialEq, clap::ValueEnum)]
enum Objects {
    Truth,
    Matched,
}

/// Each object of the matched masks in `matched` (`<image stem>.png`, the images' size) taken to
/// the true object (`ds`'s masks) most of its pixels show over every view; one mostly on the
/// background to an id of its own that no phrase names.
fn truth_of_matched(ds: &model::data::Dataset, matched: &std::path::Path) -> Result<BTreeMap<ObjectId, ObjectId>> {
    let mut votes: BTreeMap<ObjectId, BTreeMap<ObjectId, usize>> = BTreeMap::new();
    for v in ds.train.iter().chain(&ds.test) {
        let Some(truth) = &v.instance_ids else { continue };
        let name = v.image_path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let path = matched.join(format!("{}.png", train::masks::files::stem(&name)));
        let (_, _, ids) = model::data::read_ids16_any(&path)?;
        if ids.len() != truth.len() {
            return Err(model::Error::invalid(&path, "is not its image's size"));
        }
        for (&m, &t) in ids.iter().zip(truth).filter(|(m, _)| **m != 0) {
            *votes.entry(m).or_default().entry(t).or_default() += 1;
        }
    }
    Ok(votes
        .into_iter()
        .map(|(m, v)| {
            let (t, _) = v.into_iter().max_by_key(|&(t, n)| (n, std::cmp::Reverse(t))).expect("a vote");
            (m, if t == 0 { ObjectId::MAX - m } else { t })
        })
        .collect())
}

/// Bytes of a scene's language field (features and encoder) as f32.
fn field_bytes(session: &ChatSession) -> usize {
    session.scene.field.named().iter().map(|(_, t)| 4 * t.dims().iter().product::<usize>()).sum()
}

eval::bench_main!("vqa-bench", bench);

fn bench(a: &Args) -> Result<()> {
    if !a.merge.is_empty() {
        return merge(a);
    }
    let device: Device = a.model.device()?;
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
    let Totals { tallies, seconds, fid_rgb, fid_cs, points, find, find_seconds, .. } = &mut totals;
    let d = vlm.cfg.vision.hidden_size;
    for seed in a.held_out.range() {
        let dir = a.out.join(format!("seed{seed}"));
        let data = dir.join("data");
        let opts = SynthOptions { seed, views: a.views, width: side, height: side, ..Default::default() };
        // `--resume`: a capture already written is kept as it is
        let written = |d: &std::path::Path| a.resume && d.join("transforms.json").is_file();
        if !written(&data) {
            write_dataset(&data, &opts, |_, _| {})?;
        }
        let dirs = match a.objects {
            Objects::Truth => SceneDirs::beside(&data, &dir.join("run")),
            Objects::Matched => {
                // the same capture without labels, a segmenter's masks beside it
                let bare = dir.join("bare");
                let per_view = dir.join("per-view");
                if !written(&bare) {
                    write_dataset(&bare, &opts, |_, _| {})?;
                    let truth = train::masks::corrupt::strip_capture(&bare, &per_view, &Default::default(), seed)?;
                    eprintln!("seed {seed}: {truth} objects, their masks corrupted into {}", per_view.display());
                }
                let objects =
                    PerViewMasks { per_view, bare: GeometryRun::new(dir.join("geometry")), matched: dir.join("masks") };
                SceneDirs { objects: Some(objects), ..SceneDirs::beside(&bare, &dir.join("run")) }
            }
        };
        let (run, teacher) = (dirs.run.clone(), dirs.teacher.clone());
        let novel = (a.novel_views > 0).then(|| NovelViews { run: run.clone(), count: a.novel_views, seed });
        let recipe = Recipe {
            geometry: GeometryConfig::short(a.geometry_iters),
            teacher: ExtractOptions { novel, tower_tail: a.tower_tail, ..Default::default() },
            language: language_config.clone(),
            identity: Default::default(),
        };
        let mut bars = SeedBars { seed, bar: None };
        let trained = train_scene(TeacherModel::Loaded(&vlm), &dirs, &recipe, &device, a.resume, &mut bars)?;
        if let Some((m, _)) = &trained.objects {
            eprintln!("seed {seed}: {} objects matched, {:.1} ms per view", m.objects.len(), m.per_view_ms);
        }
        let load = LoadOptions::default();
        let ds = load_any(&data, &load)?;
        if let (Some(g), Some(l)) = (&trained.geometry, &trained.language) {
            eprintln!(
                "seed {seed}: geometry held-out PSNR {:.2} dB, mIoU {:.3}; language token L1 view {:.3} object {:.3}",
                g.eval.psnr,
                g.eval.miou.unwrap_or(0.0),
                l.after.0,
                l.after.1
            );
        }
        // the sweep's own rate (`--resume`, which keeps a finished language stage, has no sweep)
        let l_seconds = trained.language.as_ref().map_or(0.0, |l| l.seconds_per_iter);
        let session = ChatSession::open(&run, None, &vlm_dir, &device)?;
        let qf = load_questions(&data.join("questions.json"))?;
        let find_opts = FindOptions::of_run(&run, &mut Vec::new());
        // matched masks number the objects their own way: what is found is scored as the true
        // object most of its pixels show
        let named = match &dirs.objects {
            Some(o) => truth_of_matched(&ds, &o.matched)?,
            None => Default::default(),
        };
        let as_named = |id: ObjectId| if dirs.objects.is_some() { named.get(&id).copied().unwrap_or(0) } else { id };
        let (kinds, secs) = find_file_as(&session, &qf, &find_opts, &as_named)?;
        if dirs.objects.is_some() {
            // the truth's scene.json names its table; a capture without labels finds it as a
            // surface (masks.json): the same phrases with the matched table left out by the
            // truth, which equals the main figure when the surface found is the table
            let ground = |m: &ObjectId| named.get(m) == Some(&model::data::synth::TABLE_ID);
            let only = named.keys().copied().filter(|m| !ground(m)).collect();
            let opts = FindOptions { names: model::find::ObjectNames::only(only), ..find_opts.clone() };
            let (k, _) = find_file_as(&session, &qf, &opts, &as_named)?;
            let mut all = model::find::FindTally::default();
            k.values().for_each(|t| all.merge(t));
            eprintln!("seed {seed}: find with the matched table left out: {}", all.summary());
        }
        add_find(find, find_seconds, &kinds, secs);
        if a.find_only {
            continue;
        }
        let mut configured = None;
        let sources = if a.chatsplat_only { &[Source::ChatSplat][..] } else { &Source::ALL[..] };
        for &source in sources {
            let answered = answer_file(&vlm, &qf, &ds, Some(&session), source, CROP_MARGIN)?;
            tallies.entry(source).or_default().merge(&answered.tally);
            if source == Source::ChatSplat {
                configured = Some(answered);
            }
        }
        if a.chatsplat_only {
            continue;
        }
        // speed of each path's tokens and their fidelity to teacher(ground truth), per question target
        for q in &qf.questions {
            // one figure per target: not scene level, not a phrase to find, not a follow-up
            if matches!(q.level, Level::Scene | Level::Find) || q.follows.is_some() {
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
                Variant::Configured => (ChatSession::open_full(&run, None, &vlm_dir, &device)?, Some(l_seconds)),
                Variant::Compacted => {
                    let ans = configured.take().expect("ChatSplat's answers of the default field");
                    record(v, &session, ans, Some(l_seconds));
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
        "tower_tail": a.tower_tail, "find_only": a.find_only,
        "objects": format!("{:?}", a.objects).to_lowercase(), "chatsplat_only": a.chatsplat_only, "resume": a.resume,
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
