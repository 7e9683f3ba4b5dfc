//! The token mixer: one self-attention layer over the encoder's token grid, between the patch
//! convolution and the scaling adjustment (`LanguageConfig::token_mixer`; not in the paper).
//!
//! The paper's encoder is local: a token sees only the map under its own patch. The teacher's
//! SigLIP tokens are not (27 attention layers), and what a question such as "how many" needs is
//! spread over them: fitted on the true pixels of a view, the local encoder counts 10.7 % right
//! on held-out views where the teacher counts 75.0 %; with this layer 57.1 % (`encoder-probe`,
//! eval/journal/2026-11-28.md, "Ten held-out scenes with 48 views", paragraph "Found: the encoder's
//! locality loses the count"). The output projection starts at zero, so a fresh mixer is the
//! identity and a field trains as without it until the layer has learnt something.

use super::init::{fan_in_bound, uniform};
use crate::rng::Rng;
use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, activation};

/// `x + softmax(q kᵀ / sqrt(D)) v o` with `n` = `x` normalised per token (zero mean, unit
/// variance over channels), `q = (n + pos) W_q`, `k = (n + pos) W_k`, `v = n W_v`: one head of
/// width D, learned positions on queries and keys only, a residual around it.
#[derive(Module, Debug)]
pub struct TokenMixer {
    /// `[T, D]` learned position of each token (added to queries' and keys' input).
    pub pos: Param<Tensor<2>>,
    /// `[D, D]` query, key, value and output projections (`x W`, matmul layout).
    pub query: Param<Tensor<2>>,
    pub key: Param<Tensor<2>>,
    pub value: Param<Tensor<2>>,
    pub out: Param<Tensor<2>>,
}

/// The names of a mixer's tensors in [`TokenMixer::named`] order (prefixed `mix.` in the encoder).
pub const MIXER_TENSORS: [&str; 5] = ["pos", "q", "k", "v", "o"];

impl TokenMixer {
    /// A fresh mixer for `tokens` x `dim` grids: positions uniform ±0.02, projections uniform
    /// ±1/sqrt(D), the output projection zero (the mixer starts as the identity).
    pub fn new(tokens: usize, dim: usize, seed: u64, device: &Device) -> Self {
        let mut rng = Rng::new(seed ^ 0x5eed_a77e);
        let k = fan_in_bound(dim);
        let mut draw =
            |rows: usize, cols: usize, bound: f32| Param::from_tensor(uniform(&mut rng, rows, cols, bound, device));
        Self {
            pos: draw(tokens, dim, 0.02),
            query: draw(dim, dim, k),
            key: draw(dim, dim, k),
            value: draw(dim, dim, k),
            out: Param::from_tensor(Tensor::zeros([dim, dim], device)),
        }
    }

    /// Mixes a token grid.
    ///
    /// # Shapes
    /// `x` `[T, D]` -> `[T, D]` (T and D as the mixer was made for).
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let d = x.dims()[1];
        let centred = x.clone() - x.clone().mean_dim(1);
        let var = centred.clone().powf_scalar(2.0).mean_dim(1);
        let n = centred / (var + 1e-5).sqrt();
        let placed = n.clone() + self.pos.val();
        let q = placed.clone().matmul(self.query.val());
        let k = placed.matmul(self.key.val());
        let v = n.matmul(self.value.val());
        let w = activation::softmax(q.matmul(k.transpose()) / (d as f32).sqrt(), 1);
        x + w.matmul(v).matmul(self.out.val())
    }

    /// The tensors with their short names ([`MIXER_TENSORS`] order).
    pub fn named(&self) -> Vec<(&'static str, Tensor<2>)> {
        let t = [&self.pos, &self.query, &self.key, &self.value, &self.out].map(|p| p.val());
        MIXER_TENSORS.into_iter().zip(t).collect()
    }

    /// Rebuilds a mixer from its five tensors in [`MIXER_TENSORS`] order, checking their shapes
    /// fit together (`pos` `[T, D]`, the projections `[D, D]`); the error says what does not.
    pub fn from_tensors(t: [Tensor<2>; 5]) -> Result<Self, String> {
        let [tokens, d] = t[0].dims();
        for (name, x) in MIXER_TENSORS.iter().zip(&t).skip(1) {
            if x.dims() != [d, d] {
                return Err(format!("mix.{name} is {:?}, expected [{d}, {d}] (mix.pos is [{tokens}, {d}])", x.dims()));
            }
        }
        let [pos, query, key, value, out] = t.map(Param::from_tensor);
        Ok(Self { pos, query, key, value, out })
    }
}
