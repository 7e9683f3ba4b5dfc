//! Divergence: a training loss that became non-finite, or whose running mean rose far above where
//! the run started. Learning rates far too high rarely give NaN at once: Adam moves each weight by
//! about the rate, so the loss climbs by orders of magnitude and stays finite, and a run that only
//! checked for NaN finished "successfully" with weights that answer nonsense (a language stage at
//! 1000x the default rates went from 0.88 to 1.6e8 and saved that).

use model::error::{Error, Result};

/// How far above the first loss the running mean may rise before training stops. Early
/// transients are large: the language stage at its default rates with a one-step warm-up (what
/// `batch` gives a 3-iteration run) jumped from 0.78 to 151 (193x) on its third step, its running
/// mean peaked near 32x, and it recovered to 0.76 by step 60. At ten times those rates without a
/// warm-up the running mean passed 1,600x on the third step and the loss was still 75x after 60
/// (the field 90x worse than untrained); at a thousand times, 40,000x on the second. So 1000x:
/// far past the transients a healthy run makes, reached at once by a real blow-up.
pub const RISE_LIMIT: f64 = 1000.0;

/// Weight of the newest loss in the running mean (about the last ten steps).
const SMOOTHING: f64 = 0.1;

/// Watches one training run's loss, step by step.
#[derive(Clone, Debug)]
pub struct LossGuard {
    /// The first loss seen (the weights the run started from).
    start: Option<f64>,
    /// Running mean of the loss.
    mean: f64,
    /// What to change when it trips, e.g. "lower lr_features and lr_encoder".
    advice: &'static str,
}

impl LossGuard {
    pub fn new(advice: &'static str) -> Self {
        Self { start: None, mean: 0.0, advice }
    }

    /// The loss of iteration `iter`: an error when it is not finite or the running mean rose
    /// above [`RISE_LIMIT`] times the first loss.
    pub fn check(&mut self, iter: usize, loss: f32) -> Result<()> {
        if !loss.is_finite() {
            return Err(self.error(iter, loss, String::new()));
        }
        let x = loss as f64;
        let start = match self.start {
            Some(start) => {
                self.mean = (1.0 - SMOOTHING) * self.mean + SMOOTHING * x;
                start
            }
            None => {
                self.mean = x;
                *self.start.insert(x)
            }
        };
        if self.mean > RISE_LIMIT * start.max(f64::MIN_POSITIVE) {
            let why = format!(" (its running mean {:.4e} is over {RISE_LIMIT}x the first loss, {start:.4})", self.mean);
            return Err(self.error(iter, loss, why));
        }
        Ok(())
    }

    /// An error when `end` (a loss measured after the last step) is over [`RISE_LIMIT`] times
    /// `begin` (the same measure before the first): the last update, which no step's loss judged.
    pub fn check_end(&self, iter: usize, begin: f32, end: f32) -> Result<()> {
        if !end.is_finite() || end as f64 > RISE_LIMIT * (begin as f64).max(f64::MIN_POSITIVE) {
            return Err(self.error(iter, end, format!(" (after the last step; {begin:.4} before the first)")));
        }
        Ok(())
    }

    fn error(&self, iter: usize, loss: f32, why: String) -> Error {
        Error::Diverged { iter, loss, detail: format!("{why}; {}; the last checkpoint written is kept", self.advice) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Per-step losses of the language stage on a 6-view 48-px tabletop (the built-in model's
    /// 8x8x128 teacher), measured with the guard off: default rates with a one-step warm-up.
    const TRANSIENT: [f32; 24] = [
        0.784, 22.2, 151.0, 67.7, 30.6, 34.3, 30.1, 21.9, 5.3, 19.9, 12.0, 15.3, 7.8, 7.98, 6.65, 5.01, 3.86, 5.23,
        7.01, 3.79, 2.39, 3.68, 3.78, 2.81,
    ];
    /// The same scene at ten times the rates, no warm-up.
    const BLOW_UP: [f32; 6] = [0.784, 4.62e3, 8.35e3, 6.25e4, 1.11e5, 1.9e4];

    #[test]
    fn a_transient_passes_and_a_blow_up_or_nan_trips() {
        let mut g = LossGuard::new("lower the rates");
        for (i, l) in TRANSIENT.into_iter().enumerate() {
            g.check(i, l).unwrap();
        }
        let mut g = LossGuard::new("lower the rates");
        let tripped = BLOW_UP.into_iter().enumerate().find_map(|(i, l)| g.check(i, l).err()).expect("trips");
        let e = tripped.to_string();
        assert!(e.contains("iteration 2") && e.contains("lower the rates") && e.contains("0.784"), "{e}");
        let mut g = LossGuard::new("x");
        g.check(0, 1.0).unwrap();
        assert!(g.check(1, f32::NAN).is_err());
        assert!(g.check_end(9, 0.5, 400.0).is_ok(), "worse, but a field that may still be settling");
        assert!(g.check_end(9, 0.5, 600.0).is_err());
        assert!(g.check_end(9, 0.5, f32::INFINITY).is_err());
    }
}
