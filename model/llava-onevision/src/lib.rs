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
//!
//! Its own crate below `model`: it needs only the seeded generator and the panic guard of
//! `base`, so the language field and chat depend on it and never the other way (`model`
//! re-exports it as `model::vlm`).
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub mod config;
pub mod conversation;
pub mod cpu;
pub mod generate;
pub mod host;
pub mod layers;
pub mod llava;
pub mod preprocess;
pub mod qwen2;
pub mod siglip;
pub mod tokenizer;
pub mod weights;

pub use config::{LlavaConfig, ProcessorConfig};
pub use conversation::{Exchange, PromptCache};
pub use generate::{GenerateOptions, Generation, MAX_NEW_TOKENS, max_new_tokens_limit};
pub use llava::LlavaOnevision;
pub use preprocess::RgbImage;
pub use tokenizer::{ChatTokenizer, PromptLayout, Turn, chat_template, chat_template_in};

use std::path::{Path, PathBuf};

/// Directory name of the built-in model under `checkpoints/`: the LLaVA-OneVision trained for the
/// synthetic tabletops (`chatsplat train-vlm`).
pub const DEFAULT_MODEL: &str = "tabletop-llava-ov";
/// Environment variable naming the LLaVA-OneVision directory to use when none is given.
pub const MODEL_ENV: &str = "CHATSPLAT_VLM";

/// The model used when none is given: `$CHATSPLAT_VLM`, else `checkpoints/tabletop-llava-ov` beside
/// the executable or up to three directories above it (a cargo `target/<profile>/` build), else
/// in the working directory. The error lists every place it looked.
pub fn default_model_dir() -> Result<PathBuf, VlmError> {
    if let Some(dir) = std::env::var_os(MODEL_ENV).filter(|v| !v.is_empty()) {
        let dir = PathBuf::from(dir);
        return if dir.join("config.json").is_file() {
            Ok(dir)
        } else {
            Err(VlmError::config(&dir, format!("(from {MODEL_ENV}) holds no config.json of a LLaVA-OneVision model")))
        };
    }
    let mut looked = Vec::new();
    let exe = std::env::current_exe().ok().and_then(|e| e.parent().map(Path::to_path_buf));
    let mut bases: Vec<PathBuf> = exe.iter().flat_map(|d| d.ancestors().take(4).map(Path::to_path_buf)).collect();
    bases.extend(std::env::current_dir().ok());
    for base in bases {
        let dir = base.join("checkpoints").join(DEFAULT_MODEL);
        if dir.join("config.json").is_file() {
            return Ok(dir);
        }
        looked.push(dir.display().to_string());
    }
    Err(VlmError::Config {
        path: format!("the built-in model ({DEFAULT_MODEL})"),
        message: format!("not found; looked in {}; give --vlm DIR or set {MODEL_ENV}", looked.join(", ")),
    })
}

/// Loader and prompt errors; each names the file (or says it is about the prompt).
#[derive(Debug, thiserror::Error)]
pub enum VlmError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Config { path: String, message: String },
    #[error("{path}: {message}")]
    Weights { path: String, message: String },
    #[error("prompt: {0}")]
    Prompt(String),
}

impl VlmError {
    pub fn io(path: &Path, e: std::io::Error) -> Self {
        VlmError::Io { path: path.display().to_string(), source: e }
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
