//! The language stage's trainer: one step renders each view's (and object's) maps, encodes
//! them and steps the field, the encoder and the scaling adjustment against the teacher tokens.

use super::LanguageTrainConfig;
use crate::adam_state::{AdamStates, HostAdam};
use crate::dist::{self, Collective, Solo};
use crate::schedule::warmup_cosine;
use crate::teacher::{TeacherObject, TeacherSet};
use burn::tensor::{Device, Tensor, TensorData};
use model::ObjectId;
use model::error::{Error, Result};
use model::io;
use model::language::field::ParamGroup;
use model::language::{FrozenEncoder, LanguageField};
use model::run::{GeometryRun, LanguageRun, LanguageState, StoredPath};
use model::scene::LanguageScene;
use model::splats::host;
use splat_kernels::Camera;
use splat_kernels::blend::BlendWeights;
use std::collections::HashMap;
use std::sync::Arc;

/// Statistics of one training step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LangStep {
    pub loss: f32,
    pub view_l1: f32,
    pub object_l1: f32,
    pub objects: usize,
}

/// The training state.
pub struct LanguageTrainer {
    pub cfg: LanguageTrainConfig,
    pub scene: LanguageScene,
    pub teacher: TeacherSet,
    /// The camera of every teacher view: the training photos', then the novel views'.
    pub cameras: Vec<Camera>,
    pub states: AdamStates,
    pub iter: usize,
    /// Per-Gaussian sum of |gradient| of both feature tensors: zero = never seen by any map.
    pub contribution: Vec<f32>,
    masks: HashMap<(usize, ObjectId), (Camera, Vec<f32>)>,
    /// Blend weights of training cameras `(view, object)`.
    kept: HashMap<(usize, Option<ObjectId>), Arc<BlendWeights>>,
    /// Teacher tokens `(view, object)` as read once.
    targets: HashMap<(usize, Option<ObjectId>), Arc<Vec<f32>>>,
    /// Bytes held by `kept` and `targets` together (capped by `kept_weights_mb`).
    kept_bytes: usize,
    device: Device,
    /// The optimizer: on the host for CPU devices ([`AdamStates::step_on_host`]), else burn's
    /// Adam of the same settings.
    adam: HostAdam,
}

impl Drop for LanguageTrainer {
    /// The large blocks kept for the steps go back to the system (see [`LanguageTrainer::new`]).
    fn drop(&mut self) {
        model::alloc::keep_large_blocks(0);
    }
}

impl LanguageTrainer {
    /// A fresh language stage on a geometry run and a teacher directory.
    pub fn new(run: &GeometryRun, teacher: TeacherSet, mut cfg: LanguageTrainConfig, device: &Device) -> Result<Self> {
        cfg.validate()?;
        let ix = &teacher.index;
        cfg.field.grid = ix.grid;
        cfg.field.dim = ix.dim;
        cfg.field.teacher_image = ix.image_size;
        cfg.field.teacher_patch = ix.patch_size;
        cfg.field.tower_tail = ix.tower_tail;
        if !cfg.field.lifting {
            cfg.field.view_channels = ix.dim;
            cfg.field.object_channels = ix.dim;
        }
        let (splats, state) = run.load_model(device)?;
        let geo = &state.data.fingerprint;
        if !geo.is_empty() && !ix.fingerprint.is_empty() && *geo != ix.fingerprint {
            return Err(Error::invalid(
                teacher.dir.index(),
                format!(
                    "the teacher tokens come from {} (fingerprint {}), but the geometry run {} was trained on {} \
                     (fingerprint {geo}): extract the teacher from the run's dataset",
                    teacher.data_dir().display(),
                    ix.fingerprint,
                    run.dir.display(),
                    state.data.dir.resolve(&run.dir).display()
                ),
            ));
        }
        teacher.check_novel(&splats, run)?;
        let cameras = teacher.cameras()?;
        if cfg.field.patch == 0 {
            let (w, h) = cameras.iter().fold((0, 0), |(w, h), c| (w.max(c.width), h.max(c.height)));
            cfg.field.patch = cfg.field.auto_patch(w, h);
        }
        cfg.field.validate()?;
        let mut field = LanguageField::new(&cfg.field, splats.len(), cfg.seed, device);
        if cfg.init_scale_shift_from_teacher && cfg.field.scale_shift {
            let shape = [cfg.field.tokens(), cfg.field.dim];
            let param = |v: Vec<f32>| {
                Some(burn::module::Param::from_tensor(Tensor::from_data(TensorData::new(v, shape), device)))
            };
            let per_level = field.encoder.object_scale.is_some();
            let (a, b) = teacher_stats(&teacher, if per_level { Some(false) } else { None })?;
            field.encoder.scale = param(a);
            field.encoder.shift = param(b);
            if per_level {
                let (a, b) = teacher_stats(&teacher, Some(true))?;
                field.encoder.object_scale = param(a);
                field.encoder.object_shift = param(b);
            }
        }
        let n = splats.len();
        let scene = LanguageScene {
            cfg: cfg.field.clone(),
            splats,
            sh_degree: state.sh_degree,
            background: state.background,
            field,
            display: None,
            margin: teacher.index.object_margin,
            masks: state.data.masks,
        };
        Ok(Self::with(cfg, scene, teacher, cameras, device, n))
    }

    fn with(
        cfg: LanguageTrainConfig,
        scene: LanguageScene,
        teacher: TeacherSet,
        cameras: Vec<Camera>,
        device: &Device,
        n: usize,
    ) -> Self {
        // each step makes and frees the same large buffers (1 GB each at real size): reuse them
        if !splat_kernels::api::on_cube(device) {
            model::alloc::keep_large_blocks(model::alloc::large_block_budget());
        }
        Self {
            cfg,
            scene,
            teacher,
            cameras,
            states: AdamStates::default(),
            iter: 0,
            contribution: vec![0.0; n],
            masks: HashMap::new(),
            kept: HashMap::new(),
            targets: HashMap::new(),
            kept_bytes: 0,
            device: device.clone(),
            adam: HostAdam::new(1e-15),
        }
    }

    /// The crop camera and mask of object `obj` in training view `v` (cached: geometry is frozen).
    fn mask(&mut self, v: usize, obj: &TeacherObject) -> Result<(Camera, Vec<f32>)> {
        if let Some(m) = self.masks.get(&(v, obj.id)) {
            return Ok(m.clone());
        }
        let m = self.scene.object_crop(&self.cameras[v], obj.id, obj.bbox)?;
        self.masks.insert((v, obj.id), m.clone());
        Ok(m)
    }

    /// The blend weights of a training camera: kept from an earlier step, or found now (and kept
    /// while they fit in `kept_weights_mb`).
    fn weights(&mut self, key: (usize, Option<ObjectId>), cam: &Camera) -> Result<Arc<BlendWeights>> {
        if let Some(w) = self.kept.get(&key) {
            return Ok(w.clone());
        }
        let w = Arc::new(self.scene.blend_weights(cam)?);
        if self.fits(w.bytes()) {
            self.kept.insert(key, w.clone());
        }
        Ok(w)
    }

    /// Whether `bytes` more fit in the budget that the kept weights and tokens share (and if so,
    /// counts them).
    fn fits(&mut self, bytes: usize) -> bool {
        let fits = self.kept_bytes + bytes <= self.cfg.kept_weights_mb.saturating_mul(1 << 20);
        if fits {
            self.kept_bytes += bytes;
        }
        fits
    }

    /// Whether maps replay kept weights (a CPU backend and a budget) or are rasterised.
    fn replay(&self) -> bool {
        self.cfg.kept_weights_mb > 0 && !splat_kernels::api::on_cube(&self.device)
    }

    /// The view-level map of training view `v` with `field`.
    fn view_map(&mut self, field: &LanguageField, v: usize) -> Result<Tensor<3>> {
        let cam = self.cameras[v];
        if !self.replay() {
            return self.scene.view_map(field, &cam);
        }
        let w = self.weights((v, None), &self.scene.cfg.view_camera(&cam))?;
        self.scene.view_map_kept(field, &w)
    }

    /// Object-level tokens of object `obj` of training view `v`: its masked map with `field`,
    /// encoded by `enc` (which encodes the patches outside the mask once).
    fn object_tokens(
        &mut self,
        field: &LanguageField,
        enc: &FrozenEncoder,
        v: usize,
        obj: &TeacherObject,
    ) -> Result<Tensor<2>> {
        let (oc, mask) = self.mask(v, obj)?;
        let map = if self.replay() {
            let w = self.weights((v, Some(obj.id)), &oc)?;
            self.scene.object_map_kept(field, &w, &mask)?
        } else {
            self.scene.object_map(field, &oc, &mask)?
        };
        Ok(enc.forward_object(map, &mask))
    }

    /// `field`'s encoder frozen for the maps of one step or one evaluation: at LLaVA-OneVision's
    /// size the folded patch convolution is formed once for all of them (and its gradient
    /// taken once), not per map.
    fn frozen(&self, field: &LanguageField) -> FrozenEncoder {
        let side = self.cfg.field.map_size();
        FrozenEncoder::for_maps(field.encoder.clone(), [side, side, self.cfg.field.view_channels])
    }

    /// The teacher's tokens of view `v` (`None`) or of its object, read from disk once (and kept
    /// while they fit in the same budget as the weights).
    fn target(&mut self, v: usize, object: Option<ObjectId>) -> Result<Arc<Vec<f32>>> {
        if let Some(t) = self.targets.get(&(v, object)) {
            return Ok(t.clone());
        }
        let t = Arc::new(self.teacher.tokens(v, object)?);
        if self.fits(4 * t.len()) {
            self.targets.insert((v, object), t.clone());
        }
        Ok(t)
    }

    /// One optimisation step on training view `v`.
    pub fn step(&mut self, v: usize) -> Result<LangStep> {
        self.step_views(&[v], &Solo)
    }

    /// One optimisation step on the training views `views` (their mean loss). On a rank of a
    /// data-parallel run (`c`) every rank gets the same `views`, renders its share of them, and
    /// the gradients are averaged over the ranks ([`crate::dist`]): the step is the one a single
    /// process makes on all of them.
    pub fn step_views(&mut self, views: &[usize], c: &dyn Collective) -> Result<LangStep> {
        let mine = dist::share(views.len(), c.rank(), c.size());
        if mine.is_empty() {
            return Err(Error::input(format!(
                "language stage: {} views per step for {} ranks: every rank needs at least one (raise \
                 views_per_step to at least the ranks)",
                views.len(),
                c.size()
            )));
        }
        let ad = self.device.clone().autodiff();
        let named = self.scene.field.named();
        let params: Vec<(String, Tensor<2>)> =
            named.into_iter().map(|(n, t)| (n, t.autodiff().require_grad())).collect();
        let field = LanguageField::from_named(params.clone())?;
        let alone = views.len() == 1 && c.size() == 1;
        // each view's loss enters as `size / views` of it: averaged over the ranks, the mean
        let part = c.size() as f32 / views.len() as f32;
        let (mut loss, mut stats) = (None::<Tensor<1>>, [0f64; 4]);
        let enc = self.frozen(&field);
        for j in mine {
            let (l, lv, lo, n) = self.view_loss(&field, &enc, views[j], self.iter * views.len() + j, &ad)?;
            stats[0] += host(l.clone())[0] as f64;
            stats[1] += lv as f64;
            stats[2] += lo as f64;
            stats[3] += n as f64;
            let l = if alone { l } else { l * part };
            loss = Some(match loss {
                Some(s) => s + l,
                None => l,
            });
        }
        let loss = loss.expect("at least one view");
        c.sum_f64("the step's losses", &mut stats)?;
        let mut grads = loss.backward();
        // moved out of the gradients (a host Adam then owns each buffer: no copy of it)
        let grads: Vec<Option<Tensor<2>>> = params.iter().map(|(_, p)| p.grad_remove(&mut grads)).collect();
        let shapes: Vec<[usize; 2]> = params.iter().map(|(_, p)| p.dims()).collect();
        drop((params, field, enc));
        let grads = dist::reduce_tensors(c, grads, &shapes)?;
        let warm = warmup_cosine(self.iter, self.cfg.iters, self.cfg.warmup_iters, 1.0, self.cfg.lr_final);
        let mut new = Vec::with_capacity(shapes.len());
        // the field gives its tensors up (a hollow one stands in until the new values are in), so
        // that no second reference keeps the host Adam from updating each buffer in place
        let named = std::mem::replace(&mut self.scene.field, LanguageField::hollow(&self.device)).named();
        // a layer's fan-in: its weight's rows (`X.weight` [in, out]; `X.bias` takes X's)
        let fan_in = |name: &str| {
            let layer = name.strip_suffix(".weight").or_else(|| name.strip_suffix(".bias"))?;
            let weight = format!("{layer}.weight");
            named.iter().find(|(n, _)| *n == weight).map(|(_, t)| t.dims()[0])
        };
        let fan_ins: Vec<Option<usize>> = named.iter().map(|(n, _)| fan_in(n)).collect();
        let on_host = !splat_kernels::api::on_cube(&self.device);
        for (((name, value), g), fan_in) in named.into_iter().zip(grads).zip(fan_ins) {
            let Some(g) = g else {
                new.push((name, value));
                continue;
            };
            let group = ParamGroup::of(&name);
            if group == ParamGroup::Features {
                let c = host(g.clone().abs().sum_dim(1));
                for (acc, x) in self.contribution.iter_mut().zip(c) {
                    *acc += x;
                }
            }
            let lr = warm
                * match group {
                    ParamGroup::Features => self.cfg.lr_features,
                    ParamGroup::Encoder => self.cfg.lr_encoder * self.cfg.fan_in_factor(fan_in),
                    ParamGroup::Mixer => self.cfg.lr_mixer,
                };
            let value = if on_host {
                self.states.step_on_host(&self.adam, &name, lr, value, g)
            } else {
                self.states.step(&self.adam.config().build(), &name, lr, value, g)
            };
            new.push((name, value));
        }
        self.scene.field = LanguageField::from_named(new)?;
        self.iter += 1;
        let n = views.len() as f64;
        let mean = |x: f64| (x / n) as f32;
        Ok(LangStep {
            loss: mean(stats[0]),
            view_l1: mean(stats[1]),
            object_l1: mean(stats[2]),
            objects: stats[3] as usize,
        })
    }

    /// The loss of training view `v` with `field` (view L1 plus the weighted mean object L1 over a
    /// subset drawn by `draw`), its view and object L1 and the objects it used.
    fn view_loss(
        &mut self,
        field: &LanguageField,
        enc: &FrozenEncoder,
        v: usize,
        draw: usize,
        ad: &Device,
    ) -> Result<(Tensor<1>, f32, f32, usize)> {
        let d = self.cfg.field.dim;
        let t = self.cfg.field.tokens();
        let target = |x: Arc<Vec<f32>>| Tensor::<2>::from_data(TensorData::new(x.to_vec(), [t, d]), ad);
        let tokens = enc.forward_level(self.view_map(field, v)?, false);
        let lv = (tokens - target(self.target(v, None)?)).abs().mean();
        let mut loss = lv.clone();
        let mut objects = self.teacher.views[v].objects.clone();
        let k = self.cfg.max_objects_per_step;
        if k > 0 && objects.len() > k {
            let mut rng = model::rng::Rng::new(self.cfg.seed ^ (draw as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            rng.partial_shuffle(&mut objects, k);
            objects.truncate(k);
        }
        let mut lo_sum: Option<Tensor<1>> = None;
        for obj in &objects {
            let tok = self.object_tokens(field, enc, v, obj)?;
            let l = (tok - target(self.target(v, Some(obj.id))?)).abs().mean();
            lo_sum = Some(match lo_sum {
                Some(s) => s + l,
                None => l,
            });
        }
        let mut lo_v = 0.0;
        if let Some(s) = lo_sum {
            let lo = s / objects.len() as f32;
            lo_v = host(lo.clone())[0];
            loss = loss + lo * self.cfg.object_weight;
        }
        Ok((loss, host(lv)[0], lo_v, objects.len()))
    }

    /// Fails when the ranks' fields differ (see [`dist::check_hash`]).
    pub(super) fn check_in_step(&self, c: &dyn Collective) -> Result<()> {
        if c.size() == 1 {
            return Ok(());
        }
        let hash = self.scene.field.named().into_iter().fold(dist::HASH_START, |h, (_, t)| dist::hash_f32(h, &host(t)));
        dist::check_hash(c, hash, self.iter)
    }

    /// Mean token L1 over the training views `(view, object)` with the current field.
    pub fn token_l1(&mut self, views: &[usize]) -> Result<(f32, f32)> {
        let field = self.scene.field.clone();
        let enc = self.frozen(&field);
        self.l1_over(
            views,
            |t, v| Ok(enc.forward_level(t.view_map(&field, v)?, false)),
            |t, v, obj| t.object_tokens(&field, &enc, v, obj),
        )
    }

    /// [`token_l1`](Self::token_l1) of another scene on the same geometry, its own field and
    /// Gaussians (a [`subset`](LanguageScene::subset) of the trainer's, say), rasterised; the
    /// object crops, masks and targets are the trainer's.
    pub fn token_l1_of(&mut self, scene: &LanguageScene, views: &[usize]) -> Result<(f32, f32)> {
        self.l1_over(
            views,
            |t, v| scene.view_tokens(&scene.field, &t.cameras[v]),
            |t, v, obj| {
                let (oc, mask) = t.mask(v, obj)?;
                scene.object_tokens_with(&scene.field, &oc, &mask)
            },
        )
    }

    /// Mean token L1 (view, object) over `views` and their objects of the tokens `view` and
    /// `object` make, against the teacher's.
    fn l1_over(
        &mut self,
        views: &[usize],
        mut view: impl FnMut(&mut Self, usize) -> Result<Tensor<2>>,
        mut object: impl FnMut(&mut Self, usize, &TeacherObject) -> Result<Tensor<2>>,
    ) -> Result<(f32, f32)> {
        let (mut lv, mut lo, mut no) = (0.0, 0.0, 0);
        for &v in views {
            let tok = host(view(self, v)?);
            lv += mean_abs_diff(&tok, &self.target(v, None)?);
            for obj in self.teacher.views[v].objects.clone() {
                let tok = host(object(self, v, &obj)?);
                lo += mean_abs_diff(&tok, &self.target(v, Some(obj.id))?);
                no += 1;
            }
        }
        Ok((lv / views.len().max(1) as f32, if no > 0 { lo / no as f32 } else { 0.0 }))
    }

    /// Writes the run's checkpoint (field + Adam moments + contribution), `config.json` and
    /// `state.json`, each atomically. Non-finite values are refused and nothing is written.
    pub fn save(&self, out: &LanguageRun) -> Result<()> {
        self.write(out, &self.snapshot())
    }

    /// What a checkpoint of the current iteration holds (the tensors are shared, not copied).
    pub(super) fn snapshot(&self) -> Snapshot {
        Snapshot {
            field: self.scene.field.clone(),
            states: self.states.clone(),
            iter: self.iter,
            contribution: self.contribution.clone(),
        }
    }

    /// Writes `snap` as the run's checkpoint (see [`save`](Self::save)).
    pub(super) fn write(&self, out: &LanguageRun, snap: &Snapshot) -> Result<()> {
        let mut tensors = Vec::new();
        for (name, t) in snap.field.named() {
            tensors.push((name, t.dims().to_vec(), host(t)));
        }
        tensors.extend(snap.states.tensors());
        tensors.push(("contribution".into(), vec![snap.contribution.len()], snap.contribution.clone()));
        io::create_dir(&out.dir)?;
        io::write_f32(&out.checkpoint(), tensors, None)?;
        io::write_json(&out.config(), &self.cfg)?;
        let state = LanguageState {
            iter: snap.iter,
            adam_time: snap.states.times(),
            teacher: StoredPath::new(&self.teacher.dir.dir, &out.dir),
            teacher_model: self.teacher.index.teacher.clone(),
            margin: self.scene.margin,
            field: self.cfg.field.clone(),
        };
        io::write_json(&out.state(), &state)
    }

    /// Resumes a language run saved by [`save`](Self::save) on geometry run `run`.
    pub fn resume(run: &GeometryRun, out: &LanguageRun, device: &Device) -> Result<Self> {
        let cfg: LanguageTrainConfig = io::read_json(&out.config())?;
        cfg.validate().map_err(|e| Error::invalid(out.config(), e.to_string()))?;
        let scene = LanguageScene::load(run, out, device)?;
        let state = out.read_state()?;
        crate::adam_state::check_progress(&out.state(), state.iter, cfg.iters, &state.adam_time)?;
        let teacher = TeacherSet::open(&state.teacher.resolve(&out.dir))?;
        teacher.check_novel(&scene.splats, run)?;
        let cameras = teacher.cameras()?;
        let path = out.checkpoint();
        let (mut tensors, _) = io::read_f32(&path)?;
        let n = scene.splats.len();
        let mut t = Self::with(cfg, scene, teacher, cameras, device, n);
        t.states = AdamStates::take(&state.adam_time, &mut tensors, &path, device)?;
        let (_, contribution) =
            tensors.remove("contribution").ok_or_else(|| Error::invalid(&path, "tensor contribution is missing"))?;
        if contribution.len() != n {
            return Err(Error::invalid(
                &path,
                format!("contribution has {} values for {n} Gaussians", contribution.len()),
            ));
        }
        t.contribution = contribution;
        t.iter = state.iter;
        Ok(t)
    }
}

/// A checkpoint's content at one iteration: kept until the next step's loss has judged it.
pub(super) struct Snapshot {
    field: LanguageField,
    states: AdamStates,
    iter: usize,
    contribution: Vec<f32>,
}

fn mean_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f32>() / a.len().max(1) as f32
}

/// Per-token mean `b` and per-channel standard deviation `a` (broadcast to `[T, D]`) of the
/// teacher's view tokens (`Some(false)`), object tokens (`Some(true)`) or both (`None`).
fn teacher_stats(teacher: &TeacherSet, objects: Option<bool>) -> Result<(Vec<f32>, Vec<f32>)> {
    let (t, d) = (teacher.index.grid * teacher.index.grid, teacher.index.dim);
    let mut sum = vec![0f64; t * d];
    let mut ch_sum = vec![0f64; d];
    let mut ch_sq = vec![0f64; d];
    let mut n = 0usize;
    for (v, info) in teacher.views.iter().enumerate() {
        let mut images = Vec::new();
        if objects != Some(true) {
            images.push(None);
        }
        if objects != Some(false) {
            images.extend(info.objects.iter().map(|o| Some(o.id)));
        }
        for img in images {
            let x = teacher.tokens(v, img)?;
            n += 1;
            for (i, &val) in x.iter().enumerate() {
                sum[i] += val as f64;
                ch_sum[i % d] += val as f64;
                ch_sq[i % d] += (val as f64).powi(2);
            }
        }
    }
    let n = n.max(1) as f64;
    let cnt = n * t as f64;
    let std: Vec<f32> =
        (0..d).map(|c| ((ch_sq[c] / cnt - (ch_sum[c] / cnt).powi(2)).max(0.0).sqrt() as f32).max(1e-3)).collect();
    let a = (0..t * d).map(|i| std[i % d]).collect();
    Ok((a, sum.into_iter().map(|m| (m / n) as f32).collect()))
}
