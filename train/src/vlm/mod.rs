//! Training a LLaVA-OneVision from scratch for the synthetic tabletops (burn autodiff, burn's
//! AdamW): the same architecture and files as a llava-hf model (SigLIP tower, projector, Qwen2
//! with tied embeddings, a word-level `tokenizer.json`, the chat template), small enough to train
//! on a CPU in an hour, so that every stage of chatsplat can be checked with answers that are
//! right or wrong.
//!
//! Each step draws fresh scenes (seeds from [`TRAIN_SEEDS`], never the held-out ones), ray-casts
//! them, and asks questions in the token layouts ChatSplat feeds the LLM ([`data`]); many
//! questions share one image prefix in a packed forward pass ([`pack`], [`forward`]). An auxiliary per-token
//! colour/shape/size classification speeds up the vision tower; Gaussian noise on the vision
//! tokens teaches the LLM to read tokens that are close to the tower's (what ChatSplat's encoder
//! gives). Evaluation is exact match on held-out seeds ([`evaluate`]).
//!
//! In data-flow order: `config` (the model's shape, every knob, the seeds, the running accuracy
//! that adaptive sampling draws by), [`data`] (samples in ChatSplat's token layouts), [`hops`]
//! (where a question's reasoning steps should look), [`pack`] (samples packed into one pass),
//! [`forward`] (the model being trained, its forward pass and losses), `model_dir` (a fresh model;
//! the llava-hf directory it is written to), `evaluate`, `trainer` (the state and one step),
//! [`checkpoint`] (a stage's whole state for `--resume`); this module chains the stages
//! ([`train_from`]).

pub mod checkpoint;
mod config;
pub mod data;
mod evaluate;
pub mod forward;
pub mod hops;
mod model_dir;
pub mod pack;
mod trainer;

pub use config::*;
pub use evaluate::*;
pub use model_dir::*;
pub use trainer::*;

use crate::dist::{self, Collective, Solo};
use burn::module::Module;
use burn::tensor::Device;
use model::error::{Error, Result};
use model::io;
use model::vlm::LlavaOnevision;
use std::path::Path;

/// Trains a tabletop VLM from `cfg` on `device` (autodiff is added here) and writes it to `out`
/// (with `train_config.json` and `training_log.json`); `progress` sees every step.
pub fn train(cfg: &VlmTrainConfig, out: &Path, device: &Device, progress: impl FnMut(&LogLine)) -> Result<Accuracy> {
    train_from(cfg, out, None, device, &Solo, false, progress)
}

/// Ranks compare their weights' checksums every this many steps (and at the end of each stage).
pub const CHECK_EVERY: usize = 100;

/// [`train`]; a configuration with a `base` stage trains it first into `out/base` (`progress`
/// sees its steps too), and so on down the chain, except that the stage whose configuration is
/// exactly `base_model`'s `train_config.json` is read from that model directory instead (it and
/// the stages before it are not trained again).
///
/// On the ranks of a data-parallel run (`c`), every rank runs this with the same arguments: each
/// takes its share of every step, rank 0 alone evaluates, writes and reports progress, and the
/// others read a base stage from the `out` rank 0 wrote (a folder every rank sees). The held-out
/// accuracy it returns is rank 0's (the default on the others).
///
/// `resume`: a stage whose model `out` already holds (same configuration) is not trained again,
/// and a stage with a checkpoint goes on from it, exactly as if it had never stopped.
pub fn train_from(
    cfg: &VlmTrainConfig,
    out: &Path,
    base_model: Option<&Path>,
    device: &Device,
    c: &dyn Collective,
    resume: bool,
    mut progress: impl FnMut(&LogLine),
) -> Result<Accuracy> {
    let begun = out.join("train_config.json").is_file()
        || checkpoint::exists(out)
        || out.join("base").is_dir()
        || cfg.soup.iter().any(|s| soup_dir(out, *s).is_dir());
    if resume && !begun {
        return Err(Error::invalid(out, "--resume: there is no train-vlm run here to resume"));
    }
    train_stages(cfg, out, base_model, device, c, resume, &mut progress)
}

/// How many of `cfg`'s stages (the innermost first) a run into `out` does not train: those
/// `base_model` holds and, with `resume`, those already finished under `out` (stage `k` from the
/// end lives in `out/base/.../base`, `k` deep).
pub fn stages_done(cfg: &VlmTrainConfig, out: &Path, base_model: Option<&Path>, resume: bool) -> usize {
    let chain: Vec<&VlmTrainConfig> = std::iter::successors(Some(cfg), |c| c.base.as_deref()).collect();
    let read = |d: &Path| io::read_config::<VlmTrainConfig>(&d.join("train_config.json")).ok();
    let given =
        base_model.and_then(read).and_then(|b| chain.iter().position(|c| **c == b)).map_or(0, |i| chain.len() - i);
    if !resume {
        return given;
    }
    let mut dir = out.to_path_buf();
    for (i, c) in chain.iter().enumerate() {
        if finished(c, &dir) {
            return given.max(chain.len() - i);
        }
        dir = dir.join("base");
    }
    given
}

/// Whether `out` holds the finished model of a stage of `cfg` (its configuration, its model, no
/// checkpoint of an unfinished run).
fn finished(cfg: &VlmTrainConfig, out: &Path) -> bool {
    out.join("model.safetensors").is_file()
        && !checkpoint::exists(out)
        && io::read_config::<VlmTrainConfig>(&out.join("train_config.json")).is_ok_and(|c| c == *cfg)
}

fn train_stages(
    cfg: &VlmTrainConfig,
    out: &Path,
    base_model: Option<&Path>,
    device: &Device,
    c: &dyn Collective,
    resume: bool,
    progress: &mut dyn FnMut(&LogLine),
) -> Result<Accuracy> {
    cfg.validate()?;
    if let Some(dir) = base_model {
        let path = dir.join("train_config.json");
        if io::read_config::<VlmTrainConfig>(&path).is_ok_and(|b| b == *cfg) {
            return Err(Error::invalid(
                &path,
                "was trained with this very configuration: that model is this run's result already (nothing is \
                 left to train from it)",
            ));
        }
    }
    if resume && finished(cfg, out) {
        let log: Vec<LogLine> = io::read_json(&out.join("training_log.json"))?;
        return Ok(log.iter().rev().find_map(|l| l.eval.clone()).unwrap_or_default());
    }
    let command_device = device;
    let device = &cfg.backend.map_or_else(|| Ok(device.clone()), |b| b.device())?;
    let mut base_dir = None;
    let mut t = match &cfg.base {
        None => {
            if let Some(dir) = base_model {
                let path = dir.join("train_config.json");
                return Err(Error::invalid(&path, "was trained with none of this configuration's stages"));
            }
            Trainer::new(cfg, device)?
        }
        Some(base) => {
            let dir = match base_model {
                Some(dir) if io::read_config::<VlmTrainConfig>(&dir.join("train_config.json"))? == **base => {
                    dir.to_path_buf()
                }
                _ => {
                    let dir = out.join("base");
                    train_stages(base, &dir, base_model, command_device, c, resume, progress)?;
                    dir
                }
            };
            let ad = device.clone().autodiff();
            let mut vlm = LlavaOnevision::load(&dir, &ad)?;
            if cfg.two_turn > 0.0 {
                vlm = conversing(vlm)?;
            }
            let mut t = Trainer::starting_from(cfg, vlm, &ad)?;
            if cfg.carry_heads {
                t.load_heads(&dir)?;
            }
            base_dir = Some(dir);
            t
        }
    };
    // the soup's other runs, each a stage of its own from the same start (resumed like one)
    let mut soup = Vec::with_capacity(cfg.soup.len());
    for &seed in &cfg.soup {
        let member = VlmTrainConfig { seed, soup: Vec::new(), ..cfg.clone() };
        let dir = soup_dir(out, seed);
        train_stages(&member, &dir, base_dir.as_deref(), command_device, c, resume, progress)?;
        soup.push(dist::flat_params(&LlavaOnevision::load(&dir, device)?));
    }
    if c.size() > 1 {
        t.model = dist::broadcast_params(c, t.model)?;
    }
    // the stage's start, for `keep_base` (the same on every rank after the broadcast)
    let start_weights = (cfg.keep_base > 0.0).then(|| dist::flat_params(&t.model.vlm));
    let root = c.is_root();
    if root {
        io::create_dir(out)?;
        io::write_json(&out.join("train_config.json"), cfg)?;
    }
    let held = if root { eval_samples(t.spec(), EVAL_SEEDS..EVAL_SEEDS + cfg.eval_seeds, 2, 2) } else { Vec::new() };
    let mut log = if resume && checkpoint::exists(out) { t.restore(out)? } else { Vec::new() };
    // a resumed run's clock goes on from its log
    let before = log.last().map_or(0.0, |l| l.seconds);
    let start = std::time::Instant::now();
    let mut last = log.iter().rev().find_map(|l| l.eval.clone()).unwrap_or_default();
    while t.step < cfg.steps {
        let lr = cfg.lr_at(t.step);
        let losses = t.step(c)?;
        let step = t.step;
        if step == cfg.steps && !soup.is_empty() {
            t.model.vlm = averaged(t.model.vlm.clone(), &soup)?;
        }
        if let Some(start) = start_weights.as_deref().filter(|_| step == cfg.steps) {
            t.model.vlm = keep_base(t.model.vlm.clone(), start, cfg.keep_base)?;
        }
        if step.is_multiple_of(CHECK_EVERY) {
            dist::check_in_step(c, &t.model, step)?;
        }
        if !root {
            continue;
        }
        let (eval, eval_labels) = if cfg.eval_every > 0 && step.is_multiple_of(cfg.eval_every) || step == cfg.steps {
            let valid = t.model.valid();
            let a = evaluate(&valid, &held, device)?;
            let b = (cfg.label_probability(step) > 0.0).then(|| evaluate_with(&valid, &held, Some(&t.labels), device));
            last = a.clone();
            (Some(a), b.transpose()?)
        } else {
            (None, None)
        };
        let evaluated = eval.is_some();
        let line = LogLine {
            step,
            steps: cfg.steps,
            seconds: before + start.elapsed().as_secs_f64(),
            lr,
            answer_loss: losses.answer,
            aux_loss: losses.aux,
            hop_loss: losses.hops,
            slot_loss: losses.slots,
            place_loss: losses.places,
            tower_accuracy: losses.tower,
            eval,
            eval_labels,
            drawing_seconds: t.drawing.as_secs_f64(),
        };
        progress(&line);
        log.push(line);
        if evaluated {
            io::write_json(&out.join("training_log.json"), &log)?;
        }
        if (evaluated || cfg.checkpoint_every > 0 && step.is_multiple_of(cfg.checkpoint_every)) && step < cfg.steps {
            t.save_checkpoint(out, &log)?;
        }
    }
    if root {
        save_model(&t.model.valid().vlm, out)?;
        t.save_heads(out)?;
        io::write_json(&out.join("training_log.json"), &log)?;
        // finished: the model is the stage's state from now on
        checkpoint::remove(out);
    }
    // every rank waits here for rank 0's files (the next stage reads them) and checks the weights
    dist::check_in_step(c, &t.model, t.step)?;
    Ok(last)
}

/// Where a stage in `out` trains its soup's run of `seed` ([`VlmTrainConfig::soup`]).
fn soup_dir(out: &Path, seed: u64) -> std::path::PathBuf {
    out.join(format!("soup-seed{seed}"))
}

/// `module` with every weight the mean of its own and those of `others` (flat weights in module
/// order, [`dist::flat_params`]; [`VlmTrainConfig::soup`]).
pub fn averaged<M: Module>(module: M, others: &[Vec<f32>]) -> Result<M> {
    let mut sum: Vec<f64> = dist::flat_params(&module).into_iter().map(f64::from).collect();
    for o in others {
        if o.len() != sum.len() {
            return Err(Error::input(format!("soup: {} weights in a run, {} in this one", o.len(), sum.len())));
        }
        sum.iter_mut().zip(o).for_each(|(s, v)| *s += f64::from(*v));
    }
    let n = (others.len() + 1) as f64;
    dist::set_flat_params(module, &sum.iter().map(|s| (s / n) as f32).collect::<Vec<_>>())
}

/// `module` with every weight moved `keep` of the way back to `start` (its flat weights in module
/// order, [`dist::flat_params`]): `keep * start + (1 - keep) * now` ([`VlmTrainConfig::keep_base`]).
pub fn keep_base<M: Module>(module: M, start: &[f32], keep: f32) -> Result<M> {
    let now = dist::flat_params(&module);
    if now.len() != start.len() {
        return Err(Error::input(format!("keep_base: {} weights at the start, {} now", start.len(), now.len())));
    }
    let blended: Vec<f32> = now.iter().zip(start).map(|(t, b)| keep * b + (1.0 - keep) * t).collect();
    dist::set_flat_params(module, &blended)
}
