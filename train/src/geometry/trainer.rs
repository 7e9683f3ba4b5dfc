//! The geometry training state: one optimisation step, densification, evaluation, checkpoints.

use super::init::{SceneExtent, initial_cloud, logit};
use super::metrics::{miou, psnr, ssim};
use super::{GeometryConfig, classes_of};
use crate::adam_state::AdamStates;
use burn::optim::{Adam, AdamConfig};
use burn::tensor::{Device, Int, Tensor, TensorData, activation};
use model::data::colmap::SparsePoints;
use model::data::{Dataset, View};
use model::error::{Error, Result};
use model::io;
use model::rng::Rng;
use model::run::{DataRef, GeometryRun, GeometryState};
use model::splats::{IDENTITY_DIM, SplatModel, SplatParams, ViewRender, background, host};
use splat_kernels::Camera;
use splat_kernels::api::{ScreenGradAccumulator, SplatOptions, splat};

/// The training state: the model, a burn Adam state per parameter (by name), the densification
/// statistics.
pub struct GeometryTrainer {
    pub cfg: GeometryConfig,
    pub model: SplatModel,
    pub states: AdamStates,
    pub iter: usize,
    pub extent: SceneExtent,
    /// Screen-space gradient norms (NDC) per Gaussian since the last densification.
    pub screen: ScreenGradAccumulator,
    device: Device,
    adam: Adam,
}

/// Statistics of one training step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepStats {
    pub loss: f32,
    pub psnr: f32,
}

/// Evaluation figures.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EvalStats {
    pub psnr: f32,
    pub ssim: f32,
    pub miou: Option<f32>,
    pub views: usize,
}

impl GeometryTrainer {
    /// A fresh run: initial cloud from the training views, classes = 1 + the largest mask id.
    pub fn new(ds: &Dataset, cfg: GeometryConfig, device: &Device) -> Result<Self> {
        Self::new_with_points(ds, None, cfg, device)
    }

    /// As [`new`](Self::new), initialised from sparse SfM points when given.
    pub fn new_with_points(
        ds: &Dataset,
        points: Option<&SparsePoints>,
        cfg: GeometryConfig,
        device: &Device,
    ) -> Result<Self> {
        cfg.validate()?;
        if ds.train.is_empty() {
            return Err(Error::input("the dataset has no training views"));
        }
        let cams: Vec<&Camera> = ds.train.iter().map(|v| &v.camera).collect();
        let extent = SceneExtent::from_cameras(&cams);
        let mut cloud = initial_cloud(&ds.train, points, &extent, &cfg);
        let classes = classes_of(ds);
        // Identity features and classifier start random: with both at zero the cross-entropy
        // gradient of each is zero (a saddle), and only the bias would learn.
        let mut rng = Rng::new(cfg.seed ^ 0x1d);
        let n = cloud.len();
        cloud
            .extra
            .insert("identity".into(), (IDENTITY_DIM, (0..n * IDENTITY_DIM).map(|_| 0.5 * rng.normal()).collect()));
        let mut cls: Vec<f32> =
            (0..IDENTITY_DIM * classes).map(|_| rng.normal() / (IDENTITY_DIM as f32).sqrt()).collect();
        cls.extend(std::iter::repeat_n(0.0, classes));
        let model = SplatModel::from_cloud(&cloud, Some(&cls), classes, device);
        Ok(Self::with_model(model, cfg, extent, device))
    }

    pub fn with_model(model: SplatModel, cfg: GeometryConfig, extent: SceneExtent, device: &Device) -> Self {
        Self {
            states: AdamStates::default(),
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
    pub fn step(&mut self, view: &View) -> Result<StepStats> {
        let cam = &view.camera;
        let (w, h) = (cam.width as usize, cam.height as usize);
        let ad = self.device.clone().autodiff();
        let params = self.model.tensors().map(|_, t| t.autodiff().require_grad());
        let ad_model = SplatModel::from_tensors(params.clone());
        let n = ad_model.len();
        let densifying = self.iter < self.cfg.densify_until;
        let offsets = Tensor::<2>::zeros([n, 2], &ad).require_grad();
        let bg = background(self.cfg.background, &ad);
        let opts =
            SplatOptions { validate: false, screen_offsets: densifying.then(|| offsets.clone()), ..Default::default() };
        let out = splat(&ad_model.gaussians(cam, self.sh_degree()), cam, bg, &opts)?;
        let rgb = out.features.clone().narrow(2, 0, 3);
        let gt = Tensor::<3>::from_data(TensorData::new(view.rgb.clone(), [h, w, 3]), &ad);
        let l1 = (rgb.clone() - gt.clone()).abs().mean();
        let mut loss = l1 * (1.0 - self.cfg.ssim_weight);
        if self.cfg.ssim_weight > 0.0 {
            loss = loss + (ssim(rgb.clone(), gt.clone()).neg() + 1.0) * self.cfg.ssim_weight;
        }
        if let (Some(ids), true) = (&view.instance_ids, self.cfg.identity_weight > 0.0) {
            let k = ad_model.num_classes();
            let logp = activation::log_softmax(ad_model.identity_logits(out.features), 1);
            let target: Vec<i64> = ids.iter().map(|&i| (i as usize).min(k - 1) as i64).collect();
            let target = Tensor::<1, Int>::from_data(TensorData::new(target, [h * w]), &ad).reshape([h * w, 1]);
            let ce = logp.gather(1, target).mean().neg();
            loss = loss + ce * self.cfg.identity_weight;
        }
        let loss_v = host(loss.clone())[0];
        let psnr_v = psnr(&host(rgb.inner()), &view.rgb);
        let grads = loss.backward();
        if densifying && let Some(g) = offsets.grad(&grads) {
            self.screen.add_ndc(g, cam.width, cam.height);
        }
        let lrs = self.cfg.lrs(self.iter, self.extent.radius);
        let current = self.model.tensors();
        let (states, adam) = (&mut self.states, &self.adam);
        let updated = current.zip(params).zip(lrs).map(|name, ((value, param), lr)| match param.grad(&grads) {
            Some(g) => states.step(adam, name, lr, value, g),
            None => value,
        });
        self.model = SplatModel::from_tensors(updated);
        self.iter += 1;
        if densifying && self.iter >= self.cfg.densify_from && self.iter.is_multiple_of(self.cfg.densify_every.max(1)) {
            // An opacity reset needs iterations to recover: none in the last third of a reset
            // period (a 3,000-iteration run would otherwise end on a reset and render washed out).
            let recover = self.cfg.iters.saturating_sub(self.iter) >= self.cfg.opacity_reset_every / 3;
            let reset =
                self.cfg.opacity_reset_every > 0 && self.iter.is_multiple_of(self.cfg.opacity_reset_every) && recover;
            self.densify(reset);
        }
        Ok(StepStats { loss: loss_v, psnr: psnr_v })
    }

    /// Clone / split / prune by the accumulated statistics (and reset opacity when asked); keeps
    /// every parameter's Adam moments aligned with its Gaussian (new Gaussians start at zero).
    pub fn densify(&mut self, reset_opacity: bool) {
        let n = self.model.len();
        let t = self.model.tensors();
        let (scales, quats, opacities) =
            (host(t.log_scales.clone()), host(t.quats.clone()), host(t.opacity_logits.clone()));
        let scale_of = |i: usize| scales[3 * i..3 * i + 3].iter().map(|v| v.exp()).fold(0.0f32, f32::max);
        let opacity = |i: usize| 1.0 / (1.0 + (-opacities[i]).exp());
        let big = self.cfg.percent_dense * self.extent.radius;
        let mut rng = Rng::new(self.cfg.seed ^ (self.iter as u64).wrapping_mul(0x9E37_79B9));
        // Each output row: (source row, kind).
        let mut plan: Vec<(usize, Row)> = Vec::with_capacity(n);
        let room = self.cfg.max_gaussians.saturating_sub(n);
        let mut added = 0;
        let mean_grad = self.screen.mean();
        let too_big = self.cfg.prune_world_size * self.extent.radius;
        let prune_big = self.cfg.prune_world_size > 0.0
            && self.cfg.opacity_reset_every > 0
            && self.iter > self.cfg.opacity_reset_every;
        for (i, &g) in mean_grad.iter().enumerate() {
            let keep = opacity(i) >= self.cfg.prune_opacity && !(prune_big && scale_of(i) > too_big);
            let grow = g >= self.cfg.densify_grad_threshold && added < room;
            if grow && scale_of(i) <= big {
                if keep {
                    plan.push((i, Row::Kept));
                }
                plan.push((i, Row::Clone));
                added += 1;
            } else if grow {
                // Two children sampled inside the parent, each at 1/1.6 of its size.
                let s = &scales[3 * i..3 * i + 3];
                let q = &quats[4 * i..4 * i + 4];
                let rot = glam::Quat::from_xyzw(q[1], q[2], q[3], q[0]).normalize();
                for _ in 0..2 {
                    let local = glam::Vec3::new(
                        rng.normal() * s[0].exp(),
                        rng.normal() * s[1].exp(),
                        rng.normal() * s[2].exp(),
                    );
                    plan.push((i, Row::Split(rot * local)));
                }
                added += 1;
            } else if keep {
                plan.push((i, Row::Kept));
            }
        }
        let m = plan.len();
        let device = self.device.clone();
        let states = &mut self.states;
        let new = t.map(|name, tensor| {
            if !SplatParams::<()>::is_row(name) {
                return tensor;
            }
            let w = SplatParams::<()>::row_width(name);
            let src = host(tensor);
            let mut out = Vec::with_capacity(m * w);
            for &(i, kind) in &plan {
                let mut r = src[i * w..(i + 1) * w].to_vec();
                match (name, kind) {
                    ("means", Row::Split(d)) => {
                        r[0] += d.x;
                        r[1] += d.y;
                        r[2] += d.z;
                    }
                    ("log_scales", Row::Split(_)) => r.iter_mut().for_each(|v| *v -= 1.6f32.ln()),
                    _ => {}
                }
                if name == "opacity_logits" && reset_opacity {
                    r[0] = r[0].min(logit(0.01));
                }
                out.extend(r);
            }
            // Adam moments follow their rows; clones, split children and reset opacities start
            // from zero.
            let fresh = |kind: Row| kind != Row::Kept || (name == "opacity_logits" && reset_opacity);
            states.remap(name, |moment| {
                let h = host(moment);
                let mut o = Vec::with_capacity(m * w);
                for &(i, kind) in &plan {
                    if fresh(kind) {
                        o.extend(std::iter::repeat_n(0.0, w));
                    } else {
                        o.extend_from_slice(&h[i * w..(i + 1) * w]);
                    }
                }
                Tensor::from_data(TensorData::new(o, [m, w]), &device)
            });
            Tensor::from_data(TensorData::new(out, [m, w]), &device)
        });
        self.model = SplatModel::from_tensors(new);
        self.screen.reset(m);
    }

    /// Renders a view: RGB, identity, alpha.
    pub fn render(&self, cam: &Camera) -> Result<ViewRender> {
        self.model.render(cam, self.sh_degree(), self.cfg.background)
    }

    /// PSNR, SSIM and (with masks) identity mIoU averaged over `views`.
    pub fn evaluate(&self, views: &[View]) -> Result<EvalStats> {
        let (mut p, mut s, mut iou, mut n_iou) = (0.0, 0.0, 0.0, 0);
        for v in views {
            let r = self.render(&v.camera)?;
            let (w, h) = (v.camera.width as usize, v.camera.height as usize);
            p += psnr(&r.rgb, &v.rgb);
            let clamped: Vec<f32> = r.rgb.iter().map(|x| x.clamp(0.0, 1.0)).collect();
            let a = Tensor::<3>::from_data(TensorData::new(clamped, [h, w, 3]), &self.device);
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

    /// Writes the run's checkpoint (parameters, Adam moments, statistics), `config.json` and
    /// `state.json`, each through a temporary file and a rename. `data` is the dataset, its path
    /// stored relative to `run`.
    pub fn save(&self, run: &GeometryRun, data: &DataRef) -> Result<()> {
        io::create_dir(&run.dir)?;
        let mut tensors = Vec::new();
        for (name, t) in self.model.tensors().into_named() {
            tensors.push((name.to_string(), t.dims().to_vec(), host(t)));
        }
        tensors.extend(self.states.tensors());
        let n = self.model.len();
        tensors.push(("grad_sum".into(), vec![n], self.screen.norm_sum.clone()));
        tensors.push(("grad_count".into(), vec![n], self.screen.count.iter().map(|&c| c as f32).collect()));
        let state = GeometryState {
            iter: self.iter,
            adam_time: self.states.times(),
            extent: self.extent.stored(),
            gaussians: n,
            sh_degree: self.sh_degree(),
            background: self.cfg.background,
            data: data.clone(),
        };
        io::write_f32(&run.checkpoint(), tensors, None)?;
        io::write_json(&run.config(), &self.cfg)?;
        io::write_json(&run.state(), &state)
    }

    /// Restores a run saved by [`save`](Self::save), with the dataset it was trained on (its
    /// directory stored relative to the run: resolve it with `data.dir.resolve(&run.dir)`).
    pub fn load(run: &GeometryRun, device: &Device) -> Result<(Self, DataRef)> {
        let cfg: GeometryConfig = io::read_json(&run.config())?;
        cfg.validate().map_err(|e| Error::invalid(run.config(), e.to_string()))?;
        let (model, state) = run.load_model(device)?;
        crate::adam_state::check_progress(&run.state(), state.iter, cfg.iters, &state.adam_time)?;
        let path = run.checkpoint();
        let (mut tensors, _) = io::read_f32(&path)?;
        for name in SplatParams::<()>::NAMES {
            tensors.remove(name);
        }
        let n = model.len();
        let mut stat = |name: &str| {
            let (_, v) =
                tensors.remove(name).ok_or_else(|| Error::invalid(&path, format!("tensor {name} is missing")))?;
            if v.len() != n {
                return Err(Error::invalid(&path, format!("{name} has {} values for {n} Gaussians", v.len())));
            }
            Ok(v)
        };
        let (gs, gc) = (stat("grad_sum")?, stat("grad_count")?);
        let states = AdamStates::take(&state.adam_time, &mut tensors, &path, device)?;
        let mut t = Self::with_model(model, cfg, SceneExtent::from_stored(&state.extent), device);
        t.states = states;
        t.iter = state.iter;
        t.screen = ScreenGradAccumulator { norm_sum: gs, count: gc.into_iter().map(|c| c as u32).collect() };
        Ok((t, state.data))
    }
}

/// What an output row of densification is.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Row {
    /// The Gaussian, kept.
    Kept,
    /// A copy of a small Gaussian with a large gradient.
    Clone,
    /// A child of a large Gaussian, moved by this offset and shrunk.
    Split(glam::Vec3),
}
