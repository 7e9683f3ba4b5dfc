//! The building blocks of the port: `burn::nn` layers loaded from (or initialised for) a
//! checkpoint, the activations the configs name, and softmax attention.

use super::VlmError;
use super::config::Act;
use super::weights::WeightStore;
use crate::rng::Rng;
use burn::module::Param;
use burn::nn::{LayerNorm, LayerNormConfig, Linear, RmsNorm};
use burn::tensor::{Device, Tensor, TensorData, activation};

/// A `torch.nn.Linear` of the checkpoint (`prefix.weight` `[out, in]`, `prefix.bias`), as a
/// `burn::nn::Linear` (`weight` `[in, out]`).
pub fn load_linear(w: &WeightStore, prefix: &str, d_in: usize, d_out: usize, bias: bool) -> Result<Linear, VlmError> {
    Ok(Linear {
        weight: Param::from_tensor(w.linear_weight(&format!("{prefix}.weight"), d_in, d_out)?),
        bias: if bias { Some(Param::from_tensor(w.tensor(&format!("{prefix}.bias"), [d_out])?)) } else { None },
    })
}

/// A `LayerNorm` of the checkpoint (`prefix.weight`, `prefix.bias`).
pub fn load_layer_norm(w: &WeightStore, prefix: &str, d: usize, eps: f64) -> Result<LayerNorm, VlmError> {
    let mut ln = LayerNormConfig::new(d).with_epsilon(eps).init(w.device());
    ln.gamma = Param::from_tensor(w.tensor(&format!("{prefix}.weight"), [d])?);
    ln.beta = Some(Param::from_tensor(w.tensor(&format!("{prefix}.bias"), [d])?));
    Ok(ln)
}

/// An `RMSNorm` of the checkpoint (`prefix.weight`).
pub fn load_rms_norm(w: &WeightStore, prefix: &str, d: usize, eps: f64) -> Result<RmsNorm, VlmError> {
    Ok(RmsNorm { gamma: Param::from_tensor(w.tensor(&format!("{prefix}.weight"), [d])?), epsilon: eps })
}

/// Values ~ N(0, std²) from `rng`, as a tensor of `shape`.
pub fn normal<const D: usize>(rng: &mut Rng, shape: [usize; D], std: f32, device: &Device) -> Tensor<D> {
    let n: usize = shape.iter().product();
    Tensor::from_data(TensorData::new((0..n).map(|_| std * rng.normal()).collect::<Vec<f32>>(), shape), device)
}

/// A freshly initialised linear layer (weights ~ N(0, std²), zero bias), reproducible from `rng`
/// on every backend.
pub fn init_linear(rng: &mut Rng, d_in: usize, d_out: usize, bias: bool, std: f32, device: &Device) -> Linear {
    Linear {
        weight: Param::from_tensor(normal(rng, [d_in, d_out], std, device)),
        bias: bias.then(|| Param::from_tensor(Tensor::zeros([d_out], device))),
    }
}

/// A LayerNorm starting at the identity (gamma 1, beta 0).
pub fn init_layer_norm(d: usize, eps: f64, device: &Device) -> LayerNorm {
    LayerNormConfig::new(d).with_epsilon(eps).init(device)
}

/// An RMSNorm starting at the identity (gamma 1).
pub fn init_rms_norm(d: usize, eps: f64, device: &Device) -> RmsNorm {
    RmsNorm { gamma: Param::from_tensor(Tensor::ones([d], device)), epsilon: eps }
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
