//! `chatsplat identity` on files: a geometry run and the capture's views with masks whose ids
//! agree across views (`--masks`), written as a new run whose Gaussians are the old run's, with an
//! identity field sized to the masks' objects.

use super::LabelMap;
use super::identity::{from_labels, refine, vote_labels};
use crate::geometry::{EvalStats, GeometryTrainer, data_ref, finish, write_cameras};
use burn::tensor::Device;
use model::data::{Dataset, LoadOptions};
use model::error::{Error, Result};
use model::run::GeometryRun;
use std::path::Path;

/// How the identity is fitted.
#[derive(Clone, Debug, PartialEq)]
pub struct IdentityOptions {
    /// Cross-entropy steps after the vote (0: the vote alone).
    pub iters: usize,
    /// Adam's learning rates of the identity features and of the classifier (the codes start
    /// at length 4: larger steps than the geometry stage's, which starts from noise).
    pub lrs: (f64, f64),
}

impl Default for IdentityOptions {
    fn default() -> Self {
        Self { iters: 300, lrs: (0.02, 0.01) }
    }
}

/// What [`identity_run`] did.
#[derive(Clone, Debug)]
pub struct IdentitySummary {
    /// Classes of the identity classifier (1 + the largest id).
    pub classes: usize,
    /// Gaussians voted into an object (not the background).
    pub object_gaussians: usize,
    pub gaussians: usize,
    /// Mean cross-entropy of the first and last tenth of the refining steps (NaN without steps).
    pub first_loss: f32,
    pub last_loss: f32,
    /// Evaluation of the new run (identity mIoU against the masks of the held-out views, or the
    /// training views when none are held out).
    pub eval: EvalStats,
    pub seconds: f64,
}

/// Gives the Gaussians of `run` an identity field from the masks of `ds` (loaded from `data_dir`
/// with `load`, its `--masks` the consistent ids) and writes the result as the run `out`:
/// geometry, SH and their optimizer state unchanged, the identity and classifier new (their
/// optimizer state dropped).
#[allow(clippy::too_many_arguments)]
pub fn identity_run(
    run: &GeometryRun,
    ds: &Dataset,
    data_dir: &Path,
    load: &LoadOptions,
    out: &GeometryRun,
    opts: &IdentityOptions,
    device: &Device,
    progress: impl FnMut(usize, f32),
) -> Result<IdentitySummary> {
    let t0 = std::time::Instant::now();
    let (mut t, stored) = GeometryTrainer::load(run, device)?;
    check_same_views(run, ds, stored.downscale, load.downscale)?;
    let views: Vec<_> = ds.train.iter().filter(|v| v.instance_ids.is_some()).collect();
    if views.is_empty() {
        let masks = load.masks.as_deref().unwrap_or(data_dir);
        return Err(Error::invalid(masks, "gives none of the training views a mask: there is no identity to fit"));
    }
    let weights = views.iter().map(|v| t.model.blend_weights(&v.camera)).collect::<Result<Vec<_>>>()?;
    let maps: Vec<LabelMap> = views.iter().filter_map(|v| LabelMap::of_view(v)).collect();
    let labels = vote_labels(&weights, &maps);
    drop(weights);
    let voted = from_labels(&t.model, &labels, t.cfg.seed);
    let targets: Vec<_> = views.iter().map(|v| (v.camera, v.instance_ids.clone().expect("a mask"))).collect();
    let refined = refine(voted, &targets, opts.iters, opts.lrs, t.cfg.seed, progress)?;
    let (first_loss, last_loss) = refined.first_and_last();
    t.model = refined.model;
    for name in ["identity", "classifier_w", "classifier_b"] {
        t.states.forget(name);
    }
    let data = data_ref(ds, data_dir, load, out);
    model::io::create_dir(&out.dir)?;
    write_cameras(out, ds)?;
    let eval = finish(&t, ds, out, &data, 0.0)?;
    Ok(IdentitySummary {
        classes: t.model.num_classes(),
        object_gaussians: labels.iter().filter(|&&l| l != 0).count(),
        gaussians: labels.len(),
        first_loss,
        last_loss,
        eval,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Refuses a dataset whose views are not the run's (other images, sizes or downscale).
fn check_same_views(run: &GeometryRun, ds: &Dataset, run_downscale: u32, downscale: u32) -> Result<()> {
    if run_downscale != downscale {
        return Err(Error::invalid(
            &run.dir,
            format!("was trained at downscale {run_downscale}, not {downscale}: give --downscale {run_downscale}"),
        ));
    }
    let cams = run.read_cameras()?;
    let stem = |p: &str| super::files::stem(p);
    let ours: Vec<(String, u32, u32)> =
        cams.train.iter().chain(&cams.test).map(|c| (stem(&c.image), c.camera().width, c.camera().height)).collect();
    let theirs: Vec<(String, u32, u32)> = ds
        .train
        .iter()
        .chain(&ds.test)
        .map(|v| (stem(&v.image_path.to_string_lossy()), v.camera.width, v.camera.height))
        .collect();
    if ours != theirs {
        return Err(Error::invalid(
            &run.dir,
            format!(
                "was trained on other views than the capture's {} views ({} in the run): give the capture \
                 the run was trained on",
                theirs.len(),
                ours.len()
            ),
        ));
    }
    Ok(())
}
