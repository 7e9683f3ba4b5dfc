//! Every knob of the language stage and its short recipe.

use model::error::{Error, Result};
use model::language::LanguageConfig;
use serde::{Deserialize, Serialize};

/// The default largest relative rise of the training views' token L1 when compacting
/// ([`compact`]). On five held-out scenes (eval/journal/2026-11-27.md, "Model only what a scene
/// needs: the compact default"), 25 % of the Gaussians raised it 1.0-2.6 % (their answers: 652 of
/// 734 right against 654 with every Gaussian) and 15 % raised it 4.5-9.2 %, so 3 % keeps a quarter.
pub const DEFAULT_COMPACT_TOLERANCE: f32 = 0.03;

/// Every knob of the language stage (saved beside the run as `config.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LanguageTrainConfig {
    pub field: LanguageConfig,
    pub iters: usize,
    pub seed: u64,
    /// Adam learning rate of the per-Gaussian language features (paper: 0.05).
    pub lr_features: f64,
    /// Adam learning rate of the encoder and the scaling adjustment (paper: 0.05). At 0.05 the
    /// patch convolution overshoots during the warm-up of a short run (on the demo scene the loss
    /// rose 2.5 -> 3.9 and 100 iterations never recovered: 47-54 % exact match with a warm-up of
    /// 10-25 against 90 % at 0.02), so the default is 0.02; at 240 iterations on the bench scenes
    /// 0.05 scores about a point higher (eval/journal/2026-11-25.md, "The language stage's learning
    /// rates: a cosine decay and a slower encoder").
    pub lr_encoder: f64,
    /// The encoder's rate is `lr_encoder` for a layer whose fan-in is at most this, and
    /// `lr_encoder * lr_fan_in_ref / fan_in` above it (weight and bias alike; the scaling
    /// adjustment is element-wise and keeps `lr_encoder`); 0: every tensor at `lr_encoder`, as in
    /// the paper. Adam moves every weight by about its rate at each step, so a layer's output
    /// moves by about rate x fan-in: the patch convolution (fan-in patch² x D: 12,288 for the
    /// built-in model, 18,432-225,792 at LLaVA-OneVision's D = 1152) at the lifting layers' rate
    /// threw the tokens far past the teacher's in the first steps (on `fox` at 1/8 the training
    /// views' token L1 rose 0.594 -> 1.088 in 100 iterations; eval/journal/2026-12-01.md, "The
    /// language stage at real size: the encoder's rate scaled by fan-in"). Scaled, a step moves the
    /// tokens by the same amount at every size.
    pub lr_fan_in_ref: usize,
    /// Adam learning rate of the token mixer (`field.token_mixer`): its attention projections
    /// were fitted at 0.002 where they were measured (`encoder-probe`, eval/journal/2026-11-28.md,
    /// "Ten held-out scenes with 48 views", paragraph "Found: the encoder's locality loses the count").
    pub lr_mixer: f64,
    /// Weight of the object loss (paper: 1).
    pub object_weight: f32,
    /// Objects per step (a seeded random subset of the view's objects; 0 = all, as in the
    /// paper). A subset gives an unbiased estimate of the mean object loss at a fraction of the
    /// renders, which is what a CPU needs.
    pub max_objects_per_step: usize,
    /// Linear warm-up of both learning rates over the first iterations (0 = none). Adam's first
    /// steps move every weight by about the learning rate, which at 0.05 throws the patch
    /// convolution (fan-in 14·14·D) far off before it recovers.
    pub warmup_iters: usize,
    /// After the warm-up both learning rates follow a cosine from their value down to this
    /// fraction of it at the last iteration (1: constant, as in the paper). Adam at a constant
    /// rate keeps every feature moving by about the rate to the end; decaying it lets the field
    /// settle: on held-out views of the synthetic scenes (240 iterations) the view tokens' L1 to
    /// the teacher fell from 0.51 to 0.42 and ChatSplat's exact match rose 82 -> 89 %
    /// (eval/journal/2026-11-25.md, "The language stage's learning rates: a cosine decay and a
    /// slower encoder").
    pub lr_final: f64,
    /// Initialise the scaling adjustment from the teacher: `b` = per-token mean over the training
    /// views, `a` = per-channel standard deviation, so the encoder starts on standardised targets.
    pub init_scale_shift_from_teacher: bool,
    /// Save a checkpoint every this many iterations (0: only at the end).
    pub checkpoint_every: usize,
    /// Also save one when this many seconds passed since the last (0: never by time).
    pub checkpoint_seconds: u64,
    /// Training views per step (their mean loss; 1 as in the paper). A data-parallel run splits
    /// each step's views across its ranks, so it needs at least one per rank.
    pub views_per_step: usize,
    /// Memory (MiB) for the blend weights of the training cameras (views and object crops): the
    /// geometry is frozen, so each camera's weights are found once and every later step replays
    /// them (`splat_kernels::blend`: the same maps, no projection, sorting or Gaussian evaluation)
    /// instead of rasterising forward and backward. Cameras past the budget get their weights
    /// found again at each visit; 0 rasterises every map as the geometry stage does. The replay
    /// is a host loop, so on wgpu the maps stay with the device's rasterizer. The teacher tokens
    /// read once are kept within the same budget.
    pub kept_weights_mb: usize,
    /// Model only what a scene needs: after training, keep the fewest Gaussians (by language
    /// contribution; half, 35, 25, 15 or 10 %) whose training views' token L1 (view + weighted
    /// object) rises by at most this fraction over the whole field's, and write them to
    /// `compact.json` (inference then renders language maps from those alone; 0: keep all).
    /// Calibrated on five held-out scenes (eval/journal/2026-11-27.md, "Model only what a scene
    /// needs: the compact default").
    pub compact_tolerance: f32,
}

impl Default for LanguageTrainConfig {
    fn default() -> Self {
        Self {
            field: LanguageConfig::default(),
            iters: 3000,
            seed: 0,
            lr_features: 0.05,
            lr_encoder: 0.02,
            lr_mixer: 0.002,
            lr_fan_in_ref: 128,
            object_weight: 1.0,
            max_objects_per_step: 0,
            warmup_iters: 100,
            lr_final: 0.05,
            init_scale_shift_from_teacher: true,
            checkpoint_every: 500,
            checkpoint_seconds: 300,
            views_per_step: 1,
            kept_weights_mb: 2048,
            compact_tolerance: DEFAULT_COMPACT_TOLERANCE,
        }
    }
}

impl LanguageTrainConfig {
    /// The language stage squeezed into a short run of `iters` (the demo, `batch`, `vqa-bench`, the
    /// tests' scene): warm-up a tenth of the run, maps rendered at the views' own resolution
    /// (`field.patch = 0`).
    pub fn short(iters: usize) -> Self {
        let mut c = Self { iters, warmup_iters: (iters / 10).max(1), ..Default::default() };
        c.field.patch = 0;
        c
    }

    /// What multiplies `lr_encoder` for an encoder layer with `fan_in` inputs (`None`: an
    /// element-wise tensor, the scaling adjustment); see [`lr_fan_in_ref`](Self::lr_fan_in_ref).
    pub fn fan_in_factor(&self, fan_in: Option<usize>) -> f64 {
        match fan_in {
            Some(f) if self.lr_fan_in_ref > 0 && f > self.lr_fan_in_ref => self.lr_fan_in_ref as f64 / f as f64,
            _ => 1.0,
        }
    }

    /// Refuses values out of range, naming the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, why: &str| Err(Error::input(format!("language config: {key} {why}")));
        if self.iters == 0 {
            return bad("iters", "must be at least 1 (0 would save an untrained field as a run)");
        }
        for (k, v) in [("lr_features", self.lr_features), ("lr_encoder", self.lr_encoder), ("lr_mixer", self.lr_mixer)]
        {
            if !(v.is_finite() && v >= 0.0) {
                return bad(k, "must be a finite number >= 0");
            }
        }
        if self.lr_features == 0.0 && self.lr_encoder == 0.0 {
            return bad("lr_features", "and lr_encoder are both 0: nothing would learn");
        }
        if !(self.object_weight.is_finite() && self.object_weight >= 0.0) {
            return bad("object_weight", "must be a finite number >= 0");
        }
        if !(self.lr_final.is_finite() && (0.0..=1.0).contains(&self.lr_final)) {
            return bad("lr_final", "must be a number in [0, 1]");
        }
        if self.views_per_step == 0 {
            return bad("views_per_step", "must be at least 1");
        }
        if !(self.compact_tolerance.is_finite() && self.compact_tolerance >= 0.0) {
            return bad("compact_tolerance", "must be a finite number >= 0 (0: keep every Gaussian)");
        }
        Ok(())
    }
}
