//! `vqa-bench`: the paper's comparison reproduced offline on held-out synthetic scenes. For each
//! seed: `synth` -> geometry -> teacher tokens (the given VLM) -> language field, then every
//! question of the scene's question file (view and object level on the held-out, novel views;
//! scene level on training views) answered three ways: (a) the VLM on the ground-truth image,
//! (b) the VLM on the rendered RGB (object level: the rendered crop cut by the ground-truth mask),
//! (c) ChatSplat's tokens (object level: by click). Prints accuracy per level and question type,
//! views/s and objects/s of each path, and token L1 / cosine against teacher(ground truth).
//!
//! cargo run --release -p eval --bin vqa-bench -- [--vlm DIR] [--seeds 5] [--out out/vqa-bench]
#![allow(deprecated)]

use burn::tensor::Device;
use clap::Parser;
use eval::compare::{Source, Tally, answer_file};
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
        for source in Source::ALL {
            let t0 = Instant::now();
            let (t, _) = answer_file(&vlm, &qf, &ds, Some(&session), source, 0.1)?;
            let _ = t0;
            tallies.entry(source).or_default().merge(&t);
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
    let json = serde_json::json!({
        "seeds": [a.first_seed, a.first_seed + a.seeds], "views": a.views, "resolution": a.resolution,
        "geometry_iters": a.geometry_iters, "language_iters": a.language_iters,
        "language_config": language_config, "backend": a.backend.to_string(),
        "tallies": tallies
            .iter()
            .map(|(s, t)| (format!("{s:?}"), serde_json::to_value(t).unwrap()))
            .collect::<serde_json::Map<_, _>>(),
        "fidelity_rendered_rgb": fr, "fidelity_chatsplat": fc,
    });
    model::io::write_json(&a.out.join("bench.json"), &json)?;
    println!("\nfigures -> {}", a.out.join("bench.json").display());
    Ok(())
}
