//! Running the language stage: a fresh or resumed trainer, its steps with checkpoints judged by
//! the next step's loss, the token L1 before and after, metrics, and the compaction.

use super::trainer::Snapshot;
use super::{LangStep, LanguageTrainConfig, LanguageTrainer, compact};
use crate::dist::Collective;
use crate::geometry::view_at;
use crate::guard::LossGuard;
use crate::teacher::TeacherSet;
use burn::tensor::Device;
use model::error::{Error, Result};
use model::io;
use model::run::{GeometryRun, LanguageRun};
use serde::{Deserialize, Serialize};

/// Progress of [`fit`], reported after every iteration.
#[derive(Clone, Copy, Debug)]
pub struct LangProgress {
    pub iter: usize,
    pub iters: usize,
    pub step: LangStep,
}

/// Result of [`fit`].
#[derive(Clone, Debug)]
pub struct LangSummary {
    /// Token L1 on the training views (view, object) before and after.
    pub before: (f32, f32),
    pub after: (f32, f32),
    pub seconds_per_iter: f64,
    pub resumed_from: Option<usize>,
    pub gaussians_used: usize,
    pub gaussians: usize,
    /// What compacting kept (`None`: off, on another rank, or no fraction held).
    pub compaction: Option<model::run::Compaction>,
}

/// `metrics.json` of a language run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LanguageMetrics {
    pub iters: usize,
    pub train_view_token_l1_before: f32,
    pub train_view_token_l1: f32,
    pub train_object_token_l1_before: f32,
    pub train_object_token_l1: f32,
    pub seconds_per_iter: f64,
    pub gaussians: usize,
    /// Gaussians that reached a language map.
    pub gaussians_used: usize,
}

/// Trains (or resumes) the language stage of geometry run `run` into `out`: a first checkpoint
/// within seconds, then every `cfg.checkpoint_every` iterations and `cfg.checkpoint_seconds`.
///
/// On the ranks of a data-parallel run (`c`) every rank runs this with the same arguments: each
/// renders its share of every step's views, rank 0 alone writes checkpoints and metrics and
/// reports progress, and a resume reads the checkpoint rank 0 wrote (a folder every rank sees).
/// The token L1 before and after is rank 0's (zeros on the others).
pub fn fit(
    run: &GeometryRun,
    teacher_dir: &std::path::Path,
    out: &LanguageRun,
    cfg: LanguageTrainConfig,
    device: &Device,
    resume: bool,
    c: &dyn Collective,
    mut progress: impl FnMut(LangProgress),
) -> Result<LangSummary> {
    let (mut t, resumed_from) = if resume {
        if !out.checkpoint().is_file() {
            return Err(Error::invalid(&out.dir, "--resume: there is no language checkpoint to resume from"));
        }
        let mut t = LanguageTrainer::resume(run, out, device)?;
        // train until the requested total (nothing more when already past it; the stored total never
        // drops below the iteration reached, so the saved state stays consistent)
        t.cfg.iters = cfg.iters.max(t.iter);
        t.cfg.compact_tolerance = cfg.compact_tolerance;
        let at = t.iter;
        if c.is_root() {
            crate::adam_state::warn_if_done(&out.dir, at, cfg.iters);
        }
        (t, Some(at))
    } else {
        (LanguageTrainer::new(run, TeacherSet::open(teacher_dir)?, cfg, device)?, None)
    };
    let root = c.is_root();
    // a compaction belongs to the weights it was chosen on: training on makes it stale
    if root && out.compaction().is_file() {
        std::fs::remove_file(out.compaction()).map_err(|e| Error::io(out.compaction(), "cannot remove", e))?;
    }
    if resumed_from.is_none() && root {
        t.save(out)?;
    }
    t.check_in_step(c)?;
    // A resumed run with nothing left to train keeps the figures of the training that made its
    // weights (token L1 before and after, time per step): they are not measured again, and not
    // rewritten as before == after and no time at all.
    let stored = if root && resumed_from.is_some() && t.iter >= t.cfg.iters && out.metrics().is_file() {
        Some(io::read_json::<LanguageMetrics>(&out.metrics())?)
    } else {
        None
    };
    let all: Vec<usize> = (0..t.cameras.len()).collect();
    let before = match &stored {
        Some(m) => (m.train_view_token_l1_before, m.train_object_token_l1_before),
        None if root => t.token_l1(&all)?,
        None => (0.0, 0.0),
    };
    let start = std::time::Instant::now();
    let mut saved_at = std::time::Instant::now();
    let first = t.iter;
    let b = t.cfg.views_per_step;
    // A step's loss judges the weights it starts from, so a checkpoint due after step k holds
    // weights no loss has seen yet: it is written after step k + 1's loss passed the guard. A
    // divergence thus never reaches disk; the last checkpoint written stays loadable and sound.
    let mut guard = LossGuard::new(if t.cfg.field.token_mixer {
        "lower lr_features and lr_encoder, and lr_mixer (and check the teacher tokens)"
    } else {
        "lower lr_features and lr_encoder (and check the teacher tokens)"
    });
    let mut pending: Option<Snapshot> = None;
    while t.iter < t.cfg.iters {
        let views: Vec<usize> = (0..b).map(|j| view_at(t.iter * b + j, t.cameras.len(), t.cfg.seed)).collect();
        let at = t.iter;
        let s = t.step_views(&views, c)?;
        guard.check(at, s.loss)?;
        if t.iter.is_multiple_of(crate::vlm::CHECK_EVERY) {
            t.check_in_step(c)?;
        }
        if !root {
            continue;
        }
        if let Some(snap) = pending.take() {
            t.write(out, &snap)?;
            saved_at = std::time::Instant::now();
        }
        progress(LangProgress { iter: t.iter, iters: t.cfg.iters, step: s });
        let by_iter = t.cfg.checkpoint_every > 0 && t.iter.is_multiple_of(t.cfg.checkpoint_every);
        let by_time = t.cfg.checkpoint_seconds > 0 && saved_at.elapsed().as_secs() >= t.cfg.checkpoint_seconds;
        if by_iter || by_time {
            pending = Some(t.snapshot());
        }
    }
    t.check_in_step(c)?;
    let seconds_per_iter = start.elapsed().as_secs_f64() / (t.iter - first).max(1) as f64;
    let used = t.contribution.iter().filter(|&&c| c > 0.0).count();
    if !root {
        let gaussians = t.contribution.len();
        return Ok(LangSummary {
            before,
            after: before,
            seconds_per_iter,
            resumed_from,
            gaussians_used: used,
            gaussians,
            compaction: None,
        });
    }
    // the last update was judged by no step: its token L1 against the one before the first step
    let after = match &stored {
        Some(m) => (m.train_view_token_l1, m.train_object_token_l1),
        None => t.token_l1(&all)?,
    };
    let w = t.cfg.object_weight;
    guard.check_end(t.iter, before.0 + w * before.1, after.0 + w * after.1)?;
    t.save(out)?;
    let seconds_per_iter = stored.as_ref().map_or(seconds_per_iter, |m| m.seconds_per_iter);
    if stored.is_none() {
        let metrics = LanguageMetrics {
            iters: t.iter,
            train_view_token_l1_before: before.0,
            train_view_token_l1: after.0,
            train_object_token_l1_before: before.1,
            train_object_token_l1: after.1,
            seconds_per_iter,
            gaussians: t.contribution.len(),
            gaussians_used: used,
        };
        io::write_json(&out.metrics(), &metrics)?;
    }
    let compaction = if t.cfg.compact_tolerance > 0.0 { compact::choose(&mut t, after)? } else { None };
    if let Some(c) = &compaction {
        io::write_json(&out.compaction(), c)?;
    }
    Ok(LangSummary {
        before,
        after,
        seconds_per_iter,
        resumed_from,
        gaussians_used: used,
        gaussians: t.contribution.len(),
        compaction,
    })
}
