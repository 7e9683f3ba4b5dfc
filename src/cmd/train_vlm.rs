//! `chatsplat train-vlm`: trains the tabletop LLaVA-OneVision from scratch.

use eval::progress::Progress;
use model::Backend;
use std::path::PathBuf;
use train::vlm::{VlmTrainConfig, train};

#[derive(clap::Args)]
pub struct Args {
    /// Output model directory (a llava-hf layout the loader reads).
    #[arg(long, default_value = "out/tabletop-vlm")]
    pub out: PathBuf,
    /// A train_config.json with any VlmTrainConfig fields (others keep their defaults); the
    /// committed model's is checkpoints/tabletop-llava-ov/train_config.json.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Training steps (overrides the config).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Seed (overrides the config).
    #[arg(long)]
    pub seed: Option<u64>,
    #[arg(long, default_value_t = Backend::Ndarray)]
    pub backend: Backend,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let mut cfg = match &a.config {
        Some(p) => model::io::read_config::<VlmTrainConfig>(p)?,
        None => VlmTrainConfig::default(),
    };
    if let Some(s) = a.steps {
        cfg.steps = s;
    }
    if let Some(s) = a.seed {
        cfg.seed = s;
    }
    super::check_config(a.config.as_deref(), cfg.validate())?;
    let device = a.backend.device();
    let bar = Progress::new("train-vlm", "steps");
    let t0 = std::time::Instant::now();
    let acc = model::catch_backend("VLM training", || {
        train(&cfg, &a.out, &device, |p| {
            if let Some(e) = &p.eval {
                let labels = p.eval_labels.as_ref().map(|l| format!(" (reading label tokens: {})", l.summary()));
                eprintln!("\nstep {}: held-out exact match {}{}", p.step, e.summary(), labels.unwrap_or_default());
            }
            let loss = p.answer_loss + cfg.aux_weight * p.aux_loss;
            let msg = format!("loss {loss:.4} answer {:.4} aux {:.4}", p.answer_loss, p.aux_loss);
            bar.update_with(p.step, cfg.steps, &msg);
        })
    })??;
    println!(
        "trained {} steps in {:.1} min; held-out exact match {} -> {}",
        cfg.steps,
        t0.elapsed().as_secs_f64() / 60.0,
        acc.summary(),
        a.out.display()
    );
    Ok(())
}
