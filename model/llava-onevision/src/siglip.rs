//! The SigLIP vision tower as LLaVA-OneVision uses it, as a burn `Module`: patch embedding (a
//! stride-`patch` conv, done as one matmul over unfolded patches), learned position embeddings,
//! pre-norm encoder layers; the output is the hidden state selected by `vision_feature_layer`
//! (no post-layernorm, no pooling head).

use super::VlmError;
use super::config::{LlavaConfig, VisionConfig};
use super::layers::{
    Mask, act, attention, half_linear, init_layer_norm, init_linear, linear, load_layer_norm, load_linear,
};
use super::weights::{HfTensors, WeightStore};
use base::Rng;
use burn::module::{Module, Param};
use burn::nn::{LayerNorm, Linear};
use burn::tensor::{Device, Tensor, TensorData};

/// One pre-norm encoder layer.
#[derive(Module, Debug)]
pub struct EncoderLayer {
    pub ln1: LayerNorm,
    pub q: Linear,
    pub k: Linear,
    pub v: Linear,
    pub out: Linear,
    pub ln2: LayerNorm,
    pub fc1: Linear,
    pub fc2: Linear,
}

/// The SigLIP vision tower (the layers up to the selected hidden state).
#[derive(Module, Debug)]
pub struct VisionTower {
    #[module(skip)]
    pub cfg: VisionConfig,
    /// `[3 * p * p, D]`, rows ordered (channel, y, x) like the conv weight.
    pub patch: Linear,
    /// `[tokens, D]`
    pub position: Param<Tensor<2>>,
    pub layers: Vec<EncoderLayer>,
}

const PRE: &str = "vision_tower.vision_model";

impl VisionTower {
    pub fn load(w: &WeightStore, cfg: &LlavaConfig) -> Result<Self, VlmError> {
        let v = cfg.vision.clone();
        let (d, f, p) = (v.hidden_size, v.intermediate_size, v.patch_size);
        // [D, 3, p, p] -> [3 p p, D], rows ordered (channel, y, x) like the unfolded patches.
        let patch = Linear {
            weight: Param::from_tensor(
                w.hold(w.transposed(&format!("{PRE}.embeddings.patch_embedding.weight"), &[d, 3, p, p])?),
            ),
            bias: Some(Param::from_tensor(w.hold(w.tensor(&format!("{PRE}.embeddings.patch_embedding.bias"), [d])?))),
        };
        let mut layers = Vec::new();
        for i in 0..cfg.vision_layers_needed() {
            let l = format!("{PRE}.encoder.layers.{i}");
            let eps = v.layer_norm_eps;
            layers.push(EncoderLayer {
                ln1: load_layer_norm(w, &format!("{l}.layer_norm1"), d, eps)?,
                q: load_linear(w, &format!("{l}.self_attn.q_proj"), d, d, true)?,
                k: load_linear(w, &format!("{l}.self_attn.k_proj"), d, d, true)?,
                v: load_linear(w, &format!("{l}.self_attn.v_proj"), d, d, true)?,
                out: load_linear(w, &format!("{l}.self_attn.out_proj"), d, d, true)?,
                ln2: load_layer_norm(w, &format!("{l}.layer_norm2"), d, eps)?,
                fc1: load_linear(w, &format!("{l}.mlp.fc1"), d, f, true)?,
                fc2: load_linear(w, &format!("{l}.mlp.fc2"), f, d, true)?,
            });
        }
        let position = w.tensor(&format!("{PRE}.embeddings.position_embedding.weight"), [v.tokens(), d])?;
        Ok(Self { patch, position: Param::from_tensor(position), layers, cfg: v })
    }

    /// A freshly initialised tower with `cfg.vision_layers_needed()` layers (weights ~ N(0, 1 /
    /// (3 fan_in)), position embeddings 2D sine-cosine as in MAE,
    /// so that attention can be local from the first step), reproducible from `rng`.
    pub fn init(cfg: &LlavaConfig, rng: &mut Rng, device: &Device) -> Self {
        let v = cfg.vision.clone();
        let (d, f, p) = (v.hidden_size, v.intermediate_size, v.patch_size);
        let n = cfg.vision_layers_needed();
        // PyTorch's default scale for linear layers (1 / sqrt(3 fan_in)): a small tower trained from
        // scratch learns shapes several times faster than from GPT's N(0, 0.02²) (eval/journal/2026-11-24.md,
        // "The tower does not learn shape in burn where the same ViT does in PyTorch")
        let (std, deep) = (1.0 / (3.0 * d as f32).sqrt(), 1.0 / (3.0 * f as f32).sqrt());
        let eps = v.layer_norm_eps;
        let layers: Vec<EncoderLayer> = (0..n)
            .map(|_| EncoderLayer {
                ln1: init_layer_norm(d, eps, device),
                q: init_linear(rng, d, d, true, std, device),
                k: init_linear(rng, d, d, true, std, device),
                v: init_linear(rng, d, d, true, std, device),
                out: init_linear(rng, d, d, true, deep, device),
                ln2: init_layer_norm(d, eps, device),
                fc1: init_linear(rng, d, f, true, std, device),
                fc2: init_linear(rng, f, d, true, deep, device),
            })
            .collect();
        let fan_in = 3 * p * p;
        Self {
            patch: init_linear(rng, fan_in, d, true, 1.0 / (fan_in as f32).sqrt(), device),
            position: Param::from_tensor(sincos_positions(v.grid(), d, device)),
            layers,
            cfg: v,
        }
    }

    /// The tower's tensors under the llava-hf checkpoint names and layouts.
    pub fn export(&self, out: &mut HfTensors) {
        let (d, p) = (self.cfg.hidden_size, self.cfg.patch_size);
        let pw = self.patch.weight.val().transpose().reshape([d, 3, p, p]);
        out.tensor(&format!("{PRE}.embeddings.patch_embedding.weight"), pw);
        out.vector(&format!("{PRE}.embeddings.patch_embedding.bias"), self.patch.bias.as_ref().expect("bias").val());
        out.tensor(&format!("{PRE}.embeddings.position_embedding.weight"), self.position.val());
        for (i, l) in self.layers.iter().enumerate() {
            let pre = format!("{PRE}.encoder.layers.{i}");
            out.layer_norm(&format!("{pre}.layer_norm1"), &l.ln1);
            out.linear(&format!("{pre}.self_attn.q_proj"), &l.q);
            out.linear(&format!("{pre}.self_attn.k_proj"), &l.k);
            out.linear(&format!("{pre}.self_attn.v_proj"), &l.v);
            out.linear(&format!("{pre}.self_attn.out_proj"), &l.out);
            out.layer_norm(&format!("{pre}.layer_norm2"), &l.ln2);
            out.linear(&format!("{pre}.mlp.fc1"), &l.fc1);
            out.linear(&format!("{pre}.mlp.fc2"), &l.fc2);
        }
    }

    /// The same tower with its linear layers held in f16 (see [`linear`]).
    pub fn half(self) -> Self {
        let layers = self
            .layers
            .into_iter()
            .map(|l| EncoderLayer {
                q: half_linear(l.q),
                k: half_linear(l.k),
                v: half_linear(l.v),
                out: half_linear(l.out),
                fc1: half_linear(l.fc1),
                fc2: half_linear(l.fc2),
                ..l
            })
            .collect();
        Self { patch: half_linear(self.patch), layers, ..self }
    }

    /// `pixels`: `[B, 3, S, S]` normalised -> selected hidden state `[B, tokens, D]`.
    pub fn forward(&self, pixels: Tensor<4>) -> Tensor<3> {
        self.run_layers(self.embed(pixels), 0..self.layers.len())
    }

    /// The hidden state before the tower's last `tail` layers (`tail` = 0: [`forward`](Self::forward);
    /// `tail` = all layers: the patch embedding with positions).
    ///
    /// # Shapes
    /// `pixels` `[B, 3, S, S]` -> `[B, tokens, D]`.
    pub fn state_before_tail(&self, pixels: Tensor<4>, tail: usize) -> Tensor<3> {
        let n = self.layers.len();
        assert!(tail <= n, "the vision tower has {n} layers, not {tail} to leave out");
        self.run_layers(self.embed(pixels), 0..n - tail)
    }

    /// Runs the tower's last `tail` layers on a hidden state: `tail(state_before_tail(x, k), k)`
    /// is `forward(x)`.
    ///
    /// # Shapes
    /// `x` `[B, tokens, D]` -> `[B, tokens, D]`.
    pub fn tail(&self, x: Tensor<3>, tail: usize) -> Tensor<3> {
        let n = self.layers.len();
        assert!(tail <= n, "the vision tower has {n} layers, not {tail} to run");
        self.run_layers(x, n - tail..n)
    }

    /// Patch embedding plus positions.
    ///
    /// # Shapes
    /// `pixels` `[B, 3, S, S]` normalised -> `[B, tokens, D]`.
    pub fn embed(&self, pixels: Tensor<4>) -> Tensor<3> {
        let [b, c, s, s2] = pixels.dims();
        let p = self.cfg.patch_size;
        let g = self.cfg.grid();
        assert!(
            c == 3 && s == self.cfg.image_size && s2 == s,
            "vision tower expects [B, 3, {1}, {1}], got {0:?}",
            pixels.dims(),
            self.cfg.image_size
        );
        let d = self.cfg.hidden_size;
        let used = g * p; // 378 of 384: the conv never reaches the last 6 rows/columns
        let pixels = if used < s { pixels.narrow(2, 0, used).narrow(3, 0, used) } else { pixels };
        let patches = pixels.reshape([b, 3, g, p, g, p]).permute([0, 2, 4, 1, 3, 5]).reshape([b * g * g, 3 * p * p]);
        let x = linear(&self.patch, patches);
        x.reshape([b, g * g, d]) + self.position.val().unsqueeze_dim::<3>(0)
    }

    /// Encoder layers `range` on hidden state `x` `[B, tokens, D]`.
    fn run_layers(&self, mut x: Tensor<3>, range: std::ops::Range<usize>) -> Tensor<3> {
        let [b, t, d] = x.dims();
        let heads = self.cfg.num_heads;
        let hd = d / heads;
        let split = |y: Tensor<3>| y.reshape([b, t, heads, hd]).swap_dims(1, 2).reshape([b * heads, t, hd]);
        for l in &self.layers[range] {
            let h = l.ln1.forward(x.clone());
            let o = attention(
                split(linear(&l.q, h.clone())),
                split(linear(&l.k, h.clone())),
                split(linear(&l.v, h)),
                &Mask::All,
            );
            let o = o.reshape([b, heads, t, hd]).swap_dims(1, 2).reshape([b, t, d]);
            x = x + linear(&l.out, o);
            let h = l.ln2.forward(x.clone());
            x = x + linear(&l.fc2, act(self.cfg.act, linear(&l.fc1, h)));
        }
        x
    }
}

/// 2D sine-cosine position embeddings `[g * g, d]` (row-major grid): the first half of the
/// channels encode x, the second half y, each as sines and cosines of `d / 4` frequencies.
pub fn sincos_positions(g: usize, d: usize, device: &Device) -> Tensor<2> {
    let quarter = (d / 4).max(1);
    let mut out = vec![0f32; g * g * d];
    for t in 0..g * g {
        let (x, y) = ((t % g) as f32, (t / g) as f32);
        for (half, v) in [x, y].into_iter().enumerate() {
            for i in 0..quarter {
                let w = 1.0 / 10_000f32.powf(i as f32 / quarter as f32);
                let (a, b) = (half * d / 2 + i, half * d / 2 + quarter + i);
                if b < d {
                    out[t * d + a] = (v * w).sin();
                    out[t * d + b] = (v * w).cos();
                }
            }
        }
    }
    Tensor::from_data(TensorData::new(out, [g * g, d]), device)
}
