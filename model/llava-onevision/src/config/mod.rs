//! `config.json` / `preprocessor_config.json` of a Hugging Face LLaVA-OneVision directory, parsed
//! into the few numbers the port needs; anything we do not implement is refused by name.
//!
//! This module holds the port's own shapes ([`LlavaConfig`], [`ProcessorConfig`]); `hf` reads and
//! writes them in Hugging Face's layout.

mod hf;

pub use hf::{load_processor_config, parse_llava_config, read_json, read_llava_config};

use super::VlmError;
use std::path::Path;

/// Activation functions named in Hugging Face configs that the port implements.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Act {
    /// `gelu`: exact, erf-based.
    Gelu,
    /// `gelu_pytorch_tanh` / `gelu_new`: the tanh approximation.
    GeluTanh,
    /// `silu` / `swish`.
    Silu,
}

impl Act {
    fn parse(name: &str, file: &Path, key: &str) -> Result<Self, VlmError> {
        match name {
            "gelu" => Ok(Act::Gelu),
            "gelu_pytorch_tanh" | "gelu_new" | "gelu_fast" => Ok(Act::GeluTanh),
            "silu" | "swish" => Ok(Act::Silu),
            other => Err(VlmError::config(
                file,
                format!("{key} = \"{other}\" is not supported (gelu, gelu_pytorch_tanh, silu)"),
            )),
        }
    }
}

/// SigLIP vision tower settings (`vision_config`).
#[derive(Clone, Debug, PartialEq)]
pub struct VisionConfig {
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_layers: usize,
    pub num_heads: usize,
    pub image_size: usize,
    pub patch_size: usize,
    pub layer_norm_eps: f64,
    pub act: Act,
}

impl VisionConfig {
    /// Patch tokens per side (27 for 384 / 14: the stride-14 conv drops the last 6 pixels).
    pub fn grid(&self) -> usize {
        self.image_size / self.patch_size
    }
    /// Patch tokens per image (729 for 384 / 14).
    pub fn tokens(&self) -> usize {
        self.grid() * self.grid()
    }
}

/// Qwen2 decoder settings (`text_config`).
#[derive(Clone, Debug, PartialEq)]
pub struct TextConfig {
    pub vocab_size: usize,
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_layers: usize,
    pub num_heads: usize,
    pub num_kv_heads: usize,
    pub head_dim: usize,
    pub rms_norm_eps: f64,
    pub rope_theta: f64,
    /// Longest sequence (prompt + answer) the model takes (`max_position_embeddings`).
    pub max_positions: usize,
    pub tie_word_embeddings: bool,
    pub eos_token_ids: Vec<u32>,
    pub act: Act,
}

/// The whole `LlavaOnevisionForConditionalGeneration` config.
#[derive(Clone, Debug, PartialEq)]
pub struct LlavaConfig {
    pub vision: VisionConfig,
    pub text: TextConfig,
    pub image_token_id: u32,
    /// Index into the vision tower's hidden states (embeddings = 0, layer i = i + 1; negative from the end).
    pub vision_feature_layer: i64,
    pub projector_act: Act,
    pub projector_bias: bool,
    /// anyres grid pinpoints, (height, width) in pixels.
    pub pinpoints: Vec<(usize, usize)>,
    /// N of `anyres_max_N`: the anyres feature grid is shrunk to about N base grids.
    pub max_num_patches: usize,
}

impl LlavaConfig {
    /// Number of vision layers that must run to produce the selected hidden state.
    pub fn vision_layers_needed(&self) -> usize {
        let n = self.vision.num_layers as i64;
        let idx =
            if self.vision_feature_layer < 0 { n + 1 + self.vision_feature_layer } else { self.vision_feature_layer };
        idx as usize
    }

    /// Parameter counts (vision tower layers actually used, projector, LLM) for memory estimates.
    pub fn parameter_counts(&self) -> ParameterCounts {
        let v = &self.vision;
        let (d, f) = (v.hidden_size, v.intermediate_size);
        let vision_layer = 4 * (d * d + d) + 2 * (2 * d) + (d * f + f) + (f * d + d);
        let vision =
            3 * v.patch_size * v.patch_size * d + d + v.tokens() * d + self.vision_layers_needed() * vision_layer;
        let t = &self.text;
        let dm = t.hidden_size;
        let projector = d * dm + dm + dm * dm + dm + dm; // + image_newline
        let kv = t.num_kv_heads * t.head_dim;
        let q = t.num_heads * t.head_dim;
        let text_layer = dm * q + q + 2 * (dm * kv + kv) + q * dm + 3 * dm * t.intermediate_size + 2 * dm;
        let embed = t.vocab_size * dm;
        let head = if t.tie_word_embeddings { 0 } else { t.vocab_size * dm };
        let text = embed + head + t.num_layers * text_layer + dm;
        ParameterCounts { vision, projector, text }
    }

    /// The published `llava-hf/llava-onevision-qwen2-0.5b-ov-hf` architecture (for size estimates only).
    pub fn onevision_0_5b() -> Self {
        Self::published(TextConfig {
            vocab_size: 152_000,
            hidden_size: 896,
            intermediate_size: 4864,
            num_layers: 24,
            num_heads: 14,
            num_kv_heads: 2,
            head_dim: 64,
            rms_norm_eps: 1e-6,
            rope_theta: 1e6,
            max_positions: 32_768,
            tie_word_embeddings: true,
            eos_token_ids: vec![151_645],
            act: Act::Silu,
        })
    }

    /// The published `llava-hf/llava-onevision-qwen2-7b-ov-hf` architecture (for size estimates only).
    pub fn onevision_7b() -> Self {
        Self::published(TextConfig {
            vocab_size: 152_128,
            hidden_size: 3584,
            intermediate_size: 18_944,
            num_layers: 28,
            num_heads: 28,
            num_kv_heads: 4,
            head_dim: 128,
            rms_norm_eps: 1e-6,
            rope_theta: 1e6,
            max_positions: 32_768,
            tie_word_embeddings: false,
            eos_token_ids: vec![151_645],
            act: Act::Silu,
        })
    }

    fn published(text: TextConfig) -> Self {
        LlavaConfig {
            vision: VisionConfig {
                hidden_size: 1152,
                intermediate_size: 4304,
                num_layers: 26,
                num_heads: 16,
                image_size: 384,
                patch_size: 14,
                layer_norm_eps: 1e-6,
                act: Act::GeluTanh,
            },
            text,
            image_token_id: 151_646,
            vision_feature_layer: -1,
            projector_act: Act::Gelu,
            projector_bias: true,
            pinpoints: (1..=6).flat_map(|h| (1..=6).map(move |w| (384 * h, 384 * w))).collect(),
            max_num_patches: 9,
        }
    }
}

/// Parameter counts by part.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ParameterCounts {
    pub vision: usize,
    pub projector: usize,
    pub text: usize,
}

impl ParameterCounts {
    pub fn total(&self) -> usize {
        self.vision + self.projector + self.text
    }
}

/// The image processor settings (`preprocessor_config.json`, or `processor_config.json["image_processor"]`).
#[derive(Clone, Debug, PartialEq)]
pub struct ProcessorConfig {
    pub mean: [f32; 3],
    pub std: [f32; 3],
    pub rescale_factor: f64,
    /// Base view size (height, width).
    pub size: (usize, usize),
    /// PIL resample filter: 2 = bilinear, 3 = bicubic.
    pub resample: u32,
    pub pinpoints: Vec<(usize, usize)>,
}
