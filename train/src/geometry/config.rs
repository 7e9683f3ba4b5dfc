//! Every knob of the geometry stage, with the 3DGS defaults.

use model::error::{Error, Result};
use model::splats::SplatParams;
use serde::{Deserialize, Serialize};

/// Every knob of the geometry stage (saved beside every run as `config.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GeometryConfig {
    pub iters: usize,
    pub seed: u64,
    /// Initial Gaussians when neither points nor depth are available (random in the scene box).
    pub init_points: usize,
    /// Pixels sampled per training view for depth-based initialisation.
    pub init_per_view: usize,
    pub lr_means: f64,
    /// The means' learning rate decays exponentially to `lr_means * lr_means_final_ratio` at `iters`.
    pub lr_means_final_ratio: f64,
    pub lr_log_scales: f64,
    pub lr_quats: f64,
    pub lr_opacity: f64,
    pub lr_sh_dc: f64,
    pub lr_sh_rest: f64,
    pub lr_identity: f64,
    pub lr_classifier: f64,
    /// λ of the D-SSIM term.
    pub ssim_weight: f32,
    /// Weight of the identity cross-entropy.
    pub identity_weight: f32,
    /// Highest SH degree, reached one step every `sh_degree_every` iterations.
    pub sh_degree: usize,
    pub sh_degree_every: usize,
    pub densify_from: usize,
    pub densify_until: usize,
    pub densify_every: usize,
    /// Screen-space gradient threshold in NDC units (3DGS: 0.0002).
    pub densify_grad_threshold: f32,
    /// Clone below / split above this fraction of the scene extent.
    pub percent_dense: f32,
    pub opacity_reset_every: usize,
    pub prune_opacity: f32,
    /// After the first opacity reset, prune Gaussians whose largest scale exceeds this fraction
    /// of the scene radius (3DGS: 0.1); 0 disables.
    pub prune_world_size: f32,
    pub max_gaussians: usize,
    /// RGB background (the dataset's RGBA background).
    pub background: [f32; 3],
    /// Save a checkpoint every this many iterations (0: only at the end).
    pub checkpoint_every: usize,
    /// Also save one when this many seconds passed since the last (0: never by time).
    pub checkpoint_seconds: u64,
}

impl Default for GeometryConfig {
    fn default() -> Self {
        Self {
            iters: 7000,
            seed: 0,
            init_points: 20_000,
            init_per_view: 2000,
            lr_means: 1.6e-4,
            lr_means_final_ratio: 0.01,
            lr_log_scales: 5e-3,
            lr_quats: 1e-3,
            lr_opacity: 5e-2,
            lr_sh_dc: 2.5e-3,
            lr_sh_rest: 2.5e-3 / 20.0,
            lr_identity: 2.5e-3,
            lr_classifier: 5e-4,
            ssim_weight: 0.2,
            identity_weight: 1.0,
            sh_degree: 3,
            sh_degree_every: 1000,
            densify_from: 500,
            densify_until: 15_000,
            densify_every: 100,
            densify_grad_threshold: 2e-4,
            percent_dense: 0.01,
            opacity_reset_every: 3000,
            prune_opacity: 0.005,
            prune_world_size: 0.1,
            max_gaussians: 1_000_000,
            background: [1.0, 1.0, 1.0],
            checkpoint_every: 1000,
            checkpoint_seconds: 300,
        }
    }
}

impl GeometryConfig {
    /// The 3DGS schedule squeezed into a short run of `iters` (the demo, the benches):
    /// densification every eighth of the run from the first eighth to three quarters, SH degree
    /// raised every quarter, no opacity reset and no periodic checkpoints.
    pub fn short(iters: usize) -> Self {
        Self {
            iters,
            densify_from: iters / 8,
            densify_every: (iters / 8).max(1),
            densify_until: iters * 3 / 4,
            opacity_reset_every: 0,
            sh_degree_every: (iters / 4).max(1),
            checkpoint_every: 0,
            ..Default::default()
        }
    }

    /// The learning rate of every parameter at `iter`; the means' rate decays exponentially and
    /// is scaled by the scene radius, as 3DGS does.
    pub fn lrs(&self, iter: usize, radius: f32) -> SplatParams<f64> {
        let t = (iter as f64 / self.iters.max(1) as f64).min(1.0);
        SplatParams {
            means: self.lr_means * self.lr_means_final_ratio.powf(t) * radius as f64,
            log_scales: self.lr_log_scales,
            quats: self.lr_quats,
            opacity_logits: self.lr_opacity,
            sh_dc: self.lr_sh_dc,
            sh_rest: self.lr_sh_rest,
            identity: self.lr_identity,
            classifier_w: self.lr_classifier,
            classifier_b: self.lr_classifier,
        }
    }

    /// Refuses values out of range, naming the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, why: &str| Err(Error::input(format!("geometry config: {key} {why}")));
        if self.iters == 0 {
            return bad("iters", "must be at least 1 (0 would save the untrained initialisation as a run)");
        }
        let rates = [
            ("lr_means", self.lr_means),
            ("lr_log_scales", self.lr_log_scales),
            ("lr_quats", self.lr_quats),
            ("lr_opacity", self.lr_opacity),
            ("lr_sh_dc", self.lr_sh_dc),
            ("lr_sh_rest", self.lr_sh_rest),
            ("lr_identity", self.lr_identity),
            ("lr_classifier", self.lr_classifier),
        ];
        for (k, v) in rates {
            if !(v.is_finite() && v >= 0.0) {
                return bad(k, "must be a finite number >= 0");
            }
        }
        if rates.iter().all(|(_, v)| *v == 0.0) {
            return bad("lr_*", "are all 0: nothing would learn");
        }
        if !(self.lr_means_final_ratio > 0.0 && self.lr_means_final_ratio.is_finite()) {
            return bad("lr_means_final_ratio", "must be > 0");
        }
        for (k, v) in [("ssim_weight", self.ssim_weight), ("identity_weight", self.identity_weight)] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(k, "must be a finite number >= 0");
            }
        }
        if self.ssim_weight > 1.0 {
            return bad("ssim_weight", "must be at most 1");
        }
        if self.sh_degree > 3 {
            return bad("sh_degree", "must be 0..=3");
        }
        if self.densify_every == 0 {
            return bad("densify_every", "must be >= 1");
        }
        if !(self.densify_grad_threshold > 0.0 && self.densify_grad_threshold.is_finite()) {
            return bad("densify_grad_threshold", "must be > 0");
        }
        if !(self.percent_dense > 0.0 && self.percent_dense.is_finite()) {
            return bad("percent_dense", "must be > 0");
        }
        if !(0.0..1.0).contains(&self.prune_opacity) {
            return bad("prune_opacity", "must be in [0, 1)");
        }
        if !(self.prune_world_size >= 0.0 && self.prune_world_size.is_finite()) {
            return bad("prune_world_size", "must be >= 0");
        }
        if self.max_gaussians == 0 {
            return bad("max_gaussians", "must be >= 1");
        }
        if self.background.iter().any(|c| !(0.0..=1.0).contains(c)) {
            return bad("background", "must hold three numbers in [0, 1]");
        }
        Ok(())
    }
}
