//! The geometry stage: 3DGS fitted to posed photos with an object-identity field (Gaussian
//! Grouping). Loss = (1 - λ) L1 + λ (1 - SSIM) on RGB (λ = 0.2) + w · cross-entropy of the
//! classified identity map against the instance masks (when the dataset has them). Parameters are
//! stepped with burn's `Adam` (one state per named parameter, so densification can keep the
//! moments aligned row by row), with per-parameter learning rates and an exponential decay for the
//! means; the SH degree rises over time; densification clones small and splits large Gaussians by
//! the accumulated screen-space gradient, prunes transparent ones and periodically resets opacity.
//!
//! [`config`] (every knob), [`init`] (extent, initial Gaussians), [`metrics`] (SSIM, PSNR, mIoU),
//! [`trainer`] (step, densification, evaluation, checkpoints), and [`fit`] (the whole stage).

pub mod config;
pub mod init;
pub mod metrics;
pub mod trainer;

pub use config::GeometryConfig;
pub use init::{SceneExtent, initial_cloud};
pub use metrics::{miou, psnr, ssim};
pub use trainer::{EvalStats, GeometryTrainer, StepStats};

use burn::tensor::Device;
use model::data::colmap::SparsePoints;
use model::data::{Dataset, LoadOptions, View};
use model::error::{Error, Result};
use model::io;
use model::rng::Rng;
use model::run::{CameraSet, DataRef, GeometryRun, StoredCamera, StoredPath};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Classes for the identity classifier: 1 + the largest instance id in any mask (at least 2).
pub fn classes_of(ds: &Dataset) -> usize {
    ds.train
        .iter()
        .chain(&ds.test)
        .filter_map(|v| v.instance_ids.as_ref())
        .flat_map(|m| m.iter().copied())
        .max()
        .map(|m| m as usize + 1)
        .unwrap_or(1)
        .max(2)
}

/// Index of the training view used at iteration `iter` (a seeded permutation per epoch).
pub fn view_at(iter: usize, views: usize, seed: u64) -> usize {
    let epoch = iter / views.max(1);
    let mut order: Vec<usize> = (0..views).collect();
    Rng::new(seed ^ (epoch as u64).wrapping_mul(0x2545_F491_4F6C_DD1D)).shuffle(&mut order);
    order[iter % views.max(1)]
}

/// Progress of a run, reported after every iteration.
#[derive(Clone, Copy, Debug)]
pub struct Progress {
    pub iter: usize,
    pub iters: usize,
    pub loss: f32,
    pub psnr: f32,
    pub gaussians: usize,
}

/// Result of [`fit`].
#[derive(Clone, Debug)]
pub struct RunSummary {
    pub eval: EvalStats,
    pub gaussians: usize,
    pub seconds_per_iter: f64,
    pub resumed_from: Option<usize>,
}

/// `metrics.json` of a geometry run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeometryMetrics {
    pub iters: usize,
    pub gaussians: usize,
    pub psnr: f32,
    pub ssim: f32,
    pub miou: Option<f32>,
    pub eval_views: usize,
    /// Whether the figures are on held-out views (else on the training views).
    pub held_out: bool,
    pub seconds_per_iter: f64,
    /// Bytes of the per-Gaussian parameters and their two Adam moments.
    pub memory_bytes_params: usize,
}

/// Where the data of a run come from: the dataset directory and how it was loaded.
pub fn data_ref(ds: &Dataset, data_dir: &Path, load: &LoadOptions, run: &GeometryRun) -> DataRef {
    let bg = load.background.value();
    DataRef {
        dir: StoredPath::new(data_dir, &run.dir),
        downscale: load.downscale,
        background: [bg; 3],
        fingerprint: ds.fingerprint(),
        masks: ds.train.iter().chain(&ds.test).any(|v| v.instance_ids.is_some()),
        mask_dir: load.masks.as_ref().map(|m| StoredPath::new(m, &run.dir)),
    }
}

/// Trains (or resumes) a run in `out` on dataset `ds` (read from `data_dir` with `load`):
/// a first checkpoint within seconds, then checkpoints every `cfg.checkpoint_every` iterations and
/// every `cfg.checkpoint_seconds`; evaluation on the held-out views, `renders/` (render | ground
/// truth, | identity | true identity with masks), `point_cloud.ply` (Inria layout + identity),
/// `cameras.json`, `classifier.json` and `metrics.json`. Resuming a run made on another dataset
/// or downscale is refused.
#[allow(clippy::too_many_arguments)]
pub fn fit(
    ds: &Dataset,
    points: Option<&SparsePoints>,
    data_dir: &Path,
    load: &LoadOptions,
    out: &GeometryRun,
    cfg: GeometryConfig,
    device: &Device,
    resume: bool,
    mut progress: impl FnMut(Progress),
) -> Result<RunSummary> {
    cfg.validate()?;
    let data = data_ref(ds, data_dir, load, out);
    let (mut t, resumed_from) = if resume {
        if !out.checkpoint().is_file() {
            return Err(Error::invalid(&out.dir, "--resume: there is no checkpoint to resume from"));
        }
        let (mut t, stored) = GeometryTrainer::load(out, device)?;
        let (was, now) = (stored.dir.resolve(&out.dir), data_dir);
        let same_dir = std::fs::canonicalize(&was).ok() == std::fs::canonicalize(now).ok();
        // runs with a fingerprint may resume on a moved copy of the same data; older ones need the same path
        let same_data = if stored.fingerprint.is_empty() { same_dir } else { stored.fingerprint == data.fingerprint };
        if !same_data || stored.downscale != data.downscale {
            let problem = if stored.downscale != data.downscale {
                format!("was trained at downscale {}, not {}", stored.downscale, data.downscale)
            } else if same_dir {
                format!(
                    "the data in {} changed since the run was trained on it: its photos, poses, split or masks \
                     differ (fingerprint {} then, {} now; masks: {})",
                    now.display(),
                    stored.fingerprint,
                    data.fingerprint,
                    match &load.masks {
                        Some(m) => format!("--masks {}", m.display()),
                        None => "the capture's own, if any".into(),
                    }
                )
            } else {
                format!(
                    "was trained on {} (fingerprint {}), not on {} (fingerprint {}): other photos, poses, split \
                     or masks",
                    was.display(),
                    stored.fingerprint,
                    now.display(),
                    data.fingerprint
                )
            };
            return Err(Error::invalid(&out.dir, format!("--resume: the run {problem}")));
        }
        // train until the requested total (nothing more when already past it; the stored total never
        // drops below the iteration reached, so the saved state stays consistent)
        t.cfg.iters = cfg.iters.max(t.iter);
        let at = t.iter;
        crate::adam_state::warn_if_done(&out.dir, at, cfg.iters);
        (t, Some(at))
    } else {
        (GeometryTrainer::new_with_points(ds, points, cfg, device)?, None)
    };
    io::create_dir(&out.dir)?;
    write_cameras(out, ds)?;
    if resumed_from.is_none() {
        t.save(out, &data)?;
    }
    let start = std::time::Instant::now();
    let mut saved_at = std::time::Instant::now();
    let first = t.iter;
    while t.iter < t.cfg.iters {
        let v = &ds.train[view_at(t.iter, ds.train.len(), t.cfg.seed)];
        let s = t.step(v)?;
        if !s.loss.is_finite() {
            return Err(Error::Diverged { iter: t.iter, loss: s.loss, detail: String::new() });
        }
        progress(Progress { iter: t.iter, iters: t.cfg.iters, loss: s.loss, psnr: s.psnr, gaussians: t.model.len() });
        let by_iter = t.cfg.checkpoint_every > 0 && t.iter.is_multiple_of(t.cfg.checkpoint_every);
        let by_time = t.cfg.checkpoint_seconds > 0 && saved_at.elapsed().as_secs() >= t.cfg.checkpoint_seconds;
        if by_iter || by_time {
            t.save(out, &data)?;
            saved_at = std::time::Instant::now();
        }
    }
    let seconds_per_iter = start.elapsed().as_secs_f64() / (t.iter - first).max(1) as f64;
    let eval = finish(&t, ds, out, &data, seconds_per_iter)?;
    Ok(RunSummary { eval, gaussians: t.model.len(), seconds_per_iter, resumed_from })
}

/// The end of a run: the checkpoint, evaluation on the held-out views (the training views when
/// none are held out), `renders/`, `point_cloud.ply`, `classifier.json` and `metrics.json`.
pub fn finish(
    t: &GeometryTrainer,
    ds: &Dataset,
    out: &GeometryRun,
    data: &DataRef,
    seconds_per_iter: f64,
) -> Result<EvalStats> {
    t.save(out, data)?;
    let eval_views = if ds.test.is_empty() { &ds.train } else { &ds.test };
    let eval = t.evaluate(eval_views)?;
    write_renders(t, eval_views, &out.renders())?;
    let (cloud, cls) = t.model.to_cloud();
    model::ply::write(&out.point_cloud(), &cloud)?;
    let k = t.model.num_classes();
    io::write_json(&out.classifier(), &serde_json::json!({"classes": k, "weight_16xK_then_bias": cls}))?;
    let metrics = GeometryMetrics {
        iters: t.iter,
        gaussians: t.model.len(),
        psnr: eval.psnr,
        ssim: eval.ssim,
        miou: eval.miou,
        eval_views: eval.views,
        held_out: !ds.test.is_empty(),
        seconds_per_iter,
        memory_bytes_params: t.model.row_bytes() * 3,
    };
    io::write_json(&out.metrics(), &metrics)?;
    Ok(eval)
}

/// Writes the run's `cameras.json`: the cameras of the training and held-out views, what chat
/// and evaluation render from.
pub fn write_cameras(run: &GeometryRun, ds: &Dataset) -> Result<()> {
    let cameras = CameraSet {
        train: ds.train.iter().map(|v| StoredCamera::new(&v.image_path, &v.camera)).collect(),
        test: ds.test.iter().map(|v| StoredCamera::new(&v.image_path, &v.camera)).collect(),
    };
    io::write_json(&run.cameras(), &cameras)
}

/// Side-by-side renders of the first views: render | ground truth, and with masks also the
/// predicted | true identity.
fn write_renders(t: &GeometryTrainer, views: &[View], dir: &Path) -> Result<()> {
    io::create_dir(dir)?;
    for (i, v) in views.iter().enumerate().take(8) {
        let r = t.render(&v.camera)?;
        let (w, h) = (v.camera.width as usize, v.camera.height as usize);
        let panels = if v.instance_ids.is_some() { 4 } else { 2 };
        let mut img = vec![0f32; w * panels * h * 3];
        let put = |img: &mut Vec<f32>, panel: usize, src: &dyn Fn(usize) -> [f32; 3]| {
            for y in 0..h {
                for x in 0..w {
                    let c = src(y * w + x);
                    let o = (y * w * panels + panel * w + x) * 3;
                    img[o..o + 3].copy_from_slice(&c);
                }
            }
        };
        put(&mut img, 0, &|p| {
            [r.rgb[3 * p].clamp(0.0, 1.0), r.rgb[3 * p + 1].clamp(0.0, 1.0), r.rgb[3 * p + 2].clamp(0.0, 1.0)]
        });
        put(&mut img, 1, &|p| [v.rgb[3 * p], v.rgb[3 * p + 1], v.rgb[3 * p + 2]]);
        if let Some(gt) = &v.instance_ids {
            put(&mut img, 2, &|p| model::images::id_color(r.ids[p] as i32));
            put(&mut img, 3, &|p| model::images::id_color(gt[p] as i32));
        }
        let path = dir.join(format!("view_{i:03}.png"));
        model::images::write_rgb(&path, (w * panels) as u32, h as u32, &img)?;
    }
    Ok(())
}
