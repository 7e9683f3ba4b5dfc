//! `sam-bench`: speed of Segment Anything's automatic masks (`sam::automatic`) on one image: the
//! image embeddings alone, then the whole generation (embeddings, a grid of point prompts decoded
//! in batches, the filters, box NMS), per backend.
//!
//! cargo build --workspace --profile test --bin sam-bench
//! target/debug/sam-bench --model DIR --image PATH [--backend flex ndarray] [--reference t.json]
//!
//! `--reference` reads what `eval/bench/transformers_sam.py` measured for transformers' pipeline
//! on the same model, image and machine and prints both side by side, as ratios
//! (`eval/bench/sam_vs_transformers.sh` runs the two one after the other).

use clap::Parser;
use model::Backend;
use model::data::read_rgb_any;
use sam::Sam;
use sam::automatic::{AutoOptions, Filters};
use std::path::PathBuf;
use std::time::Instant;

#[derive(Parser)]
#[command(name = "sam-bench", about = "Segment Anything's automatic masks: speed")]
struct Args {
    /// A SAM model directory (transformers' layout: config.json, model.safetensors).
    #[arg(long)]
    model: PathBuf,
    /// The image (PNG or JPEG).
    #[arg(long)]
    image: PathBuf,
    #[arg(long, num_args = 1.., default_values_t = [Backend::Flex, Backend::Ndarray])]
    backend: Vec<Backend>,
    /// Points per side of the prompt grid.
    #[arg(long, default_value_t = 32)]
    points: usize,
    /// Point prompts decoded together.
    #[arg(long, default_value_t = 64)]
    batch: usize,
    #[arg(long, default_value_t = Filters::default().pred_iou)]
    pred_iou: f32,
    #[arg(long, default_value_t = Filters::default().stability)]
    stability: f32,
    /// transformers' timings (JSON from eval/bench/transformers_sam.py), printed beside these.
    #[arg(long)]
    reference: Option<PathBuf>,
}

fn main() {
    if let Err(e) = run(Args::parse()) {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run(a: Args) -> Result<(), String> {
    let img = read_rgb_any(&a.image).map_err(|e| e.to_string())?;
    let reference: Option<serde_json::Value> = match &a.reference {
        Some(p) => Some(
            std::fs::read_to_string(p)
                .map_err(|e| format!("{}: {e}", p.display()))
                .and_then(|s| serde_json::from_str(&s).map_err(|e| format!("{}: {e}", p.display())))?,
        ),
        None => None,
    };
    let o = AutoOptions {
        points_per_side: a.points,
        points_per_batch: a.batch,
        filters: Filters { pred_iou: a.pred_iou, stability: a.stability, ..Filters::default() },
    };
    println!(
        "image {}x{}, {}x{} points in batches of {}, {} threads",
        img.width,
        img.height,
        a.points,
        a.points,
        a.batch,
        rayon_threads()
    );
    println!(
        "| backend | load | image embeddings | automatic masks | of which: embeddings, decoding, masks, NMS | \
         masks passing / kept |"
    );
    println!("|---|---|---|---|---|---|");
    let mut rows = Vec::new();
    for backend in &a.backend {
        let device = backend.device().map_err(|e| e.to_string())?;
        let t = Instant::now();
        let sam = Sam::load(&a.model, &device).map_err(|e| e.to_string())?;
        let load = t.elapsed().as_secs_f64();
        let pixels = sam::preprocess::Input::new(&img, sam.cfg.vision_config.image_size, &device).pixels;
        let _ = sam.image_embeddings(pixels.clone()).into_data(); // warm-up
        let t = Instant::now();
        let _ = sam.image_embeddings(pixels).into_data();
        let encoder = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (passing, parts) = sam.passing_masks_timed(&img, &o, &device);
        let n_passing = passing.len();
        let t_nms = Instant::now();
        let kept = sam::automatic::suppress(passing, o.filters.nms_iou);
        let nms = t_nms.elapsed().as_secs_f64();
        let total = t.elapsed().as_secs_f64();
        let (e, d, m) = (parts.embeddings_s, parts.decode_s, parts.masks_s);
        let parts = format!("{e:.2}, {d:.2}, {m:.2}, {nms:.3} s");
        println!(
            "| {backend} | {load:.1} s | {encoder:.2} s | {total:.2} s | {parts} | {n_passing} / {} |",
            kept.len()
        );
        rows.push((backend, encoder, total));
    }
    if let Some(r) = reference {
        let get = |k: &str| r[k].as_f64().ok_or_else(|| format!("the reference has no {k}"));
        let (enc, auto) = (get("encoder_s")?, get("automatic_s")?);
        println!("\n| stage | transformers | backend | chatsplat | transformers / chatsplat |");
        println!("|---|---|---|---|---|");
        for (backend, encoder, total) in rows {
            println!("| image embeddings | {enc:.2} s | {backend} | {encoder:.2} s | {:.2}x |", enc / encoder);
            println!("| automatic masks | {auto:.2} s | {backend} | {total:.2} s | {:.2}x |", auto / total);
        }
    }
    Ok(())
}

fn rayon_threads() -> String {
    std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "all".into())
}
