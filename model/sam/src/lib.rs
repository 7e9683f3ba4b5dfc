//! Segment Anything (transformers' `SamModel`) on burn, loaded from a local Hugging Face
//! directory (`config.json`, `model.safetensors`; e.g. `facebook/sam-vit-base`), inference only.
//!
//! Data flow (shapes for SAM ViT-B; the tiny fixture in `checkpoints/tiny-sam` only narrows them):
//! pixels `[B, 3, 1024, 1024]` (normalised, padded) -> [`image_encoder::ImageEncoder`] -> image
//! embeddings `[B, 256, 64, 64]`; a [`Prompt`] (points, boxes, a mask) ->
//! [`prompt_encoder::PromptEncoder`] -> sparse `[B, P, n, 256]` and dense `[B, 256, 64, 64]`
//! embeddings -> [`mask_decoder::MaskDecoder`] -> low-resolution mask logits
//! `[B, P, 3, 256, 256]` and their predicted IoU `[B, P, 3]`.
//!
//! Weights load through [`llava_onevision::weights::WeightStore`] under transformers' key names.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub mod automatic;
pub mod config;
pub mod image_encoder;
pub mod mask_decoder;
pub mod preprocess;
pub mod prompt_encoder;
pub mod transformer;
pub mod weights;

pub use config::SamConfig;
pub use llava_onevision::{RgbImage, VlmError};
pub use prompt_encoder::Prompt;

use burn::module::Module;
use burn::tensor::{Device, Tensor};
use std::path::Path;

/// The whole model.
#[derive(Module, Debug)]
pub struct Sam {
    #[module(skip)]
    pub cfg: SamConfig,
    pub image_encoder: image_encoder::ImageEncoder,
    pub prompt_encoder: prompt_encoder::PromptEncoder,
    pub mask_decoder: mask_decoder::MaskDecoder,
}

impl Sam {
    /// Loads `dir/config.json` and the weights of `dir` (`model.safetensors` or shards).
    pub fn load(dir: &Path, device: &Device) -> Result<Self, VlmError> {
        let cfg = SamConfig::read(dir)?;
        let w = weights::WeightStore::open(dir, device)?;
        Ok(Self {
            image_encoder: image_encoder::ImageEncoder::load(&w, &cfg.vision_config)?,
            prompt_encoder: prompt_encoder::PromptEncoder::load(&w, &cfg)?,
            mask_decoder: mask_decoder::MaskDecoder::load(&w, &cfg.mask_decoder_config)?,
            cfg,
        })
    }

    /// The image embeddings (`SamModel.get_image_embeddings`).
    ///
    /// # Shapes
    /// `pixels` `[B, 3, S, S]` -> `[B, D, s, s]`.
    pub fn image_embeddings(&self, pixels: Tensor<4>) -> Tensor<4> {
        self.image_encoder.forward(pixels)
    }

    /// Masks for `prompt` on images already embedded (`SamModel.forward(image_embeddings=...)`).
    ///
    /// # Shapes
    /// `image_embeddings` `[B, D, s, s]` -> (low-resolution mask logits `[B, P, k, 4 s, 4 s]`,
    /// predicted IoU `[B, P, k]`), k = 3 with `multimask`, else 1.
    pub fn segment(&self, image_embeddings: Tensor<4>, prompt: &Prompt, multimask: bool) -> (Tensor<5>, Tensor<3>) {
        let (sparse, dense) = self.prompt_encoder.forward(prompt);
        let image_pe = self.prompt_encoder.image_positional_embeddings();
        self.mask_decoder.forward(image_embeddings, image_pe, sparse, dense, multimask)
    }
}
