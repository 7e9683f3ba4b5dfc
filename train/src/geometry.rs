//! The geometry stage: 3DGS fitted to posed photos with an object-identity field (Gaussian
//! Grouping). Loss = (1 - λ) L1 + λ (1 - SSIM) on RGB (λ = 0.2) + w · cross-entropy of the
//! classified identity map against the instance masks (when the dataset has them). Parameters are
//! stepped with burn's `Adam` (one state per parameter, so densification can keep the moments
//! aligned row by row), with per-parameter learning rates and an exponential decay for the means;
//! the SH degree rises over time; densification clones small and splits large Gaussians by the
//! accumulated screen-space gradient, prunes transparent ones and periodically resets opacity.

use crate::ckpt::{self, AdamTensors};
use crate::data::colmap::SparsePoints;
use crate::data::nerfstudio::{Dataset, View};
use burn::optim::{Adam, AdamConfig, AdamState, AdaptiveMomentumState, Optimizer};
use burn::tensor::{Device, Int, Tensor, TensorData, activation};
use model::rng::Rng;
use model::splats::{host, SplatModel, IDENTITY_DIM, ROW_PARAMS};
use model::GaussianCloud;
use serde::{Deserialize, Serialize};
use splat_kernels::api::{splat, ScreenGradAccumulator, SplatOptions};
use splat_kernels::Camera;
use std::path::Path;

/// Every knob of the geometry stage (saved beside every run as `config.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct GeometryConfig {
    pub iters: usize,
    pub seed: u64,
    /// Initial Gaussians when neither points nor depth are available (random in the scene box).
    pub init_points: usize,
    /// Pixels sampled per training view for depth-based initialisation.
    pub init_per_view: usize,
    pub lr_means: f64,
    /// The means' learning rate decays exponentially to `lr_means * lr_means_final_ratio` at `iters`.
    pub lr_means_final_ratio: f64,
    pub lr_log_scales: f64,
    pub lr_quats: f64,
    pub lr_opacity: f64,
    pub lr_sh_dc: f64,
    pub lr_sh_rest: f64,
    pub lr_identity: f64,
    pub lr_classifier: f64,
    /// λ of the D-SSIM term.
    pub ssim_weight: f32,
    /// Weight of the identity cross-entropy.
    pub identity_weight: f32,
    /// Highest SH degree, reached one step every `sh_degree_every` iterations.
    pub sh_degree: usize,
    pub sh_degree_every: usize,
    pub densify_from: usize,
    pub densify_until: usize,
    pub densify_every: usize,
    /// Screen-space gradient threshold in NDC units (3DGS: 0.0002).
    pub densify_grad_threshold: f32,
    /// Clone below / split above this fraction of the scene extent.
    pub percent_dense: f32,
    pub opacity_reset_every: usize,
    pub prune_opacity: f32,
    /// After the first opacity reset, prune Gaussians whose largest scale exceeds this fraction
    /// of the scene radius (3DGS: 0.1); 0 disables.
    pub prune_world_size: f32,
    pub max_gaussians: usize,
    /// RGB background (the dataset's RGBA background).
    pub background: [f32; 3],
    /// Save a checkpoint every this many iterations (0: only at the end).
    pub checkpoint_every: usize,
}

impl Default for GeometryConfig {
    fn default() -> Self {
        Self {
            iters: 7000,
            seed: 0,
            init_points: 20_000,
            init_per_view: 2000,
            lr_means: 1.6e-4,
            lr_means_final_ratio: 0.01,
            lr_log_scales: 5e-3,
            lr_quats: 1e-3,
            lr_opacity: 5e-2,
            lr_sh_dc: 2.5e-3,
            lr_sh_rest: 2.5e-3 / 20.0,
            lr_identity: 2.5e-3,
            lr_classifier: 5e-4,
            ssim_weight: 0.2,
            identity_weight: 1.0,
            sh_degree: 3,
            sh_degree_every: 1000,
            densify_from: 500,
            densify_until: 15_000,
            densify_every: 100,
            densify_grad_threshold: 2e-4,
            percent_dense: 0.01,
            opacity_reset_every: 3000,
            prune_opacity: 0.005,
            prune_world_size: 0.1,
            max_gaussians: 1_000_000,
            background: [1.0, 1.0, 1.0],
            checkpoint_every: 1000,
        }
    }
}

impl GeometryConfig {
    /// Learning rate of per-Gaussian parameter `i` (ROW_PARAMS order) or the classifier (7, 8) at `iter`.
    pub fn lr(&self, i: usize, iter: usize) -> f64 {
        match i {
            0 => {
                let t = (iter as f64 / self.iters.max(1) as f64).min(1.0);
                self.lr_means * self.lr_means_final_ratio.powf(t)
            }
            // (the trainer multiplies the means' rate by the scene radius, as 3DGS does)
            1 => self.lr_log_scales,
            2 => self.lr_quats,
            3 => self.lr_opacity,
            4 => self.lr_sh_dc,
            5 => self.lr_sh_rest,
            6 => self.lr_identity,
            _ => self.lr_classifier,
        }
    }
}

/// Scene bounds used for initialisation and densification.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneExtent {
    /// Mean of the camera centres.
    pub center: glam::Vec3,
    /// 1.1 x the largest camera distance from `center` (3DGS's `cameras_extent`): scales the
    /// means' learning rate and the clone/split size threshold.
    pub radius: f32,
    /// The point closest (least squares) to every camera's optical axis: what they look at.
    pub focus: glam::Vec3,
}

impl SceneExtent {
    pub fn from_cameras(cams: &[&Camera]) -> Self {
        let centers: Vec<glam::Vec3> = cams.iter().map(|c| c.world_to_cam.inverse().w_axis.truncate()).collect();
        let mean = centers.iter().fold(glam::Vec3::ZERO, |a, b| a + *b) / centers.len().max(1) as f32;
        let r = centers.iter().map(|c| (*c - mean).length()).fold(0.0f32, f32::max);
        // Least-squares point nearest to all optical axes: sum (I - d d^T) p = sum (I - d d^T) c.
        let (mut a, mut b) = (glam::DMat3::ZERO, glam::DVec3::ZERO);
        for (cam, c) in cams.iter().zip(&centers) {
            let d = cam.world_to_cam.inverse().z_axis.truncate().normalize().as_dvec3();
            let m = glam::DMat3::IDENTITY - glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z);
            a += m;
            b += m * c.as_dvec3();
        }
        let focus = if a.determinant().abs() > 1e-6 { (a.inverse() * b).as_vec3() } else { mean };
        let focus = if focus.is_finite() { focus } else { mean };
        Self { center: mean, radius: (1.1 * r).max(1e-3), focus }
    }
}

fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// Initial Gaussians: the sparse SfM points when given (COLMAP), else back-projected depth pixels
/// when the views have depth, else `cfg.init_points`
/// random points in a box around the cameras' look-at region with random colours.
pub fn initial_cloud(views: &[View], points: Option<&SparsePoints>, extent: &SceneExtent, cfg: &GeometryConfig) -> GaussianCloud {
    let mut rng = Rng::new(cfg.seed ^ 0x1517);
    let mut cloud = GaussianCloud::default();
    let push = |p: glam::Vec3, rgb: [f32; 3], cloud: &mut GaussianCloud| {
        cloud.means.push(p.to_array());
        cloud.sh_dc.push(rgb.map(|c| (c - 0.5) / model::cloud::SH_C0));
    };
    let with_depth = views.iter().any(|v| v.depth.is_some());
    if let Some(sp) = points.filter(|p| !p.xyz.is_empty()) {
        for (p, c) in sp.xyz.iter().zip(&sp.rgb) {
            push(glam::Vec3::from(*p), c.map(|v| v as f32 / 255.0), &mut cloud);
        }
    } else if with_depth {
        for v in views {
            let Some(depth) = &v.depth else { continue };
            let c = &v.camera;
            let c2w = c.world_to_cam.inverse();
            let (w, h) = (c.width as usize, c.height as usize);
            for _ in 0..cfg.init_per_view {
                let x = (rng.f() * w as f32) as usize % w;
                let y = (rng.f() * h as f32) as usize % h;
                let d = depth[y * w + x];
                if d <= 0.0 {
                    continue;
                }
                let pc = glam::Vec3::new((x as f32 + 0.5 - c.cx) / c.fx * d, (y as f32 + 0.5 - c.cy) / c.fy * d, d);
                let p = c2w.transform_point3(pc);
                let o = (y * w + x) * 3;
                push(p, [v.rgb[o], v.rgb[o + 1], v.rgb[o + 2]], &mut cloud);
            }
        }
    }
    if cloud.means.is_empty() {
        // A box around what the cameras look at; the content sits well inside their ring.
        let half = extent.radius * 0.35;
        for _ in 0..cfg.init_points {
            let p = extent.focus + glam::Vec3::new(rng.range(-half, half), rng.range(-half, half), rng.range(-half, half));
            push(p, [rng.f(), rng.f(), rng.f()], &mut cloud);
        }
    }
    let n = cloud.means.len();
    // Isotropic size ~ the mean spacing of n points in the scene box.
    let (lo, hi) = cloud.bounds().unwrap_or((glam::Vec3::ZERO, glam::Vec3::ONE));
    let vol = ((hi - lo).max(glam::Vec3::splat(1e-3))).element_product();
    let s = (vol / n.max(1) as f32).cbrt().max(1e-4) * 0.5;
    cloud.log_scales = vec![[s.ln(); 3]; n];
    cloud.quats = vec![[1.0, 0.0, 0.0, 0.0]; n];
    cloud.opacity_logits = vec![logit(0.1); n];
    cloud.rest_per_gaussian = 45;
    cloud.sh_rest = vec![0.0; n * 45];
    cloud
}

/// Separable 11-tap Gaussian blur (σ = 1.5) of `[C, H, W]` along `axis` (1 or 2), zero padded:
/// 11 shifted, weighted copies, cheap on every backend and in autodiff (a grouped 11x11
/// convolution on burn-ndarray cost ~1.9 s per 128x128 step).
fn blur_axis(x: Tensor<3>, axis: usize) -> Tensor<3> {
    let g: Vec<f32> = (0..11).map(|i| (-((i as f32 - 5.0).powi(2)) / (2.0 * 1.5f32 * 1.5)).exp()).collect();
    let sum: f32 = g.iter().sum();
    let dims = x.dims();
    let n = dims[axis];
    let mut pad_dims = dims;
    pad_dims[axis] = 5;
    let zeros = Tensor::<3>::zeros(pad_dims, &x.device());
    let padded = Tensor::cat(vec![zeros.clone(), x, zeros], axis);
    let mut out: Option<Tensor<3>> = None;
    for (k, w) in g.iter().enumerate() {
        let term = padded.clone().narrow(axis, k, n) * (w / sum);
        out = Some(match out {
            Some(o) => o + term,
            None => term,
        });
    }
    out.expect("11 taps")
}

/// Mean of a Gaussian-windowed SSIM (11x11, σ = 1.5, zero padded) between two `[H, W, 3]` images.
pub fn ssim(a: Tensor<3>, b: Tensor<3>) -> Tensor<1> {
    let blur = |x: Tensor<3>| blur_axis(blur_axis(x, 1), 2);
    let (a, b) = (a.permute([2, 0, 1]), b.permute([2, 0, 1]));
    let (mu_a, mu_b) = (blur(a.clone()), blur(b.clone()));
    let (mu_a2, mu_b2, mu_ab) = (mu_a.clone().powf_scalar(2.0), mu_b.clone().powf_scalar(2.0), mu_a * mu_b);
    let s_a = blur(a.clone() * a.clone()) - mu_a2.clone();
    let s_b = blur(b.clone() * b.clone()) - mu_b2.clone();
    let s_ab = blur(a * b) - mu_ab.clone();
    let (c1, c2) = (0.01f32 * 0.01, 0.03f32 * 0.03);
    let map = ((mu_ab * 2.0 + c1) * (s_ab * 2.0 + c2)) / ((mu_a2 + mu_b2 + c1) * (s_a + s_b + c2));
    map.mean()
}

/// PSNR (dB) of `[0,1]` images given as host slices.
pub fn psnr(a: &[f32], b: &[f32]) -> f32 {
    let mse = a.iter().zip(b).map(|(x, y)| (x.clamp(0.0, 1.0) - y) * (x.clamp(0.0, 1.0) - y)).sum::<f32>() / a.len().max(1) as f32;
    -10.0 * mse.max(1e-10).log10()
}

/// Mean IoU over the classes present in `gt` (predicted vs ground-truth id maps).
pub fn miou(pred: &[u8], gt: &[u8]) -> f32 {
    let mut ious = Vec::new();
    for class in 0..=255u8 {
        let (mut inter, mut union, mut any) = (0usize, 0usize, false);
        for (p, g) in pred.iter().zip(gt) {
            let (pp, gg) = (*p == class, *g == class);
            any |= gg;
            inter += (pp && gg) as usize;
            union += (pp || gg) as usize;
        }
        if any {
            ious.push(inter as f32 / union as f32);
        }
    }
    ious.iter().sum::<f32>() / ious.len().max(1) as f32
}

/// Renders of one view: RGB `[H,W,3]`, identity class per pixel, alpha.
pub struct ViewRender {
    pub rgb: Vec<f32>,
    pub ids: Vec<u8>,
    pub alpha: Vec<f32>,
}

/// The training state: the model, one burn Adam state per parameter, the densification statistics.
pub struct GeometryTrainer {
    pub cfg: GeometryConfig,
    pub model: SplatModel,
    pub states: Vec<Option<AdamState<2>>>,
    pub iter: usize,
    pub extent: SceneExtent,
    /// Screen-space gradient norms (NDC) per Gaussian since the last densification.
    pub screen: ScreenGradAccumulator,
    device: Device,
    adam: Adam,
}

/// Tensor names in checkpoints: the per-Gaussian rows, then the classifier.
const PARAM_NAMES: [&str; 9] = [
    ROW_PARAMS[0], ROW_PARAMS[1], ROW_PARAMS[2], ROW_PARAMS[3], ROW_PARAMS[4], ROW_PARAMS[5], ROW_PARAMS[6],
    "classifier_w", "classifier_b",
];

/// The splat background `[3 + 16]`: the RGB background, zero identity.
fn background(rgb: [f32; 3], device: &Device) -> Tensor<1> {
    let mut bg = rgb.to_vec();
    bg.extend([0.0; IDENTITY_DIM]);
    Tensor::from_data(TensorData::new(bg, [3 + IDENTITY_DIM]), device)
}

/// Identity logits `[H*W, K]` of a rendered `[H, W, 3 + 16]` feature map.
fn identity_logits(model: &SplatModel, features: Tensor<3>) -> Tensor<2> {
    let [h, w, _] = features.dims();
    let feat = features.narrow(2, 3, IDENTITY_DIM).reshape([h * w, IDENTITY_DIM]);
    feat.matmul(model.classifier_w.val()) + model.classifier_b.val()
}

/// Statistics of one training step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepStats {
    pub loss: f32,
    pub psnr: f32,
}

impl GeometryTrainer {
    /// A fresh run: initial cloud from the training views, classes = 1 + the largest mask id.
    pub fn new(ds: &Dataset, cfg: GeometryConfig, device: &Device) -> Result<Self, String> {
        Self::new_with_points(ds, None, cfg, device)
    }

    /// As [`new`](Self::new), initialised from sparse SfM points when given.
    pub fn new_with_points(ds: &Dataset, points: Option<&SparsePoints>, cfg: GeometryConfig, device: &Device) -> Result<Self, String> {
        if ds.train.is_empty() {
            return Err("the dataset has no training views".into());
        }
        let cams: Vec<&Camera> = ds.train.iter().map(|v| &v.camera).collect();
        let extent = SceneExtent::from_cameras(&cams);
        let cloud = initial_cloud(&ds.train, points, &extent, &cfg);
        let classes = classes_of(ds);
        // Identity features and classifier start random: with both at zero the cross-entropy
        // gradient of each is zero (a saddle), and only the bias would learn.
        let mut rng = Rng::new(cfg.seed ^ 0x1d);
        let n = cloud.len();
        let mut cloud = cloud;
        cloud.extra.insert("identity".into(), (IDENTITY_DIM, (0..n * IDENTITY_DIM).map(|_| 0.5 * rng.normal()).collect()));
        let mut cls: Vec<f32> = (0..IDENTITY_DIM * classes).map(|_| rng.normal() / (IDENTITY_DIM as f32).sqrt()).collect();
        cls.extend(std::iter::repeat_n(0.0, classes));
        let model = SplatModel::from_cloud(&cloud, Some(&cls), classes, device);
        Ok(Self::with_model(model, cfg, extent, device))
    }

    pub fn with_model(model: SplatModel, cfg: GeometryConfig, extent: SceneExtent, device: &Device) -> Self {
        Self {
            states: vec![None; 9],
            iter: 0,
            extent,
            screen: ScreenGradAccumulator { norm_sum: vec![0.0; model.len()], count: vec![0; model.len()] },
            model,
            cfg,
            device: device.clone(),
            adam: AdamConfig::new().with_epsilon(1e-15).build(),
        }
    }

    /// Active SH degree at the current iteration.
    pub fn sh_degree(&self) -> usize {
        (self.iter / self.cfg.sh_degree_every.max(1)).min(self.cfg.sh_degree)
    }

    /// One optimisation step on `view`.
    pub fn step(&mut self, view: &View) -> Result<StepStats, String> {
        let cam = &view.camera;
        let (w, h) = (cam.width as usize, cam.height as usize);
        let ad = self.device.clone().autodiff();
        let params: Vec<Tensor<2>> = self.model.tensors().into_iter().map(|t| t.autodiff().require_grad()).collect();
        let ad_model = SplatModel::from_tensors(params.clone().try_into().expect("9 tensors"));
        let n = ad_model.len();
        let densifying = self.iter < self.cfg.densify_until;
        let offsets = Tensor::<2>::zeros([n, 2], &ad).require_grad();
        let bg = background(self.cfg.background, &ad);
        let opts = SplatOptions { validate: false, screen_offsets: densifying.then(|| offsets.clone()), ..Default::default() };
        let out = splat(&ad_model.gaussians(cam, self.sh_degree()), cam, bg, &opts).map_err(|e| e.to_string())?;
        let rgb = out.features.clone().narrow(2, 0, 3);
        let gt = Tensor::<3>::from_data(TensorData::new(view.rgb.clone(), [h, w, 3]), &ad);
        let l1 = (rgb.clone() - gt.clone()).abs().mean();
        let mut loss = l1 * (1.0 - self.cfg.ssim_weight);
        if self.cfg.ssim_weight > 0.0 {
            loss = loss + (ssim(rgb.clone(), gt.clone()).neg() + 1.0) * self.cfg.ssim_weight;
        }
        if let (Some(ids), true) = (&view.instance_ids, self.cfg.identity_weight > 0.0) {
            let k = ad_model.num_classes();
            let logp = activation::log_softmax(identity_logits(&ad_model, out.features), 1);
            let target: Vec<i64> = ids.iter().map(|&i| (i as usize).min(k - 1) as i64).collect();
            let target = Tensor::<1, Int>::from_data(TensorData::new(target, [h * w]), &ad).reshape([h * w, 1]);
            let ce = logp.gather(1, target).mean().neg();
            loss = loss + ce * self.cfg.identity_weight;
        }
        let loss_v = host(loss.clone())[0];
        let psnr_v = psnr(&host(rgb.inner()), &view.rgb);
        let grads = loss.backward();
        if densifying {
            if let Some(g) = offsets.grad(&grads) {
                self.screen.add_ndc(g, cam.width, cam.height);
            }
        }
        let mut new = self.model.tensors();
        for (i, p) in params.iter().enumerate() {
            let Some(g) = p.grad(&grads) else { continue };
            let lr = self.cfg.lr(i, self.iter) * if i == 0 { self.extent.radius as f64 } else { 1.0 };
            let (t, s) = self.adam.step(lr, new[i].clone(), g, self.states[i].take());
            new[i] = t;
            self.states[i] = s;
        }
        self.model = SplatModel::from_tensors(new);
        self.iter += 1;
        if densifying && self.iter >= self.cfg.densify_from && self.iter % self.cfg.densify_every.max(1) == 0 {
            // An opacity reset needs iterations to recover: none in the last third of a reset period
            // (a 3,000-iteration run would otherwise end on a reset and render washed out).
            let recover = self.cfg.iters.saturating_sub(self.iter) >= self.cfg.opacity_reset_every / 3;
            let reset = self.cfg.opacity_reset_every > 0 && self.iter % self.cfg.opacity_reset_every == 0 && recover;
            self.densify(reset);
        }
        Ok(StepStats { loss: loss_v, psnr: psnr_v })
    }

    /// Clone / split / prune by the accumulated statistics (and reset opacity when asked); keeps
    /// every parameter's Adam moments aligned with its Gaussian (new Gaussians start at zero).
    pub fn densify(&mut self, reset_opacity: bool) {
        let n = self.model.len();
        let t = self.model.tensors();
        let host_rows: Vec<Vec<f32>> = t[..7].iter().map(|x| host(x.clone())).collect();
        let widths = SplatModel::row_widths();
        let scale_of = |i: usize| host_rows[1][3 * i..3 * i + 3].iter().map(|v| v.exp()).fold(0.0f32, f32::max);
        let opacity = |i: usize| 1.0 / (1.0 + (-host_rows[3][i]).exp());
        let big = self.cfg.percent_dense * self.extent.radius;
        let mut rng = Rng::new(self.cfg.seed ^ (self.iter as u64).wrapping_mul(0x9E37_79B9));
        // Each output row: (source row, kind) with kind 0 = kept, 1 = clone, 2 = split child.
        let mut plan: Vec<(usize, u8)> = Vec::with_capacity(n);
        let room = self.cfg.max_gaussians.saturating_sub(n);
        let mut added = 0;
        let mean_grad = self.screen.mean();
        let too_big = self.cfg.prune_world_size * self.extent.radius;
        let prune_big = self.cfg.prune_world_size > 0.0 && self.cfg.opacity_reset_every > 0 && self.iter > self.cfg.opacity_reset_every;
        for (i, &g) in mean_grad.iter().enumerate() {
            let keep = opacity(i) >= self.cfg.prune_opacity && !(prune_big && scale_of(i) > too_big);
            let grow = g >= self.cfg.densify_grad_threshold && added < room;
            if grow && scale_of(i) <= big {
                if keep {
                    plan.push((i, 0));
                }
                plan.push((i, 1));
                added += 1;
            } else if grow {
                plan.push((i, 2));
                plan.push((i, 2));
                added += 1;
            } else if keep {
                plan.push((i, 0));
            }
        }
        let m = plan.len();
        let mut rows: Vec<Vec<f32>> = widths.iter().map(|w| Vec::with_capacity(m * w)).collect();
        for &(src, kind) in &plan {
            for p in 0..7 {
                let w = widths[p];
                let mut r = host_rows[p][src * w..(src + 1) * w].to_vec();
                if kind == 2 {
                    if p == 0 {
                        // sample inside the Gaussian (rotated scales)
                        let s = &host_rows[1][3 * src..3 * src + 3];
                        let q = &host_rows[2][4 * src..4 * src + 4];
                        let rot = glam::Quat::from_xyzw(q[1], q[2], q[3], q[0]).normalize();
                        let local = glam::Vec3::new(rng.normal() * s[0].exp(), rng.normal() * s[1].exp(), rng.normal() * s[2].exp());
                        let d = rot * local;
                        r[0] += d.x;
                        r[1] += d.y;
                        r[2] += d.z;
                    } else if p == 1 {
                        for v in r.iter_mut() {
                            *v -= 1.6f32.ln();
                        }
                    }
                }
                if p == 3 && reset_opacity {
                    r[0] = r[0].min(logit(0.01));
                }
                rows[p].extend(r);
            }
        }
        let mut new_t = t;
        for p in 0..7 {
            new_t[p] = Tensor::from_data(TensorData::new(std::mem::take(&mut rows[p]), [m, widths[p]]), &self.device);
            // Adam moments follow their rows; clones and split children start from zero.
            if let Some(s) = self.states[p].take() {
                let remap = |x: Tensor<2>| -> Tensor<2> {
                    let h = host(x);
                    let w = widths[p];
                    let mut out = Vec::with_capacity(m * w);
                    for &(src, kind) in &plan {
                        if kind == 0 && !(p == 3 && reset_opacity) {
                            out.extend_from_slice(&h[src * w..(src + 1) * w]);
                        } else {
                            out.extend(std::iter::repeat_n(0.0, w));
                        }
                    }
                    Tensor::from_data(TensorData::new(out, [m, w]), &self.device)
                };
                let mom = s.momentum;
                let mut state = AdaptiveMomentumState::new(mom.time, remap(mom.moment_1), remap(mom.moment_2));
                state.max_moment_2 = mom.max_moment_2.map(remap);
                self.states[p] = Some(AdamState::new(state));
            }
        }
        self.model = SplatModel::from_tensors(new_t);
        self.screen.reset(m);
    }

    /// Renders a view for evaluation.
    pub fn render(&self, cam: &Camera) -> Result<ViewRender, String> {
        let bg = background(self.cfg.background, &self.device);
        let opts = SplatOptions { validate: false, ..Default::default() };
        let out = splat(&self.model.gaussians(cam, self.sh_degree()), cam, bg, &opts).map_err(|e| e.to_string())?;
        let logits = identity_logits(&self.model, out.features.clone());
        let ids: Vec<u8> = logits.argmax(1).into_data().convert::<i64>().try_to_vec::<i64>().map_err(|e| format!("{e:?}"))?.into_iter().map(|i| i as u8).collect();
        Ok(ViewRender { rgb: host(out.features.narrow(2, 0, 3)), ids, alpha: host(out.alpha) })
    }

    /// PSNR, SSIM and (with masks) identity mIoU averaged over `views`.
    pub fn evaluate(&self, views: &[View]) -> Result<EvalStats, String> {
        let (mut p, mut s, mut iou, mut n_iou) = (0.0, 0.0, 0.0, 0);
        for v in views {
            let r = self.render(&v.camera)?;
            let (w, h) = (v.camera.width as usize, v.camera.height as usize);
            p += psnr(&r.rgb, &v.rgb);
            let a = Tensor::<3>::from_data(TensorData::new(r.rgb.iter().map(|x| x.clamp(0.0, 1.0)).collect::<Vec<_>>(), [h, w, 3]), &self.device);
            let b = Tensor::<3>::from_data(TensorData::new(v.rgb.clone(), [h, w, 3]), &self.device);
            s += host(ssim(a, b))[0];
            if let Some(ids) = &v.instance_ids {
                iou += miou(&r.ids, ids);
                n_iou += 1;
            }
        }
        let k = views.len().max(1) as f32;
        Ok(EvalStats { psnr: p / k, ssim: s / k, miou: (n_iou > 0).then(|| iou / n_iou as f32), views: views.len() })
    }

    /// Writes `dir/checkpoint.safetensors` (parameters, Adam moments, statistics) and
    /// `dir/config.json` / `dir/state.json`, each through a temporary file and a rename.
    pub fn save(&self, dir: &Path) -> Result<(), String> {
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: cannot create: {e}", dir.display()))?;
        let mut tensors = Vec::new();
        for (i, t) in self.model.tensors().into_iter().enumerate() {
            tensors.push((PARAM_NAMES[i].to_string(), t.dims().to_vec(), host(t)));
            tensors.extend(AdamTensors::of(PARAM_NAMES[i], self.states[i].as_ref()).tensors());
        }
        let n = self.model.len();
        tensors.push(("grad_sum".into(), vec![n], self.screen.norm_sum.clone()));
        tensors.push(("grad_count".into(), vec![n], self.screen.count.iter().map(|&c| c as f32).collect()));
        let state = serde_json::json!({
            "iter": self.iter,
            "adam_time": self.states.iter().map(|s| s.as_ref().map(|s| s.momentum.time)).collect::<Vec<_>>(),
            "extent_center": self.extent.center.to_array(),
            "extent_radius": self.extent.radius,
            "extent_focus": self.extent.focus.to_array(),
            "gaussians": n,
        });
        ckpt::write_f32(&dir.join("checkpoint.safetensors"), tensors, None)?;
        ckpt::write_json(&dir.join("config.json"), &serde_json::to_value(&self.cfg).expect("config JSON"))?;
        ckpt::write_json(&dir.join("state.json"), &state)
    }

    /// Restores a run saved by [`save`](Self::save).
    pub fn load(dir: &Path, device: &Device) -> Result<Self, String> {
        let cfg_path = dir.join("config.json");
        let cfg: GeometryConfig = serde_json::from_value(ckpt::read_json(&cfg_path)?).map_err(|e| format!("{}: invalid config: {e}", cfg_path.display()))?;
        let state = ckpt::read_json(&dir.join("state.json"))?;
        let ck_path = dir.join("checkpoint.safetensors");
        let (mut tensors, _) = ckpt::read_f32(&ck_path)?;
        let mut get = |name: &str| tensors.remove(name).ok_or_else(|| format!("{}: tensor {name} missing", ck_path.display()));
        let to2 = |(s, v): (Vec<usize>, Vec<f32>)| -> Result<Tensor<2>, String> {
            if s.len() != 2 {
                return Err(format!("{}: expected a rank-2 tensor, got {s:?}", ck_path.display()));
            }
            Ok(Tensor::from_data(TensorData::new(v, [s[0], s[1]]), device))
        };
        let mut ts = Vec::new();
        for name in PARAM_NAMES {
            ts.push(to2(get(name)?)?);
        }
        let (gs, gc) = (get("grad_sum")?.1, get("grad_count")?.1);
        let times = state["adam_time"].as_array().cloned().unwrap_or_default();
        let mut states = Vec::new();
        for (i, name) in PARAM_NAMES.iter().enumerate() {
            let time = times.get(i).and_then(|t| t.as_u64()).map(|t| t as usize);
            states.push(AdamTensors::take(name, time, &mut tensors, device).map_err(|e| format!("{}: {e}", ck_path.display()))?);
        }
        let model = SplatModel::from_tensors(ts.try_into().map_err(|_| "9 tensors".to_string())?);
        let n = model.len();
        let v3 = |key: &str| -> glam::Vec3 {
            let c: Vec<f32> = state[key].as_array().map(|a| a.iter().filter_map(|x| x.as_f64()).map(|x| x as f32).collect()).unwrap_or_default();
            if c.len() == 3 { glam::Vec3::new(c[0], c[1], c[2]) } else { glam::Vec3::ZERO }
        };
        let extent = SceneExtent { center: v3("extent_center"), radius: state["extent_radius"].as_f64().unwrap_or(1.0) as f32, focus: v3("extent_focus") };
        let mut t = Self::with_model(model, cfg, extent, device);
        t.states = states;
        t.iter = state["iter"].as_u64().ok_or_else(|| format!("{}: no iter", dir.join("state.json").display()))? as usize;
        if gs.len() != n || gc.len() != n {
            return Err(format!("{}: statistics do not match {n} Gaussians", ck_path.display()));
        }
        t.screen = ScreenGradAccumulator { norm_sum: gs, count: gc.into_iter().map(|c| c as u32).collect() };
        Ok(t)
    }
}

/// Evaluation figures.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EvalStats {
    pub psnr: f32,
    pub ssim: f32,
    pub miou: Option<f32>,
    pub views: usize,
}

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
    let mut rng = Rng::new(seed ^ (epoch as u64).wrapping_mul(0x2545_F491_4F6C_DD1D));
    for i in (1..order.len()).rev() {
        let j = (rng.next_u64() % (i as u64 + 1)) as usize;
        order.swap(i, j);
    }
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

/// Result of [`run`].
#[derive(Clone, Debug)]
pub struct RunSummary {
    pub eval: EvalStats,
    pub gaussians: usize,
    pub seconds_per_iter: f64,
    pub resumed_from: Option<usize>,
}

/// Trains (or resumes) a run in `out`: checkpoints every `cfg.checkpoint_every` iterations,
/// evaluation on the held-out views, `renders/` (render | ground truth | identity side by side),
/// `point_cloud.ply` (Inria layout + identity), `classifier.json` and `metrics.json`.
pub fn run(
    ds: &Dataset,
    points: Option<&SparsePoints>,
    out: &Path,
    cfg: GeometryConfig,
    device: &Device,
    resume: bool,
    mut progress: impl FnMut(Progress),
) -> Result<RunSummary, String> {
    let (mut t, resumed_from) = if resume && out.join("checkpoint.safetensors").exists() {
        let mut t = GeometryTrainer::load(out, device)?;
        t.cfg.iters = cfg.iters.max(t.cfg.iters);
        let at = t.iter;
        (t, Some(at))
    } else {
        (GeometryTrainer::new_with_points(ds, points, cfg, device)?, None)
    };
    let start = std::time::Instant::now();
    let first = t.iter;
    while t.iter < t.cfg.iters {
        let v = &ds.train[view_at(t.iter, ds.train.len(), t.cfg.seed)];
        let s = t.step(v)?;
        if !s.loss.is_finite() {
            return Err(format!("loss became {} at iteration {}", s.loss, t.iter));
        }
        progress(Progress { iter: t.iter, iters: t.cfg.iters, loss: s.loss, psnr: s.psnr, gaussians: t.model.len() });
        if t.cfg.checkpoint_every > 0 && t.iter % t.cfg.checkpoint_every == 0 {
            t.save(out)?;
        }
    }
    let seconds_per_iter = start.elapsed().as_secs_f64() / (t.iter - first).max(1) as f64;
    t.save(out)?;
    let eval_views = if ds.test.is_empty() { &ds.train } else { &ds.test };
    let eval = t.evaluate(eval_views)?;
    write_renders(&t, eval_views, &out.join("renders"))?;
    let (cloud, cls) = t.model.to_cloud();
    model::ply::write(&out.join("point_cloud.ply"), &cloud).map_err(|e| e.to_string())?;
    let k = t.model.num_classes();
    std::fs::write(out.join("classifier.json"), serde_json::json!({"classes": k, "weight_16xK_then_bias": cls}).to_string())
        .map_err(|e| format!("{}: {e}", out.join("classifier.json").display()))?;
    let metrics = serde_json::json!({
        "iters": t.iter, "gaussians": t.model.len(), "psnr": eval.psnr, "ssim": eval.ssim, "miou": eval.miou,
        "eval_views": eval.views, "held_out": !ds.test.is_empty(), "seconds_per_iter": seconds_per_iter,
        "memory_bytes_params": t.model.len() * (SplatModel::row_widths().iter().sum::<usize>()) * 4 * 3,
    });
    std::fs::write(out.join("metrics.json"), serde_json::to_string_pretty(&metrics).unwrap()).map_err(|e| format!("{}: {e}", out.join("metrics.json").display()))?;
    Ok(RunSummary { eval, gaussians: t.model.len(), seconds_per_iter, resumed_from })
}

fn write_renders(t: &GeometryTrainer, views: &[View], dir: &Path) -> Result<(), String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: cannot create: {e}", dir.display()))?;
    for (i, v) in views.iter().enumerate().take(8) {
        let r = t.render(&v.camera)?;
        let (w, h) = (v.camera.width as usize, v.camera.height as usize);
        let panels = 2 + usize::from(v.instance_ids.is_some()) + 1;
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
        put(&mut img, 0, &|p| [r.rgb[3 * p].clamp(0.0, 1.0), r.rgb[3 * p + 1].clamp(0.0, 1.0), r.rgb[3 * p + 2].clamp(0.0, 1.0)]);
        put(&mut img, 1, &|p| [v.rgb[3 * p], v.rgb[3 * p + 1], v.rgb[3 * p + 2]]);
        put(&mut img, 2, &|p| model::images::id_color(r.ids[p] as i32));
        if let Some(gt) = &v.instance_ids {
            put(&mut img, 3, &|p| model::images::id_color(gt[p] as i32));
        }
        let path = dir.join(format!("view_{i:03}.png"));
        model::images::write_rgb(&path, (w * panels) as u32, h as u32, &img)?;
    }
    Ok(())
}
