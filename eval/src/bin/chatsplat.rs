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
    /// LLaVA-OneVision's multi-image layout).
    #[arg(long, required = true)]
    image: Vec<PathBuf>,
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
    use model::vlm::{chat_template, GenerateOptions, LlavaOnevision, RgbImage, Turn};
    use std::io::Write;
    let imgs = a.image.iter().map(|p| RgbImage::read_png(p)).collect::<Result<Vec<_>, _>>()?;
    if !(0.0..=1.0).contains(&a.top_p) || a.top_p == 0.0 || a.temperature < 0.0 || !a.temperature.is_finite() {
        return Err("--top-p must be in (0, 1] and --temperature >= 0".into());
    }
    let device = a.backend.device();
    let t0 = std::time::Instant::now();
    let m = catch_backend("loading the model", || LlavaOnevision::load(&a.vlm, &device))?.map_err(|e| e.to_string())?;
    eprintln!("loaded {} in {:.1} s", a.vlm.display(), t0.elapsed().as_secs_f64());
    let prompt = chat_template(&[Turn::user(imgs.len(), a.question.clone())], true);
    let opts = GenerateOptions { max_new_tokens: a.max_new_tokens, temperature: a.temperature, top_p: a.top_p, seed: a.seed, ignore_stop: false };
    let t1 = std::time::Instant::now();
    let out = catch_backend("generation", || -> Result<_, model::vlm::VlmError> {
        let multi = imgs.len() > 1;
        let patches: Vec<_> = imgs.iter().map(|i| m.preprocess(i, multi)).collect();
        let counts: Vec<usize> = patches.iter().map(|p| m.num_image_tokens(p)).collect();
        let ids = m.expand_image_tokens(&m.tokenizer.encode(&prompt)?, &counts)?;
        let images: Vec<_> = patches.iter().map(|p| m.image_embeds(p)).collect();
        let embeds = m.embed_prompt(&ids, &images)?;
        m.generate(embeds, &opts, |piece| {
            print!("{piece}");
            let _ = std::io::stdout().flush();
        })
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
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
