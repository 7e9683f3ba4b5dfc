//! SAM's mask decoder (transformers' `SamMaskDecoder`): an IoU token and one token per mask
//! joined to the prompt's sparse embeddings, the two-way transformer over them and the image
//! embeddings (plus the dense prompt), the image upscaled 4x by two transposed convs, each mask
//! token mapped by its own MLP (a hypernetwork) to the weights of a per-pixel product with the
//! upscaled image, and an MLP head predicting each mask's IoU.

use crate::config::MaskDecoderConfig;
use crate::transformer::TwoWayTransformer;
use crate::weights::{ConvTranspose2d, WeightStore, layer_norm, linear, param};
use burn::module::{Module, Param};
use burn::nn::{LayerNorm, Linear};
use burn::tensor::Tensor;
use burn::tensor::activation::{gelu, relu};
use llava_onevision::VlmError;

/// An MLP with ReLU between its layers (`SamFeedForward`, no sigmoid output in SAM).
#[derive(Module, Debug)]
pub struct FeedForward {
    pub proj_in: Linear,
    pub layers: Vec<Linear>,
    pub proj_out: Linear,
}

impl FeedForward {
    fn load(
        w: &WeightStore,
        prefix: &str,
        d_in: usize,
        hidden: usize,
        d_out: usize,
        depth: usize,
    ) -> Result<Self, VlmError> {
        let mut layers = Vec::new();
        for i in 0..depth - 2 {
            layers.push(linear(w, &format!("{prefix}.layers.{i}"), hidden, hidden)?);
        }
        Ok(Self {
            proj_in: linear(w, &format!("{prefix}.proj_in"), d_in, hidden)?,
            layers,
            proj_out: linear(w, &format!("{prefix}.proj_out"), hidden, d_out)?,
        })
    }

    /// # Shapes
    /// `x` `[..., d_in]` -> `[..., d_out]`.
    pub fn forward<const D: usize>(&self, x: Tensor<D>) -> Tensor<D> {
        let mut x = relu(self.proj_in.forward(x));
        for l in &self.layers {
            x = relu(l.forward(x));
        }
        self.proj_out.forward(x)
    }
}

/// The mask decoder.
#[derive(Module, Debug)]
pub struct MaskDecoder {
    /// `[1, D]`
    pub iou_token: Param<Tensor<2>>,
    /// `[masks + 1, D]`
    pub mask_tokens: Param<Tensor<2>>,
    pub transformer: TwoWayTransformer,
    pub upscale_conv1: ConvTranspose2d,
    pub upscale_layer_norm: LayerNorm,
    pub upscale_conv2: ConvTranspose2d,
    pub output_hypernetworks_mlps: Vec<FeedForward>,
    pub iou_prediction_head: FeedForward,
}

const PRE: &str = "mask_decoder";

impl MaskDecoder {
    pub fn load(w: &WeightStore, cfg: &MaskDecoderConfig) -> Result<Self, VlmError> {
        let d = cfg.hidden_size;
        let tokens = cfg.num_multimask_outputs + 1;
        let hyper = (0..tokens)
            .map(|i| FeedForward::load(w, &format!("{PRE}.output_hypernetworks_mlps.{i}"), d, d, d / 8, 3))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            iou_token: param(w, &format!("{PRE}.iou_token.weight"), [1, d])?,
            mask_tokens: param(w, &format!("{PRE}.mask_tokens.weight"), [tokens, d])?,
            transformer: TwoWayTransformer::load(w, &format!("{PRE}.transformer"), cfg)?,
            upscale_conv1: ConvTranspose2d::load(w, &format!("{PRE}.upscale_conv1"), d, d / 4, 2)?,
            // `SamLayerNorm` at its default eps (1e-6)
            upscale_layer_norm: layer_norm(w, &format!("{PRE}.upscale_layer_norm"), d / 4, 1e-6)?,
            upscale_conv2: ConvTranspose2d::load(w, &format!("{PRE}.upscale_conv2"), d / 4, d / 8, 2)?,
            output_hypernetworks_mlps: hyper,
            iou_prediction_head: FeedForward::load(
                w,
                &format!("{PRE}.iou_prediction_head"),
                d,
                cfg.iou_head_hidden_dim,
                tokens,
                cfg.iou_head_depth,
            )?,
        })
    }

    /// Low-resolution mask logits and their predicted IoU; `multimask`: the 3 masks of the
    /// multimask tokens, else the single-mask token's.
    ///
    /// # Shapes
    /// `image` `[B, D, s, s]`, `image_pe` `[1, D, s, s]`, `sparse` `[B, P, n, D]`, `dense`
    /// `[B, D, s, s]` -> (masks `[B, P, k, 4 s, 4 s]`, iou `[B, P, k]`), k = 3 or 1.
    pub fn forward(
        &self,
        image: Tensor<4>,
        image_pe: Tensor<4>,
        sparse: Option<Tensor<4>>,
        dense: Tensor<4>,
        multimask: bool,
    ) -> (Tensor<5>, Tensor<3>) {
        let [b, d, h, w] = image.dims();
        let p = sparse.as_ref().map_or(1, |s| s.dims()[1]);
        let n = b * p;
        let k = self.mask_tokens.val().dims()[0];
        let output_tokens = Tensor::cat(vec![self.iou_token.val(), self.mask_tokens.val()], 0);
        let mut tokens = output_tokens.unsqueeze_dims::<4>(&[0, 1]).repeat_dim(0, b).repeat_dim(1, p);
        if let Some(sparse) = sparse {
            tokens = Tensor::cat(vec![tokens, sparse], 2);
        }
        let t = tokens.dims()[2];
        let tokens = tokens.reshape([n, t, d]);
        // per image -> per point batch entry (repeat_interleave), channels last
        let per_entry = |x: Tensor<4>| {
            let x = x.flatten::<3>(2, 3).swap_dims(1, 2); // [B, hw, D]
            x.unsqueeze_dim::<4>(1).repeat_dim(1, p).reshape([n, h * w, d])
        };
        let image = per_entry(image + dense);
        // one image's positions, shared by every entry (added by broadcasting)
        let image_pe = image_pe.flatten::<3>(2, 3).swap_dims(1, 2);
        let (hs, image) = self.transformer.forward(tokens, image, image_pe);
        let iou_out = hs.clone().narrow(1, 0, 1);
        let mask_out = hs.narrow(1, 1, k);

        // the upscaling channels last, as the transformer leaves the image
        let up = self.upscale_conv1.forward_channels_last(image.reshape([n, h, w, d]));
        let up = gelu(self.upscale_layer_norm.forward(up));
        let up = gelu(self.upscale_conv2.forward_channels_last(up));
        let [_, uh, uw, c] = up.dims();
        let hyper: Vec<Tensor<3>> = self
            .output_hypernetworks_mlps
            .iter()
            .enumerate()
            .map(|(i, mlp)| mlp.forward(mask_out.clone().narrow(1, i, 1)))
            .collect();
        let hyper = Tensor::cat(hyper, 1); // [N, k, c]
        // [N, uh uw, c] x [N, c, k], the small result turned
        let masks =
            up.reshape([n, uh * uw, c]).matmul(hyper.swap_dims(1, 2)).swap_dims(1, 2).reshape([b, p, k, uh, uw]);
        let iou = self.iou_prediction_head.forward(iou_out).reshape([b, p, k]);
        if multimask {
            (masks.narrow(2, 1, k - 1), iou.narrow(2, 1, k - 1))
        } else {
            (masks.narrow(2, 0, 1), iou.narrow(2, 0, 1))
        }
    }
}
