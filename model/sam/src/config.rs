//! transformers' `SamConfig` (`config.json` of a `SamModel` directory): the vision, prompt-encoder
//! and mask-decoder sub-configs, with transformers' defaults for the keys a file leaves out.

use llava_onevision::VlmError;
use serde::Deserialize;
use std::path::Path;

/// The activations SAM's configs name.
#[derive(Deserialize, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Act {
    /// erf GELU (`"gelu"`).
    #[serde(rename = "gelu")]
    Gelu,
    #[serde(rename = "relu")]
    Relu,
}

impl Act {
    pub fn apply<const D: usize>(self, x: burn::tensor::Tensor<D>) -> burn::tensor::Tensor<D> {
        match self {
            Act::Gelu => burn::tensor::activation::gelu(x),
            Act::Relu => burn::tensor::activation::relu(x),
        }
    }
}

/// The ViT image encoder (`vision_config`).
#[derive(Deserialize, Debug, Clone)]
#[serde(default)]
pub struct VisionConfig {
    pub hidden_size: usize,
    pub output_channels: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub num_channels: usize,
    pub image_size: usize,
    pub patch_size: usize,
    pub hidden_act: Act,
    pub layer_norm_eps: f64,
    pub qkv_bias: bool,
    pub mlp_ratio: f64,
    /// `None`: `hidden_size * mlp_ratio`.
    pub mlp_dim: Option<usize>,
    pub use_abs_pos: bool,
    pub use_rel_pos: bool,
    /// 0: every layer global.
    pub window_size: usize,
    pub global_attn_indexes: Vec<usize>,
    /// Width of the random-Fourier positional embedding (half the prompt width).
    pub num_pos_feats: usize,
}

impl Default for VisionConfig {
    /// transformers' defaults (`facebook/sam-vit-huge` style, but ViT-B widths).
    fn default() -> Self {
        Self {
            hidden_size: 768,
            output_channels: 256,
            num_hidden_layers: 12,
            num_attention_heads: 12,
            num_channels: 3,
            image_size: 1024,
            patch_size: 16,
            hidden_act: Act::Gelu,
            layer_norm_eps: 1e-6,
            qkv_bias: true,
            mlp_ratio: 4.0,
            mlp_dim: None,
            use_abs_pos: true,
            use_rel_pos: true,
            window_size: 14,
            global_attn_indexes: vec![2, 5, 8, 11],
            num_pos_feats: 128,
        }
    }
}

impl VisionConfig {
    pub fn mlp_dim(&self) -> usize {
        self.mlp_dim.unwrap_or((self.hidden_size as f64 * self.mlp_ratio) as usize)
    }

    /// Patches per side.
    pub fn grid(&self) -> usize {
        self.image_size / self.patch_size
    }

    /// The attention window of layer `i` (0: global attention over the whole grid).
    pub fn window_of(&self, i: usize) -> usize {
        if self.global_attn_indexes.contains(&i) { 0 } else { self.window_size }
    }
}

/// The prompt encoder (`prompt_encoder_config`).
#[derive(Deserialize, Debug, Clone)]
#[serde(default)]
pub struct PromptEncoderConfig {
    pub hidden_size: usize,
    pub image_size: usize,
    pub patch_size: usize,
    pub mask_input_channels: usize,
    pub num_point_embeddings: usize,
    pub hidden_act: Act,
    pub layer_norm_eps: f64,
    /// `None`: `image_size / patch_size`.
    pub image_embedding_size: Option<usize>,
}

impl Default for PromptEncoderConfig {
    fn default() -> Self {
        Self {
            hidden_size: 256,
            image_size: 1024,
            patch_size: 16,
            mask_input_channels: 16,
            num_point_embeddings: 4,
            hidden_act: Act::Gelu,
            layer_norm_eps: 1e-6,
            image_embedding_size: None,
        }
    }
}

impl PromptEncoderConfig {
    /// Side of the image embedding grid.
    pub fn embedding_size(&self) -> usize {
        self.image_embedding_size.unwrap_or(self.image_size / self.patch_size)
    }
}

/// The mask decoder (`mask_decoder_config`).
#[derive(Deserialize, Debug, Clone)]
#[serde(default)]
pub struct MaskDecoderConfig {
    pub hidden_size: usize,
    pub hidden_act: Act,
    pub mlp_dim: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub attention_downsample_rate: usize,
    pub num_multimask_outputs: usize,
    pub iou_head_depth: usize,
    pub iou_head_hidden_dim: usize,
    pub layer_norm_eps: f64,
}

impl Default for MaskDecoderConfig {
    fn default() -> Self {
        Self {
            hidden_size: 256,
            hidden_act: Act::Relu,
            mlp_dim: 2048,
            num_hidden_layers: 2,
            num_attention_heads: 8,
            attention_downsample_rate: 2,
            num_multimask_outputs: 3,
            iou_head_depth: 3,
            iou_head_hidden_dim: 256,
            layer_norm_eps: 1e-6,
        }
    }
}

/// The whole `SamConfig`.
#[derive(Deserialize, Debug, Clone, Default)]
#[serde(default)]
pub struct SamConfig {
    pub vision_config: VisionConfig,
    pub prompt_encoder_config: PromptEncoderConfig,
    pub mask_decoder_config: MaskDecoderConfig,
}

impl SamConfig {
    /// Reads `dir/config.json` and checks that the three parts fit together.
    pub fn read(dir: &Path) -> Result<Self, VlmError> {
        let path = dir.join("config.json");
        let text = std::fs::read_to_string(&path).map_err(|e| VlmError::io(&path, e))?;
        let cfg: SamConfig =
            serde_json::from_str(&text).map_err(|e| VlmError::config(&path, format!("not a SamConfig: {e}")))?;
        cfg.check().map_err(|m| VlmError::config(&path, m))?;
        Ok(cfg)
    }

    /// The constraints transformers' modules assume.
    pub fn check(&self) -> Result<(), String> {
        let (v, p, m) = (&self.vision_config, &self.prompt_encoder_config, &self.mask_decoder_config);
        let positive = [
            ("vision_config.hidden_size", v.hidden_size),
            ("vision_config.num_attention_heads", v.num_attention_heads),
            ("vision_config.patch_size", v.patch_size),
            ("mask_decoder_config.num_attention_heads", m.num_attention_heads),
            ("mask_decoder_config.attention_downsample_rate", m.attention_downsample_rate),
            ("prompt_encoder_config.patch_size", p.patch_size),
        ];
        if let Some((name, _)) = positive.iter().find(|(_, x)| *x == 0) {
            return Err(format!("{name} is 0"));
        }
        if v.hidden_size % v.num_attention_heads != 0 {
            return Err("vision_config.num_attention_heads does not divide hidden_size".into());
        }
        if v.image_size % v.patch_size != 0 {
            return Err("vision_config.patch_size does not divide image_size".into());
        }
        if v.output_channels != p.hidden_size || p.hidden_size != m.hidden_size {
            return Err(format!(
                "the image embedding ({}), prompt ({}) and mask decoder ({}) widths differ",
                v.output_channels, p.hidden_size, m.hidden_size
            ));
        }
        if 2 * v.num_pos_feats != p.hidden_size {
            return Err("vision_config.num_pos_feats is not half the prompt encoder's hidden_size".into());
        }
        if p.embedding_size() != v.grid() {
            return Err("prompt_encoder_config.image_embedding_size is not the vision grid".into());
        }
        if m.hidden_size % 8 != 0 || p.mask_input_channels % 4 != 0 || p.mask_input_channels == 0 {
            return Err("mask_decoder_config.hidden_size must be a multiple of 8, mask_input_channels of 4".into());
        }
        let internal = m.hidden_size / m.attention_downsample_rate;
        if internal % m.num_attention_heads != 0 || m.hidden_size % m.num_attention_heads != 0 {
            return Err("mask_decoder_config.num_attention_heads does not divide the attention width".into());
        }
        if m.iou_head_depth < 2 || p.num_point_embeddings < 4 {
            return Err("iou_head_depth must be at least 2 and num_point_embeddings at least 4".into());
        }
        Ok(())
    }
}
