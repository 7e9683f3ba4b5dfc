//! A fresh tabletop model of a configuration, and the llava-hf directory it is written to.

use super::VlmTrainConfig;
use burn::tensor::Device;
use model::data::synth::questions::vocabulary;
use model::error::Result;
use model::io;
use model::vlm::LlavaOnevision;
use model::vlm::tokenizer::{ChatTokenizer, word_level_tokenizer_json};
use std::path::Path;

/// A fresh tabletop VLM of `cfg`'s shape, with its word-level tokenizer.
pub fn init_model(cfg: &VlmTrainConfig, device: &Device) -> Result<LlavaOnevision> {
    let json = word_level_tokenizer_json(&vocabulary())?;
    let tokenizer = ChatTokenizer::from_json(&json, 3)?;
    let llava = cfg.llava_config(tokenizer.vocab_size());
    Ok(LlavaOnevision::init(llava, cfg.processor(), tokenizer, cfg.seed, device))
}

/// Writes a model directory a llava-hf loader reads: `config.json`, `processor_config.json`,
/// `tokenizer.json`, `tokenizer_config.json`, `chat_template.jinja`, `generation_config.json`
/// and `model.safetensors` (f32), each atomically.
pub fn save_model(vlm: &LlavaOnevision, dir: &Path) -> Result<usize> {
    save_model_as(vlm, dir, false)
}

/// [`save_model`], with the weights in bf16 when `bf16` (as the llava-hf checkpoints store them).
pub fn save_model_as(vlm: &LlavaOnevision, dir: &Path, bf16: bool) -> Result<usize> {
    io::create_dir(dir)?;
    io::write_json(&dir.join("config.json"), &vlm.cfg.to_hf_json())?;
    io::write_json(&dir.join("processor_config.json"), &vlm.processor.to_hf_json(&vlm.cfg))?;
    io::write_atomic(&dir.join("tokenizer.json"), vlm.tokenizer.to_json()?.as_bytes())?;
    let tok_cfg = serde_json::json!({
        "backend": "tokenizers", "eos_token": "<|im_end|>", "pad_token": "<|endoftext|>", "unk_token": "<unk>",
        "image_token": "<image>", "video_token": "<video>", "model_max_length": 4096,
        "processor_class": "LlavaOnevisionProcessor", "tokenizer_class": "PreTrainedTokenizerFast",
    });
    io::write_json(&dir.join("tokenizer_config.json"), &tok_cfg)?;
    io::write_atomic(&dir.join("chat_template.jinja"), vlm.tokenizer.layout.jinja().as_bytes())?;
    let gen_cfg = serde_json::json!({"eos_token_id": vlm.cfg.text.eos_token_ids, "pad_token_id": 0});
    io::write_json(&dir.join("generation_config.json"), &gen_cfg)?;
    let tensors = vlm.export();
    let weights = dir.join("model.safetensors");
    io::write_atomic(&weights, &tensors.to_bytes(&weights, bf16)?)?;
    Ok(tensors.count())
}
