//! `vlm-bench`: speed of the LLaVA-OneVision port (vision tower images/s, LLM prefill and decode
//! tokens/s) on a model directory (default: the tiny parity fixture), per backend, a
//! conversation's follow-up against the same prompt prefilled afresh (first token), and the
//! parameter counts and memory of the published 0.5B and 7B models.
//!
//! cargo run --release -p eval --bin vlm-bench -- [--vlm DIR] [--backend flex|ndarray|wgpu ...]
//!     [--random 0.5b|7b] [--reference transformers.json] [--half]
//!
//! `--reference` reads the timings `eval/bench/transformers_vlm.py` wrote for transformers on
//! the same machine and prints both side by side, as ratios (`eval/bench/vlm_vs_transformers.sh`
//! runs the two one after the other).
#![allow(deprecated)]

use burn::tensor::Tensor;
use clap::Parser;
use eval::launches::count_launches;
use model::vlm::config::LlavaConfig;
use model::vlm::generate::{last_row, pick};
use model::vlm::{Exchange, GenerateOptions, LlavaOnevision, PromptCache, RgbImage};
use model::{Backend, catch_backend};
use std::ops::ControlFlow;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Parser)]
#[command(name = "vlm-bench", about = "LLaVA-OneVision port: speed and memory")]
struct Args {
    /// Model directory (default: the built-in model).
    #[arg(long)]
    vlm: Option<PathBuf>,
    #[arg(long, num_args = 1.., default_values_t = [Backend::Flex, Backend::Ndarray, Backend::Wgpu])]
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
    /// With `--random`: N layers in the vision tower and in the LLM instead of the published
    /// depths (the widths and token shapes stay; the real-size tests run such a model with 1).
    #[arg(long, value_name = "N", requires = "random", value_parser = clap::value_parser!(u64).range(1..=256))]
    layers: Option<u64>,
    /// Transformers' timings of the same configuration (JSON from eval/bench/transformers_vlm.py),
    /// printed beside this port's as ratios.
    #[arg(long)]
    reference: Option<PathBuf>,
    /// Hold the linear layers and embeddings in f16, as checkpoints store them (half the memory;
    /// activations, norms and attention stay f32). Needs a backend that holds f16 (flex, or wgpu
    /// on an adapter with f16 shaders).
    #[arg(long)]
    half: bool,
    /// With `--random`: write the random model to DIR as a llava-hf directory (bf16 weights, as
    /// the published checkpoints) and stop, so that loading it (`--vlm DIR`) can be measured.
    #[arg(long)]
    save: Option<PathBuf>,
    /// One pass of each stage without the warm-up passes, the prefill's cache reused for the
    /// decode (for the 7B model on a CPU, where a 2k-token prefill takes minutes; GPU backends
    /// want the warm-up for their kernels' compilation). Implies `--reps 1`.
    #[arg(long)]
    cold: bool,
}

/// One backend's figures.
struct Timing {
    /// Seconds: vision tower on one view, whole anyres image, prefill.
    vision: f64,
    anyres: f64,
    prefill: f64,
    prompt_tokens: usize,
    decode_tokens_per_s: f64,
    follow_up: FollowUp,
    /// Kernels launched on a CubeCL device: one tower pass, one prefill, one decoded token (the
    /// mean over the decoded tokens); `None` on the host backends.
    launches: Option<[usize; 3]>,
}

/// A conversation's second question: its prompt, the tokens its cache held, and the seconds to
/// its first token with that cache and prefilled afresh.
struct FollowUp {
    prompt_tokens: usize,
    cached_tokens: usize,
    cached: f64,
    fresh: f64,
}

/// Times the second question of a conversation about one base view (how ChatSplat feeds a token
/// grid) against the same prompt prefilled afresh: seconds to the first token, `reps` times each,
/// the conversation's first turn (16 tokens answered) rebuilt untimed before each.
fn follow_up(m: &LlavaOnevision, image: Tensor<2>, reps: usize, warm_up: bool) -> model::Result<FollowUp> {
    let counts = [image.dims()[0]];
    let images = [image];
    let first = GenerateOptions { max_new_tokens: 16, ignore_stop: true, ..Default::default() };
    let one = GenerateOptions { max_new_tokens: 1, ..first.clone() };
    let go = |ids: &[u32], images: &[Tensor<2>], cache: &mut PromptCache, opts: &GenerateOptions| {
        m.generate_cached(ids, images, cache, opts, |_| ControlFlow::Continue(()))
    };
    let q1 = "What is on the table?";
    let ids1 = m.conversation_ids(&[], q1, &counts)?;
    let opened = || -> model::Result<(PromptCache, String)> {
        let mut cache = PromptCache::default();
        let answer = go(&ids1, &images, &mut cache, &first)?.text;
        Ok((cache, answer))
    };
    let (_, answer) = opened()?;
    let earlier = [Exchange { question: q1.into(), answer }];
    let ids2 = m.conversation_ids(&earlier, "Is it left of the blue cube?", &counts)?;
    if warm_up {
        go(&ids2, &images, &mut PromptCache::default(), &one)?;
    }
    let (mut cached, mut fresh, mut cached_tokens) = (0.0, 0.0, 0);
    for _ in 0..reps {
        let (mut cache, _) = opened()?;
        let t0 = Instant::now();
        cached_tokens = go(&ids2, &[], &mut cache, &one)?.cached_tokens;
        cached += t0.elapsed().as_secs_f64() / reps as f64;
        let t0 = Instant::now();
        go(&ids2, &images, &mut PromptCache::default(), &one)?;
        fresh += t0.elapsed().as_secs_f64() / reps as f64;
    }
    Ok(FollowUp { prompt_tokens: ids2.len(), cached_tokens, cached, fresh })
}

/// What eval/bench/transformers_vlm.py writes (the fields read here).
#[derive(serde::Deserialize)]
struct Reference {
    size: String,
    threads: usize,
    vision_s: f64,
    prefill_tokens: usize,
    prefill_tokens_per_s: f64,
    decode_tokens_per_s: f64,
    transformers: String,
    torch: String,
}

fn read_reference(path: &std::path::Path) -> model::Result<Reference> {
    let text = std::fs::read_to_string(path).map_err(|e| model::Error::io(path, "cannot read", e))?;
    let r: Reference = serde_json::from_str(&text)
        .map_err(|e| model::Error::input(format!("{}: not a transformers_vlm.py result: {e}", path.display())))?;
    let rates = [r.vision_s, r.prefill_tokens_per_s, r.decode_tokens_per_s];
    if rates.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(model::Error::input(format!("{}: timings must be positive numbers", path.display())));
    }
    Ok(r)
}

/// The side-by-side table: per stage transformers, this port, and this port's speed relative
/// to transformers (> 1: faster).
fn print_reference(r: &Reference, timings: &[(Backend, Timing)]) {
    println!();
    println!(
        "Side by side with transformers {} / torch {} ({} threads, random {} of the same configuration):",
        r.transformers, r.torch, r.threads, r.size
    );
    println!();
    println!("| stage | transformers | backend | chatsplat | chatsplat / transformers |");
    println!("|---|---|---|---|---|");
    for (backend, t) in timings {
        let prefill = t.prompt_tokens as f64 / t.prefill;
        println!(
            "| vision tower, one 384x384 view | {:.2} s | {backend} | {:.2} s | {:.2}x |",
            r.vision_s,
            t.vision,
            r.vision_s / t.vision
        );
        println!(
            "| prefill ({} / {} tokens) | {:.0} tokens/s | {backend} | {prefill:.0} tokens/s | {:.2}x |",
            r.prefill_tokens,
            t.prompt_tokens,
            r.prefill_tokens_per_s,
            prefill / r.prefill_tokens_per_s
        );
        println!(
            "| decode with KV cache | {:.2} tokens/s | {backend} | {:.2} tokens/s | {:.2}x |",
            r.decode_tokens_per_s,
            t.decode_tokens_per_s,
            t.decode_tokens_per_s / r.decode_tokens_per_s
        );
        if t.prompt_tokens != r.prefill_tokens {
            println!("(prefill lengths differ: pass --prefill-tokens {} to transformers_vlm.py)", t.prompt_tokens);
        }
    }
}

/// A random-weight LLaVA-OneVision of the published `size` configuration, `layers` deep in the
/// tower and the LLM when given ([`train::vlm::random_published`]).
fn random_model(
    size: &str,
    layers: Option<usize>,
    device: &burn::tensor::Device,
    half: bool,
) -> model::Result<LlavaOnevision> {
    let mut cfg = match size {
        "0.5b" => LlavaConfig::onevision_0_5b(),
        "7b" => LlavaConfig::onevision_7b(),
        other => return Err(model::Error::input(format!("--random {other}: expected 0.5b or 7b"))),
    };
    if let Some(n) = layers {
        (cfg.vision.num_layers, cfg.text.num_layers) = (n, n);
    }
    train::vlm::random_published(cfg, 0, device, half)
}

/// "on" or "off".
fn on(yes: bool) -> &'static str {
    if yes { "on" } else { "off" }
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

eval::bench_main!("vlm-bench", bench);

fn bench(a: &Args) -> model::Result<()> {
    let reference = a.reference.as_deref().map(read_reference).transpose()?;
    let dir = eval::harness::vlm_dir(a.vlm.as_deref())?;
    let layers = a.layers.map(|n| n as usize);
    if let Some(out) = &a.save {
        let Some(size) = &a.random else {
            return Err(model::Error::input("--save writes a --random model: pass --random 0.5b"));
        };
        // drawn in f16 (written in bf16 anyway): the peak is the f16 model and one f32 copy for the
        // writer, under twice the model's f32 size
        let m = random_model(size, layers, &burn::tensor::Device::flex(), true)?;
        let n = train::vlm::save_model_as(&m, out, true)?;
        println!("random {size}: {n} parameters (bf16) -> {}", out.display());
        return Ok(());
    }
    match &a.random {
        Some(size) => println!("## vlm-bench: random-weight {size} (published configuration)"),
        None => println!("## vlm-bench: {}", dir.display()),
    }
    if a.half {
        println!("(linear layers and embeddings held in f16)");
    }
    if a.backend.contains(&Backend::Wgpu) {
        match Backend::Wgpu.device().and_then(|d| catch_backend("wgpu", || splat_kernels::cube::adapter_report(&d))) {
            Ok(Some(line)) => {
                println!(
                    "{line}; burn autotune {}, fusion {}",
                    on(cfg!(feature = "autotune")),
                    on(cfg!(feature = "fusion"))
                )
            }
            Ok(None) => println!("wgpu: no adapter"),
            Err(e) => println!("{e}"),
        }
    }
    println!();
    println!(
        "| backend | vision tower (1 view 384x384) | images/s | anyres image (3 views) | prefill tokens | \
            prefill tokens/s | decode tokens/s |"
    );
    println!("|---|---|---|---|---|---|---|");
    let mut timings = Vec::new();
    for backend in &a.backend {
        if a.half && !backend.holds_half() {
            println!(
                "| {backend} | n/a: --half needs f16 matmuls (flex, or wgpu on an adapter with f16 shaders) | | | | | |"
            );
            continue;
        }
        let r = catch_backend("benchmark", || -> model::Result<Timing> {
            let device = backend.device()?;
            let m = match &a.random {
                Some(size) => random_model(size, layers, &device, a.half)?,
                None => LlavaOnevision::load_with(&dir, &device, a.half)?,
            };
            if let Some(gib) = scoring::progress::peak_rss_gib() {
                eprintln!("{backend}: model ready, peak resident memory so far {gib:.2} GiB");
            }
            let img = model::images::read_rgb_image(&dir.join("image_wide.png")).unwrap_or_else(|_| {
                let (w, h) = (700, 300);
                RgbImage::new(w, h, (0..w * h * 3).map(|i| (i * 37 % 256) as u8).collect())
            });
            let reps = if a.cold { 1 } else { a.reps };
            let warm_up = |f: &dyn Fn()| {
                if !a.cold {
                    f()
                }
            };
            // Vision tower alone, one base view.
            let one = m.preprocess(&img, true);
            let px = m.pixels(&one);
            let tower = || sync(m.vision_features(px.clone()).reshape([-1, 1]).narrow(0, 0, 1));
            warm_up(&tower); // kernel compilation
            let t0 = Instant::now();
            (0..reps).for_each(|_| tower());
            let vis = t0.elapsed().as_secs_f64() / reps as f64;
            // Whole anyres image -> packed embeddings.
            let p = m.preprocess(&img, false);
            warm_up(&|| sync(m.image_embeds(&p)));
            let t0 = Instant::now();
            (0..reps).for_each(|_| sync(m.image_embeds(&p)));
            let anyres = t0.elapsed().as_secs_f64() / reps as f64;
            // Prefill of the full prompt (a KV cache filled and the first token picked), then decode
            // timed on its own (not total minus prefill, whose jitter would swamp it): greedy steps
            // of one token each after that cache.
            let embeds = m.prompt_embeds("What is on the table?", &[m.image_embeds(&p)])?;
            let prompt_tokens = embeds.dims()[0];
            let greedy = GenerateOptions { temperature: 0.0, ..Default::default() };
            let mut rng = model::rng::Rng::new(0);
            // as `generate` does: logits of the last position only
            let last_logits = |cache: &mut model::vlm::qwen2::KvCache| {
                let h = m.llm.forward(embeds.clone(), cache);
                last_row(m.llm.logits(h.narrow(0, prompt_tokens - 1, 1)))
            };
            warm_up(&|| drop(last_logits(&mut Default::default())));
            // `a.decode` greedy steps of one token each after `cache`, from `next`
            let decode_tokens = |cache: &mut model::vlm::qwen2::KvCache, mut next: u32, rng: &mut model::rng::Rng| {
                for _ in 0..a.decode {
                    let h = m.llm.forward(m.llm.embed(&[next]), cache);
                    next = pick(&last_row(m.llm.logits(h)), &greedy, rng);
                }
            };
            let (mut prefill, mut decode) = (0.0, f64::INFINITY);
            for _ in 0..reps {
                let t0 = Instant::now();
                let mut cache = model::vlm::qwen2::KvCache::with_capacity(prompt_tokens + a.decode + 1);
                let next = pick(&last_logits(&mut cache), &greedy, &mut rng);
                prefill += t0.elapsed().as_secs_f64() / reps as f64;
                let t0 = Instant::now();
                decode_tokens(&mut cache, next, &mut rng);
                decode = decode.min(t0.elapsed().as_secs_f64());
            }
            // kernel launches, counted on warm kernels (after the timed runs: no autotune trials)
            let launches = splat_kernels::api::on_cube(&device).then(|| {
                let (_, vision) = count_launches(tower);
                let mut cache = model::vlm::qwen2::KvCache::with_capacity(prompt_tokens + a.decode + 1);
                let (next, prefill) = count_launches(|| pick(&last_logits(&mut cache), &greedy, &mut rng));
                let (_, decode) = count_launches(|| decode_tokens(&mut cache, next, &mut rng));
                [vision, prefill, decode / a.decode.max(1)]
            });
            let follow_up = follow_up(&m, m.image_embeds(&one), reps, !a.cold)?;
            Ok(Timing {
                vision: vis,
                anyres,
                prefill,
                prompt_tokens,
                decode_tokens_per_s: a.decode as f64 / decode,
                follow_up,
                launches,
            })
        });
        match r {
            Ok(Ok(t)) => {
                println!(
                    "| {backend} | {:.1} ms | {:.1} | {:.1} ms | {} | {:.0} | {:.1} |",
                    t.vision * 1e3,
                    1.0 / t.vision,
                    t.anyres * 1e3,
                    t.prompt_tokens,
                    t.prompt_tokens as f64 / t.prefill,
                    t.decode_tokens_per_s
                );
                timings.push((*backend, t));
            }
            Ok(Err(e)) | Err(e) => println!("| {backend} | n/a: {e} | | | | | |"),
        }
    }
    for (backend, t) in &timings {
        if let Some([vision, prefill, decode]) = t.launches {
            println!();
            println!(
                "{backend} kernel launches (burn fusion {}): vision tower {vision}, prefill {prefill}, decode {decode} \
                    per token",
                on(cfg!(feature = "fusion"))
            );
        }
    }
    println!();
    println!(
        "A conversation's second question about one base view, to its first token: its earlier turn's keys \
            and values kept (the cache) against the same prompt prefilled afresh:"
    );
    println!();
    println!(
        "| backend | follow-up prompt tokens | of them cached | first token, cached | first token, afresh | ratio |"
    );
    println!("|---|---|---|---|---|---|");
    for (backend, t) in &timings {
        let f = &t.follow_up;
        println!(
            "| {backend} | {} | {} | {:.1} ms | {:.1} ms | {:.2} |",
            f.prompt_tokens,
            f.cached_tokens,
            f.cached * 1e3,
            f.fresh * 1e3,
            f.cached / f.fresh
        );
    }
    if let Some(r) = &reference {
        print_reference(r, &timings);
    }
    if let Some(gib) = scoring::progress::peak_rss_gib() {
        println!();
        println!("Peak resident memory of this run: {gib:.2} GiB");
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
    if let Ok(cfg) = model::vlm::config::read_llava_config(&dir) {
        memory_table("this directory", &cfg);
    }
    memory_table("llava-onevision-qwen2-0.5b-ov-hf", &LlavaConfig::onevision_0_5b());
    memory_table("llava-onevision-qwen2-7b-ov-hf", &LlavaConfig::onevision_7b());
    Ok(())
}
