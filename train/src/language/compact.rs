//! Model only what a scene needs: after the language stage, the fewest Gaussians, ranked by
//! their language contribution, whose language maps still give the training views' tokens.
//!
//! Candidates are fractions of the Gaussians ([`FRACTIONS`], largest first); each is scored by
//! the training views' token L1 against the teacher (view + `object_weight` x object), its maps
//! rasterised from the kept rows alone, and the smallest whose score rises by at most the
//! tolerance over the whole field's is kept. Scoring stops at the first fraction past it. The
//! tolerance was set on five held-out scenes, where answers through the kept rows were also
//! measured (eval/journal/2026-11-27.md, "Model only what a scene needs: the compact default").

use super::LanguageTrainer;
use model::error::Result;
use model::run::Compaction;
use model::scene::top_contributors;

/// Fractions of the Gaussians tried, largest first.
pub const FRACTIONS: [f64; 5] = [0.5, 0.35, 0.25, 0.15, 0.1];

/// The compaction of trainer `t`'s field at its `cfg.compact_tolerance`; `full` = its training
/// views' token L1 (view, object) with every Gaussian. `None` when not even half the Gaussians
/// stay within the tolerance (or the scene is too small to gain).
pub fn choose(t: &mut LanguageTrainer, full: (f32, f32)) -> Result<Option<Compaction>> {
    let tolerance = t.cfg.compact_tolerance;
    let w = t.cfg.object_weight;
    let score = |(v, o): (f32, f32)| v + w * o;
    let views: Vec<usize> = (0..t.cameras.len()).collect();
    let n = t.contribution.len();
    let mut candidates = Vec::new();
    let mut best: Option<(Vec<usize>, (f32, f32))> = None;
    for f in FRACTIONS {
        let k = (n as f64 * f).ceil() as usize;
        if k == 0 || k >= n {
            continue;
        }
        let keep = top_contributors(&t.contribution, k);
        let sub = t.scene.subset(&keep);
        let l1 = t.token_l1_of(&sub, &views)?;
        candidates.push((f, l1.0, l1.1));
        if score(l1) > score(full) * (1.0 + tolerance) {
            break;
        }
        best = Some((keep, l1));
    }
    Ok(best.map(|(kept, l1)| Compaction {
        gaussians: n,
        kept,
        tolerance,
        token_l1_full: full,
        token_l1_kept: l1,
        candidates,
    }))
}
