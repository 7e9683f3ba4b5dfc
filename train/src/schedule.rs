//! Learning-rate schedules shared by the training stages.

/// Step `i` of `steps`: a linear warm-up to `peak` over `warmup` steps, then a cosine to `floor`
/// at the last step (`floor == peak`: constant after the warm-up).
pub fn warmup_cosine(i: usize, steps: usize, warmup: usize, peak: f64, floor: f64) -> f64 {
    if i < warmup {
        return peak * (i + 1) as f64 / warmup as f64;
    }
    let t = ((i - warmup) as f64 / (steps.saturating_sub(warmup)).max(1) as f64).min(1.0);
    floor + 0.5 * (peak - floor) * (1.0 + (std::f64::consts::PI * t).cos())
}
