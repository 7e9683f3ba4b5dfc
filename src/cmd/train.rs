//! `chatsplat train`: the geometry stage.

use super::bars::Bars;
use anyhow::bail;
use model::Backend;
use model::data::{Background, LoadOptions};
use model::guard::{Existing, Kind};
use model::run::GeometryRun;
use std::path::{Path, PathBuf};
use train::geometry::{GeometryConfig, fit as train_geometry};
use train::pipeline::{Observer, Stage, load_for_geometry};

#[derive(clap::Args)]
pub struct Args {
    /// Dataset directory: nerfstudio transforms.json / Blender, COLMAP (sparse/0), LLFF
    /// (poses_bounds.npy) or Replica (traj_w_c.txt); `chatsplat synth` writes one.
    #[arg(long)]
    pub data: PathBuf,
    /// Run directory (checkpoints, config.json, renders/, point_cloud.ply, metrics.json).
    #[arg(long, default_value = "out/run")]
    pub out: PathBuf,
    #[arg(long)]
    pub iters: Option<usize>,
    #[arg(long, default_value_t = Backend::Ndarray)]
    pub backend: Backend,
    /// Integer image downscale.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Instance masks from another tool (e.g. SAM + DEVA, Gaussian Grouping): DIR/<image
    /// stem>.png per image, 8- or 16-bit ids (0 = background, at most 4095) the image's size,
    /// replacing the dataset's own masks; they train the identity field that object-level chat needs.
    #[arg(long, value_name = "DIR")]
    pub masks: Option<PathBuf>,
    /// Continue from the run directory's last checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// A config.json with any GeometryConfig fields (others keep their defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Background of transparent (RGBA) images: white (default) or black.
    #[arg(long)]
    pub background: Option<String>,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let (bg, bgc) = match a.background.as_deref().unwrap_or("white") {
        "white" => (Background::White, [1.0; 3]),
        "black" => (Background::Black, [0.0; 3]),
        other => bail!("--background {other}: expected white or black"),
    };
    if a.downscale == 0 {
        bail!("--downscale must be >= 1");
    }
    let mut cfg = match &a.config {
        Some(p) => model::io::read_config::<GeometryConfig>(p)?,
        None => GeometryConfig { background: bgc, ..Default::default() },
    };
    let stored_path = GeometryRun::new(&a.out).config();
    if a.resume && stored_path.is_file() {
        let stored = model::io::read_json::<GeometryConfig>(&stored_path)?;
        let options: Vec<_> =
            a.background.iter().map(|b| ("background", format!("--background {b}"), serde_json::json!(bgc))).collect();
        super::resume::refuse_changes(&stored_path, &stored, a.config.as_deref(), &options, |_, _| false)?;
        // resuming without --iters: the run's own total
        cfg.iters = stored.iters;
    }
    if let Some(n) = a.iters {
        cfg.iters = n;
    }
    super::check_config(a.config.as_deref(), cfg.validate())?;
    let mut inputs = vec![("the --data directory", a.data.clone())];
    inputs.extend(a.masks.iter().map(|m| ("the --masks directory", m.clone())));
    // a new run replaces nothing: a folder that holds a run (whose language run would stay
    // beside the new geometry) or anything else is refused
    let existing = if a.resume {
        Existing::GoOn
    } else {
        Existing::Refuse { instead: "--resume goes on with it; a new run needs a new or empty --out" }
    };
    model::guard::output_folder("--out", &a.out, Kind::GeometryRun, existing, &inputs)?;
    let load = LoadOptions { downscale: a.downscale, background: bg, masks: a.masks.clone(), ..Default::default() };
    fit(&a.data, &load, &GeometryRun::new(&a.out), cfg, a.backend, a.resume)
}

/// Fits the geometry of the capture in `data` into `out`, with a progress bar and a summary line;
/// `resume` goes on from the run's checkpoint.
pub fn fit(
    data: &Path,
    load: &LoadOptions,
    out: &GeometryRun,
    cfg: GeometryConfig,
    backend: Backend,
    resume: bool,
) -> anyhow::Result<()> {
    cfg.validate()?;
    let (ds, points) = load_for_geometry(data, load)?;
    let mut bars = Bars::new(backend);
    bars.start(Stage::Geometry, None);
    bars.dataset(data, &ds);
    let device = backend.device()?;
    let s = model::catch_backend("training", || {
        train_geometry(&ds, points.as_ref(), data, load, out, cfg, &device, resume, |p| bars.geometry(&p))
    })??;
    bars.geometry_done(&s, out);
    Ok(())
}
