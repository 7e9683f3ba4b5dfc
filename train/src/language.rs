//! The language stage (ChatSplat, Sec. 3.5): with the geometry, opacity and identity frozen,
//! train the per-Gaussian view- and object-level language features, the encoder and the scaling
//! adjustment so that encoded rendered maps reproduce the teacher's SigLIP tokens.
//!
//! Loss per training view: `L1(Encoder(view map), teacher(view))` + mean over the view's objects
//! of `L1(Encoder(MaskOut(object map, rendered identity mask)), teacher(masked object image))`.
//! The object map is rendered with a camera that frames the same square crop the teacher saw
//! (box + margin, padded square), so each token covers the same part of the picture, and only the
//! tiles of that crop are rasterised. Parameters are stepped with burn's `Adam`, one state per
//! tensor (paper: lr 0.05 for features and encoder).

use crate::ckpt::{self, AdamTensors};
use crate::data::nerfstudio::{self, Dataset, LoadOptions, View};
use crate::geometry::GeometryTrainer;
use crate::teacher;
use burn::optim::{Adam, AdamConfig, AdamState, Optimizer};
use burn::tensor::{Device, Tensor, TensorData};
use model::language::{mask_out, object_box, LanguageConfig, LanguageField};
use model::splats::host;
use serde::{Deserialize, Serialize};
use splat_kernels::api::{splat, SplatOptions};
use splat_kernels::{Camera, Gaussians};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Every knob of the language stage (saved beside the run as `config.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LanguageTrainConfig {
    pub field: LanguageConfig,
    pub iters: usize,
    pub seed: u64,
    /// Adam learning rate of the per-Gaussian language features (paper: 0.05).
    pub lr_features: f64,
    /// Adam learning rate of the encoder and the scaling adjustment (paper: 0.05).
    pub lr_encoder: f64,
    /// Weight of the object loss (paper: 1).
    pub object_weight: f32,
    /// Objects per step (a seeded random subset of the view's objects; 0 = all, as in the
    /// paper). A subset gives an unbiased estimate of the mean object loss at a fraction of the
    /// renders, which is what a CPU needs.
    pub max_objects_per_step: usize,
    /// Linear warm-up of both learning rates over the first iterations (0 = none). Adam's first
    /// steps move every weight by about the learning rate, which at 0.05 throws the patch
    /// convolution (fan-in 14·14·D) far off before it recovers.
    pub warmup_iters: usize,
    /// Initialise the scaling adjustment from the teacher: `b` = per-token mean over the training
    /// views, `a` = per-channel standard deviation, so the encoder starts on standardised targets.
    pub init_scale_shift_from_teacher: bool,
    /// Save a checkpoint every this many iterations (0: only at the end).
    pub checkpoint_every: usize,
}

impl Default for LanguageTrainConfig {
    fn default() -> Self {
        Self {
            field: LanguageConfig::default(),
            iters: 3000,
            seed: 0,
            lr_features: 0.05,
            lr_encoder: 0.05,
            object_weight: 1.0,
            max_objects_per_step: 0,
            warmup_iters: 100,
            init_scale_shift_from_teacher: true,
            checkpoint_every: 500,
        }
    }
}

/// One object of one teacher view.
#[derive(Clone, Debug, PartialEq)]
pub struct TeacherObject {
    pub id: u8,
    /// `[x0, y0, x1, y1)` crop box in view pixels.
    pub bbox: [usize; 4],
}

/// One training view's teacher file.
#[derive(Clone, Debug, PartialEq)]
pub struct TeacherViewInfo {
    pub file: PathBuf,
    pub objects: Vec<TeacherObject>,
}

/// A teacher directory written by `chatsplat extract` (teacher.json + one file per view).
#[derive(Clone, Debug)]
pub struct TeacherSet {
    pub dir: PathBuf,
    pub data: PathBuf,
    pub grid: usize,
    pub dim: usize,
    pub margin: f32,
    pub downscale: u32,
    pub model: String,
    pub views: Vec<TeacherViewInfo>,
}

impl TeacherSet {
    /// Reads `dir/teacher.json` and every view file's object boxes.
    pub fn open(dir: &Path) -> Result<Self, String> {
        let path = dir.join("teacher.json");
        let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: {e} (run `chatsplat extract` first)", path.display()))?;
        let j: serde_json::Value = serde_json::from_str(&text).map_err(|e| format!("{}: invalid JSON: {e}", path.display()))?;
        let field = |k: &str| j.get(k).ok_or_else(|| format!("{}: missing \"{k}\"", path.display()));
        let grid = field("grid")?.as_u64().ok_or_else(|| format!("{}: \"grid\" is not a number", path.display()))? as usize;
        let dim = field("dim")?.as_u64().ok_or_else(|| format!("{}: \"dim\" is not a number", path.display()))? as usize;
        let data = PathBuf::from(field("data")?.as_str().ok_or_else(|| format!("{}: \"data\" is not a string", path.display()))?);
        let margin = j.get("object_margin").and_then(|m| m.as_f64()).unwrap_or(0.1) as f32;
        let downscale = j.get("downscale").and_then(|m| m.as_u64()).unwrap_or(1) as u32;
        let model = j.get("teacher").and_then(|m| m.as_str()).unwrap_or("").to_string();
        let mut views = Vec::new();
        for (i, v) in field("views")?.as_array().ok_or_else(|| format!("{}: \"views\" is not a list", path.display()))?.iter().enumerate() {
            let file = dir.join(v.get("file").and_then(|f| f.as_str()).ok_or_else(|| format!("{}: views[{i}] has no file", path.display()))?);
            let objects = read_boxes(&file)?;
            views.push(TeacherViewInfo { file, objects });
        }
        Ok(Self { dir: dir.to_path_buf(), data, grid, dim, margin, downscale, model, views })
    }

    /// The dataset the tokens were extracted from (same split and downscale).
    pub fn dataset(&self) -> Result<Dataset, String> {
        let ds = nerfstudio::load(&self.data, &LoadOptions { downscale: self.downscale, ..Default::default() })?;
        if ds.train.len() != self.views.len() {
            return Err(format!("{}: {} teacher views but the dataset {} has {} training views", self.dir.display(), self.views.len(), self.data.display(), ds.train.len()));
        }
        Ok(ds)
    }

    /// Tokens `[grid * grid * dim]` of the view (`None`) or of object `id`.
    pub fn tokens(&self, view: usize, object: Option<u8>) -> Result<Vec<f32>, String> {
        let name = object.map(|id| format!("object_{id}")).unwrap_or_else(|| "view".into());
        let (shape, v) = teacher::read_tokens(&self.views[view].file, &name)?;
        if shape != [self.grid, self.grid, self.dim] {
            return Err(format!("{}: {name} has shape {shape:?}, expected [{g}, {g}, {d}]", self.views[view].file.display(), g = self.grid, d = self.dim));
        }
        Ok(v)
    }
}

fn read_boxes(file: &Path) -> Result<Vec<TeacherObject>, String> {
    let bytes = std::fs::read(file).map_err(|e| format!("{}: {e}", file.display()))?;
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes).map_err(|e| format!("{}: not a valid safetensors file: {e}", file.display()))?;
    let boxes = meta.metadata().as_ref().and_then(|m| m.get("boxes_xyxy").cloned()).unwrap_or_default();
    let mut out = Vec::new();
    for item in boxes.split_whitespace() {
        let bad = || format!("{}: malformed box \"{item}\" in boxes_xyxy", file.display());
        let (id, rest) = item.split_once(':').ok_or_else(bad)?;
        let c: Vec<usize> = rest.split(',').map(|x| x.parse().map_err(|_| bad())).collect::<Result<_, _>>()?;
        if c.len() != 4 || c[2] <= c[0] || c[3] <= c[1] {
            return Err(bad());
        }
        out.push(TeacherObject { id: id.parse().map_err(|_| bad())?, bbox: [c[0], c[1], c[2], c[3]] });
    }
    Ok(out)
}

/// A trained (or training) language field with its frozen geometry: renders maps, encodes them
/// into tokens, picks objects. Used by training, chat and evaluation.
pub struct LanguageScene {
    pub cfg: LanguageConfig,
    pub geometry: GeometryTrainer,
    pub field: LanguageField,
    /// Crop margin of object tokens (the teacher's).
    pub margin: f32,
}

/// Zero background of `c` channels.
fn zeros_bg(c: usize, device: &Device) -> Tensor<1> {
    Tensor::zeros([c], device)
}

impl LanguageScene {
    /// Frozen Gaussians carrying `features` (`[N, C]`, on `features`' device).
    pub fn gaussians(&self, features: Tensor<2>) -> Gaussians {
        let ad = features.is_autodiff();
        let m = &self.geometry.model;
        let n = m.len();
        let on = |t: Tensor<2>| if ad { t.autodiff() } else { t };
        Gaussians {
            means: on(m.means.val()),
            log_scales: on(m.log_scales.val()),
            quats: on(m.quats.val()),
            opacity_logits: on(m.opacity_logits.val()).reshape([n]),
            features,
        }
    }

    /// Renders `features` `[N, C]` from `cam`: `[H, W, C]`.
    pub fn render_map(&self, features: Tensor<2>, cam: &Camera) -> Result<Tensor<3>, String> {
        let c = features.dims()[1];
        let bg = zeros_bg(c, &features.device());
        let opts = SplatOptions { validate: false, ..Default::default() };
        Ok(splat(&self.gaussians(features), cam, bg, &opts).map_err(|e| e.to_string())?.features)
    }

    /// View-level tokens `[T, D]` of a view camera.
    pub fn view_tokens(&self, field: &LanguageField, cam: &Camera) -> Result<Tensor<2>, String> {
        let map = self.render_map(field.view_features.val(), &self.cfg.view_camera(cam))?;
        Ok(field.encoder.forward(map))
    }

    /// The object crop camera and its `[r, r]` 0/1 mask of object `id` (rendered identity,
    /// restricted to the view's frame, as the teacher's crop was).
    pub fn object_crop(&self, cam: &Camera, id: u8, bbox: [usize; 4]) -> Result<(Camera, Vec<f32>), String> {
        let oc = self.cfg.object_camera(cam, bbox);
        let r = self.geometry.render(&oc)?;
        let size = oc.width as usize;
        let mut mask = vec![0f32; size * size];
        for y in 0..size {
            for x in 0..size {
                // pixel centre back in view pixels
                let vx = (x as f32 + 0.5 - oc.cx) / oc.fx * cam.fx + cam.cx;
                let vy = (y as f32 + 0.5 - oc.cy) / oc.fy * cam.fy + cam.cy;
                let inside = vx >= bbox[0] as f32 && vy >= bbox[1] as f32 && vx < bbox[2] as f32 && vy < bbox[3] as f32;
                if inside && r.ids[y * size + x] == id {
                    mask[y * size + x] = 1.0;
                }
            }
        }
        Ok((oc, mask))
    }

    /// Object-level tokens `[T, D]` of object `id` through its crop camera and mask.
    pub fn object_tokens_with(&self, field: &LanguageField, oc: &Camera, mask: &[f32]) -> Result<Tensor<2>, String> {
        let feats = field.object_features.val();
        let dev = feats.device();
        let size = oc.width as usize;
        let map = self.render_map(feats, oc)?;
        let mask = Tensor::<2>::from_data(TensorData::new(mask.to_vec(), [size, size]), &dev);
        Ok(field.encoder.forward_level(mask_out(map, mask), true))
    }

    /// Rendered identity of a view: `[H, W]` object ids.
    pub fn identity(&self, cam: &Camera) -> Result<Vec<u8>, String> {
        Ok(self.geometry.render(cam)?.ids)
    }

    /// The object under pixel `(x, y)` of `cam` and its crop box (from the rendered identity);
    /// `None` for the background (id 0) or outside the image.
    pub fn pick(&self, cam: &Camera, x: usize, y: usize) -> Result<Option<(u8, [usize; 4])>, String> {
        let (w, h) = (cam.width as usize, cam.height as usize);
        if x >= w || y >= h {
            return Ok(None);
        }
        let ids = self.identity(cam)?;
        let id = ids[y * w + x];
        if id == 0 {
            return Ok(None);
        }
        Ok(object_box(&ids, w, h, id, self.margin).map(|b| (id, b)))
    }

    /// Object tokens for a click at `(x, y)`: `(id, tokens)`.
    pub fn object_tokens_at(&self, cam: &Camera, x: usize, y: usize) -> Result<Option<(u8, Tensor<2>)>, String> {
        let Some((id, bbox)) = self.pick(cam, x, y)? else { return Ok(None) };
        let (oc, mask) = self.object_crop(cam, id, bbox)?;
        Ok(Some((id, self.object_tokens_with(&self.field, &oc, &mask)?)))
    }

    /// The scene restricted to Gaussians `keep` (row indices): "model only what a scene needs".
    pub fn subset(&self, keep: &[usize]) -> LanguageScene {
        let dev = self.geometry.model.means.val().device();
        let idx = Tensor::<1, burn::tensor::Int>::from_data(TensorData::new(keep.iter().map(|&i| i as i64).collect::<Vec<_>>(), [keep.len()]), &dev);
        let rows = |t: Tensor<2>| t.select(0, idx.clone());
        let mut g = self.geometry.model.tensors();
        for t in g.iter_mut().take(7) {
            *t = rows(t.clone());
        }
        let model = model::splats::SplatModel::from_tensors(g);
        let mut geometry = GeometryTrainer::with_model(model, self.geometry.cfg.clone(), self.geometry.extent, &dev);
        geometry.iter = self.geometry.iter; // same SH degree
        let mut named = self.field.named();
        for (n, t) in named.iter_mut() {
            if n == "view_features" || n == "object_features" {
                *t = rows(t.clone());
            }
        }
        let field = LanguageField::from_named(named).expect("same tensors");
        LanguageScene { cfg: self.cfg.clone(), geometry, field, margin: self.margin }
    }

    /// Loads a geometry run and its language run.
    pub fn load(run: &Path, language: &Path, device: &Device) -> Result<Self, String> {
        let geometry = GeometryTrainer::load(run, device)?;
        let (cfg, field, _, margin, _) = load_field(language, device)?;
        if field.len() != geometry.model.len() {
            return Err(format!("{}: {} Gaussians, but the geometry run {} has {}", language.display(), field.len(), run.display(), geometry.model.len()));
        }
        Ok(Self { cfg: cfg.field, geometry, field, margin })
    }
}

/// Highlights object `id` in red over a rendered RGB view (the paper's picked-object display):
/// `rgb` `[H, W, 3]`, `ids` `[H, W]`.
pub fn highlight(rgb: &[f32], ids: &[u8], id: u8) -> Vec<f32> {
    let mut out = rgb.to_vec();
    for (p, &i) in ids.iter().enumerate() {
        let c = &mut out[3 * p..3 * p + 3];
        if i == id {
            c[0] = 0.45 * c[0].clamp(0.0, 1.0) + 0.55;
            c[1] *= 0.45;
            c[2] *= 0.45;
        } else {
            for v in c.iter_mut() {
                *v = 0.35 * v.clamp(0.0, 1.0) + 0.2;
            }
        }
    }
    out
}

/// `k` training views spread around the scene (farthest-point sampling on camera centres,
/// starting from view 0), for scene-level chat.
pub fn spread_views(cams: &[Camera], k: usize) -> Vec<usize> {
    let centres: Vec<glam::Vec3> = cams.iter().map(|c| c.world_to_cam.inverse().w_axis.truncate()).collect();
    let mut chosen = Vec::new();
    if centres.is_empty() {
        return chosen;
    }
    chosen.push(0);
    let mut dist: Vec<f32> = centres.iter().map(|c| c.distance(centres[0])).collect();
    while chosen.len() < k.min(centres.len()) {
        let (i, _) = dist.iter().enumerate().fold((0, -1.0), |b, (i, &d)| if d > b.1 { (i, d) } else { b });
        chosen.push(i);
        for (j, c) in centres.iter().enumerate() {
            dist[j] = dist[j].min(c.distance(centres[i]));
        }
    }
    chosen
}

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
    pub views: Vec<View>,
    pub states: Vec<Option<AdamState<2>>>,
    pub iter: usize,
    /// Per-Gaussian sum of |gradient| of both feature tensors: zero = never seen by any map.
    pub contribution: Vec<f32>,
    masks: HashMap<(usize, u8), (Camera, Vec<f32>)>,
    device: Device,
    adam: Adam,
}

impl LanguageTrainer {
    /// A fresh language stage on a geometry run and a teacher directory.
    pub fn new(run: &Path, teacher: TeacherSet, mut cfg: LanguageTrainConfig, device: &Device) -> Result<Self, String> {
        cfg.field.grid = teacher.grid;
        cfg.field.dim = teacher.dim;
        if !cfg.field.lifting {
            cfg.field.view_channels = teacher.dim;
            cfg.field.object_channels = teacher.dim;
        }
        let geometry = GeometryTrainer::load(run, device)?;
        let views = teacher.dataset()?.train;
        if cfg.field.patch == 0 {
            let (w, h) = views.iter().fold((0, 0), |(w, h), v| (w.max(v.camera.width), h.max(v.camera.height)));
            cfg.field.patch = cfg.field.auto_patch(w, h);
        }
        cfg.field.validate()?;
        let mut field = LanguageField::new(&cfg.field, geometry.model.len(), cfg.seed, device);
        if cfg.init_scale_shift_from_teacher && cfg.field.scale_shift {
            let shape = [cfg.field.tokens(), cfg.field.dim];
            let param = |v: Vec<f32>| Some(burn::module::Param::from_tensor(Tensor::from_data(TensorData::new(v, shape), device)));
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
        let n = geometry.model.len();
        let scene = LanguageScene { cfg: cfg.field.clone(), geometry, field, margin: teacher.margin };
        let count = scene.field.named().len();
        Ok(Self { cfg, scene, teacher, views, states: vec![None; count], iter: 0, contribution: vec![0.0; n], masks: HashMap::new(), device: device.clone(), adam: AdamConfig::new().with_epsilon(1e-15).build() })
    }

    /// The crop camera and mask of object `id` in training view `v` (cached: geometry is frozen).
    fn mask(&mut self, v: usize, obj: &TeacherObject) -> Result<(Camera, Vec<f32>), String> {
        if let Some(m) = self.masks.get(&(v, obj.id)) {
            return Ok(m.clone());
        }
        let m = self.scene.object_crop(&self.views[v].camera, obj.id, obj.bbox)?;
        self.masks.insert((v, obj.id), m.clone());
        Ok(m)
    }

    /// One optimisation step on training view `v`.
    pub fn step(&mut self, v: usize) -> Result<LangStep, String> {
        let ad = self.device.clone().autodiff();
        let named = self.scene.field.named();
        let names: Vec<String> = named.iter().map(|(n, _)| n.clone()).collect();
        let params: Vec<Tensor<2>> = named.into_iter().map(|(_, t)| t.autodiff().require_grad()).collect();
        let field = LanguageField::from_named(names.iter().cloned().zip(params.iter().cloned()).collect())?;
        let d = self.cfg.field.dim;
        let t = self.cfg.field.tokens();
        let target = |x: Vec<f32>| Tensor::<2>::from_data(TensorData::new(x, [t, d]), &ad);
        let cam = self.views[v].camera;
        let tokens = self.scene.view_tokens(&field, &cam)?;
        let lv = (tokens - target(self.teacher.tokens(v, None)?)).abs().mean();
        let mut loss = lv.clone();
        let mut objects = self.teacher.views[v].objects.clone();
        let k = self.cfg.max_objects_per_step;
        if k > 0 && objects.len() > k {
            let mut rng = model::rng::Rng::new(self.cfg.seed ^ (self.iter as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
            for i in 0..k {
                let j = i + (rng.next_u64() % (objects.len() - i) as u64) as usize;
                objects.swap(i, j);
            }
            objects.truncate(k);
        }
        let mut lo_sum: Option<Tensor<1>> = None;
        for obj in &objects {
            let (oc, mask) = self.mask(v, obj)?;
            let tok = self.scene.object_tokens_with(&field, &oc, &mask)?;
            let l = (tok - target(self.teacher.tokens(v, Some(obj.id))?)).abs().mean();
            lo_sum = Some(match lo_sum { Some(s) => s + l, None => l });
        }
        let mut lo_v = 0.0;
        if let Some(s) = lo_sum {
            let lo = s / objects.len() as f32;
            lo_v = host(lo.clone())[0];
            loss = loss + lo * self.cfg.object_weight;
        }
        let lv_v = host(lv)[0];
        let loss_v = host(loss.clone())[0];
        let grads = loss.backward();
        let mut new: Vec<Tensor<2>> = self.scene.field.named().into_iter().map(|(_, t)| t).collect();
        for (i, p) in params.iter().enumerate() {
            let Some(g) = p.grad(&grads) else { continue };
            if i < 2 {
                let c = host(g.clone().abs().sum_dim(1));
                for (acc, x) in self.contribution.iter_mut().zip(c) {
                    *acc += x;
                }
            }
            let warm = if self.cfg.warmup_iters > 0 { ((self.iter + 1) as f64 / self.cfg.warmup_iters as f64).min(1.0) } else { 1.0 };
            let lr = warm * if i < 2 { self.cfg.lr_features } else { self.cfg.lr_encoder };
            let (t, s) = self.adam.step(lr, new[i].clone(), g, self.states[i].take());
            new[i] = t;
            self.states[i] = s;
        }
        self.scene.field = LanguageField::from_named(names.into_iter().zip(new).collect())?;
        self.iter += 1;
        Ok(LangStep { loss: loss_v, view_l1: lv_v, object_l1: lo_v, objects: objects.len() })
    }

    /// Mean token L1 over the training views `(view, object)` with the current field.
    pub fn token_l1(&mut self, views: &[usize]) -> Result<(f32, f32), String> {
        let (mut lv, mut lo, mut no) = (0.0, 0.0, 0);
        for &v in views {
            let cam = self.views[v].camera;
            let tok = host(self.scene.view_tokens(&self.scene.field, &cam)?);
            lv += mean_abs_diff(&tok, &self.teacher.tokens(v, None)?);
            for obj in self.teacher.views[v].objects.clone() {
                let (oc, mask) = self.mask(v, &obj)?;
                let tok = host(self.scene.object_tokens_with(&self.scene.field, &oc, &mask)?);
                lo += mean_abs_diff(&tok, &self.teacher.tokens(v, Some(obj.id))?);
                no += 1;
            }
        }
        Ok((lv / views.len().max(1) as f32, if no > 0 { lo / no as f32 } else { 0.0 }))
    }

    /// Writes `dir/language.safetensors` (field + Adam moments + contribution), `config.json`
    /// and `state.json`, each atomically.
    pub fn save(&self, dir: &Path) -> Result<(), String> {
        let mut tensors = Vec::new();
        let mut adam = Vec::new();
        for (i, (name, t)) in self.scene.field.named().into_iter().enumerate() {
            adam.push(AdamTensors::of(&name, self.states[i].as_ref()));
            tensors.push((name, t.dims().to_vec(), host(t)));
        }
        for a in &adam {
            tensors.extend(a.tensors());
        }
        tensors.push(("contribution".into(), vec![self.contribution.len()], self.contribution.clone()));
        let mut meta = HashMap::new();
        meta.insert("margin".to_string(), self.scene.margin.to_string());
        meta.insert("teacher".to_string(), self.teacher.model.clone());
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: cannot create: {e}", dir.display()))?;
        ckpt::write_f32(&dir.join("language.safetensors"), tensors, Some(meta))?;
        ckpt::write_json(&dir.join("config.json"), &serde_json::to_value(&self.cfg).unwrap())?;
        let state = serde_json::json!({
            "iter": self.iter,
            "adam_time": self.states.iter().map(|s| s.as_ref().map(|s| s.momentum.time)).collect::<Vec<_>>(),
            "teacher_dir": self.teacher.dir.display().to_string(),
        });
        ckpt::write_json(&dir.join("state.json"), &state)
    }

    /// Resumes a language run saved by [`save`](Self::save).
    pub fn resume(run: &Path, dir: &Path, device: &Device) -> Result<Self, String> {
        let (cfg, field, states, _, contribution) = load_field(dir, device)?;
        let state: serde_json::Value = ckpt::read_json(&dir.join("state.json"))?;
        let teacher = TeacherSet::open(&teacher_dir(dir)?)?;
        let mut t = Self::new(run, teacher, cfg, device)?;
        if field.len() != t.scene.geometry.model.len() {
            return Err(format!("{}: {} Gaussians, but the geometry run {} has {}", dir.display(), field.len(), run.display(), t.scene.geometry.model.len()));
        }
        t.scene.field = field;
        t.states = states;
        t.contribution = contribution;
        t.iter = state["iter"].as_u64().ok_or_else(|| format!("{}: no iter", dir.join("state.json").display()))? as usize;
        Ok(t)
    }
}

fn mean_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f32>() / a.len().max(1) as f32
}

/// Per-token mean `b` and per-channel standard deviation `a` (broadcast to `[T, D]`) of the
/// teacher's view tokens (`Some(false)`), object tokens (`Some(true)`) or both (`None`).
fn teacher_stats(teacher: &TeacherSet, objects: Option<bool>) -> Result<(Vec<f32>, Vec<f32>), String> {
    let (t, d) = (teacher.grid * teacher.grid, teacher.dim);
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
    let std: Vec<f32> = (0..d).map(|c| ((ch_sq[c] / cnt - (ch_sum[c] / cnt).powi(2)).max(0.0).sqrt() as f32).max(1e-3)).collect();
    let a = (0..t * d).map(|i| std[i % d]).collect();
    Ok((a, sum.into_iter().map(|m| (m / n) as f32).collect()))
}

/// The teacher directory a language run was trained on (recorded in its `state.json`).
pub fn teacher_dir(language: &Path) -> Result<PathBuf, String> {
    let path = language.join("state.json");
    let state = ckpt::read_json(&path)?;
    state["teacher_dir"].as_str().map(PathBuf::from).ok_or_else(|| format!("{}: no teacher_dir", path.display()))
}

type LoadedField = (LanguageTrainConfig, LanguageField, Vec<Option<AdamState<2>>>, f32, Vec<f32>);

/// Reads a language run directory: config, field, Adam states, object margin, contribution.
pub fn load_field(dir: &Path, device: &Device) -> Result<LoadedField, String> {
    let cfg_path = dir.join("config.json");
    let cfg: LanguageTrainConfig = serde_json::from_value(ckpt::read_json(&cfg_path)?).map_err(|e| format!("{}: invalid config: {e}", cfg_path.display()))?;
    let path = dir.join("language.safetensors");
    let (mut tensors, meta) = ckpt::read_f32(&path)?;
    let state: serde_json::Value = ckpt::read_json(&dir.join("state.json"))?;
    let times = state["adam_time"].as_array().cloned().unwrap_or_default();
    let order = LanguageField::new(&LanguageConfig { dim: 1, grid: 1, patch: 1, hidden: 1, ..cfg.field.clone() }, 0, 0, device).named();
    let mut named = Vec::new();
    let mut states = Vec::new();
    for (i, (name, _)) in order.iter().enumerate() {
        let (shape, v) = tensors.remove(name).ok_or_else(|| format!("{}: tensor {name} missing", path.display()))?;
        let to2 = |s: &[usize], v: Vec<f32>| -> Result<Tensor<2>, String> {
            if s.len() != 2 {
                return Err(format!("{}: {name} has shape {s:?}, expected rank 2", path.display()));
            }
            Ok(Tensor::from_data(TensorData::new(v, [s[0], s[1]]), device))
        };
        named.push((name.clone(), to2(&shape, v)?));
        let time = times.get(i).and_then(|t| t.as_u64()).map(|t| t as usize);
        states.push(AdamTensors::take(name, time, &mut tensors, device)?);
    }
    let field = LanguageField::from_named(named)?;
    let margin = meta.get("margin").and_then(|m| m.parse().ok()).unwrap_or(0.1);
    let contribution = tensors.remove("contribution").map(|(_, v)| v).unwrap_or_else(|| vec![1.0; field.len()]);
    Ok((cfg, field, states, margin, contribution))
}

/// Progress of [`run`], reported after every iteration.
#[derive(Clone, Copy, Debug)]
pub struct LangProgress {
    pub iter: usize,
    pub iters: usize,
    pub step: LangStep,
}

/// Result of [`run`].
#[derive(Clone, Debug)]
pub struct LangSummary {
    /// Token L1 on the training views (view, object) before and after.
    pub before: (f32, f32),
    pub after: (f32, f32),
    pub seconds_per_iter: f64,
    pub resumed_from: Option<usize>,
    pub gaussians_used: usize,
    pub gaussians: usize,
}

/// Trains (or resumes) the language stage of geometry run `run` into `out`.
pub fn run(
    run_dir: &Path,
    teacher_dir: &Path,
    out: &Path,
    cfg: LanguageTrainConfig,
    device: &Device,
    resume: bool,
    mut progress: impl FnMut(LangProgress),
) -> Result<LangSummary, String> {
    let (mut t, resumed_from) = if resume && out.join("language.safetensors").exists() {
        let mut t = LanguageTrainer::resume(run_dir, out, device)?;
        t.cfg.iters = cfg.iters.max(t.cfg.iters);
        let at = t.iter;
        (t, Some(at))
    } else {
        (LanguageTrainer::new(run_dir, TeacherSet::open(teacher_dir)?, cfg, device)?, None)
    };
    let all: Vec<usize> = (0..t.views.len()).collect();
    let before = t.token_l1(&all)?;
    let start = std::time::Instant::now();
    let first = t.iter;
    while t.iter < t.cfg.iters {
        let v = crate::geometry::view_at(t.iter, t.views.len(), t.cfg.seed);
        let s = t.step(v)?;
        if !s.loss.is_finite() {
            return Err(format!("loss became {} at iteration {}", s.loss, t.iter));
        }
        progress(LangProgress { iter: t.iter, iters: t.cfg.iters, step: s });
        if t.cfg.checkpoint_every > 0 && t.iter % t.cfg.checkpoint_every == 0 {
            t.save(out)?;
        }
    }
    let seconds_per_iter = start.elapsed().as_secs_f64() / (t.iter - first).max(1) as f64;
    t.save(out)?;
    let after = t.token_l1(&all)?;
    let used = t.contribution.iter().filter(|&&c| c > 0.0).count();
    let metrics = serde_json::json!({
        "iters": t.iter, "train_view_token_l1_before": before.0, "train_view_token_l1": after.0,
        "train_object_token_l1_before": before.1, "train_object_token_l1": after.1,
        "seconds_per_iter": seconds_per_iter, "gaussians": t.contribution.len(), "gaussians_used": used,
    });
    ckpt::write_json(&out.join("metrics.json"), &metrics)?;
    Ok(LangSummary { before, after, seconds_per_iter, resumed_from, gaussians_used: used, gaussians: t.contribution.len() })
}
