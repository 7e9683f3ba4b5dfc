//! Checkpoints of a train-vlm stage, `OUT/checkpoint/`: everything `--resume` needs to go on as
//! if the run had never stopped (bit-identical): every weight of [`Trainable`] (module order, one
//! f32 tensor), AdamW's state (burn's optimizer record, keyed by parameter id; the ids are saved
//! in module order and given back to the reloaded model), the data generator, the running
//! accuracy, the step and the log so far. A checkpoint is written beside the last one and swapped
//! in by renames, so a kill at any moment leaves one whole checkpoint.

use super::{LogLine, RunningAccuracy, Trainer, VlmTrainConfig};
use crate::dist;
use burn::optim::OptimizerRecord;
use model::error::{Error, IoContext, Result};
use model::io;
use model::rng::Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// `state.json` of a checkpoint.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct State {
    step: usize,
    rng: u64,
    running: RunningAccuracy,
    param_ids: Vec<u64>,
    config: VlmTrainConfig,
    log: Vec<LogLine>,
}

/// The checkpoint folder of the stage written to `out`.
pub fn dir(out: &Path) -> PathBuf {
    out.join("checkpoint")
}

/// Whether `out` holds a whole checkpoint (the current one, or the previous one a swap left).
pub fn exists(out: &Path) -> bool {
    found(out).is_some()
}

/// Removes the checkpoints of `out` (its stage has finished).
pub fn remove(out: &Path) {
    for d in ["checkpoint", "checkpoint.new", "checkpoint.old"] {
        let _ = std::fs::remove_dir_all(out.join(d));
    }
}

fn found(out: &Path) -> Option<PathBuf> {
    let cur = dir(out);
    let old = out.join("checkpoint.old");
    [cur, old].into_iter().find(|d| d.join("state.json").is_file())
}

impl Trainer {
    /// Writes the checkpoint of this stage into `out` (with `log`, the lines so far).
    pub fn save_checkpoint(&self, out: &Path, log: &[LogLine]) -> Result<()> {
        let (cur, new, old) = (dir(out), out.join("checkpoint.new"), out.join("checkpoint.old"));
        let _ = std::fs::remove_dir_all(&new);
        io::create_dir(&new)?;
        let flat = dist::flat_params(&self.model);
        io::write_f32(&new.join("weights.safetensors"), vec![("params".into(), vec![flat.len()], flat)], None)?;
        let opt = new.join("optimizer.bpk");
        self.optim.to_record().save(&opt).map_err(|e| Error::invalid(&opt, format!("cannot write: {e}")))?;
        let state = State {
            step: self.step,
            rng: self.rng.state(),
            running: self.running.clone(),
            param_ids: dist::param_ids(&self.model),
            config: self.cfg.clone(),
            log: log.to_vec(),
        };
        io::write_json(&new.join("state.json"), &state)?;
        // swap: the current one becomes the old one until the new one is in place
        let _ = std::fs::remove_dir_all(&old);
        if cur.exists() {
            std::fs::rename(&cur, &old).at(&cur, "cannot rename")?;
        }
        std::fs::rename(&new, &cur).at(&new, "cannot rename")?;
        let _ = std::fs::remove_dir_all(&old);
        Ok(())
    }

    /// Restores the checkpoint in `out` into this trainer (made from the same configuration);
    /// returns the log lines so far.
    pub fn restore(&mut self, out: &Path) -> Result<Vec<LogLine>> {
        let d = found(out).ok_or_else(|| Error::invalid(out, "--resume: there is no train-vlm checkpoint here"))?;
        let state_path = d.join("state.json");
        let state: State = io::read_json(&state_path)?;
        if state.config != self.cfg {
            return Err(Error::invalid(
                &state_path,
                "was written by a run of another configuration (resume with the configuration it was trained with)",
            ));
        }
        let weights = d.join("weights.safetensors");
        let (mut tensors, _) = io::read_f32(&weights)?;
        let (_, flat) = tensors.remove("params").ok_or_else(|| Error::invalid(&weights, "tensor params is missing"))?;
        let model =
            dist::set_flat_params(self.model.clone(), &flat).map_err(|e| Error::invalid(&weights, e.to_string()))?;
        self.model =
            dist::set_param_ids(model, &state.param_ids).map_err(|e| Error::invalid(&state_path, e.to_string()))?;
        let opt = d.join("optimizer.bpk");
        let record = OptimizerRecord::load(&opt).map_err(|e| Error::invalid(&opt, format!("cannot read: {e}")))?;
        self.optim = self.optim.clone().load_record(record);
        self.rng = Rng::from_state(state.rng);
        self.running = state.running;
        self.step = state.step;
        Ok(state.log)
    }
}
