//! `chatsplat`: the user-facing command-line tool.
#![allow(deprecated)]

use burn::tensor::{Tensor, TensorData};
use clap::{Parser, Subcommand};
use eval::{BackendChoice, Progress, catch_backend, images};
use glam::Vec3;
use model::GaussianCloud;
use splat_kernels::api::{SplatOptions, splat};
use splat_kernels::Camera;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(name = "chatsplat", version, about = "3D conversational Gaussian splatting in Rust on burn")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The whole pipeline on the built-in synthetic tabletop with the tiny LLaVA-OneVision fixture
    /// (no downloads): synth -> geometry -> teacher tokens -> language field -> chat at view,
    /// object and scene level -> VQA scoring -> encoder export.
    Demo(DemoArgs),
    /// Render a Gaussian scene (an Inria-layout .ply, or the built-in synthetic tabletop) to PNG.
    Render(RenderArgs),
    /// Write the built-in synthetic tabletop as a dataset: ray-cast RGB views, instance masks,
    /// depth, transforms.json and scene.json.
    Synth(SynthArgs),
    /// Plain LLaVA-OneVision on one image (the paper's baseline: the VLM fed with a rendered view).
    Ask(AskArgs),
    /// Geometry stage: fit 3D Gaussians with a 16-channel identity field to a posed dataset.
    Train(TrainArgs),
    /// Export a run's Gaussians as an Inria-layout .ply (with identity features as extra properties).
    ExportPly(ExportPlyArgs),
    /// Teacher tokens for the language field: SigLIP patch features of every training view and of
    /// every masked object, as f16 safetensors (resumable).
    Extract(ExtractArgs),
    /// Language stage: train the per-Gaussian language features, the encoder and the scaling
    /// adjustment against the teacher tokens (geometry frozen).
    TrainLanguage(TrainLanguageArgs),
    /// Write the encoder and scaling adjustment as safetensors (PyTorch Conv2d layout) with a JSON header.
    ExportEncoder(ExportEncoderArgs),
    /// Interactive chat with a trained scene: view, object (click) and scene level.
    Chat(ChatArgs),
    /// Answer an annotated question file about a trained scene and score the answers (offline
    /// exact-match/keyword scorer; plus an OpenAI-compatible grader when CHATSPLAT_GRADER_URL is set).
    Vqa(VqaArgs),
}

#[derive(clap::Args)]
struct TrainArgs {
    /// Dataset directory: nerfstudio transforms.json / Blender, COLMAP (sparse/0), LLFF
    /// (poses_bounds.npy) or Replica (traj_w_c.txt); `chatsplat synth` writes one.
    #[arg(long)]
    data: PathBuf,
    /// Run directory (checkpoints, config.json, renders/, point_cloud.ply, metrics.json).
    #[arg(long, default_value = "out/run")]
    out: PathBuf,
    #[arg(long)]
    iters: Option<usize>,
    #[arg(long, value_enum, default_value_t = BackendChoice::Ndarray)]
    backend: BackendChoice,
    /// Integer image downscale.
    #[arg(long, default_value_t = 1)]
    downscale: u32,
    /// Continue from the run directory's last checkpoint.
    #[arg(long)]
    resume: bool,
    /// A config.json with any GeometryConfig fields (others keep their defaults).
    #[arg(long)]
    config: Option<PathBuf>,
    /// RGBA background: white or black.
    #[arg(long, default_value = "white")]
    background: String,
}

fn train_cmd(a: TrainArgs) -> Result<(), String> {
    use train::data::{load_any, Background, LoadOptions};
    use train::geometry::{run, GeometryConfig};
    let (bg, bgc) = match a.background.as_str() {
        "white" => (Background::White, [1.0; 3]),
        "black" => (Background::Black, [0.0; 3]),
        other => return Err(format!("--background {other}: expected white or black")),
    };
    if a.downscale == 0 {
        return Err("--downscale must be >= 1".into());
    }
    let mut cfg = match &a.config {
        Some(p) => {
            let text = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
            serde_json::from_str::<GeometryConfig>(&text).map_err(|e| format!("{}: invalid config: {e}", p.display()))?
        }
        None => GeometryConfig { background: bgc, ..Default::default() },
    };
    if let Some(n) = a.iters {
        cfg.iters = n;
    }
    let lo = LoadOptions { downscale: a.downscale, background: bg, ..Default::default() };
    // COLMAP projects initialise from their sparse points.
    let (ds, points) = if a.data.join("sparse").is_dir() && !a.data.join("poses_bounds.npy").is_file() {
        let (ds, p) = train::data::colmap::load(&a.data, &lo)?;
        (ds, Some(p))
    } else {
        (load_any(&a.data, &lo)?, None)
    };
    eprintln!("{}: {} training / {} held-out views of {}x{}", a.data.display(), ds.train.len(), ds.test.len(), ds.train[0].camera.width, ds.train[0].camera.height);
    let device = a.backend.device();
    let bar = Progress::new("train", "it");
    let mut last = std::time::Instant::now();
    let s = catch_backend("training", || {
        run(&ds, points.as_ref(), &a.out, cfg, &device, a.resume, |p| {
            if last.elapsed().as_millis() > 250 || p.iter == p.iters {
                bar.update_with(p.iter, p.iters, &format!("loss {:.4} psnr {:.2} N {}", p.loss, p.psnr, p.gaussians));
                last = std::time::Instant::now();
            }
        })
    })??;
    if let Some(at) = s.resumed_from {
        println!("resumed from iteration {at}");
    }
    println!(
        "{} Gaussians; {} views: PSNR {:.2} dB, SSIM {:.4}{}; {:.3} s/iter on {:?} -> {}",
        s.gaussians,
        s.eval.views,
        s.eval.psnr,
        s.eval.ssim,
        s.eval.miou.map(|m| format!(", identity mIoU {m:.3}")).unwrap_or_default(),
        s.seconds_per_iter,
        a.backend,
        a.out.display()
    );
    Ok(())
}

#[derive(clap::Args)]
struct ExportPlyArgs {
    /// Run directory written by `chatsplat train`.
    #[arg(long)]
    run: PathBuf,
    #[arg(long)]
    out: PathBuf,
}

fn export_ply(a: ExportPlyArgs) -> Result<(), String> {
    let t = train::geometry::GeometryTrainer::load(&a.run, &burn::tensor::Device::ndarray())?;
    let (cloud, _) = t.model.to_cloud();
    model::ply::write(&a.out, &cloud).map_err(|e| e.to_string())?;
    println!("{} Gaussians (iteration {}) -> {}", cloud.len(), t.iter, a.out.display());
    Ok(())
}

#[derive(clap::Args)]
struct AskArgs {
    /// Local Hugging Face directory of llava-hf/llava-onevision-qwen2-{0.5b,7b}-ov-hf (or the tiny fixture).
    #[arg(long)]
    vlm: PathBuf,
    /// PNG image to ask about; repeat for a multi-image prompt (one base view + newline per image,
    /// LLaVA-OneVision's multi-image layout). Either images or `--run`.
    #[arg(long)]
    image: Vec<PathBuf>,
    /// A trained ChatSplat scene (geometry run directory with a `language/` run): the question
    /// goes to the scene's tokens instead of an image.
    #[arg(long)]
    run: Option<PathBuf>,
    /// Language run directory (default: RUN/language).
    #[arg(long)]
    language: Option<PathBuf>,
    /// View to ask about (training views first, then held-out views).
    #[arg(long, default_value_t = 0)]
    view: usize,
    /// Object level: the object under pixel X Y of the view (its highlighted view is written as PNG).
    #[arg(long, num_args = 2, value_names = ["X", "Y"])]
    object: Option<Vec<usize>>,
    /// Scene level: tokens of `--views` views spread around the scene.
    #[arg(long)]
    scene: bool,
    /// Views for scene level.
    #[arg(long, default_value_t = 4)]
    views: usize,
    /// The question.
    question: String,
    #[arg(long, default_value_t = 256)]
    max_new_tokens: usize,
    /// 0 = greedy.
    #[arg(long, default_value_t = 0.0)]
    temperature: f32,
    #[arg(long, default_value_t = 1.0)]
    top_p: f32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long, value_enum, default_value_t = BackendChoice::Ndarray)]
    backend: BackendChoice,
}

fn ask(a: AskArgs) -> Result<(), String> {
    use model::vlm::{chat_template, LlavaOnevision, RgbImage, Turn};
    if a.run.is_some() {
        return ask_scene(a);
    }
    if a.image.is_empty() {
        return Err("give --image PNG (plain LLaVA-OneVision) or --run DIR (a trained ChatSplat scene)".into());
    }
    let imgs = a.image.iter().map(|p| RgbImage::read_png(p)).collect::<Result<Vec<_>, _>>()?;
    let opts = check_sampling(&a)?;
    let device = a.backend.device();
    let t0 = std::time::Instant::now();
    let m = catch_backend("loading the model", || LlavaOnevision::load(&a.vlm, &device))?.map_err(|e| e.to_string())?;
    eprintln!("loaded {} in {:.1} s", a.vlm.display(), t0.elapsed().as_secs_f64());
    let prompt = chat_template(&[Turn::user(imgs.len(), a.question.clone())], true);
    let t1 = std::time::Instant::now();
    let out = catch_backend("generation", || -> Result<_, model::vlm::VlmError> {
        let multi = imgs.len() > 1;
        let patches: Vec<_> = imgs.iter().map(|i| m.preprocess(i, multi)).collect();
        let counts: Vec<usize> = patches.iter().map(|p| m.num_image_tokens(p)).collect();
        let ids = m.expand_image_tokens(&m.tokenizer.encode(&prompt)?, &counts)?;
        let images: Vec<_> = patches.iter().map(|p| m.image_embeds(p)).collect();
        let embeds = m.embed_prompt(&ids, &images)?;
        m.generate(embeds, &opts, print_piece)
    })?
    .map_err(|e| e.to_string())?;
    println!();
    let secs = t1.elapsed().as_secs_f64();
    eprintln!(
        "{} prompt tokens, {} new tokens{} in {secs:.2} s on {:?}",
        out.prompt_tokens,
        out.ids.len(),
        if out.stopped { " (stopped at <|im_end|>)" } else { "" },
        a.backend
    );
    Ok(())
}

fn check_sampling(a: &AskArgs) -> Result<model::vlm::GenerateOptions, String> {
    if !(0.0..=1.0).contains(&a.top_p) || a.top_p == 0.0 || a.temperature < 0.0 || !a.temperature.is_finite() {
        return Err("--top-p must be in (0, 1] and --temperature >= 0".into());
    }
    Ok(model::vlm::GenerateOptions { max_new_tokens: a.max_new_tokens, temperature: a.temperature, top_p: a.top_p, seed: a.seed, ignore_stop: false })
}

/// Streams a generation to stdout.
fn print_piece(piece: &str) {
    use std::io::Write;
    print!("{piece}");
    let _ = std::io::stdout().flush();
}

fn ask_scene(a: AskArgs) -> Result<(), String> {
    use eval::chat::{ChatSession, Target};
    let opts = check_sampling(&a)?;
    let run = a.run.clone().expect("checked");
    let device = a.backend.device();
    let t0 = std::time::Instant::now();
    let s = catch_backend("loading", || ChatSession::open(&run, a.language.as_deref(), &a.vlm, &device))??;
    eprintln!("loaded {} ({} Gaussians, {} views) and {} in {:.1} s", run.display(), s.scene.field.len(), s.cameras.len(), a.vlm.display(), t0.elapsed().as_secs_f64());
    let target = match (&a.object, a.scene) {
        (Some(_), true) => return Err("--object and --scene exclude each other".into()),
        (Some(xy), false) => Target::Object { view: a.view, x: xy[0], y: xy[1] },
        (None, true) => Target::Scene(s.scene_views(a.views.max(1))),
        (None, false) => Target::View(a.view),
    };
    let t1 = std::time::Instant::now();
    let (out, picked) = catch_backend("generation", || s.ask(&target, &a.question, &opts, print_piece))??;
    println!();
    eprintln!("{} prompt tokens, {} new tokens in {:.2} s", out.prompt_tokens, out.ids.len(), t1.elapsed().as_secs_f64());
    if let Some(id) = picked {
        let path = a.language.clone().unwrap_or_else(|| run.join("language")).join(format!("picked_view{}_object{id}.png", a.view));
        s.show(a.view, Some(id), &path)?;
        eprintln!("picked object {id}; highlighted view -> {}", path.display());
    }
    Ok(())
}

#[derive(clap::Args)]
struct TrainLanguageArgs {
    /// Geometry run directory (`chatsplat train --out`).
    #[arg(long)]
    run: PathBuf,
    /// Teacher directory (`chatsplat extract --out`).
    #[arg(long)]
    teacher: PathBuf,
    /// Language run directory (default: RUN/language).
    #[arg(long)]
    out: Option<PathBuf>,
    #[arg(long)]
    iters: Option<usize>,
    /// Language feature channels per level (paper: 32).
    #[arg(long)]
    channels: Option<usize>,
    #[arg(long, value_enum, default_value_t = BackendChoice::Ndarray)]
    backend: BackendChoice,
    /// Continue from the language run's last checkpoint.
    #[arg(long)]
    resume: bool,
    /// A config.json with any LanguageTrainConfig fields (others keep their defaults).
    #[arg(long)]
    config: Option<PathBuf>,
}

fn train_language(a: TrainLanguageArgs) -> Result<(), String> {
    use train::language::{run, LanguageTrainConfig};
    let mut cfg: LanguageTrainConfig = match &a.config {
        Some(p) => serde_json::from_value(train::ckpt::read_json(p)?).map_err(|e| format!("{}: invalid language config: {e}", p.display()))?,
        None => LanguageTrainConfig::default(),
    };
    if let Some(n) = a.iters {
        cfg.iters = n;
    }
    if let Some(c) = a.channels {
        if c == 0 {
            return Err("--channels must be >= 1".into());
        }
        cfg.field.view_channels = c;
        cfg.field.object_channels = c;
    }
    let out = a.out.clone().unwrap_or_else(|| a.run.join("language"));
    let device = a.backend.device();
    let bar = Progress::new("language", "it");
    let s = catch_backend("language training", || {
        run(&a.run, &a.teacher, &out, cfg, &device, a.resume, |p| {
            if p.iter % 5 == 0 || p.iter == p.iters {
                bar.update_with(p.iter, p.iters, &format!("loss {:.4} view {:.4} obj {:.4} ({})", p.step.loss, p.step.view_l1, p.step.object_l1, p.step.objects));
            }
        })
    })??;
    if let Some(at) = s.resumed_from {
        eprintln!("resumed from iteration {at}");
    }
    println!(
        "token L1 on training views: view {:.4} -> {:.4}, object {:.4} -> {:.4}; {:.3} s/iter; {} of {} Gaussians reached a language map -> {}",
        s.before.0, s.after.0, s.before.1, s.after.1, s.seconds_per_iter, s.gaussians_used, s.gaussians, out.display()
    );
    Ok(())
}

#[derive(clap::Args)]
struct ExportEncoderArgs {
    /// Geometry run directory.
    #[arg(long)]
    run: PathBuf,
    /// Language run directory (default: RUN/language).
    #[arg(long)]
    language: Option<PathBuf>,
    /// Output .safetensors file.
    #[arg(long)]
    out: PathBuf,
}

fn export_encoder(a: ExportEncoderArgs) -> Result<(), String> {
    let lang = a.language.clone().unwrap_or_else(|| a.run.join("language"));
    let device = BackendChoice::Ndarray.device();
    let (cfg, field, _, _, _) = train::language::load_field(&lang, &device)?;
    // the teacher model id is optional metadata: a moved teacher directory does not block export
    let model_id = train::language::teacher_dir(&lang).and_then(|d| train::language::TeacherSet::open(&d)).map(|t| t.model).unwrap_or_default();
    let n = train::export::write_encoder(&a.out, &field.encoder, &cfg.field, &model_id)?;
    println!("encoder ({n} parameters, {} lifting layers, scale/shift {}) -> {}", field.encoder.lift_weights.len(), field.encoder.scale.is_some(), a.out.display());
    Ok(())
}

#[derive(clap::Args)]
struct ChatArgs {
    /// Geometry run directory with a trained `language/` run.
    #[arg(long)]
    run: PathBuf,
    /// Language run directory (default: RUN/language).
    #[arg(long)]
    language: Option<PathBuf>,
    /// Local LLaVA-OneVision directory (the one the teacher tokens came from).
    #[arg(long)]
    vlm: PathBuf,
    #[arg(long, default_value_t = 256)]
    max_new_tokens: usize,
    #[arg(long, value_enum, default_value_t = BackendChoice::Ndarray)]
    backend: BackendChoice,
}

const CHAT_HELP: &str = "commands: :view N (view level) | :click X Y (object level, in the current view) | :scene [K] (scene level) | :show (write the current view PNG) | :help | :quit; anything else is a question";

fn chat(a: ChatArgs) -> Result<(), String> {
    use eval::chat::{ChatSession, Target};
    use std::io::BufRead;
    let device = a.backend.device();
    let s = catch_backend("loading", || ChatSession::open(&a.run, a.language.as_deref(), &a.vlm, &device))??;
    let lang = a.language.clone().unwrap_or_else(|| a.run.join("language"));
    eprintln!("{} views ({} training), {} Gaussians. {CHAT_HELP}", s.cameras.len(), s.train_views, s.scene.field.len());
    let opts = model::vlm::GenerateOptions { max_new_tokens: a.max_new_tokens, ..Default::default() };
    let mut view = 0usize;
    let mut target = Target::View(0);
    let stdin = std::io::stdin();
    eprint!("[view 0] > ");
    for line in stdin.lock().lines() {
        let line = line.map_err(|e| format!("stdin: {e}"))?;
        let words: Vec<&str> = line.split_whitespace().collect();
        let num = |i: usize| words.get(i).and_then(|w| w.parse::<usize>().ok());
        match words.first().copied() {
            None => {}
            Some(":quit") | Some(":q") => break,
            Some(":help") => eprintln!("{CHAT_HELP}"),
            Some(":view") => match num(1) {
                Some(v) if v < s.cameras.len() => {
                    view = v;
                    target = Target::View(v);
                }
                _ => eprintln!("usage: :view N with N < {}", s.cameras.len()),
            },
            Some(":click") => match (num(1), num(2)) {
                (Some(x), Some(y)) => match s.scene.pick(&s.cameras[view], x, y) {
                    Ok(Some((id, _))) => {
                        let path = lang.join(format!("picked_view{view}_object{id}.png"));
                        match s.show(view, Some(id), &path) {
                            Ok(()) => eprintln!("object {id} picked; highlighted -> {}", path.display()),
                            Err(e) => eprintln!("error: {e}"),
                        }
                        target = Target::Object { view, x, y };
                    }
                    Ok(None) => eprintln!("pixel ({x}, {y}) shows no object"),
                    Err(e) => eprintln!("error: {e}"),
                },
                _ => eprintln!("usage: :click X Y"),
            },
            Some(":scene") => target = Target::Scene(s.scene_views(num(1).unwrap_or(4).max(1))),
            Some(":show") => {
                let path = lang.join(format!("view{view}.png"));
                match s.show(view, None, &path) {
                    Ok(()) => eprintln!("-> {}", path.display()),
                    Err(e) => eprintln!("error: {e}"),
                }
            }
            Some(w) if w.starts_with(':') => eprintln!("unknown command {w}; {CHAT_HELP}"),
            Some(_) => {
                match catch_backend("generation", || s.ask(&target, &line, &opts, print_piece)) {
                    Ok(Ok(_)) => println!(),
                    Ok(Err(e)) | Err(e) => eprintln!("error: {e}"),
                }
            }
        }
        let label = match &target {
            Target::View(v) => format!("view {v}"),
            Target::Object { view, x, y } => format!("view {view} object at ({x}, {y})"),
            Target::Scene(vs) => format!("scene {vs:?}"),
        };
        eprint!("[{label}] > ");
    }
    eprintln!();
    Ok(())
}

#[derive(clap::Args)]
struct DemoArgs {
    /// Output directory (data/, run/, run/language/).
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// LLaVA-OneVision directory (default: the tiny random fixture, whose answers are gibberish
    /// by construction; give a real llava-onevision-qwen2-0.5b-ov-hf directory for real answers).
    #[arg(long)]
    vlm: Option<PathBuf>,
    /// Geometry iterations.
    #[arg(long, default_value_t = 600)]
    iters: usize,
    /// Language-field iterations.
    #[arg(long, default_value_t = 100)]
    language_iters: usize,
    #[arg(long, value_enum, default_value_t = BackendChoice::Ndarray)]
    backend: BackendChoice,
}

fn demo(a: DemoArgs) -> Result<(), String> {
    let vlm = a.vlm.clone().unwrap_or_else(|| std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../checkpoints/tiny-llava-ov"));
    let (data, run, lang) = (a.out.join("data"), a.out.join("run"), a.out.join("run").join("language"));
    let step = |n: usize, what: &str| eprintln!("\n== {n}/7 {what}");
    step(1, "synthetic tabletop (32 views, 96x96)");
    synth(SynthArgs { seed: 7, out: data.clone(), views: 32, width: 96, height: 96 })?;
    step(2, "geometry stage: 3DGS + identity field");
    std::fs::create_dir_all(&a.out).map_err(|e| format!("{}: cannot create: {e}", a.out.display()))?;
    let d = a.iters;
    let geo_cfg = serde_json::json!({"iters": d, "densify_from": d / 8, "densify_every": (d / 8).max(1), "densify_until": d * 3 / 4,
        "opacity_reset_every": 0, "sh_degree_every": (d / 4).max(1), "checkpoint_every": 0});
    let cfg_path = a.out.join("geometry_config.json");
    train::ckpt::write_json(&cfg_path, &geo_cfg)?;
    train_cmd(TrainArgs { data: data.clone(), out: run.clone(), iters: None, backend: a.backend, downscale: 1, resume: false, config: Some(cfg_path), background: "white".into() })?;
    step(3, "teacher tokens (SigLIP features of every training view and masked object)");
    extract(ExtractArgs { vlm: vlm.clone(), data: data.clone(), out: Some(data.join("teacher")), downscale: 1, margin: 0.1, backend: a.backend })?;
    step(4, "language field, encoder and scaling adjustment");
    // patch 0: render maps at the views' own resolution (96 px views -> 4 px per token)
    let lang_cfg = a.out.join("language_config.json");
    train::ckpt::write_json(&lang_cfg, &serde_json::json!({"warmup_iters": (a.language_iters / 4).max(1), "field": {"patch": 0}}))?;
    train_language(TrainLanguageArgs { run: run.clone(), teacher: data.join("teacher"), out: None, iters: Some(a.language_iters), channels: None, backend: a.backend, resume: false, config: Some(lang_cfg) })?;
    step(5, "chat: view, object (click) and scene level");
    let ask_args = |object: Option<Vec<usize>>, scene: bool, q: &str| AskArgs {
        vlm: vlm.clone(), image: vec![], run: Some(run.clone()), language: None, view: 0, object, scene, views: 3,
        question: q.into(), max_new_tokens: 16, temperature: 0.0, top_p: 1.0, seed: 0, backend: a.backend,
    };
    let qf = eval::vqa::load_questions(&data.join("questions.json"))?;
    let click = qf.questions.iter().find(|q| q.level == eval::vqa::Level::Object && q.view == Some(0)).and_then(|q| q.object).map(|[x, y]| vec![x as usize, y as usize]);
    eprintln!("[view 0] What is on the table?");
    ask_scene(ask_args(None, false, "What is on the table?"))?;
    if let Some(xy) = click {
        eprintln!("[view 0, click ({}, {})] What is this object?", xy[0], xy[1]);
        ask_scene(ask_args(Some(xy), false, "What is this object?"))?;
    }
    eprintln!("[scene, 3 views] List the objects on the table.");
    ask_scene(ask_args(None, true, "List the objects on the table."))?;
    step(6, "VQA on the generated question file (offline scorer)");
    vqa(VqaArgs { run: run.clone(), language: None, vlm: vlm.clone(), questions: data.join("questions.json"), out: None, views: 3, max_new_tokens: 16, backend: a.backend })?;
    step(7, "encoder export");
    export_encoder(ExportEncoderArgs { run: run.clone(), language: None, out: lang.join("encoder.safetensors") })?;
    println!("\ndemo done: renders in {}, language run in {}, highlighted pick in {}", run.join("renders").display(), lang.display(), lang.display());
    if a.vlm.is_none() {
        println!("(answers come from the tiny random fixture and are gibberish by construction; pass --vlm with a real LLaVA-OneVision directory)");
    }
    Ok(())
}

#[derive(clap::Args)]
struct VqaArgs {
    /// Geometry run directory with a trained `language/` run.
    #[arg(long)]
    run: PathBuf,
    /// Language run directory (default: RUN/language).
    #[arg(long)]
    language: Option<PathBuf>,
    #[arg(long)]
    vlm: PathBuf,
    /// Question file (`chatsplat synth` writes DATA/questions.json).
    #[arg(long)]
    questions: PathBuf,
    /// Answers and scores as JSON (default: LANGUAGE/vqa.json).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Scene-level questions use this many views spread around the scene.
    #[arg(long, default_value_t = 4)]
    views: usize,
    #[arg(long, default_value_t = 64)]
    max_new_tokens: usize,
    #[arg(long, value_enum, default_value_t = BackendChoice::Ndarray)]
    backend: BackendChoice,
}

fn vqa(a: VqaArgs) -> Result<(), String> {
    use eval::chat::{ChatSession, Target};
    use eval::vqa::{load_questions, offline_score, summarize, Grader, Level};
    let qf = load_questions(&a.questions)?;
    let grader = Grader::from_env()?;
    let device = a.backend.device();
    let s = catch_backend("loading", || ChatSession::open(&a.run, a.language.as_deref(), &a.vlm, &device))??;
    let opts = model::vlm::GenerateOptions { max_new_tokens: a.max_new_tokens, ..Default::default() };
    let bar = Progress::new("vqa", "questions");
    let (mut offline, mut graded, mut rows) = (Vec::new(), Vec::new(), Vec::new());
    for (i, q) in qf.questions.iter().enumerate() {
        let target = match q.level {
            Level::View => Target::View(q.view.unwrap_or(0)),
            Level::Scene => Target::Scene(s.scene_views(a.views.max(1))),
            Level::Object => {
                let [x, y] = q.object.unwrap_or([0.0, 0.0]);
                Target::Object { view: q.view.unwrap_or(0), x: x.max(0.0) as usize, y: y.max(0.0) as usize }
            }
        };
        let answer = match catch_backend("generation", || s.ask(&target, &q.question, &opts, |_| {})) {
            Ok(Ok((g, _))) => g.text,
            Ok(Err(e)) | Err(e) => format!("<error: {e}>"),
        };
        let off = offline_score(&answer, &q.answer, &q.keywords);
        offline.push((q.level, off.score));
        let grade = match &grader {
            Some(g) => match g.grade(&q.question, &q.answer, &answer) {
                Ok(v) => {
                    graded.push((q.level, v));
                    Some(v)
                }
                Err(e) => {
                    eprintln!("\n{}: grader: {e}", q.id);
                    None
                }
            },
            None => None,
        };
        rows.push(serde_json::json!({"id": q.id, "level": q.level, "question": q.question, "reference": q.answer, "answer": answer, "offline": off.score, "exact": off.exact, "grader": grade}));
        bar.update(i + 1, qf.questions.len());
    }
    let out = a.out.clone().unwrap_or_else(|| a.language.clone().unwrap_or_else(|| a.run.join("language")).join("vqa.json"));
    let so = summarize(&offline);
    let sg = (!graded.is_empty()).then(|| summarize(&graded));
    let fmt = |x: Option<f32>| x.map(|v| format!("{v:.1}")).unwrap_or_else(|| "-".into());
    println!("| scorer | view | object | scene | overall | questions |\n|---|---|---|---|---|---|");
    println!("| offline (exact / keyword, 0-100) | {} | {} | {} | {} | {} |", fmt(so.view.mean), fmt(so.object.mean), fmt(so.scene.mean), fmt(so.overall.mean), so.overall.count);
    if let Some(g) = &sg {
        println!("| grader {} (0-100) | {} | {} | {} | {} | {} |", grader.as_ref().map(|g| g.model.as_str()).unwrap_or(""), fmt(g.view.mean), fmt(g.object.mean), fmt(g.scene.mean), fmt(g.overall.mean), g.overall.count);
    } else {
        eprintln!("(no grader: set CHATSPLAT_GRADER_URL, CHATSPLAT_GRADER_MODEL and CHATSPLAT_GRADER_KEY for GPT-4o-style 0-100 grades)");
    }
    train::ckpt::write_json(&out, &serde_json::json!({"questions": a.questions.display().to_string(), "answers": rows}))?;
    println!("answers -> {}", out.display());
    Ok(())
}

#[derive(clap::Args)]
struct ExtractArgs {
    /// Local Hugging Face LLaVA-OneVision directory (the teacher).
    #[arg(long)]
    vlm: PathBuf,
    /// Scene dataset (nerfstudio transforms.json or Blender layout, e.g. from `chatsplat synth`).
    #[arg(long)]
    data: PathBuf,
    /// Output directory (default: DATA/teacher).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Integer image downscale before extraction.
    #[arg(long, default_value_t = 1)]
    downscale: u32,
    /// Object crop margin as a fraction of the object's box, per side.
    #[arg(long, default_value_t = 0.1)]
    margin: f32,
    #[arg(long, value_enum, default_value_t = BackendChoice::Ndarray)]
    backend: BackendChoice,
}

fn extract(a: ExtractArgs) -> Result<(), String> {
    use train::teacher::{extract, ExtractOptions};
    if a.downscale == 0 || !(0.0..=2.0).contains(&a.margin) {
        return Err("--downscale must be >= 1 and --margin in [0, 2]".into());
    }
    let out = a.out.clone().unwrap_or_else(|| a.data.join("teacher"));
    let device = a.backend.device();
    let m = catch_backend("loading the model", || model::vlm::LlavaOnevision::load(&a.vlm, &device))?.map_err(|e| e.to_string())?;
    let opts = ExtractOptions { margin: a.margin, load: train::data::nerfstudio::LoadOptions { downscale: a.downscale, ..Default::default() }, ..Default::default() };
    let bar = Progress::new("extract", "views");
    let t0 = std::time::Instant::now();
    let summary = catch_backend("extraction", || {
        extract(
            &m,
            &a.data,
            &out,
            &opts,
            |plan| {
                let objects: usize = plan.views.iter().map(|v| v.objects.len()).sum();
                eprintln!(
                    "{} training views + {objects} object crops -> {} images of {}x{} tokens; about {:.1} MB of f16 in {}",
                    plan.views.len(),
                    plan.views.len() + objects,
                    plan.tokens_per_image,
                    plan.dim,
                    plan.bytes as f64 / 1e6,
                    out.display()
                );
            },
            |done, total| bar.update(done, total),
        )
    })??;
    println!(
        "teacher tokens: {} view files written, {} already complete (skipped), {} images encoded in {:.1} s -> {}",
        summary.written,
        summary.skipped,
        summary.images,
        t0.elapsed().as_secs_f64(),
        out.join("teacher.json").display()
    );
    Ok(())
}

#[derive(clap::Args)]
struct SynthArgs {
    /// Scene seed (object placement and sizes).
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Output directory.
    #[arg(long, default_value = "out/synth")]
    out: PathBuf,
    /// Number of views around the table.
    #[arg(long, default_value_t = 48)]
    views: usize,
    #[arg(long, default_value_t = 200)]
    width: u32,
    #[arg(long, default_value_t = 200)]
    height: u32,
}

fn synth(a: SynthArgs) -> Result<(), String> {
    let opts = train::data::synth::SynthOptions {
        seed: a.seed,
        views: a.views,
        width: a.width,
        height: a.height,
        ..Default::default()
    };
    let t0 = std::time::Instant::now();
    let bar = Progress::new("synth", "views");
    train::data::synth::write_dataset(&a.out, &opts, |done, total| bar.update(done, total))?;
    println!(
        "wrote {} views of seed {} ({}x{}) with masks, depth, transforms.json and scene.json to {} in {:.1} s",
        a.views,
        a.seed,
        a.width,
        a.height,
        a.out.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}

#[derive(clap::Args)]
struct RenderArgs {
    /// Inria-layout 3DGS .ply to render (gsplat, Inria 3DGS and Brush write this layout).
    /// Without it, the built-in synthetic tabletop is rendered.
    #[arg(long)]
    ply: Option<PathBuf>,
    /// Seed of the built-in tabletop.
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Surface sampling density of the built-in tabletop (Gaussians ~ 5 x density^2).
    #[arg(long, default_value_t = 60)]
    density: usize,
    /// Compute backend.
    #[arg(long, value_enum, default_value_t = BackendChoice::Ndarray)]
    backend: BackendChoice,
    #[arg(long, default_value_t = 640)]
    width: u32,
    #[arg(long, default_value_t = 480)]
    height: u32,
    /// Camera position "x,y,z" (default: looking at the scene from above one corner).
    #[arg(long)]
    eye: Option<String>,
    /// Point the camera looks at, "x,y,z" (default: the scene centre).
    #[arg(long)]
    target: Option<String>,
    /// World direction that appears up in the image, "x,y,z".
    #[arg(long, default_value = "0,1,0")]
    up: String,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 50.0)]
    fov: f32,
    /// Background colour "r,g,b" in [0, 1].
    #[arg(long, default_value = "1,1,1")]
    background: String,
    /// Output PNG of the colour render.
    #[arg(long, default_value = "out/render.png")]
    out: PathBuf,
    /// Also write the expected-depth map here.
    #[arg(long)]
    depth: Option<PathBuf>,
    /// Also write the top-contributor id map (one colour per Gaussian) here.
    #[arg(long)]
    ids: Option<PathBuf>,
}

fn parse_vec3(what: &str, s: &str) -> Result<Vec3, String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(format!("--{what} expects three comma-separated numbers, got `{s}`"));
    }
    let mut v = [0.0f32; 3];
    for (k, p) in parts.iter().enumerate() {
        v[k] = p
            .parse::<f32>()
            .ok()
            .filter(|x| x.is_finite())
            .ok_or_else(|| format!("--{what}: `{p}` is not a finite number"))?;
    }
    Ok(Vec3::from(v))
}

fn render(a: RenderArgs) -> Result<(), String> {
    let (cloud, source): (GaussianCloud, String) = match &a.ply {
        Some(path) => (model::ply::read(path).map_err(|e| e.to_string())?, path.display().to_string()),
        None => {
            let (cloud, objects) = model::synthetic::tabletop(a.seed, a.density);
            let names: Vec<&str> = objects.iter().map(|o| o.name).collect();
            (cloud, format!("built-in tabletop (seed {}: {})", a.seed, names.join(", ")))
        }
    };
    if cloud.is_empty() {
        return Err(format!("{source}: the scene holds no Gaussians"));
    }
    let (lo, hi) = cloud.bounds().expect("non-empty");
    let centre = match &a.target {
        Some(t) => parse_vec3("target", t)?,
        None if a.ply.is_none() => Vec3::new(0.0, 0.3, 0.0),
        None => (lo + hi) * 0.5,
    };
    let eye = match &a.eye {
        Some(e) => parse_vec3("eye", e)?,
        None if a.ply.is_none() => Vec3::new(2.6, 2.2, 3.0),
        None => centre + (hi - lo).length().max(1e-3) * Vec3::new(0.6, 0.45, 0.6),
    };
    let up = parse_vec3("up", &a.up)?;
    let bg = parse_vec3("background", &a.background)?;
    if (eye - centre).length() < 1e-6 || (eye - centre).normalize().cross(up.normalize_or_zero()).length() < 1e-4 {
        return Err("--eye, --target and --up must not be collinear".into());
    }
    if a.width == 0 || a.height == 0 || !(1.0..179.0).contains(&a.fov) {
        return Err("--width/--height must be positive and --fov within 1..179 degrees".into());
    }
    let cam = Camera::look_at(eye, centre, up, a.fov, a.width, a.height);
    let backend = a.backend;
    let t0 = std::time::Instant::now();
    let (rgb, alpha, depth, ids) = catch_backend(&format!("rendering on {backend:?}"), || {
        let device = backend.device();
        let g = cloud.to_gaussians(&device);
        let bgt = Tensor::<1>::from_data(TensorData::new(bg.to_array().to_vec(), [3]), &device);
        let out = splat(&g, &cam, bgt, &SplatOptions::default()).map_err(|e| e.to_string())?;
        let depth = out.expected_depth();
        Ok::<_, String>((
            out.features.into_data().to_vec::<f32>().expect("f32"),
            out.alpha.into_data().to_vec::<f32>().expect("f32"),
            depth.into_data().to_vec::<f32>().expect("f32"),
            out.top_id.into_data().convert::<i32>().to_vec::<i32>().expect("i32"),
        ))
    })??;
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    images::write_rgb(&a.out, a.width, a.height, &rgb)?;
    println!(
        "rendered {} Gaussians from {source} at {}x{} on {backend:?} in {ms:.1} ms -> {}",
        cloud.len(),
        a.width,
        a.height,
        a.out.display()
    );
    if let Some(p) = &a.depth {
        images::write_rgb(p, a.width, a.height, &images::depth_to_rgb(&depth, &alpha))?;
        println!("depth map -> {}", p.display());
    }
    if let Some(p) = &a.ids {
        let rgb: Vec<f32> = ids.iter().flat_map(|&i| images::id_color(i)).collect();
        images::write_rgb(p, a.width, a.height, &rgb)?;
        println!("top-contributor id map -> {}", p.display());
    }
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Render(a) => render(a),
        Command::Synth(a) => synth(a),
        Command::Ask(a) => ask(a),
        Command::Train(a) => train_cmd(a),
        Command::ExportPly(a) => export_ply(a),
        Command::Extract(a) => extract(a),
        Command::TrainLanguage(a) => train_language(a),
        Command::ExportEncoder(a) => export_encoder(a),
        Command::Chat(a) => chat(a),
        Command::Demo(a) => demo(a),
        Command::Vqa(a) => vqa(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
