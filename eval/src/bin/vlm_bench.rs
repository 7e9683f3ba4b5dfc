//! `vlm-bench`: speed of the LLaVA-OneVision port (vision tower images/s, LLM prefill and decode
//! tokens/s) on a model directory (default: the tiny parity fixture), per backend, and the
//! parameter counts and memory of the published 0.5B and 7B models.
//!
//! cargo run --release -p eval --bin vlm-bench -- [--vlm DIR] [--backend ndarray|wgpu ...]
#![allow(deprecated)]

use burn::tensor::Tensor;
use clap::Parser;
use model::vlm::config::LlavaConfig;
use model::vlm::{GenerateOptions, LlavaOnevision, RgbImage};
use model::{Backend, catch_backend};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Parser)]
#[command(name = "vlm-bench", about = "LLaVA-OneVision port: speed and memory")]
struct Args {
    /// Model directory (default: the built-in model).
    #[arg(long)]
    vlm: Option<PathBuf>,
    #[arg(long, num_args = 1.., default_values_t = [Backend::Ndarray, Backend::Wgpu])]
    backend: Vec<Backend>,
    /// Timed repetitions.
    #[arg(long, default_value_t = 5)]
    reps: usize,
    /// Decoded tokens per repetition.
    #[arg(long, default_value_t = 32)]
    decode: usize,
    /// Time a random-weight model of the published configuration (`0.5b` or `7b`) built in
    /// memory instead of a directory (no download, no Python; a word-level tokenizer).
    #[arg(long)]
    random: Option<String>,
}

/// A random-weight LLaVA-OneVision of the published `size` configuration.
fn random_model(size: &str, device: &burn::tensor::Device) -> model::Result<LlavaOnevision> {
    use model::vlm::tokenizer::{ChatTokenizer, word_level_tokenizer_json};
    let mut cfg = match size {
        "0.5b" => LlavaConfig::onevision_0_5b(),
        "7b" => LlavaConfig::onevision_7b(),
        other => return Err(model::Error::input(format!("--random {other}: expected 0.5b or 7b"))),
    };
    let words = model::data::synth::questions::vocabulary();
    let tokenizer = ChatTokenizer::from_json(&word_level_tokenizer_json(&words)?, 3)?;
    cfg.image_token_id = tokenizer.image_token_id;
    let processor = model::vlm::ProcessorConfig {
        mean: [0.5; 3],
        std: [0.5; 3],
        rescale_factor: 1.0 / 255.0,
        size: (384, 384),
        resample: 3,
        pinpoints: cfg.pinpoints.clone(),
    };
    Ok(LlavaOnevision::init(cfg, processor, tokenizer, 0, device))
}

fn sync(t: Tensor<2>) {
    let _ = t.into_data();
}

fn gib(bytes: f64) -> String {
    format!("{:.2}", bytes / (1u64 << 30) as f64)
}

fn memory_table(name: &str, cfg: &LlavaConfig) {
    let p = cfg.parameter_counts();
    let t = &cfg.text;
    let kv_per_token = 2 * t.num_layers * t.num_kv_heads * t.head_dim;
    // Largest transient: the vision tower's attention scores for an anyres image of 10 views.
    let attn = 10 * cfg.vision.num_heads * cfg.vision.tokens() * cfg.vision.tokens();
    println!(
        "| {name} | {:.3} M | {:.3} M | {:.3} M | {:.3} M | {} | {} | {} | {} |",
        p.vision as f64 / 1e6,
        p.projector as f64 / 1e6,
        p.text as f64 / 1e6,
        p.total() as f64 / 1e6,
        gib(p.total() as f64 * 4.0),
        gib(p.total() as f64 * 2.0),
        gib(kv_per_token as f64 * 4.0 * 4096.0),
        gib(attn as f64 * 4.0),
    );
}

fn main() -> std::process::ExitCode {
    let a = Args::parse();
    let dir = match a.vlm.clone().map(Ok).unwrap_or_else(model::vlm::default_model_dir) {
        Ok(d) => d,
        Err(e) => {
            eprintln!("error: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    match &a.random {
        Some(size) => println!("## vlm-bench: random-weight {size} (published configuration)"),
        None => println!("## vlm-bench: {}", dir.display()),
    }
    println!();
    println!(
        "| backend | vision tower (1 view 384x384) | images/s | anyres image (3 views) | prefill tokens | \
            prefill tokens/s | decode tokens/s |"
    );
    println!("|---|---|---|---|---|---|---|");
    for backend in &a.backend {
        let r = catch_backend("benchmark", || -> model::Result<String> {
            let device = backend.device();
            let m = match &a.random {
                Some(size) => random_model(size, &device)?,
                None => LlavaOnevision::load(&dir, &device)?,
            };
            let img = RgbImage::read_png(&dir.join("image_wide.png")).unwrap_or_else(|_| {
                let (w, h) = (700, 300);
                RgbImage::new(w, h, (0..w * h * 3).map(|i| (i * 37 % 256) as u8).collect())
            });
            // Vision tower alone, one base view.
            let one = m.preprocess(&img, true);
            let px = m.pixels(&one);
            sync(m.vision_features(px.clone()).reshape([-1, 1]).narrow(0, 0, 1)); // warm-up (kernel compilation)
            let t0 = Instant::now();
            for _ in 0..a.reps {
                sync(m.vision_features(px.clone()).reshape([-1, 1]).narrow(0, 0, 1));
            }
            let vis = t0.elapsed().as_secs_f64() / a.reps as f64;
            // Whole anyres image -> packed embeddings.
            let p = m.preprocess(&img, false);
            sync(m.image_embeds(&p));
            let t0 = Instant::now();
            for _ in 0..a.reps {
                sync(m.image_embeds(&p));
            }
            let anyres = t0.elapsed().as_secs_f64() / a.reps as f64;
            // Prefill of the full prompt and decode.
            let embeds = m.prompt_embeds("What is on the table?", &[m.image_embeds(&p)])?;
            let prompt_tokens = embeds.dims()[0];
            let opts = GenerateOptions { max_new_tokens: 1, ignore_stop: true, ..Default::default() };
            m.generate(embeds.clone(), &opts, |_| {})?;
            let t0 = Instant::now();
            for _ in 0..a.reps {
                m.generate(embeds.clone(), &opts, |_| {})?;
            }
            let prefill = t0.elapsed().as_secs_f64() / a.reps as f64;
            let opts = GenerateOptions { max_new_tokens: a.decode + 1, ignore_stop: true, ..Default::default() };
            m.generate(embeds.clone(), &opts, |_| {})?;
            let t0 = Instant::now();
            for _ in 0..a.reps {
                m.generate(embeds.clone(), &opts, |_| {})?;
            }
            let total = t0.elapsed().as_secs_f64() / a.reps as f64;
            let decode = (total - prefill).max(1e-9);
            Ok(format!(
                "| {backend} | {:.1} ms | {:.1} | {:.1} ms | {} | {:.0} | {:.1} |",
                vis * 1e3,
                1.0 / vis,
                anyres * 1e3,
                prompt_tokens,
                prompt_tokens as f64 / prefill,
                a.decode as f64 / decode
            ))
        });
        match r {
            Ok(Ok(line)) => println!("{line}"),
            Ok(Err(e)) | Err(e) => println!("| {backend} | n/a: {e} | | | | | |"),
        }
    }
    println!();
    println!(
        "Parameters and memory (weights as loaded here in f32, and f16 as stored; KV cache for 4,096 tokens \
            in f32; vision attention scores of one 10-view anyres image in f32):"
    );
    println!();
    println!(
        "| model | vision (used layers) | projector | LLM | total | weights f32 GiB | weights f16 GiB | KV 4k \
            GiB | vision attn GiB |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    if let Ok(cfg) = LlavaOnevision::load(&dir, &burn::tensor::Device::ndarray()).map(|m| m.cfg) {
        memory_table("this directory", &cfg);
    }
    memory_table("llava-onevision-qwen2-0.5b-ov-hf", &LlavaConfig::onevision_0_5b());
    memory_table("llava-onevision-qwen2-7b-ov-hf", &LlavaConfig::onevision_7b());
    std::process::ExitCode::SUCCESS
}
