//! The Qwen2 decoder: token embeddings, pre-RMSNorm layers with rotary grouped-query attention
//! (q/k/v bias, no o bias) and a SwiGLU MLP, final norm, lm_head (tied to the embeddings when the
//! config says so). It takes `inputs_embeds`, so image tokens from anywhere can be spliced in, and
//! keeps a KV cache for generation.

use super::VlmError;
use super::config::TextConfig;
use super::layers::{Linear, RmsNorm, act, attention};
use super::weights::WeightStore;
use burn::tensor::{Device, Int, Tensor, TensorData};

#[derive(Clone, Debug)]
struct DecoderLayer {
    ln1: RmsNorm,
    q: Linear,
    k: Linear,
    v: Linear,
    o: Linear,
    ln2: RmsNorm,
    gate: Linear,
    up: Linear,
    down: Linear,
}

/// Keys and values of every layer so far, `[kv_heads, T, head_dim]` each.
#[derive(Clone, Debug, Default)]
pub struct KvCache {
    layers: Vec<(Tensor<3>, Tensor<3>)>,
    len: usize,
}

impl KvCache {
    /// Tokens already in the cache (the position of the next token).
    pub fn len(&self) -> usize {
        self.len
    }
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

/// Qwen2 causal LM (frozen).
#[derive(Clone, Debug)]
pub struct Qwen2 {
    pub cfg: TextConfig,
    /// `[vocab, D]`
    embed: Tensor<2>,
    layers: Vec<DecoderLayer>,
    norm: RmsNorm,
    /// `[D, vocab]`
    lm_head: Tensor<2>,
    device: Device,
}

impl Qwen2 {
    pub fn load(w: &WeightStore, cfg: &TextConfig) -> Result<Self, VlmError> {
        let (d, f) = (cfg.hidden_size, cfg.intermediate_size);
        let (q, kv) = (cfg.num_heads * cfg.head_dim, cfg.num_kv_heads * cfg.head_dim);
        let pre = "language_model.model";
        let mut layers = Vec::new();
        for i in 0..cfg.num_layers {
            let l = format!("{pre}.layers.{i}");
            layers.push(DecoderLayer {
                ln1: RmsNorm::load(w, &format!("{l}.input_layernorm"), d, cfg.rms_norm_eps)?,
                q: Linear::load(w, &format!("{l}.self_attn.q_proj"), d, q, true)?,
                k: Linear::load(w, &format!("{l}.self_attn.k_proj"), d, kv, true)?,
                v: Linear::load(w, &format!("{l}.self_attn.v_proj"), d, kv, true)?,
                o: Linear::load(w, &format!("{l}.self_attn.o_proj"), q, d, false)?,
                ln2: RmsNorm::load(w, &format!("{l}.post_attention_layernorm"), d, cfg.rms_norm_eps)?,
                gate: Linear::load(w, &format!("{l}.mlp.gate_proj"), d, f, false)?,
                up: Linear::load(w, &format!("{l}.mlp.up_proj"), d, f, false)?,
                down: Linear::load(w, &format!("{l}.mlp.down_proj"), f, d, false)?,
            });
        }
        let embed = w.tensor(&format!("{pre}.embed_tokens.weight"), [cfg.vocab_size, d])?;
        let lm_head = if cfg.tie_word_embeddings || !w.contains("language_model.lm_head.weight") {
            if !cfg.tie_word_embeddings {
                return Err(VlmError::weights(
                    std::path::Path::new("lm_head"),
                    "language_model.lm_head.weight is missing and the config does not tie embeddings",
                ));
            }
            embed.clone().transpose()
        } else {
            w.linear_weight("language_model.lm_head.weight", d, cfg.vocab_size)?
        };
        Ok(Self {
            norm: RmsNorm::load(w, &format!("{pre}.norm"), d, cfg.rms_norm_eps)?,
            embed,
            layers,
            lm_head,
            device: w.device().clone(),
            cfg: cfg.clone(),
        })
    }

    /// Token embeddings `[T, D]` of `ids`.
    pub fn embed(&self, ids: &[u32]) -> Tensor<2> {
        let idx: Vec<i64> = ids.iter().map(|&i| i as i64).collect();
        let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [ids.len()]), &self.device);
        self.embed.clone().select(0, idx)
    }

    /// cos and sin `[T, head_dim/2]` for positions `start..start+t`, computed in f32 as transformers does.
    fn rope(&self, start: usize, t: usize) -> (Tensor<2>, Tensor<2>) {
        let hd = self.cfg.head_dim;
        let half = hd / 2;
        let base = self.cfg.rope_theta as f32;
        let inv: Vec<f32> = (0..half).map(|i| 1.0 / base.powf((2 * i) as f32 / hd as f32)).collect();
        let mut cos = Vec::with_capacity(t * half);
        let mut sin = Vec::with_capacity(t * half);
        for p in start..start + t {
            for f in &inv {
                let a = p as f32 * f;
                cos.push(a.cos());
                sin.push(a.sin());
            }
        }
        (
            Tensor::from_data(TensorData::new(cos, [t, half]), &self.device),
            Tensor::from_data(TensorData::new(sin, [t, half]), &self.device),
        )
    }

    /// Runs `x` (`[T, D]` input embeddings) after the cached tokens; returns the final-norm hidden states `[T, D]`.
    pub fn forward(&self, x: Tensor<2>, cache: &mut KvCache) -> Tensor<2> {
        let [t, _] = x.dims();
        let (h, kvh, hd) = (self.cfg.num_heads, self.cfg.num_kv_heads, self.cfg.head_dim);
        let start = cache.len;
        let (cos, sin) = self.rope(start, t);
        let (cos, sin) = (cos.unsqueeze_dim::<3>(0), sin.unsqueeze_dim::<3>(0));
        let half = hd / 2;
        let rotate = |y: Tensor<3>| {
            // y: [heads, T, hd] -> y*cos + rotate_half(y)*sin, with cos/sin repeated over both halves.
            let heads = y.dims()[0];
            let a = y.clone().narrow(2, 0, half);
            let b = y.narrow(2, half, half);
            let ra = a.clone() * cos.clone() - b.clone() * sin.clone();
            let rb = b * cos.clone() + a * sin.clone();
            Tensor::cat(vec![ra, rb], 2).reshape([heads, t, hd])
        };
        let total = start + t;
        let mask = (t > 1).then(|| {
            let m: Vec<f32> = (0..t)
                .flat_map(|i| (0..total).map(move |j| if j > start + i { f32::NEG_INFINITY } else { 0.0 }))
                .collect();
            Tensor::<2>::from_data(TensorData::new(m, [t, total]), &self.device)
        });
        let mut x = x;
        for (li, l) in self.layers.iter().enumerate() {
            let hs = l.ln1.forward(x.clone());
            let q = rotate(l.q.forward(hs.clone()).reshape([t, h, hd]).swap_dims(0, 1));
            let k = rotate(l.k.forward(hs.clone()).reshape([t, kvh, hd]).swap_dims(0, 1));
            let v = l.v.forward(hs).reshape([t, kvh, hd]).swap_dims(0, 1);
            let (k, v) = match cache.layers.get(li) {
                Some((pk, pv)) => (Tensor::cat(vec![pk.clone(), k], 1), Tensor::cat(vec![pv.clone(), v], 1)),
                None => (k, v),
            };
            if li < cache.layers.len() {
                cache.layers[li] = (k.clone(), v.clone());
            } else {
                cache.layers.push((k.clone(), v.clone()));
            }
            // grouped-query attention: query head i uses kv head i / (h / kvh)
            let rep = h / kvh;
            let expand = |y: Tensor<3>| y.unsqueeze_dim::<4>(1).repeat_dim(1, rep).reshape([h, total, hd]);
            let o = attention(q, expand(k), expand(v), mask.clone());
            let o = o.swap_dims(0, 1).reshape([t, h * hd]);
            x = x + l.o.forward(o);
            let hs = l.ln2.forward(x.clone());
            let mlp = l.down.forward(act(self.cfg.act, l.gate.forward(hs.clone())) * l.up.forward(hs));
            x = x + mlp;
        }
        cache.len = total;
        self.norm.forward(x)
    }

    /// Logits `[T, vocab]` of final hidden states `[T, D]`.
    pub fn logits(&self, hidden: Tensor<2>) -> Tensor<2> {
        hidden.matmul(self.lm_head.clone())
    }

    pub fn device(&self) -> &Device {
        &self.device
    }
}
