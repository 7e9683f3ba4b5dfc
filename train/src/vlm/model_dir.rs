//! A fresh tabletop model of a configuration, and the llava-hf directory it is written to.

use super::VlmTrainConfig;
use burn::tensor::Device;
use model::data::synth::questions::{conversation_vocabulary, vocabulary};
use model::error::Result;
use model::io;
use model::vlm::tokenizer::{ChatTokenizer, word_level_tokenizer_json};
use model::vlm::{LlavaConfig, LlavaOnevision, ProcessorConfig};
use std::path::Path;

/// A fresh tabletop VLM of `cfg`'s shape, with its word-level tokenizer (the conversations'
/// vocabulary where `cfg` asks two-turn questions).
pub fn init_model(cfg: &VlmTrainConfig, device: &Device) -> Result<LlavaOnevision> {
    let tokenizer = if cfg.two_turn > 0.0 { conversation_tokenizer()? } else { synthetic_tokenizer()? };
    let llava = cfg.llava_config(tokenizer.vocab_size());
    Ok(LlavaOnevision::init(llava, cfg.processor(), tokenizer, cfg.seed, device))
}

/// A random-weight LLaVA-OneVision of a published architecture (`cfg`, for example
/// [`LlavaConfig::onevision_0_5b`], with whatever depths the caller set), the synthetic questions'
/// word-level tokenizer and SigLIP's processor (mean and std 0.5, `image_size` squares): what
/// `vlm-bench --random` times and the real-size tests run through every stage. The vocabulary is
/// raised to the tokenizer's where it is smaller (set `cfg.text.vocab_size = 0` for exactly the
/// tokenizer's), and generation stops on the tokenizer's stop tokens. With `half` the weights are
/// held in f16 as they are drawn.
pub fn random_published(mut cfg: LlavaConfig, seed: u64, device: &Device, half: bool) -> Result<LlavaOnevision> {
    let tokenizer = synthetic_tokenizer()?;
    cfg.image_token_id = tokenizer.image_token_id;
    cfg.text.vocab_size = cfg.text.vocab_size.max(tokenizer.vocab_size());
    cfg.text.eos_token_ids = tokenizer.stop_ids.clone();
    let processor = ProcessorConfig::siglip(cfg.vision.image_size, cfg.pinpoints.clone());
    Ok(LlavaOnevision::init_with(cfg, processor, tokenizer, seed, device, half))
}

/// The word-level tokenizer of the synthetic questions' vocabulary.
fn synthetic_tokenizer() -> Result<ChatTokenizer> {
    Ok(ChatTokenizer::from_json(&word_level_tokenizer_json(&vocabulary())?, 3)?)
}

/// The word-level tokenizer of conversations about the synthetic scenes (the questions' words and
/// "it").
fn conversation_tokenizer() -> Result<ChatTokenizer> {
    Ok(ChatTokenizer::from_json(&word_level_tokenizer_json(&conversation_vocabulary())?, 3)?)
}

/// `vlm` reading the conversations' vocabulary (a base stage's model, trained on single questions,
/// before a two-turn stage): "it" starts as "this" reads, which object follow-ups ask in its place.
pub fn conversing(vlm: LlavaOnevision) -> Result<LlavaOnevision> {
    let tokenizer = conversation_tokenizer()?;
    if tokenizer.vocab_size() == vlm.tokenizer.vocab_size() {
        return Ok(vlm);
    }
    Ok(vlm.with_vocabulary(tokenizer, |t| (t == "it").then_some("this"))?)
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
    let count = tensors.count();
    let weights = dir.join("model.safetensors");
    io::write_atomic_with(&weights, |tmp| Ok(tensors.write(tmp, bf16)?))?;
    Ok(count)
}
