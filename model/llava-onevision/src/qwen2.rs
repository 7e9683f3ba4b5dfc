//! The Qwen2 decoder as a burn `Module`: token embeddings, pre-RMSNorm layers with rotary
//! grouped-query attention (q/k/v bias, no o bias) and a SwiGLU MLP, final norm, lm_head (tied to
//! the embeddings when the config says so). It takes input embeddings, so image tokens from
//! anywhere can be spliced in; inference keeps a KV cache, training runs whole batches with an
//! explicit attention mask and positions (several questions sharing one image prefix).

use super::VlmError;
use super::config::TextConfig;
use super::layers::{
    Mask, attention, attention_probs, gated, half_linear, host_product, in_dtype, in_precision, init_linear,
    init_rms_norm, linear, load_linear, load_rms_norm, normal,
};
use super::weights::{HfTensors, WeightStore};
use base::Rng;
use burn::module::{Module, Param};
use burn::nn::{Embedding, Linear, RmsNorm};
use burn::tensor::{DType, Device, Int, Tensor, TensorData};

/// One decoder layer.
#[derive(Module, Debug)]
pub struct DecoderLayer {
    pub ln1: RmsNorm,
    pub q: Linear,
    pub k: Linear,
    pub v: Linear,
    pub o: Linear,
    pub ln2: RmsNorm,
    pub gate: Linear,
    pub up: Linear,
    pub down: Linear,
}

impl DecoderLayer {
    /// The same layer with its linear layers held in f16.
    fn half(self) -> Self {
        Self {
            q: half_linear(self.q),
            k: half_linear(self.k),
            v: half_linear(self.v),
            o: half_linear(self.o),
            gate: half_linear(self.gate),
            up: half_linear(self.up),
            down: half_linear(self.down),
            ..self
        }
    }
}

/// Keys and values of every layer so far, `[kv_heads, room, head_dim]` each with the first `len`
/// positions filled: a step writes its keys after them in place (burn-flex writes into a tensor
/// nothing else holds without copying it) instead of concatenating, which copied the whole cache
/// (2 MB per layer at a 2k context at 0.5B) in every layer of every decoded token.
#[derive(Clone, Debug, Default)]
pub struct KvCache {
    layers: Vec<Option<(Tensor<3>, Tensor<3>)>>,
    len: usize,
    /// Positions to make room for at the first write (grown by doubling past it).
    reserve: usize,
}

impl KvCache {
    /// A cache that will hold `tokens` positions without growing.
    pub fn with_capacity(tokens: usize) -> Self {
        Self { reserve: tokens, ..Self::default() }
    }

    /// Tokens already in the cache (the position of the next token).
    pub fn len(&self) -> usize {
        self.len
    }
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Keeps the first `len` positions (a conversation whose prompt changed after them): the next
    /// write goes after them, over what was there.
    pub fn truncate(&mut self, len: usize) {
        self.len = self.len.min(len);
    }

    /// Writes `layer`'s keys and values `[kv_heads, t, head_dim]` of the `t` positions after the
    /// cached ones and returns all of that layer's so far, `[kv_heads, len + t, head_dim]` (views
    /// into the cache). The caller advances `len` once every layer has written.
    fn append(&mut self, layer: usize, k: Tensor<3>, v: Tensor<3>) -> (Tensor<3>, Tensor<3>) {
        let (past, t) = (self.len, k.dims()[1]);
        let need = past + t;
        let reserve = self.reserve;
        let write = |held: Option<Tensor<3>>, new: Tensor<3>| {
            let [h, _, d] = new.dims();
            let room = held.as_ref().map_or(0, |c| c.dims()[1]);
            let store = match held {
                Some(c) if room >= need => c,
                held => {
                    let room = need.max(reserve).max(2 * room);
                    let fresh = Tensor::<3>::zeros([h, room, d], &new.device()).cast(new.dtype());
                    match held {
                        Some(c) if past > 0 => fresh.slice_assign([0..h, 0..past, 0..d], c.narrow(1, 0, past)),
                        _ => fresh,
                    }
                }
            };
            store.slice_assign([0..h, past..need, 0..d], new)
        };
        if self.layers.len() <= layer {
            self.layers.resize(layer + 1, None);
        }
        // taken out, so that the write finds the cache held nowhere else
        let (hk, hv) = self.layers[layer].take().unzip();
        let (ck, cv) = (write(hk, k), write(hv, v));
        let seen = (ck.clone().narrow(1, 0, need), cv.clone().narrow(1, 0, need));
        self.layers[layer] = Some((ck, cv));
        seen
    }
}

/// What a training pass records besides its output.
#[derive(Debug, Default)]
pub struct Probe {
    /// Record the attention weights of these layers ...
    pub layers: Vec<usize>,
    /// ... as `(layer, [B * heads * T, T])`, row `(b * heads + head) * T + query`.
    pub probs: Vec<(usize, Tensor<2>)>,
    /// Record the residual stream entering these layers (the number of layers: after the
    /// last, before the final norm) ...
    pub residual_at: Vec<usize>,
    /// ... as `(layer, [B, T, D])`.
    pub residuals: Vec<(usize, Tensor<3>)>,
}

impl Probe {
    /// The residual stream recorded entering `layer`.
    pub fn residual(&self, layer: usize) -> Option<Tensor<3>> {
        self.residuals.iter().find(|(l, _)| *l == layer).map(|(_, r)| r.clone())
    }

    fn record(probe: Option<&mut Probe>, layer: usize, x: &Tensor<3>) {
        if let Some(p) = probe
            && p.residual_at.contains(&layer)
        {
            p.residuals.push((layer, x.clone()));
        }
    }
}

/// Qwen2 causal LM.
#[derive(Module, Debug)]
pub struct Qwen2 {
    #[module(skip)]
    pub cfg: TextConfig,
    /// `[vocab, D]`
    pub embed: Embedding,
    pub layers: Vec<DecoderLayer>,
    pub norm: RmsNorm,
    /// `None`: tied to the embeddings.
    pub lm_head: Option<Linear>,
}

const PRE: &str = "language_model.model";

impl Qwen2 {
    pub fn load(w: &WeightStore, cfg: &TextConfig) -> Result<Self, VlmError> {
        let (d, f) = (cfg.hidden_size, cfg.intermediate_size);
        let (q, kv) = (cfg.num_heads * cfg.head_dim, cfg.num_kv_heads * cfg.head_dim);
        let eps = cfg.rms_norm_eps;
        let mut layers = Vec::new();
        for i in 0..cfg.num_layers {
            let l = format!("{PRE}.layers.{i}");
            layers.push(DecoderLayer {
                ln1: load_rms_norm(w, &format!("{l}.input_layernorm"), d, eps)?,
                q: load_linear(w, &format!("{l}.self_attn.q_proj"), d, q, true)?,
                k: load_linear(w, &format!("{l}.self_attn.k_proj"), d, kv, true)?,
                v: load_linear(w, &format!("{l}.self_attn.v_proj"), d, kv, true)?,
                o: load_linear(w, &format!("{l}.self_attn.o_proj"), q, d, false)?,
                ln2: load_rms_norm(w, &format!("{l}.post_attention_layernorm"), d, eps)?,
                gate: load_linear(w, &format!("{l}.mlp.gate_proj"), d, f, false)?,
                up: load_linear(w, &format!("{l}.mlp.up_proj"), d, f, false)?,
                down: load_linear(w, &format!("{l}.mlp.down_proj"), f, d, false)?,
            });
        }
        let embed = Embedding {
            weight: Param::from_tensor(w.hold(w.tensor(&format!("{PRE}.embed_tokens.weight"), [cfg.vocab_size, d])?)),
        };
        let lm_head = if cfg.tie_word_embeddings || !w.contains("language_model.lm_head.weight") {
            if !cfg.tie_word_embeddings {
                return Err(VlmError::weights(
                    std::path::Path::new("lm_head"),
                    "language_model.lm_head.weight is missing and the config does not tie embeddings",
                ));
            }
            None
        } else {
            Some(load_linear(w, "language_model.lm_head", d, cfg.vocab_size, false)?)
        };
        Ok(Self { norm: load_rms_norm(w, &format!("{PRE}.norm"), d, eps)?, embed, layers, lm_head, cfg: cfg.clone() })
    }

    /// A freshly initialised decoder (weights ~ N(0, 0.02²), output projections scaled down by
    /// the depth, tied embeddings when the config says so), reproducible from `rng`.
    pub fn init(cfg: &TextConfig, rng: &mut Rng, device: &Device) -> Self {
        Self::init_with(cfg, rng, device, false)
    }

    /// [`Qwen2::init`], each layer held in f16 as soon as it is drawn when `half` (the same
    /// weights as `init(..).half()`, without ever holding the whole model in f32: a 7B decoder is
    /// 30 GB in f32, 15 GB in f16).
    pub fn init_with(cfg: &TextConfig, rng: &mut Rng, device: &Device, half: bool) -> Self {
        let (d, f) = (cfg.hidden_size, cfg.intermediate_size);
        let (q, kv) = (cfg.num_heads * cfg.head_dim, cfg.num_kv_heads * cfg.head_dim);
        let (std, deep) = (0.02, 0.02 / (2.0 * cfg.num_layers.max(1) as f32).sqrt());
        let eps = cfg.rms_norm_eps;
        let layers = (0..cfg.num_layers)
            .map(|_| DecoderLayer {
                ln1: init_rms_norm(d, eps, device),
                q: init_linear(rng, d, q, true, std, device),
                k: init_linear(rng, d, kv, true, std, device),
                v: init_linear(rng, d, kv, true, std, device),
                o: init_linear(rng, q, d, false, deep, device),
                ln2: init_rms_norm(d, eps, device),
                gate: init_linear(rng, d, f, false, std, device),
                up: init_linear(rng, d, f, false, std, device),
                down: init_linear(rng, f, d, false, deep, device),
            })
            .map(|l| if half { l.half() } else { l })
            .collect();
        let embed = normal(rng, [cfg.vocab_size, d], std, device);
        let embed = Embedding { weight: Param::from_tensor(if half { in_dtype(embed, DType::F16) } else { embed }) };
        let lm_head = (!cfg.tie_word_embeddings)
            .then(|| init_linear(rng, d, cfg.vocab_size, false, std, device))
            .map(|l| if half { half_linear(l) } else { l });
        Self { embed, layers, norm: init_rms_norm(d, eps, device), lm_head, cfg: cfg.clone() }
    }

    /// The decoder's tensors under the llava-hf checkpoint names and layouts.
    pub fn export(&self, out: &mut HfTensors) {
        out.tensor(&format!("{PRE}.embed_tokens.weight"), self.embed.weight.val());
        for (i, l) in self.layers.iter().enumerate() {
            let pre = format!("{PRE}.layers.{i}");
            out.rms_norm(&format!("{pre}.input_layernorm"), &l.ln1);
            out.linear(&format!("{pre}.self_attn.q_proj"), &l.q);
            out.linear(&format!("{pre}.self_attn.k_proj"), &l.k);
            out.linear(&format!("{pre}.self_attn.v_proj"), &l.v);
            out.linear(&format!("{pre}.self_attn.o_proj"), &l.o);
            out.rms_norm(&format!("{pre}.post_attention_layernorm"), &l.ln2);
            out.linear(&format!("{pre}.mlp.gate_proj"), &l.gate);
            out.linear(&format!("{pre}.mlp.up_proj"), &l.up);
            out.linear(&format!("{pre}.mlp.down_proj"), &l.down);
        }
        out.rms_norm(&format!("{PRE}.norm"), &self.norm);
        if let Some(h) = &self.lm_head {
            out.linear("language_model.lm_head", h);
        }
    }

    fn device(&self) -> Device {
        self.embed.weight.val().device()
    }

    /// The same model with its linear layers and embeddings held in f16 (see [`linear`]).
    pub fn half(self) -> Self {
        let layers = self.layers.into_iter().map(DecoderLayer::half).collect();
        Self {
            embed: Embedding { weight: Param::from_tensor(in_dtype(self.embed.weight.val(), DType::F16)) },
            lm_head: self.lm_head.map(half_linear),
            layers,
            ..self
        }
    }

    /// Token embeddings `[T, D]` of `ids`.
    pub fn embed(&self, ids: &[u32]) -> Tensor<2> {
        let idx: Vec<i64> = ids.iter().map(|&i| i as i64).collect();
        let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [ids.len()]), &self.device());
        in_dtype(self.embed.weight.val().select(0, idx), DType::F32)
    }

    /// cos and sin `[T, head_dim/2]` at `positions`, computed in f32 as transformers does.
    fn rope(&self, positions: &[usize]) -> (Tensor<2>, Tensor<2>) {
        let hd = self.cfg.head_dim;
        let half = hd / 2;
        let base = self.cfg.rope_theta as f32;
        let inv: Vec<f32> = (0..half).map(|i| 1.0 / base.powf((2 * i) as f32 / hd as f32)).collect();
        let t = positions.len();
        let mut cos = Vec::with_capacity(t * half);
        let mut sin = Vec::with_capacity(t * half);
        for &p in positions {
            for f in &inv {
                let a = p as f32 * f;
                cos.push(a.cos());
                sin.push(a.sin());
            }
        }
        let dev = self.device();
        (
            Tensor::from_data(TensorData::new(cos, [t, half]), &dev),
            Tensor::from_data(TensorData::new(sin, [t, half]), &dev),
        )
    }

    /// All layers over `x` `[B, T, D]` at `positions`, attending to the cached keys/values (when
    /// given) and then causally or through `mask` `[T, past + T]`; returns the final-norm hidden
    /// states `[B, T, D]`.
    fn run(
        &self,
        x: Tensor<3>,
        positions: &[usize],
        mask: Mask,
        mut cache: Option<&mut KvCache>,
        mut probe: Option<&mut Probe>,
    ) -> Tensor<3> {
        let [b, t, _] = x.dims();
        let (h, kvh, hd) = (self.cfg.num_heads, self.cfg.num_kv_heads, self.cfg.head_dim);
        let (cos, sin) = self.rope(positions);
        let (cos, sin) =
            (cos.unsqueeze_dim::<3>(0).unsqueeze_dim::<4>(0), sin.unsqueeze_dim::<3>(0).unsqueeze_dim::<4>(0));
        let half = hd / 2;
        let rotate = |y: Tensor<4>| {
            // y: [B, heads, T, hd] -> y*cos + rotate_half(y)*sin, cos/sin repeated over both halves.
            let a = y.clone().narrow(3, 0, half);
            let bb = y.narrow(3, half, half);
            let ra = a.clone() * cos.clone() - bb.clone() * sin.clone();
            let rb = bb * cos.clone() + a * sin.clone();
            Tensor::cat(vec![ra, rb], 3)
        };
        let rep = h / kvh;
        // an additive mask for every query row of a grouped block (`rep` copies of `[T, past + T]`)
        let mask = match mask {
            Mask::Additive(m) if rep > 1 => Mask::Additive(Box::new(m.repeat_dim(0, rep))),
            m => m,
        };
        let past = cache.as_deref().map_or(0, |c| c.len);
        let mask = mask.for_layers(&x, rep * t, past + t);
        let mut x = x;
        for (li, l) in self.layers.iter().enumerate() {
            Probe::record(probe.as_deref_mut(), li, &x);
            let hs = l.ln1.forward(x.clone());
            let heads = |y: Tensor<3>, n: usize| y.reshape([b, t, n, hd]).swap_dims(1, 2);
            let q = rotate(heads(linear(&l.q, hs.clone()), h));
            let k = rotate(heads(linear(&l.k, hs.clone()), kvh)).reshape([b * kvh, t, hd]);
            let v = heads(linear(&l.v, hs), kvh).reshape([b * kvh, t, hd]);
            // the cache holds one sequence (b = 1: `forward`)
            let (k, v) = match cache.as_deref_mut() {
                Some(c) => c.append(li, k, v),
                None => (k, v),
            };
            // grouped-query attention: query head i uses kv head i / rep, so the rep query heads
            // of a kv head attend as one block of rep * t rows (no copy of the keys and values
            // per query head: at decode the cache would be copied rep times per layer and token)
            let q = q.reshape([b * kvh, rep * t, hd]);
            let total = k.dims()[1];
            let o = match probe.as_deref_mut() {
                Some(p) if p.layers.contains(&li) => {
                    let m = mask.additive(rep * t, total, &q.device());
                    let (o, probs) = attention_probs(q, k, v, m);
                    p.probs.push((li, probs.reshape([b * h * t, total])));
                    o
                }
                _ => attention(q, k, v, &mask),
            };
            let o = o.reshape([b, h, t, hd]).swap_dims(1, 2).reshape([b, t, h * hd]);
            x = x + linear(&l.o, o);
            let hs = l.ln2.forward(x.clone());
            x = x + linear(&l.down, gated(self.cfg.act, linear(&l.gate, hs.clone()), linear(&l.up, hs)));
        }
        Probe::record(probe, self.layers.len(), &x);
        self.norm.forward(x)
    }

    /// Inference: runs `x` (`[T, D]` input embeddings) after the cached tokens, causally; returns
    /// the final-norm hidden states `[T, D]`.
    pub fn forward(&self, x: Tensor<2>, cache: &mut KvCache) -> Tensor<2> {
        let [t, d] = x.dims();
        let start = cache.len;
        let positions: Vec<usize> = (start..start + t).collect();
        let out = self.run(x.unsqueeze_dim::<3>(0), &positions, Mask::Causal { past: start }, Some(cache), None);
        cache.len = start + t;
        out.reshape([t, d])
    }

    /// Training: `x` `[B, T, D]` with each token at `positions[i]`, attending where `mask`
    /// (`[T, T]`, additive: 0 or -inf) allows; returns the final-norm hidden states `[B, T, D]`.
    /// With `probe`, also what it asks for: attention weights of some layers, residual streams.
    pub fn forward_masked(
        &self,
        x: Tensor<3>,
        positions: &[usize],
        mask: Tensor<2>,
        probe: Option<&mut Probe>,
    ) -> Tensor<3> {
        self.run(x, positions, Mask::Additive(Box::new(mask)), None, probe)
    }

    /// Logits `[..., vocab]` of final hidden states `[..., D]`.
    pub fn logits<const N: usize>(&self, hidden: Tensor<N>) -> Tensor<N> {
        match &self.lm_head {
            Some(h) => linear(h, hidden),
            None => {
                let dims = hidden.dims();
                let d = dims[N - 1];
                let rows: usize = dims[..N - 1].iter().product();
                // (E h^T)^T rather than h E^T: E^T as a strided view makes burn-ndarray copy the whole
                // [vocab, D] embedding on every call (3.0 s vs 0.13 s per decode step at vocab 152k, D 896)
                let e = self.embed.weight.val();
                // CPU inference: E read where it lies, in its precision
                let y = host_product(hidden.reshape([rows, d]), &e.clone().transpose(), None)
                    .unwrap_or_else(|h| in_precision(e.dtype(), h, |h| e.matmul(h.transpose()).transpose()));
                let mut out = dims;
                out[N - 1] = self.cfg.vocab_size;
                y.reshape(out)
            }
        }
    }
}
