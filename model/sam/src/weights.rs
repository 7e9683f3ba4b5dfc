//! Loading transformers' `SamModel` tensors (its key names, torch layouts) through
//! [`llava_onevision::weights::WeightStore`], and the small layers SAM is built from that
//! `burn::nn` does not hold in torch's layout: convolutions, channels-first layer norm.

use burn::module::{Module, Param};
use burn::nn::{LayerNorm, Linear};
use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Tensor, TensorData};
pub use llava_onevision::weights::WeightStore;
use llava_onevision::{VlmError, layers};

/// A `torch.nn.Linear` with bias (`prefix.weight` `[out, in]`, `prefix.bias`).
pub fn linear(w: &WeightStore, prefix: &str, d_in: usize, d_out: usize) -> Result<Linear, VlmError> {
    layers::load_linear(w, prefix, d_in, d_out, true)
}

/// A `torch.nn.LayerNorm` (`prefix.weight`, `prefix.bias`).
pub fn layer_norm(w: &WeightStore, prefix: &str, d: usize, eps: f64) -> Result<LayerNorm, VlmError> {
    layers::load_layer_norm(w, prefix, d, eps)
}

/// A parameter stored under `name` with `shape`.
pub fn param<const D: usize>(w: &WeightStore, name: &str, shape: [usize; D]) -> Result<Param<Tensor<D>>, VlmError> {
    Ok(Param::from_tensor(w.tensor(name, shape)?))
}

/// The first of `names` the checkpoint holds (a tied parameter saved under one of its names).
pub fn param_any<const D: usize>(
    w: &WeightStore,
    names: &[&str],
    shape: [usize; D],
) -> Result<Param<Tensor<D>>, VlmError> {
    let name = names.iter().find(|n| w.contains(n)).unwrap_or(&names[0]);
    param(w, name, shape)
}

/// `torch.nn.Conv2d` (square kernel, same stride and padding on both axes).
#[derive(Module, Debug)]
pub struct Conv2d {
    /// `[out, in, k, k]`
    pub weight: Param<Tensor<4>>,
    pub bias: Option<Param<Tensor<1>>>,
    #[module(skip)]
    pub stride: usize,
    #[module(skip)]
    pub padding: usize,
}

impl Conv2d {
    /// `prefix.weight` `[c_out, c_in, k, k]` (and `prefix.bias` with `bias`).
    pub fn load(
        w: &WeightStore,
        prefix: &str,
        [c_out, c_in, k]: [usize; 3],
        stride: usize,
        padding: usize,
        bias: bool,
    ) -> Result<Self, VlmError> {
        Ok(Self {
            weight: param(w, &format!("{prefix}.weight"), [c_out, c_in, k, k])?,
            bias: if bias { Some(param(w, &format!("{prefix}.bias"), [c_out])?) } else { None },
            stride,
            padding,
        })
    }

    /// # Shapes
    /// `x` `[B, c_in, H, W]` -> `[B, c_out, H', W']`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let options = ConvOptions::new([self.stride; 2], [self.padding; 2], [1, 1], 1);
        conv2d(x, self.weight.val(), self.bias.as_ref().map(Param::val), options)
    }
}

/// `torch.nn.ConvTranspose2d` with kernel = stride (SAM's 2x upscaling: no overlap, no padding);
/// the kernel size is the weight's.
#[derive(Module, Debug)]
pub struct ConvTranspose2d {
    /// `[in, out, k, k]` (torch's layout, also burn's)
    pub weight: Param<Tensor<4>>,
    pub bias: Param<Tensor<1>>,
}

impl ConvTranspose2d {
    pub fn load(w: &WeightStore, prefix: &str, c_in: usize, c_out: usize, k: usize) -> Result<Self, VlmError> {
        Ok(Self {
            weight: param(w, &format!("{prefix}.weight"), [c_in, c_out, k, k])?,
            bias: param(w, &format!("{prefix}.bias"), [c_out])?,
        })
    }

    /// Channels last: every input pixel's k x k output block is one product with the weight
    /// as a `[c_in, c_out k k]` matrix (kernel = stride: the blocks do not overlap).
    ///
    /// # Shapes
    /// `x` `[B, H, W, c_in]` -> `[B, k H, k W, c_out]`.
    pub fn forward_channels_last(&self, x: Tensor<4>) -> Tensor<4> {
        let [b, h, w, c] = x.dims();
        let [_, o, k, _] = self.weight.dims();
        let wm = self.weight.val().reshape([c, o * k * k]);
        let y = x.reshape([b * h * w, c]).matmul(wm).reshape([b, h, w, o, k, k]);
        // [B, H, W, O, ky, kx] -> [B, H, ky, W, kx, O]
        let y = y.permute([0, 1, 4, 2, 5, 3]).reshape([b, k * h, k * w, o]);
        y + self.bias.val().reshape([1, 1, 1, o])
    }
}

/// transformers' `SamLayerNorm(data_format="channels_first")`: a layer norm over the channels
/// of an NCHW tensor.
///
/// # Shapes
/// `x` `[B, C, H, W]` -> `[B, C, H, W]`.
pub fn layer_norm_2d(ln: &LayerNorm, x: Tensor<4>) -> Tensor<4> {
    ln.forward(x.permute([0, 2, 3, 1])).permute([0, 3, 1, 2])
}

/// A host matrix `[rows, cols]` on `device`.
pub fn host_matrix(values: Vec<f32>, rows: usize, cols: usize, device: &burn::tensor::Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(values, [rows, cols]), device)
}
