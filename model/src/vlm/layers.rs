//! Small building blocks on plain burn tensors (frozen weights, any backend).

use super::VlmError;
use super::config::Act;
use super::weights::WeightStore;
use burn::tensor::{Tensor, activation};

/// `y = x W + b` with `W` stored `[in, out]`.
#[derive(Clone, Debug)]
pub struct Linear {
    pub weight: Tensor<2>,
    pub bias: Option<Tensor<1>>,
}

impl Linear {
    pub fn load(w: &WeightStore, prefix: &str, d_in: usize, d_out: usize, bias: bool) -> Result<Self, VlmError> {
        Ok(Self {
            weight: w.linear_weight(&format!("{prefix}.weight"), d_in, d_out)?,
            bias: if bias { Some(w.tensor(&format!("{prefix}.bias"), [d_out])?) } else { None },
        })
    }

    /// `x`: `[..., in]` -> `[..., out]`.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let dims = x.dims();
        let d_in = dims[D - 1];
        let rows: usize = dims[..D - 1].iter().product();
        let y = x.reshape([rows, d_in]).matmul(self.weight.clone());
        let y = match &self.bias {
            Some(b) => y + b.clone().unsqueeze_dim::<2>(0),
            None => y,
        };
        let mut out = dims;
        out[D - 1] = self.weight.dims()[1];
        y.reshape(out)
    }
}

/// LayerNorm over the last dimension (biased variance, as torch).
#[derive(Clone, Debug)]
pub struct LayerNorm {
    pub weight: Tensor<1>,
    pub bias: Tensor<1>,
    pub eps: f64,
}

impl LayerNorm {
    pub fn load(w: &WeightStore, prefix: &str, d: usize, eps: f64) -> Result<Self, VlmError> {
        Ok(Self {
            weight: w.tensor(&format!("{prefix}.weight"), [d])?,
            bias: w.tensor(&format!("{prefix}.bias"), [d])?,
            eps,
        })
    }

    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        let mean = x.clone().mean_dim(2);
        let centered = x - mean;
        let var = centered.clone().powf_scalar(2.0).mean_dim(2);
        let y = centered / (var + self.eps).sqrt();
        y * self.weight.clone().unsqueeze_dim::<2>(0).unsqueeze_dim::<3>(0)
            + self.bias.clone().unsqueeze_dim::<2>(0).unsqueeze_dim::<3>(0)
    }
}

/// RMSNorm over the last dimension (Qwen2: computed in f32, weight applied after).
#[derive(Clone, Debug)]
pub struct RmsNorm {
    pub weight: Tensor<1>,
    pub eps: f64,
}

impl RmsNorm {
    pub fn load(w: &WeightStore, prefix: &str, d: usize, eps: f64) -> Result<Self, VlmError> {
        Ok(Self { weight: w.tensor(&format!("{prefix}.weight"), [d])?, eps })
    }

    /// `x`: `[T, D]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let ms = x.clone().powf_scalar(2.0).mean_dim(1);
        x * (ms + self.eps).sqrt().recip() * self.weight.clone().unsqueeze_dim::<2>(0)
    }
}

/// Applies an activation.
pub fn act<const D: usize>(a: Act, x: Tensor<D>) -> Tensor<D> {
    match a {
        Act::Gelu => activation::gelu(x),
        Act::Silu => activation::silu(x),
        Act::GeluTanh => {
            // 0.5 x (1 + tanh(sqrt(2/pi) (x + 0.044715 x^3)))
            let inner = (x.clone() + x.clone().powf_scalar(3.0) * 0.044715) * (2.0f64 / std::f64::consts::PI).sqrt();
            x * (inner.tanh() + 1.0) * 0.5
        }
    }
}

/// Softmax attention: `q` `[B, Tq, d]`, `k`/`v` `[B, Tk, d]`, optional additive mask `[Tq, Tk]`.
pub fn attention(q: Tensor<3>, k: Tensor<3>, v: Tensor<3>, mask: Option<Tensor<2>>) -> Tensor<3> {
    let d = q.dims()[2];
    let scores = q.matmul(k.swap_dims(1, 2)) * (1.0 / (d as f64).sqrt());
    let scores = match mask {
        Some(m) => scores + m.unsqueeze_dim::<3>(0),
        None => scores,
    };
    activation::softmax(scores, 2).matmul(v)
}
