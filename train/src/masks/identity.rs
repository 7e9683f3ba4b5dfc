//! Identity on frozen geometry: a run trained without masks gets its identity field afterwards
//! from masks whose ids agree across views (`chatsplat masks`'s, or any tool's), its Gaussians
//! untouched.
//!
//! 1. [`vote_labels`]: each Gaussian takes the id whose pixels get most of its blend weight over
//!    the views (the shares of matching, every pixel counting alike).
//! 2. [`from_labels`]: identity features and a classifier sized to the scene (`1 +` the largest
//!    id) that classify each Gaussian as its vote, a code per id (one-hot up to 16 ids, seeded
//!    unit vectors past it).
//! 3. [`refine`]: cross-entropy on the masks trains the identity and classifier alone (burn
//!    autodiff through the splat op; no geometry parameter takes a gradient), so pixels where
//!    several objects blend are classified as the masks draw them.

use super::LabelMap;
use crate::adam_state::AdamStates;
use burn::optim::AdamConfig;
use burn::tensor::{Device, Int, Tensor, TensorData, activation};
use model::ObjectId;
use model::error::Result;
use model::rng::Rng;
use model::splats::{IDENTITY_DIM, SplatModel, host};
use splat_kernels::Camera;
use splat_kernels::api::{SplatOptions, splat};
use splat_kernels::blend::BlendWeights;

/// Each Gaussian's id (`[N]`, 0 = background): the id whose pixels get most of its blend weight
/// over the views ([`super::soft::Shares`]); a Gaussian no view sees is background.
pub fn vote_labels(weights: &[BlendWeights], masks: &[LabelMap]) -> Vec<u16> {
    super::soft::Shares::from_maps(weights, masks, 1.0).argmax()
}

/// The code of each of `classes` ids: one-hot while the ids in use (`used`, ascending, 0 among
/// them) fit the 16 channels, else unit vectors drawn from `seed` (nearly orthogonal; [`refine`]
/// separates what they do not); `None` for an id no Gaussian carries.
fn codes(classes: usize, used: &[u16], seed: u64) -> Vec<Option<[f32; IDENTITY_DIM]>> {
    let mut rng = Rng::new(seed ^ 0x1de7);
    let mut out = vec![None; classes];
    for (rank, &id) in used.iter().enumerate() {
        let mut c = [0f32; IDENTITY_DIM];
        if used.len() <= IDENTITY_DIM {
            c[rank] = 1.0;
        } else {
            c.iter_mut().for_each(|v| *v = rng.normal());
            let norm = c.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-6);
            c.iter_mut().for_each(|v| *v /= norm);
        }
        out[id as usize] = Some(c);
    }
    out
}

/// `model` with identity features and a classifier of `1 + max(labels)` classes (at least 2) that
/// classify Gaussian `g` as `labels[g]`; everything else as it was. Ids need not be dense: an id
/// no Gaussian carries gets no code and a bias that never wins.
///
/// A pixel's logit for id `k` is proportional to the blend weight of id `k`'s Gaussians there,
/// less a margin for every object (a pixel mostly transparent stays background, as the masks
/// count the light that passes every Gaussian as background).
pub fn from_labels(model: &SplatModel, labels: &[u16], seed: u64) -> SplatModel {
    assert_eq!(labels.len(), model.len(), "one label per Gaussian");
    let classes = (labels.iter().copied().max().unwrap_or(0) as usize + 1).max(2);
    let mut used: Vec<u16> = labels.iter().copied().chain([0]).collect();
    used.sort_unstable();
    used.dedup();
    let code = codes(classes, &used, seed);
    const SCALE: f32 = 4.0;
    const MARGIN: f32 = 0.25;
    const NEVER: f32 = -1e4;
    let identity: Vec<f32> =
        labels.iter().flat_map(|&l| code[l as usize].expect("a used id").map(|v| v * SCALE)).collect();
    // W [16, K]: column k is code k (zero for an unused id)
    let w: Vec<f32> =
        (0..IDENTITY_DIM).flat_map(|d| code.iter().map(move |c| c.map_or(0.0, |c| c[d]) * SCALE)).collect();
    let b: Vec<f32> = code
        .iter()
        .enumerate()
        .map(|(k, c)| match (k, c) {
            (0, _) => 0.0,
            (_, None) => NEVER,
            _ => -MARGIN * SCALE * SCALE,
        })
        .collect();
    let dev = model.means.val().device();
    let t = model.tensors();
    let t = model::splats::SplatParams {
        identity: Tensor::from_data(TensorData::new(identity, [labels.len(), IDENTITY_DIM]), &dev),
        classifier_w: Tensor::from_data(TensorData::new(w, [IDENTITY_DIM, classes]), &dev),
        classifier_b: Tensor::from_data(TensorData::new(b, [1, classes]), &dev),
        ..t
    };
    SplatModel::from_tensors(t)
}

/// What [`refine`] did.
pub struct Refined {
    pub model: SplatModel,
    /// Cross-entropy of every step.
    pub losses: Vec<f32>,
}

impl Refined {
    /// The mean cross-entropy of the first and of the last tenth of the steps (at least one
    /// step each; NaN without steps).
    pub fn first_and_last(&self) -> (f32, f32) {
        let k = (self.losses.len() / 10).max(1).min(self.losses.len());
        let mean = |s: &[f32]| if s.is_empty() { f32::NAN } else { s.iter().sum::<f32>() / s.len() as f32 };
        (mean(&self.losses[..k]), mean(&self.losses[self.losses.len() - k..]))
    }
}

/// Trains `model`'s identity features and classifier for `iters` steps of cross-entropy against
/// `views` (each a camera and its ids, `[H * W]`, the camera's size), one view a step in a seeded
/// order, learning rates `lr_identity` and `lr_classifier`; the geometry takes no gradient.
pub fn refine(
    model: SplatModel,
    views: &[(Camera, Vec<ObjectId>)],
    iters: usize,
    lrs: (f64, f64),
    seed: u64,
    mut progress: impl FnMut(usize, f32),
) -> Result<Refined> {
    let adam = AdamConfig::new().with_epsilon(1e-15).build();
    let mut states = AdamStates::default();
    let mut model = model;
    let mut losses = Vec::with_capacity(iters);
    for it in 0..iters {
        let (cam, ids) = &views[crate::geometry::view_at(it, views.len(), seed)];
        let ad: Device = model.means.val().device().autodiff();
        let t = model.tensors();
        let identity = t.identity.clone().autodiff().require_grad();
        let w = t.classifier_w.clone().autodiff().require_grad();
        let b = t.classifier_b.clone().autodiff().require_grad();
        let frozen = |x: Tensor<2>| x.autodiff();
        let g = splat_kernels::api::Gaussians {
            means: frozen(t.means.clone()),
            log_scales: frozen(t.log_scales.clone()),
            quats: frozen(t.quats.clone()),
            opacity_logits: frozen(t.opacity_logits.clone()).reshape([model.len()]),
            features: identity.clone(),
        };
        let opts = SplatOptions { validate: false, ..Default::default() };
        let out = splat(&g, cam, Tensor::zeros([IDENTITY_DIM], &ad), &opts)?;
        let (h, wd) = (cam.height as usize, cam.width as usize);
        let logits = out.features.reshape([h * wd, IDENTITY_DIM]).matmul(w.clone()) + b.clone();
        let k = w.dims()[1];
        let target: Vec<i64> = ids.iter().map(|&i| (i as usize).min(k - 1) as i64).collect();
        let target = Tensor::<1, Int>::from_data(TensorData::new(target, [h * wd]), &ad).reshape([h * wd, 1]);
        let loss = activation::log_softmax(logits, 1).gather(1, target).mean().neg();
        let value = host(loss.clone())[0];
        losses.push(value);
        progress(it + 1, value);
        let grads = loss.backward();
        let mut step = |name: &str, lr: f64, p: Tensor<2>, v: Tensor<2>| match p.grad(&grads) {
            Some(gr) => states.step(&adam, name, lr, v, gr),
            None => v,
        };
        let identity = step("identity", lrs.0, identity, t.identity);
        let cw = step("classifier_w", lrs.1, w, t.classifier_w);
        let cb = step("classifier_b", lrs.1, b, t.classifier_b);
        model = SplatModel::from_tensors(model::splats::SplatParams {
            identity,
            classifier_w: cw,
            classifier_b: cb,
            ..model.tensors()
        });
    }
    Ok(Refined { model, losses })
}
