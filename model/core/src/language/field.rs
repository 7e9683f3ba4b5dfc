//! The trainable parts of ChatSplat as burn modules: the per-Gaussian language features and the
//! encoder (lifting 1x1 convolutions, the non-overlapping patch convolution, the scaling
//! adjustment).

use super::LanguageConfig;
use super::init::{fan_in_bound, uniform};
use super::mix::{MIXER_TENSORS, TokenMixer};
use crate::error::{Error, Result};
use crate::rng::Rng;
use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData, activation};

/// The encoder: lifting network (1x1 convolutions, GELU between them), the non-overlapping
/// patch convolution, the optional token mixer ([`TokenMixer`]), and the scaling adjustment
/// (shared by both levels, or one pair per level).
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
    /// One self-attention layer over the token grid (with `token_mixer`), shared by both levels.
    pub mixer: Option<TokenMixer>,
    /// `[T, D]` scaling `a` (absent without the scaling adjustment).
    pub scale: Option<Param<Tensor<2>>>,
    /// `[T, D]` shift `b`.
    pub shift: Option<Param<Tensor<2>>>,
    /// `[T, D]` object-level `a` and `b` (with `scale_shift_per_level`).
    pub object_scale: Option<Param<Tensor<2>>>,
    pub object_shift: Option<Param<Tensor<2>>>,
}

impl Encoder {
    /// A freshly initialised encoder (uniform ±1/sqrt(fan-in), a = 1, b = 0).
    pub fn new(cfg: &LanguageConfig, seed: u64, device: &Device) -> Self {
        let mut rng = Rng::new(seed ^ 0xe2c0_de5e);
        let widths: Vec<usize> = if cfg.lifting { vec![cfg.view_channels, cfg.hidden, cfg.dim] } else { vec![] };
        let mut lift_weights = Vec::new();
        let mut lift_biases = Vec::new();
        for w in widths.windows(2) {
            lift_weights.push(Param::from_tensor(uniform(&mut rng, w[0], w[1], fan_in_bound(w[0]), device)));
            lift_biases.push(Param::from_tensor(uniform(&mut rng, 1, w[1], fan_in_bound(w[0]), device)));
        }
        let fan = cfg.patch * cfg.patch * cfg.dim;
        let t = cfg.tokens();
        let pair = |on: bool| {
            if on {
                (
                    Some(Param::from_tensor(Tensor::ones([t, cfg.dim], device))),
                    Some(Param::from_tensor(Tensor::zeros([t, cfg.dim], device))),
                )
            } else {
                (None, None)
            }
        };
        let (scale, shift) = pair(cfg.scale_shift);
        let (object_scale, object_shift) = pair(cfg.scale_shift && cfg.scale_shift_per_level);
        Self {
            lift_weights,
            lift_biases,
            patch_weight: Param::from_tensor(uniform(&mut rng, fan, cfg.dim, fan_in_bound(fan), device)),
            patch_bias: Param::from_tensor(uniform(&mut rng, 1, cfg.dim, fan_in_bound(fan), device)),
            mixer: cfg.token_mixer.then(|| TokenMixer::new(t, cfg.dim, seed, device)),
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
    ///
    /// The last lifting convolution is linear (no activation after it), so it can be folded into
    /// the patch convolution: one matmul per patch over `patch² x hidden` inputs instead of
    /// `patch² x D`. At LLaVA-OneVision's size (hidden 128, D 1152, 14x14 patches) that is 54
    /// instead of 211 G multiply-adds per 378x378 view, so it is taken whenever it is cheaper
    /// (the built-in model's too: D 192 against 144 tokens); [`Encoder::tokens_raw_plain`] is the
    /// unfolded twin.
    pub fn tokens_raw(&self, map: Tensor<3>) -> Tensor<2> {
        if self.fold_is_cheaper(&map.dims()) { self.tokens_raw_folded(map) } else { self.tokens_raw_plain(map) }
    }

    /// Multiply-adds of the plain and of the folded last lifting layer + patch convolution for a
    /// `[H, W, C]` map: whether folding is cheaper.
    pub(crate) fn fold_is_cheaper(&self, dims: &[usize; 3]) -> bool {
        let Some(last) = self.lift_weights.last() else { return false };
        let [hidden, d] = last.val().dims();
        let (pixels, p, out) = (dims[0] * dims[1], self.patch(), self.dim());
        let tokens = pixels / (p * p);
        let plain = pixels * hidden * d + tokens * p * p * d * out;
        let folded = p * p * hidden * d * out + tokens * p * p * hidden * out;
        folded < plain
    }

    /// Runs the lifting layers (all, or all but the last) on pixels as rows: `[N, C]` -> `[N, width]`,
    /// GELU after each but the last.
    pub(crate) fn lift_rows(&self, mut x: Tensor<2>, keep_last: bool) -> Tensor<2> {
        let layers = self.lift_weights.len();
        let run = if keep_last { layers } else { layers - 1 };
        for (i, (wt, b)) in self.lift_weights.iter().zip(&self.lift_biases).enumerate().take(run) {
            x = x.matmul(wt.val()) + b.val();
            if i + 1 < layers {
                x = activation::gelu(x);
            }
        }
        x
    }

    /// A map's pixels in patch order: `[H, W, C]` -> `[H * W, C]`, patch by patch (row-major over
    /// the token grid), each patch's pixels row-major, so `[T, patch² x C]` is a free reshape.
    pub(crate) fn patch_order(&self, map: Tensor<3>) -> Tensor<2> {
        let [h, w, c] = map.dims();
        let p = self.patch();
        let (gh, gw) = (h / p, w / p);
        assert_eq!((gh * p, gw * p), (h, w), "Encoder: a {h}x{w} map is not a whole number of {p}x{p} patches");
        map.reshape([gh, p, gw, p, c]).swap_dims(1, 2).reshape([h * w, c])
    }

    /// A view map's pixels lifted ([`lift_rows`](Self::lift_rows)), then put in
    /// [`patch_order`](Self::patch_order). Lifting first moves the lifted width, not the map's
    /// channels, but the weight gradients then sum over the pixels in the order the built-in
    /// model was trained with (reordered first, its demo field changed by rounding and one
    /// borderline answer of 215 with it).
    fn lifted_in_patch_order(&self, map: Tensor<3>, keep_last: bool) -> Tensor<2> {
        let [h, w, c] = map.dims();
        let x = self.lift_rows(map.reshape([h * w, c]), keep_last);
        let d = x.dims()[1];
        self.patch_order(x.reshape([h, w, d]))
    }

    /// Lifted pixels in [`patch_order`](Self::patch_order) `[T * patch², d]` -> `[T, patch² x d]` rows.
    fn patch_rows(&self, x: Tensor<2>) -> Tensor<2> {
        let [n, d] = x.dims();
        let pp = self.patch() * self.patch();
        x.reshape([n / pp, pp * d])
    }

    /// [`Encoder::tokens_raw`] as written: every lifting layer per pixel, then the patch matmul.
    pub fn tokens_raw_plain(&self, map: Tensor<3>) -> Tensor<2> {
        self.patch_rows(self.lifted_in_patch_order(map, true)).matmul(self.patch_weight.val()) + self.patch_bias.val()
    }

    /// [`Encoder::tokens_raw`] with the last lifting layer folded into the patch convolution
    /// (formed for this map: training changes the weights every step; [`FrozenEncoder`](super::FrozenEncoder) forms it
    /// once).
    fn tokens_raw_folded(&self, map: Tensor<3>) -> Tensor<2> {
        let (weight, bias) = self.folded_patch();
        self.tokens_raw_with_fold(map, weight, bias)
    }

    /// The last lifting layer `(W, b)` folded into the patch weight `P` (`[patch², D, out]` by
    /// pixel): `P'[pixel] = W P[pixel]` as `[patch² x hidden, out]` and the bias
    /// `b Σ_pixel P[pixel] + c` as `[1, out]`.
    ///
    /// Where `P` is large (LLaVA-OneVision's: 1 GB), `b` rides along as one more row of `W`
    /// instead, the bias summed as `Σ_pixel (b P[pixel]) + c`: one product makes both and its
    /// gradient reaches `P` once, where summing `P` over the pixels would, backward, spread the
    /// bias gradient over a tensor of `P`'s size and add it to `P`'s. The two differ by rounding
    /// only; small encoders (the built-in model's, 9 MB) keep the sum, and so their figures.
    pub(crate) fn folded_patch(&self) -> (Tensor<2>, Tensor<2>) {
        /// Elements of `P` from which the bias rides along in the product (32 MB of f32).
        const BIAS_IN_PRODUCT: usize = 1 << 23;
        let elements = self.patch_weight.val().dims().iter().product::<usize>();
        self.fold(elements >= BIAS_IN_PRODUCT)
    }

    /// [`folded_patch`](Self::folded_patch) with the bias summed over `P` or carried in the product.
    fn fold(&self, bias_in_product: bool) -> (Tensor<2>, Tensor<2>) {
        let (last_w, last_b) = (
            self.lift_weights.last().expect("folding needs a lifting layer").val(),
            self.lift_biases.last().expect("a bias per lifting layer").val(),
        );
        let [hidden, d] = last_w.dims();
        let (pp, out) = (self.patch() * self.patch(), self.dim());
        let per_pixel = self.patch_weight.val().reshape([pp, d, out]);
        if !bias_in_product {
            let folded = last_w.unsqueeze_dim::<3>(0).matmul(per_pixel.clone()).reshape([pp * hidden, out]);
            let bias = last_b.matmul(per_pixel.sum_dim(0).reshape([d, out])) + self.patch_bias.val();
            return (folded, bias);
        }
        let both = Tensor::cat(vec![last_w, last_b], 0).unsqueeze_dim::<3>(0).matmul(per_pixel);
        let folded = both.clone().slice([0..pp, 0..hidden, 0..out]).reshape([pp * hidden, out]);
        let bias = both.slice([0..pp, hidden..hidden + 1, 0..out]).sum_dim(0).reshape([1, out]) + self.patch_bias.val();
        (folded, bias)
    }

    /// Tokens before the scaling adjustment through a folded patch convolution
    /// ([`folded_patch`](Self::folded_patch)): every lifting layer but the last, then one matmul.
    pub(crate) fn tokens_raw_with_fold(&self, map: Tensor<3>, weight: Tensor<2>, bias: Tensor<2>) -> Tensor<2> {
        self.patch_rows(self.lifted_in_patch_order(map, false)).matmul(weight) + bias
    }

    /// Encodes a rendered view-level map `[H, W, C]` into tokens `[T, D]` (scaling adjustment applied).
    pub fn forward(&self, map: Tensor<3>) -> Tensor<2> {
        self.forward_level(map, false)
    }

    /// As [`forward`](Self::forward) for a view-level (`object = false`) or a masked
    /// object-level map (the object pair `(a, b)` when the encoder has one).
    pub fn forward_level(&self, map: Tensor<3>, object: bool) -> Tensor<2> {
        self.adjust(self.mix(self.tokens_raw(map)), object)
    }

    /// The token mixer on a `[T, D]` grid of patch tokens (unchanged without one).
    pub fn mix(&self, t: Tensor<2>) -> Tensor<2> {
        match &self.mixer {
            Some(m) => m.forward(t),
            None => t,
        }
    }

    /// The scaling adjustment `t * a + b` of a view-level or object-level token grid `t` `[T, D]`
    /// (the object pair when the encoder has one; `t` unchanged without the adjustment).
    pub fn adjust(&self, t: Tensor<2>, object: bool) -> Tensor<2> {
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
    /// mix.pos/q/k/v/o, scale, shift, object_scale, object_shift), in this module's matmul layout.
    pub fn named(&self) -> Vec<(String, Tensor<2>)> {
        let mut out = Vec::new();
        for (i, (w, b)) in self.lift_weights.iter().zip(&self.lift_biases).enumerate() {
            out.push((format!("lift.{i}.weight"), w.val()));
            out.push((format!("lift.{i}.bias"), b.val()));
        }
        out.push(("patch.weight".into(), self.patch_weight.val()));
        out.push(("patch.bias".into(), self.patch_bias.val()));
        if let Some(m) = &self.mixer {
            out.extend(m.named().into_iter().map(|(n, t)| (format!("mix.{n}"), t)));
        }
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
    pub fn from_named(tensors: Vec<(String, Tensor<2>)>) -> Result<Self> {
        let mut lift_weights = Vec::new();
        let mut lift_biases = Vec::new();
        let (mut patch_weight, mut patch_bias, mut scale, mut shift, mut object_scale, mut object_shift) =
            (None, None, None, None, None, None);
        let mut mix: [Option<Tensor<2>>; 5] = Default::default();
        for (name, t) in tensors {
            if let Some(i) = name.strip_prefix("mix.").and_then(|n| MIXER_TENSORS.iter().position(|m| *m == n)) {
                mix[i] = Some(t);
                continue;
            }
            match name.as_str() {
                "patch.weight" => patch_weight = Some(t),
                "patch.bias" => patch_bias = Some(t),
                "scale" => scale = Some(Param::from_tensor(t)),
                "shift" => shift = Some(Param::from_tensor(t)),
                "object_scale" => object_scale = Some(Param::from_tensor(t)),
                "object_shift" => object_shift = Some(Param::from_tensor(t)),
                n if n.starts_with("lift.") && n.ends_with(".weight") => lift_weights.push(Param::from_tensor(t)),
                n if n.starts_with("lift.") && n.ends_with(".bias") => lift_biases.push(Param::from_tensor(t)),
                n => return Err(Error::input(format!("unknown encoder tensor {n}"))),
            }
        }
        let (Some(pw), Some(pb)) = (patch_weight, patch_bias) else {
            return Err(Error::input("encoder: patch.weight or patch.bias missing"));
        };
        if lift_weights.len() != lift_biases.len()
            || scale.is_some() != shift.is_some()
            || object_scale.is_some() != object_shift.is_some()
        {
            return Err(Error::input("encoder: lifting weights/biases or scale/shift are incomplete"));
        }
        let mixer = match mix {
            [None, None, None, None, None] => None,
            [Some(p), Some(q), Some(k), Some(v), Some(o)] => {
                Some(TokenMixer::from_tensors([p, q, k, v, o]).map_err(|e| Error::input(format!("encoder: {e}")))?)
            }
            _ => return Err(Error::input("encoder: the token mixer is incomplete (needs mix.pos, q, k, v and o)")),
        };
        Ok(Self {
            lift_weights,
            lift_biases,
            patch_weight: Param::from_tensor(pw),
            patch_bias: Param::from_tensor(pb),
            mixer,
            scale,
            shift,
            object_scale,
            object_shift,
        })
    }
}

/// The two parameter groups of a language field (the paper trains both with lr 0.05; the
/// trainer lets them differ).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ParamGroup {
    /// The per-Gaussian `view_features` and `object_features`.
    Features,
    /// The encoder: lifting, patch convolution, scaling adjustment (`encoder.*` but the mixer).
    Encoder,
    /// The token mixer (`encoder.mix.*`): attention weights want a smaller rate than the
    /// convolutions (the probe that measured it fitted the mixer at 0.002).
    Mixer,
}

impl ParamGroup {
    /// The group of a [`LanguageField::named`] tensor.
    pub fn of(name: &str) -> Self {
        if name.starts_with("encoder.mix.") {
            ParamGroup::Mixer
        } else if name.starts_with("encoder.") {
            ParamGroup::Encoder
        } else {
            ParamGroup::Features
        }
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
        let mut feat = || {
            Tensor::from_data(
                TensorData::new((0..gaussians * c).map(|_| 0.1 * rng.normal()).collect::<Vec<f32>>(), [gaussians, c]),
                device,
            )
        };
        Self {
            view_features: Param::from_tensor(feat()),
            object_features: Param::from_tensor(feat()),
            encoder: Encoder::new(cfg, seed, device),
        }
    }

    /// The tensor names of a field of shapes `cfg`, in [`named`](Self::named) order.
    pub fn names(cfg: &LanguageConfig) -> Vec<String> {
        let mut out = vec!["view_features".to_string(), "object_features".to_string()];
        let layers = if cfg.lifting { 2 } else { 0 };
        for i in 0..layers {
            out.push(format!("encoder.lift.{i}.weight"));
            out.push(format!("encoder.lift.{i}.bias"));
        }
        out.push("encoder.patch.weight".into());
        out.push("encoder.patch.bias".into());
        if cfg.token_mixer {
            out.extend(MIXER_TENSORS.iter().map(|n| format!("encoder.mix.{n}")));
        }
        if cfg.scale_shift {
            out.push("encoder.scale".into());
            out.push("encoder.shift".into());
            if cfg.scale_shift_per_level {
                out.push("encoder.object_scale".into());
                out.push("encoder.object_shift".into());
            }
        }
        out
    }

    /// Every tensor with its name (`view_features`, `object_features`, `encoder.*`).
    pub fn named(&self) -> Vec<(String, Tensor<2>)> {
        let mut out = vec![
            ("view_features".to_string(), self.view_features.val()),
            ("object_features".to_string(), self.object_features.val()),
        ];
        out.extend(self.encoder.named().into_iter().map(|(n, t)| (format!("encoder.{n}"), t)));
        out
    }

    /// A field of no Gaussians with an empty encoder: it stands in while a trainer holds the
    /// field's tensors alone, so that an optimizer on the host owns their buffers and updates
    /// them in place instead of copying them (at LLaVA-OneVision's size the patch weight is 1 GB).
    pub fn hollow(device: &Device) -> Self {
        let empty = || Param::from_tensor(Tensor::<2>::zeros([0, 0], device));
        let encoder = Encoder {
            lift_weights: Vec::new(),
            lift_biases: Vec::new(),
            patch_weight: empty(),
            patch_bias: empty(),
            mixer: None,
            scale: None,
            shift: None,
            object_scale: None,
            object_shift: None,
        };
        Self { view_features: empty(), object_features: empty(), encoder }
    }

    /// Rebuilds from [`named`](Self::named) tensors.
    pub fn from_named(tensors: Vec<(String, Tensor<2>)>) -> Result<Self> {
        let (mut v, mut o, mut enc) = (None, None, Vec::new());
        for (n, t) in tensors {
            match n.as_str() {
                "view_features" => v = Some(t),
                "object_features" => o = Some(t),
                _ => match n.strip_prefix("encoder.") {
                    Some(rest) => enc.push((rest.to_string(), t)),
                    None => return Err(Error::input(format!("unknown language tensor {n}"))),
                },
            }
        }
        let (Some(v), Some(o)) = (v, o) else {
            return Err(Error::input("language field: view_features or object_features missing"));
        };
        Ok(Self {
            view_features: Param::from_tensor(v),
            object_features: Param::from_tensor(o),
            encoder: Encoder::from_named(enc)?,
        })
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The fold's two bias forms (summed over the patch weight, or carried as a row of the last
    /// lifting weight) give the same folded weight and bias, and the same gradients of every
    /// encoder tensor through a weighted sum of both.
    #[test]
    fn the_folds_bias_forms_agree_in_values_and_gradients() {
        let cfg = LanguageConfig {
            view_channels: 3,
            object_channels: 3,
            hidden: 5,
            dim: 7,
            grid: 2,
            patch: 3,
            ..Default::default()
        };
        let dev = Device::ndarray().autodiff();
        let enc = Encoder::new(&cfg, 11, &dev);
        let mut rng = Rng::new(4);
        let mut weights = |rows: usize, cols: usize| uniform(&mut rng, rows, cols, 1.0, &dev);
        let (wf, wb) = (weights(9 * 5, 7), weights(1, 7));
        let run = |in_product: bool| {
            let (folded, bias) = enc.fold(in_product);
            let g = ((folded.clone() * wf.clone()).sum() + (bias.clone() * wb.clone()).sum()).backward();
            let grad =
                |p: &Param<Tensor<2>>| p.val().grad(&g).expect("a gradient").into_data().to_vec::<f32>().unwrap();
            let mut out = vec![folded.into_data().to_vec::<f32>().unwrap(), bias.into_data().to_vec::<f32>().unwrap()];
            out.extend([&enc.patch_weight, &enc.patch_bias, &enc.lift_weights[1], &enc.lift_biases[1]].map(grad));
            out
        };
        let (a, b) = (run(true), run(false));
        let what = [
            "folded weight",
            "bias",
            "patch weight grad",
            "patch bias grad",
            "last lift weight grad",
            "last lift bias grad",
        ];
        for ((name, x), y) in what.iter().zip(&a).zip(&b) {
            let scale = y.iter().fold(1f32, |m, v| m.max(v.abs()));
            let err = x.iter().zip(y).fold(0f32, |m, (p, q)| m.max((p - q).abs()));
            assert!(err <= 1e-5 * scale, "{name}: the two bias forms differ by {err} (scale {scale})");
        }
        assert_ne!(a[1], vec![0.0; 7], "a zero bias would not test its two forms");
    }
}
