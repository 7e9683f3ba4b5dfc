//! `chatsplat render`: a Gaussian scene (Inria-layout .ply, Niantic .spz or the built-in tabletop)
//! to PNG.

use anyhow::{Context, bail};
use burn::tensor::{Tensor, TensorData};
use glam::Vec3;
use model::{Backend, GaussianCloud, images};
use splat_kernels::Camera;
use splat_kernels::api::{SplatOptions, splat};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Gaussians to render: an Inria-layout 3DGS .ply (gsplat, Inria 3DGS and Brush write this
    /// layout) or a Niantic .spz (by its extension or its gzip magic). Without it, the built-in
    /// synthetic tabletop is rendered.
    #[arg(long)]
    ply: Option<PathBuf>,
    /// Seed of the built-in tabletop.
    #[arg(long, default_value_t = model::data::synth::DEFAULT_SEED)]
    seed: u64,
    /// Surface sampling density of the built-in tabletop (Gaussians ~ 5 x density^2).
    #[arg(long, default_value_t = 60)]
    density: usize,
    /// Compute backend.
    #[arg(long, default_value_t = Backend::Ndarray)]
    backend: Backend,
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

/// Largest image side `render` accepts (a 16384² RGB float buffer is 3 GB).
const MAX_SIDE: u32 = 16384;

fn parse_vec3(what: &str, s: &str) -> anyhow::Result<Vec3> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        bail!("--{what} expects three comma-separated numbers, got `{s}`");
    }
    let mut v = [0.0f32; 3];
    for (k, p) in parts.iter().enumerate() {
        v[k] = p
            .parse::<f32>()
            .ok()
            .filter(|x| x.is_finite())
            .with_context(|| format!("--{what}: `{p}` is not a finite number"))?;
    }
    Ok(Vec3::from(v))
}

pub fn run(a: Args) -> anyhow::Result<()> {
    if a.width == 0 || a.height == 0 || a.width > MAX_SIDE || a.height > MAX_SIDE || !(1.0..179.0).contains(&a.fov) {
        bail!("--width/--height must be within 1..={MAX_SIDE} and --fov within 1..179 degrees");
    }
    let outputs: Vec<(&str, &std::path::Path)> =
        [("--out", Some(&a.out)), ("--depth", a.depth.as_ref()), ("--ids", a.ids.as_ref())]
            .into_iter()
            .filter_map(|(o, p)| p.map(|p| (o, p.as_path())))
            .collect();
    model::io::refuse_shared_outputs(&outputs)?;
    for (option, out) in &outputs {
        let inputs: Vec<_> = a.ply.iter().map(|p| ("the --ply file", p.clone())).collect();
        model::guard::output_file(option, out, "a PNG", |h| h.starts_with(b"\x89PNG"), &inputs)?;
    }
    let (cloud, source): (GaussianCloud, String) = match &a.ply {
        Some(path) => (model::spz::read_any(path)?, path.display().to_string()),
        None => {
            let (cloud, scene) = model::data::synth::gaussians::tabletop(a.seed, a.density);
            let names: Vec<String> = scene.objects.iter().map(|o| o.name()).collect();
            (cloud, format!("built-in tabletop (seed {}: {})", a.seed, names.join(", ")))
        }
    };
    if cloud.is_empty() {
        bail!("{source}: the scene holds no Gaussians");
    }
    let (lo, hi) = cloud.bounds().expect("non-empty");
    let centre = match &a.target {
        Some(t) => parse_vec3("target", t)?,
        None if a.ply.is_none() => model::data::synth::LOOK_AT,
        None => (lo + hi) * 0.5,
    };
    let eye = match &a.eye {
        Some(e) => parse_vec3("eye", e)?,
        None if a.ply.is_none() => Vec3::new(2.0, 1.7, 2.3),
        None => centre + (hi - lo).length().max(1e-3) * Vec3::new(0.6, 0.45, 0.6),
    };
    let up = parse_vec3("up", &a.up)?;
    let bg = parse_vec3("background", &a.background)?;
    if !bg.to_array().iter().all(|c| (0.0..=1.0).contains(c)) {
        bail!("--background {}: each channel must be in [0, 1]", a.background);
    }
    if (eye - centre).length() < 1e-6 || (eye - centre).normalize().cross(up.normalize_or_zero()).length() < 1e-4 {
        bail!("--eye, --target and --up must not be collinear");
    }
    let cam = Camera::look_at(eye, centre, up, a.fov, a.width, a.height);
    let backend = a.backend;
    let t0 = std::time::Instant::now();
    let (rgb, alpha, depth, ids) = model::catch_backend(&format!("rendering on {backend}"), || {
        let device = backend.device()?;
        let g = cloud.to_gaussians(&device);
        let bgt = Tensor::<1>::from_data(TensorData::new(bg.to_array().to_vec(), [3]), &device);
        let out = splat(&g, &cam, bgt, &SplatOptions::default())?;
        let depth = out.expected_depth();
        let f32s = |t: Tensor<3>| t.into_data().to_vec::<f32>().expect("f32");
        Ok::<_, model::Error>((
            f32s(out.features),
            out.alpha.into_data().to_vec::<f32>().expect("f32"),
            depth.into_data().to_vec::<f32>().expect("f32"),
            out.top_id.into_data().convert::<i32>().to_vec::<i32>().expect("i32"),
        ))
    })??;
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    images::write_rgb(&a.out, a.width, a.height, &rgb)?;
    println!(
        "rendered {} Gaussians from {source} at {}x{} on {backend} in {ms:.1} ms -> {}",
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
