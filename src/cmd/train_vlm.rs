//! `chatsplat train-vlm`: trains the tabletop LLaVA-OneVision from scratch.

use model::Backend;
use model::guard::{Existing, Kind};
use scoring::progress::Progress;
use std::path::PathBuf;
use train::vlm::{EVAL_SEEDS, TRAIN_SEEDS, VlmTrainConfig, evaluate_model, train_from};

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
    /// Instead of training: score the model in this directory on ground-truth images of held-out
    /// seeds (exact match per level and question type).
    #[arg(long)]
    pub evaluate: Option<PathBuf>,
    /// For a config with a `base` stage: read that stage's model from this directory (whose
    /// train_config.json must equal the base) instead of training it.
    #[arg(long)]
    pub base_model: Option<PathBuf>,
    /// Held-out seeds for --evaluate (seeds `FROM..FROM + n`).
    #[arg(long, default_value_t = 50)]
    pub eval_seeds: u64,
    /// The first held-out seed for --evaluate (10000: the seeds training evaluates on; any other
    /// start below the training seeds, 1000000, gives scenes the model has never been scored on).
    #[arg(long, default_value_t = EVAL_SEEDS)]
    pub eval_from: u64,
    /// Go on from OUT's checkpoints: stages OUT already holds are not trained again, an
    /// interrupted one continues from its last checkpoint (the same weights as an uninterrupted
    /// run).
    #[arg(long)]
    pub resume: bool,
}

/// `--evaluate DIR`: exact match of a saved model on ground-truth images of held-out seeds.
fn evaluate(dir: &std::path::Path, a: &Args) -> anyhow::Result<()> {
    let cfg_path = dir.join("train_config.json");
    let cfg =
        if cfg_path.is_file() { model::io::read_config::<VlmTrainConfig>(&cfg_path)? } else { Default::default() };
    // a hand-edited value out of range is named, not clamped (e.g. supersample 0)
    super::check_config(Some(&cfg_path), cfg.validate())?;
    if a.eval_seeds == 0 {
        anyhow::bail!("--eval-seeds must be at least 1 (the number of held-out scenes to ask about)");
    }
    if a.eval_from.saturating_add(a.eval_seeds) > TRAIN_SEEDS {
        anyhow::bail!(
            "--eval-from {} with --eval-seeds {} reaches the training seeds ({TRAIN_SEEDS} and up): held-out \
             seeds lie below",
            a.eval_from,
            a.eval_seeds
        );
    }
    let device = a.backend.device()?;
    let t0 = std::time::Instant::now();
    let seeds = a.eval_from..a.eval_from + a.eval_seeds;
    let acc = model::catch_backend("VLM evaluation", || {
        let vlm = model::vlm::LlavaOnevision::load(dir, &device)?;
        evaluate_model(vlm, seeds.clone(), (2, 2), &cfg, &device)
    })??;
    let n: usize = acc.by_kind.values().map(|v| v.1).sum();
    println!(
        "{}: {n} questions on ground-truth images of held-out seeds {seeds:?} in {:.0} s",
        dir.display(),
        t0.elapsed().as_secs_f64()
    );
    println!("exact match {}", acc.summary());
    println!("by type: {}", acc.by_kind_line());
    if let Some(line) = acc.follow_up_line() {
        println!("follow-ups (second turns): {line}");
    }
    for line in acc.smallest_lines() {
        println!("{line}");
    }
    Ok(())
}

/// The stages of `cfg`'s chain, and the number of the first one to train (1: the innermost base),
/// after those `base_model` was trained with and, with `--resume`, those already finished under
/// the run's folder (`train::vlm::stages_done`).
fn stages(
    cfg: &VlmTrainConfig,
    out: &std::path::Path,
    base_model: Option<&std::path::Path>,
    resume: bool,
) -> (usize, usize) {
    let chain = std::iter::successors(Some(cfg), |c| c.base.as_deref()).count();
    (chain, train::vlm::stages_done(cfg, out, base_model, resume) + 1)
}

/// What `--out` may be, checked before anything is written: a new or empty folder, or with
/// `--resume` one whose `train_config.json` is this configuration (a run of another one, a
/// model folder, anything else is refused by name, and stays as it was).
fn check_out(
    out: &std::path::Path,
    cfg: &VlmTrainConfig,
    resume: bool,
    inputs: &model::guard::Inputs,
) -> anyhow::Result<()> {
    let stored = out.join("train_config.json");
    let model = out.join("config.json").is_file() || out.join("model.safetensors").is_file();
    let existing = if resume {
        Existing::GoOn
    } else {
        Existing::Refuse {
            instead: "--resume goes on with a run of this configuration; a new model needs a new or empty --out",
        }
    };
    model::guard::output_folder("--out", out, Kind::VlmRun, existing, inputs)?;
    if stored.is_file() {
        let was: VlmTrainConfig = model::io::read_config(&stored)?;
        if was != *cfg {
            anyhow::bail!(
                "{}: --resume: this run was made with another configuration (its train_config.json differs from \
                 --config's and the options'): resume it with its own, or train the new one into a new --out",
                stored.display()
            );
        }
    } else if model {
        anyhow::bail!(
            "{}: --resume: this folder holds a model but no train_config.json, so no train-vlm run of this \
             configuration to go on with: give --base-model it to train from it, or a new --out",
            out.display()
        );
    }
    Ok(())
}

pub fn run(a: Args, ranks: &crate::ranks::Ranks) -> anyhow::Result<()> {
    if let Some(dir) = &a.evaluate {
        if ranks.collective().size() > 1 {
            anyhow::bail!("train-vlm --evaluate runs on one process (run it without mpirun)");
        }
        return evaluate(dir, &a);
    }
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
    let mut inputs: Vec<_> = a.base_model.iter().map(|b| ("the --base-model directory", b.clone())).collect();
    inputs.extend(a.config.iter().map(|c| ("the --config file", c.clone())));
    check_out(&a.out, &cfg, a.resume, &inputs)?;
    let device = a.backend.device()?;
    let (stages, first) = stages(&cfg, &a.out, a.base_model.as_deref(), a.resume);
    let mut stage = first;
    let stage_label =
        |i: usize| if stages > 1 { format!("train-vlm (stage {i} of {stages})") } else { "train-vlm".into() };
    let (mut bar, mut stage_started) = (Progress::new(stage_label(stage), "steps"), false);
    let t0 = std::time::Instant::now();
    let c = ranks.collective();
    let mut drawing = None;
    if c.size() > 1 && c.is_root() {
        eprintln!("train-vlm: data-parallel on {} ranks (each takes its share of every step's samples)", c.size());
    }
    let acc = model::catch_backend("VLM training", || {
        train_from(&cfg, &a.out, a.base_model.as_deref(), &device, c, a.resume, |p| {
            if p.step == 1 && stage_started {
                stage += 1;
                bar.restart(stage_label(stage));
            }
            stage_started = true;
            drawing = Some(p.drawing_seconds);
            if let Some(e) = &p.eval {
                let labels = p.eval_labels.as_ref().map(|l| format!(" (reading label tokens: {})", l.summary()));
                eprintln!("\nstep {}: held-out exact match {}{}", p.step, e.summary(), labels.unwrap_or_default());
                eprintln!("  {}", e.by_kind_line());
                if let Some(line) = e.follow_up_line() {
                    eprintln!("  follow-ups: {line}");
                }
            }
            let [d, w, f] = p.hop_loss;
            let [c, s, z] = p.tower_accuracy.map(|a| (100.0 * a).round());
            let (answer, aux, slots, places) = (p.answer_loss, p.aux_loss, p.slot_loss, p.place_loss);
            let msg = format!(
                "answer {answer:.3} aux {aux:.3} (tower sees colour {c}% shape {s}% size {z}%) \
                 hops {d:.2}/{w:.2}/{f:.2} slots {slots:.2} places {places:.2}"
            );
            bar.update_with(p.step, p.steps, &msg);
        })
    })??;
    ranks.report(t0.elapsed().as_secs_f64());
    if !c.is_root() {
        return Ok(());
    }
    if let Some(d) = drawing {
        eprintln!("drawing samples took {d:.1} s of the last stage (every rank draws every step's samples)");
    }
    println!(
        "trained {} stage(s) in {:.1} min; held-out exact match {} -> {}",
        stages + 1 - first,
        t0.elapsed().as_secs_f64() / 60.0,
        acc.summary(),
        a.out.display()
    );
    Ok(())
}
