//! The SigLIP vision tower as LLaVA-OneVision uses it: patch embedding (a stride-`patch` conv,
//! done as one matmul over unfolded patches), learned position embeddings, pre-norm encoder
//! layers; the output is the hidden state selected by `vision_feature_layer` (no post-layernorm,
//! no pooling head).

use super::VlmError;
use super::config::{LlavaConfig, VisionConfig};
use super::layers::{LayerNorm, Linear, act, attention};
use super::weights::WeightStore;
use burn::tensor::Tensor;

#[derive(Clone, Debug)]
struct EncoderLayer {
    ln1: LayerNorm,
    q: Linear,
    k: Linear,
    v: Linear,
    out: Linear,
    ln2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
}

/// SigLIP vision tower (frozen).
#[derive(Clone, Debug)]
pub struct VisionTower {
    pub cfg: VisionConfig,
    /// `[3 * p * p, D]`, rows ordered (channel, y, x) like the conv weight.
    patch_weight: Tensor<2>,
    patch_bias: Tensor<1>,
    /// `[tokens, D]`
    position: Tensor<2>,
    layers: Vec<EncoderLayer>,
}

impl VisionTower {
    pub fn load(w: &WeightStore, cfg: &LlavaConfig) -> Result<Self, VlmError> {
        let v = cfg.vision.clone();
        let (d, f, p) = (v.hidden_size, v.intermediate_size, v.patch_size);
        let pre = "vision_tower.vision_model";
        // [D, 3, p, p] -> [3 p p, D], rows ordered (channel, y, x) like the unfolded patches.
        let patch_weight = w.transposed(&format!("{pre}.embeddings.patch_embedding.weight"), &[d, 3, p, p])?;
        let mut layers = Vec::new();
        for i in 0..cfg.vision_layers_needed() {
            let l = format!("{pre}.encoder.layers.{i}");
            layers.push(EncoderLayer {
                ln1: LayerNorm::load(w, &format!("{l}.layer_norm1"), d, v.layer_norm_eps)?,
                q: Linear::load(w, &format!("{l}.self_attn.q_proj"), d, d, true)?,
                k: Linear::load(w, &format!("{l}.self_attn.k_proj"), d, d, true)?,
                v: Linear::load(w, &format!("{l}.self_attn.v_proj"), d, d, true)?,
                out: Linear::load(w, &format!("{l}.self_attn.out_proj"), d, d, true)?,
                ln2: LayerNorm::load(w, &format!("{l}.layer_norm2"), d, v.layer_norm_eps)?,
                fc1: Linear::load(w, &format!("{l}.mlp.fc1"), d, f, true)?,
                fc2: Linear::load(w, &format!("{l}.mlp.fc2"), f, d, true)?,
            });
        }
        Ok(Self {
            patch_bias: w.tensor(&format!("{pre}.embeddings.patch_embedding.bias"), [d])?,
            position: w.tensor(&format!("{pre}.embeddings.position_embedding.weight"), [v.tokens(), d])?,
            patch_weight,
            layers,
            cfg: v,
        })
    }

    /// `pixels`: `[B, 3, S, S]` normalised -> selected hidden state `[B, tokens, D]`.
    pub fn forward(&self, pixels: Tensor<4>) -> Tensor<3> {
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
        let x = patches.matmul(self.patch_weight.clone()) + self.patch_bias.clone().unsqueeze_dim::<2>(0);
        let mut x = x.reshape([b, g * g, d]) + self.position.clone().unsqueeze_dim::<3>(0);
        let heads = self.cfg.num_heads;
        let hd = d / heads;
        let t = g * g;
        let split = |y: Tensor<3>| y.reshape([b, t, heads, hd]).swap_dims(1, 2).reshape([b * heads, t, hd]);
        for l in &self.layers {
            let h = l.ln1.forward(x.clone());
            let o =
                attention(split(l.q.forward(h.clone())), split(l.k.forward(h.clone())), split(l.v.forward(h)), None);
            let o = o.reshape([b, heads, t, hd]).swap_dims(1, 2).reshape([b, t, d]);
            x = x + l.out.forward(o);
            let h = l.ln2.forward(x.clone());
            x = x + l.fc2.forward(act(self.cfg.act, l.fc1.forward(h)));
        }
        x
    }
}
