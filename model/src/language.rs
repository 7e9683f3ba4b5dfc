//! ChatSplat's language field (CVPR 2025, Sec. 3.2-3.4): per-Gaussian view-level and
//! object-level language features, the encoder that turns a rendered feature map into the
//! teacher's token grid, and the scaling adjustment.
//!
//! Data flow for one view (shapes for the paper's settings, grid 27, patch 14, D = 1152):
//!
//! ```text
//! features [N, C] --splat--> map [27*14, 27*14, C] --lift (1x1 convs C -> hidden -> D)-->
//!   [378, 378, D] --14x14 stride-14 conv--> tokens [729, D] --* a + b--> tokens [729, D]
//! ```
//!
//! The 1x1 convolutions are per-pixel matrix products and the non-overlapping 14x14 convolution is
//! a matrix product over flattened patches, so both are written as `matmul`s (identical maths,
//! and no convolution kernel is needed on any backend). [`Encoder::export`] writes them in
//! PyTorch's `Conv2d` layout.

use crate::rng::Rng;
use burn::module::{Module, Param};
use burn::tensor::{activation, Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};
use splat_kernels::Camera;

/// Shapes of the language field and its encoder (saved with every run).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct LanguageConfig {
    /// Channels of the per-Gaussian view-level features (paper: 32).
    pub view_channels: usize,
    /// Channels of the per-Gaussian object-level features (paper: 32). The encoder is shared by
    /// both levels, so it must equal `view_channels`.
    pub object_channels: usize,
    /// Width of the hidden 1x1 convolution of the lifting network.
    pub hidden: usize,
    /// Use the lifting network. Without it the features live at `dim` channels directly (the
    /// paper's "w/o encoder" ablation; `view_channels` is then ignored and set to `dim`).
    pub lifting: bool,
    /// Learn the scaling adjustment `tokens * a + b`.
    pub scale_shift: bool,
    /// One `(a, b)` per level (view, object) instead of one shared pair. The paper has a single
    /// pair; object crops (mostly black) and whole views have very different token statistics,
    /// and with one pair the view loss rose during training on the synthetic test scene (see
    /// BENCHMARKS.md), so the default is per level.
    pub scale_shift_per_level: bool,
    /// Teacher token width D (SigLIP hidden size: 1152 for LLaVA-OneVision).
    pub dim: usize,
    /// Token grid side (27 for SigLIP at 384 px with 14 px patches).
    pub grid: usize,
    /// Render pixels per token side: the encoder's non-overlapping convolution kernel (paper: 14).
    /// Smaller values render smaller maps (faster, coarser); 0 = what the views need: one render
    /// pixel per view pixel under a token, at most 14 ([`LanguageConfig::auto_patch`]).
    pub patch: usize,
    /// The teacher's input image side (384) and patch size (14): a token covers the same part of
    /// the picture as the teacher's token did.
    pub teacher_image: usize,
    pub teacher_patch: usize,
}

impl Default for LanguageConfig {
    fn default() -> Self {
        Self { view_channels: 32, object_channels: 32, hidden: 128, lifting: true, scale_shift: true, scale_shift_per_level: true, dim: 1152, grid: 27, patch: 14, teacher_image: 384, teacher_patch: 14 }
    }
}

impl LanguageConfig {
    /// Checks the shapes fit together.
    pub fn validate(&self) -> Result<(), String> {
        if self.grid == 0 || self.patch == 0 || self.dim == 0 || self.teacher_patch == 0 {
            return Err("language config: grid, patch, dim and teacher_patch must be positive".into());
        }
        if self.grid * self.teacher_patch > self.teacher_image {
            return Err(format!("language config: a {0}x{0} grid of {1} px patches does not fit a {2} px teacher image", self.grid, self.teacher_patch, self.teacher_image));
        }
        if self.lifting && (self.view_channels == 0 || self.hidden == 0) {
            return Err("language config: view_channels and hidden must be positive".into());
        }
        if self.lifting && self.view_channels != self.object_channels {
            return Err(format!(
                "language config: the encoder is shared by both levels, so view_channels ({}) must equal object_channels ({})",
                self.view_channels, self.object_channels
            ));
        }
        Ok(())
    }

    /// Channels of the per-Gaussian features the encoder reads.
    pub fn feature_channels(&self) -> usize {
        if self.lifting { self.view_channels } else { self.dim }
    }

    /// The patch that renders a `width` x `height` view at about its own resolution: the token
    /// grid covers `grid * teacher_patch / teacher_image` of the view, so a token spans
    /// `max(width, height) * teacher_patch / teacher_image` view pixels (rounded up, 1..=14).
    pub fn auto_patch(&self, width: u32, height: u32) -> usize {
        let span = width.max(height) as f32 * self.teacher_patch as f32 / self.teacher_image as f32;
        (span.ceil() as usize).clamp(1, self.teacher_patch)
    }

    /// Tokens per image.
    pub fn tokens(&self) -> usize {
        self.grid * self.grid
    }

    /// Side of the rendered feature map.
    pub fn map_size(&self) -> usize {
        self.grid * self.patch
    }

    /// Camera that renders the map of a whole view: the teacher squashes the view to a
    /// `teacher_image` square and its tokens cover the top-left `grid * teacher_patch` pixels.
    pub fn view_camera(&self, cam: &Camera) -> Camera {
        let (sx, sy) = (self.teacher_image as f32 / cam.width as f32, self.teacher_image as f32 / cam.height as f32);
        self.scaled(cam, sx, sy, 0.0, 0.0)
    }

    /// Camera that renders the map of the square crop the teacher saw for one object: `bbox` =
    /// `[x0, y0, x1, y1)` in view pixels (box plus margin), padded to a square around its centre.
    pub fn object_camera(&self, cam: &Camera, bbox: [usize; 4]) -> Camera {
        let (cw, ch) = (bbox[2].saturating_sub(bbox[0]).max(1), bbox[3].saturating_sub(bbox[1]).max(1));
        let side = cw.max(ch);
        let (ox, oy) = ((side - cw) / 2, (side - ch) / 2);
        let s = self.teacher_image as f32 / side as f32;
        self.scaled(cam, s, s, bbox[0] as f32 - ox as f32, bbox[1] as f32 - oy as f32)
    }

    fn scaled(&self, cam: &Camera, sx: f32, sy: f32, x0: f32, y0: f32) -> Camera {
        let k = self.map_size() as f32 / (self.grid * self.teacher_patch) as f32;
        let r = self.map_size() as u32;
        Camera { fx: cam.fx * sx * k, fy: cam.fy * sy * k, cx: (cam.cx - x0) * sx * k, cy: (cam.cy - y0) * sy * k, width: r, height: r, ..*cam }
    }
}

/// The object crop the teacher uses: the mask's bounding box plus `margin` of its size on every
/// side, clipped to the image, as `[x0, y0, x1, y1)`. `None` when `id` is absent.
pub fn object_box(ids: &[u8], width: usize, height: usize, id: u8, margin: f32) -> Option<[usize; 4]> {
    let (mut x0, mut y0, mut x1, mut y1) = (width, height, 0, 0);
    for y in 0..height {
        for x in 0..width {
            if ids[y * width + x] == id {
                x0 = x0.min(x);
                y0 = y0.min(y);
                x1 = x1.max(x + 1);
                y1 = y1.max(y + 1);
            }
        }
    }
    if x1 <= x0 {
        return None;
    }
    let mx = ((x1 - x0) as f32 * margin).round() as usize;
    let my = ((y1 - y0) as f32 * margin).round() as usize;
    Some([x0.saturating_sub(mx), y0.saturating_sub(my), (x1 + mx).min(width), (y1 + my).min(height)])
}

/// The encoder: lifting network (1x1 convolutions, GELU between them), the non-overlapping
/// patch convolution, and the scaling adjustment (shared by both levels, or one pair per level).
#[derive(Module, Debug)]
pub struct Encoder {
    /// Lifting 1x1 convolutions as `[in, out]` matrices (empty without lifting).
    pub lift_weights: Vec<Param<Tensor<2>>>,
    /// `[1, out]` biases of the lifting convolutions.
    pub lift_biases: Vec<Param<Tensor<2>>>,
    /// `[patch * patch * D, D]`: row `(py * patch + px) * D + c` multiplies input channel `c` at
    /// patch pixel `(px, py)`.
    pub patch_weight: Param<Tensor<2>>,
    /// `[1, D]`
    pub patch_bias: Param<Tensor<2>>,
    /// `[T, D]` scaling `a` (absent without the scaling adjustment).
    pub scale: Option<Param<Tensor<2>>>,
    /// `[T, D]` shift `b`.
    pub shift: Option<Param<Tensor<2>>>,
    /// `[T, D]` object-level `a` and `b` (with `scale_shift_per_level`).
    pub object_scale: Option<Param<Tensor<2>>>,
    pub object_shift: Option<Param<Tensor<2>>>,
}

fn uniform(rng: &mut Rng, rows: usize, cols: usize, fan_in: usize, device: &Device) -> Tensor<2> {
    let k = 1.0 / (fan_in as f32).sqrt();
    let v: Vec<f32> = (0..rows * cols).map(|_| rng.range(-k, k)).collect();
    Tensor::from_data(TensorData::new(v, [rows, cols]), device)
}

impl Encoder {
    /// A freshly initialised encoder (uniform ±1/sqrt(fan-in), a = 1, b = 0).
    pub fn new(cfg: &LanguageConfig, seed: u64, device: &Device) -> Self {
        let mut rng = Rng::new(seed ^ 0xe2c0_de5e);
        let widths: Vec<usize> = if cfg.lifting { vec![cfg.view_channels, cfg.hidden, cfg.dim] } else { vec![] };
        let mut lift_weights = Vec::new();
        let mut lift_biases = Vec::new();
        for w in widths.windows(2) {
            lift_weights.push(Param::from_tensor(uniform(&mut rng, w[0], w[1], w[0], device)));
            lift_biases.push(Param::from_tensor(uniform(&mut rng, 1, w[1], w[0], device)));
        }
        let fan = cfg.patch * cfg.patch * cfg.dim;
        let t = cfg.tokens();
        let pair = |on: bool| {
            if on {
                (Some(Param::from_tensor(Tensor::ones([t, cfg.dim], device))), Some(Param::from_tensor(Tensor::zeros([t, cfg.dim], device))))
            } else {
                (None, None)
            }
        };
        let (scale, shift) = pair(cfg.scale_shift);
        let (object_scale, object_shift) = pair(cfg.scale_shift && cfg.scale_shift_per_level);
        Self {
            lift_weights,
            lift_biases,
            patch_weight: Param::from_tensor(uniform(&mut rng, fan, cfg.dim, fan, device)),
            patch_bias: Param::from_tensor(uniform(&mut rng, 1, cfg.dim, fan, device)),
            scale,
            shift,
            object_scale,
            object_shift,
        }
    }

    /// Token width D.
    pub fn dim(&self) -> usize {
        self.patch_bias.val().dims()[1]
    }

    /// Patch side (the convolution kernel).
    pub fn patch(&self) -> usize {
        let rows = self.patch_weight.val().dims()[0];
        ((rows / self.dim()) as f64).sqrt().round() as usize
    }

    /// Tokens before the scaling adjustment: `map` `[H, W, C]` (H = W = grid * patch) -> `[T, D]`.
    pub fn tokens_raw(&self, map: Tensor<3>) -> Tensor<2> {
        let [h, w, c] = map.dims();
        let mut x = map.reshape([h * w, c]);
        let layers = self.lift_weights.len();
        for (i, (wt, b)) in self.lift_weights.iter().zip(&self.lift_biases).enumerate() {
            x = x.matmul(wt.val()) + b.val();
            if i + 1 < layers {
                x = activation::gelu(x);
            }
        }
        let d = x.dims()[1];
        let p = self.patch();
        let (gh, gw) = (h / p, w / p);
        assert_eq!((gh * p, gw * p), (h, w), "Encoder: a {h}x{w} map is not a whole number of {p}x{p} patches");
        let x = x.reshape([gh, p, gw, p, d]).swap_dims(1, 2).reshape([gh * gw, p * p * d]);
        x.matmul(self.patch_weight.val()) + self.patch_bias.val()
    }

    /// Encodes a rendered view-level map `[H, W, C]` into tokens `[T, D]` (scaling adjustment applied).
    pub fn forward(&self, map: Tensor<3>) -> Tensor<2> {
        self.forward_level(map, false)
    }

    /// As [`forward`](Self::forward) for a view-level (`object = false`) or a masked
    /// object-level map (the object pair `(a, b)` when the encoder has one).
    pub fn forward_level(&self, map: Tensor<3>, object: bool) -> Tensor<2> {
        let t = self.tokens_raw(map);
        let pair = match (object, &self.object_scale, &self.object_shift) {
            (true, Some(a), Some(b)) => Some((a, b)),
            _ => self.scale.as_ref().zip(self.shift.as_ref()),
        };
        match pair {
            Some((a, b)) => t * a.val() + b.val(),
            None => t,
        }
    }

    /// Every tensor with its name, in a fixed order (lift.{i}.weight/bias, patch.weight/bias,
    /// scale, shift), in this module's matmul layout.
    pub fn named(&self) -> Vec<(String, Tensor<2>)> {
        let mut out = Vec::new();
        for (i, (w, b)) in self.lift_weights.iter().zip(&self.lift_biases).enumerate() {
            out.push((format!("lift.{i}.weight"), w.val()));
            out.push((format!("lift.{i}.bias"), b.val()));
        }
        out.push(("patch.weight".into(), self.patch_weight.val()));
        out.push(("patch.bias".into(), self.patch_bias.val()));
        if let (Some(a), Some(b)) = (&self.scale, &self.shift) {
            out.push(("scale".into(), a.val()));
            out.push(("shift".into(), b.val()));
        }
        if let (Some(a), Some(b)) = (&self.object_scale, &self.object_shift) {
            out.push(("object_scale".into(), a.val()));
            out.push(("object_shift".into(), b.val()));
        }
        out
    }

    /// Rebuilds an encoder from [`named`](Self::named) tensors (same order).
    pub fn from_named(tensors: Vec<(String, Tensor<2>)>) -> Result<Self, String> {
        let mut lift_weights = Vec::new();
        let mut lift_biases = Vec::new();
        let (mut patch_weight, mut patch_bias, mut scale, mut shift, mut object_scale, mut object_shift) = (None, None, None, None, None, None);
        for (name, t) in tensors {
            match name.as_str() {
                "patch.weight" => patch_weight = Some(t),
                "patch.bias" => patch_bias = Some(t),
                "scale" => scale = Some(Param::from_tensor(t)),
                "shift" => shift = Some(Param::from_tensor(t)),
                "object_scale" => object_scale = Some(Param::from_tensor(t)),
                "object_shift" => object_shift = Some(Param::from_tensor(t)),
                n if n.starts_with("lift.") && n.ends_with(".weight") => lift_weights.push(Param::from_tensor(t)),
                n if n.starts_with("lift.") && n.ends_with(".bias") => lift_biases.push(Param::from_tensor(t)),
                n => return Err(format!("unknown encoder tensor {n}")),
            }
        }
        let (Some(pw), Some(pb)) = (patch_weight, patch_bias) else { return Err("encoder: patch.weight or patch.bias missing".into()) };
        if lift_weights.len() != lift_biases.len() || scale.is_some() != shift.is_some() || object_scale.is_some() != object_shift.is_some() {
            return Err("encoder: lifting weights/biases or scale/shift are incomplete".into());
        }
        Ok(Self { lift_weights, lift_biases, patch_weight: Param::from_tensor(pw), patch_bias: Param::from_tensor(pb), scale, shift, object_scale, object_shift })
    }
}

/// The trainable part of ChatSplat: per-Gaussian language features and the encoder.
#[derive(Module, Debug)]
pub struct LanguageField {
    /// `[N, Cv]` view-level features.
    pub view_features: Param<Tensor<2>>,
    /// `[N, Co]` object-level features.
    pub object_features: Param<Tensor<2>>,
    pub encoder: Encoder,
}

impl LanguageField {
    /// Features ~ N(0, 0.1²), a fresh encoder.
    pub fn new(cfg: &LanguageConfig, gaussians: usize, seed: u64, device: &Device) -> Self {
        let mut rng = Rng::new(seed ^ 0x1a46);
        let c = cfg.feature_channels();
        let mut feat = || Tensor::from_data(TensorData::new((0..gaussians * c).map(|_| 0.1 * rng.normal()).collect::<Vec<f32>>(), [gaussians, c]), device);
        Self { view_features: Param::from_tensor(feat()), object_features: Param::from_tensor(feat()), encoder: Encoder::new(cfg, seed, device) }
    }

    /// Every tensor with its name (`view_features`, `object_features`, `encoder.*`).
    pub fn named(&self) -> Vec<(String, Tensor<2>)> {
        let mut out = vec![("view_features".to_string(), self.view_features.val()), ("object_features".to_string(), self.object_features.val())];
        out.extend(self.encoder.named().into_iter().map(|(n, t)| (format!("encoder.{n}"), t)));
        out
    }

    /// Rebuilds from [`named`](Self::named) tensors.
    pub fn from_named(tensors: Vec<(String, Tensor<2>)>) -> Result<Self, String> {
        let (mut v, mut o, mut enc) = (None, None, Vec::new());
        for (n, t) in tensors {
            match n.as_str() {
                "view_features" => v = Some(t),
                "object_features" => o = Some(t),
                _ => match n.strip_prefix("encoder.") {
                    Some(rest) => enc.push((rest.to_string(), t)),
                    None => return Err(format!("unknown language tensor {n}")),
                },
            }
        }
        let (Some(v), Some(o)) = (v, o) else { return Err("language field: view_features or object_features missing".into()) };
        Ok(Self { view_features: Param::from_tensor(v), object_features: Param::from_tensor(o), encoder: Encoder::from_named(enc)? })
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.view_features.val().dims()[0]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// MaskOut (paper Eq. 7): zeroes the map outside the mask. `map` `[H, W, C]`, `mask` `[H, W]` of 0/1.
pub fn mask_out(map: Tensor<3>, mask: Tensor<2>) -> Tensor<3> {
    map * mask.unsqueeze_dim::<3>(2)
}
