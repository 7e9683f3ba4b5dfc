//! LLaVA-OneVision on burn: SigLIP vision tower, projector, Qwen2 decoder, tokenizer and chat
//! template, loaded from a local Hugging Face model directory
//! (`llava-hf/llava-onevision-qwen2-{0.5b,7b}-ov-hf`). ChatSplat distils the vision tower's patch
//! features into the Gaussians and chats through the LLM with `inputs_embeds`.
//!
//! Data flow (shapes for the real model; the tiny fixture only narrows the widths):
//! image (H, W, RGB u8) -> [`preprocess`] -> views `[V, 3, 384, 384]` -> [`siglip::VisionTower`]
//! -> `[V, 729, 1152]` (the teacher tokens) -> [`llava::Projector`] -> `[V, 729, 896]` ->
//! [`llava::LlavaOnevision::pack`] -> `[N, 896]` -> spliced at the `<image>` placeholders ->
//! [`qwen2::Qwen2`] -> logits `[T, vocab]`.

pub mod config;
pub mod generate;
pub mod layers;
pub mod llava;
pub mod preprocess;
pub mod qwen2;
pub mod siglip;
pub mod tokenizer;
pub mod weights;

pub use config::{LlavaConfig, ProcessorConfig};
pub use generate::{GenerateOptions, Generation};
pub use llava::LlavaOnevision;
pub use preprocess::RgbImage;
pub use tokenizer::{chat_template, ChatTokenizer, Turn};

use std::path::Path;

/// Loader and prompt errors; each names the file (or says it is about the prompt).
#[derive(Debug)]
pub enum VlmError {
    Io { path: String, message: String },
    Config { path: String, message: String },
    Weights { path: String, message: String },
    Prompt(String),
}

impl VlmError {
    pub fn io(path: &Path, e: std::io::Error) -> Self {
        VlmError::Io { path: path.display().to_string(), message: e.to_string() }
    }
    pub fn config(path: &Path, message: impl Into<String>) -> Self {
        VlmError::Config { path: path.display().to_string(), message: message.into() }
    }
    pub fn weights(path: &Path, message: impl Into<String>) -> Self {
        VlmError::Weights { path: path.display().to_string(), message: message.into() }
    }
    pub fn prompt(message: impl Into<String>) -> Self {
        VlmError::Prompt(message.into())
    }
}

impl std::fmt::Display for VlmError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            VlmError::Io { path, message } => write!(f, "{path}: {message}"),
            VlmError::Config { path, message } => write!(f, "{path}: {message}"),
            VlmError::Weights { path, message } => write!(f, "{path}: {message}"),
            VlmError::Prompt(m) => write!(f, "prompt: {m}"),
        }
    }
}

impl std::error::Error for VlmError {}
