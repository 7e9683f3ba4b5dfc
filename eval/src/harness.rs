//! What the benchmark and probe binaries share: their `main` ([`bench_main!`]: the large-block
//! allocator, malloc's settings, a panicking backend turned into an error, the error printed and
//! a failing exit), the model and backend arguments with the built-in tabletop model as default
//! ([`ModelArgs`]), held-out seed ranges ([`HeldOutSeeds`]), and the token-fidelity accumulator
//! ([`TokenFidelity`]).

use burn::tensor::Device;
use model::{Backend, Result, catch_backend};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

pub use model::alloc::KeepLarge;

/// A binary's `main`: `eval::bench_main!("vqa-bench", bench)` with `fn bench(a: &Args) ->
/// Result<()>` and `Args: clap::Parser`. Large tensors' blocks are mapped with huge pages and
/// reused ([`KeepLarge`]).
#[macro_export]
macro_rules! bench_main {
    ($name:literal, $body:path) => {
        #[global_allocator]
        static ALLOC: $crate::harness::KeepLarge = $crate::harness::KeepLarge;

        fn main() -> std::process::ExitCode {
            let args = <Args as clap::Parser>::parse();
            $crate::harness::run($name, || $body(&args))
        }
    };
}

/// Runs a binary's body with malloc keeping freed memory: success, or the error (a backend's
/// panic among them) printed as `error: ...` and a failing exit.
pub fn run(name: &str, body: impl FnOnce() -> Result<()>) -> ExitCode {
    model::alloc::keep_freed_memory();
    match catch_backend(name, body).and_then(|r| r) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// The model a bench reads and the backend it runs on.
#[derive(clap::Args, Clone, Debug)]
pub struct ModelArgs {
    /// LLaVA-OneVision directory (default: the built-in model).
    #[arg(long)]
    pub vlm: Option<PathBuf>,
    #[arg(long, default_value_t = Backend::Ndarray)]
    pub backend: Backend,
}

impl ModelArgs {
    /// `--vlm`, or the built-in model ([`vlm_dir`]).
    pub fn vlm_dir(&self) -> Result<PathBuf> {
        vlm_dir(self.vlm.as_deref())
    }

    /// `--backend`'s device, or why there is none (no usable wgpu adapter).
    pub fn device(&self) -> Result<Device> {
        self.backend.device()
    }
}

/// `vlm`, or the built-in model (`CHATSPLAT_MODEL`, then `checkpoints/` beside the binary or the
/// working directory).
pub fn vlm_dir(vlm: Option<&Path>) -> Result<PathBuf> {
    match vlm {
        Some(d) => Ok(d.to_path_buf()),
        None => Ok(model::vlm::default_model_dir()?),
    }
}

/// Held-out synthetic scenes: seeds `first-seed..first-seed + seeds` (training never uses seeds
/// below 1e6).
#[derive(clap::Args, Clone, Copy, Debug)]
pub struct HeldOutSeeds {
    /// Held-out scenes (seeds `first-seed..first-seed + seeds`; training never uses seeds below 1e6).
    #[arg(long, default_value_t = 5)]
    pub seeds: u64,
    #[arg(long, default_value_t = 30_000)]
    pub first_seed: u64,
}

impl HeldOutSeeds {
    pub fn range(&self) -> Range<u64> {
        self.first_seed..self.first_seed + self.seeds
    }
}

/// L1 and cosine of token grids against the teacher's, per token: sums while a run adds grids,
/// means after [`TokenFidelity::mean`]. `n` counts tokens, `grids` the grids added.
#[derive(Default, Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TokenFidelity {
    pub l1: f64,
    pub cos: f64,
    pub n: usize,
    #[serde(default)]
    pub grids: usize,
}

impl TokenFidelity {
    /// Adds grid `a` against `b` (both `[tokens * d]`): each token's mean absolute difference and
    /// cosine.
    pub fn add(&mut self, a: &[f32], b: &[f32], d: usize) {
        for (x, y) in a.chunks(d).zip(b.chunks(d)) {
            let l1 = x.iter().zip(y).map(|(p, q)| (p - q).abs() as f64).sum::<f64>() / d as f64;
            let dot: f64 = x.iter().zip(y).map(|(p, q)| *p as f64 * *q as f64).sum();
            let nx = x.iter().map(|p| (*p as f64).powi(2)).sum::<f64>().sqrt();
            let ny = y.iter().map(|p| (*p as f64).powi(2)).sum::<f64>().sqrt();
            self.l1 += l1;
            self.cos += dot / (nx * ny).max(1e-12);
            self.n += 1;
        }
        self.grids += 1;
    }

    /// The means per token (`n` and `grids` kept).
    pub fn mean(self) -> Self {
        let n = self.n.max(1) as f64;
        Self { l1: self.l1 / n, cos: self.cos / n, ..self }
    }

    /// Adds the means `m` of another run back as sums.
    pub fn add_mean(&mut self, m: TokenFidelity) {
        self.l1 += m.l1 * m.n as f64;
        self.cos += m.cos * m.n as f64;
        self.n += m.n;
        self.grids += m.grids;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fidelity_is_the_mean_per_token_and_merges_back() {
        // two tokens of d = 2: identical (L1 0, cos 1) and opposite (L1 2, cos -1)
        let mut f = TokenFidelity::default();
        f.add(&[1.0, 0.0, 0.0, 1.0], &[1.0, 0.0, 0.0, -1.0], 2);
        let m = f.mean();
        assert_eq!((m.n, m.grids), (2, 1));
        assert!((m.l1 - 0.5).abs() < 1e-12 && m.cos.abs() < 1e-12, "{m:?}");
        // a run's means added back weigh by its tokens
        let mut g = TokenFidelity::default();
        g.add(&[3.0, 4.0], &[3.0, 4.0], 2);
        let mut total = TokenFidelity::default();
        total.add_mean(m);
        total.add_mean(g.mean());
        let t = total.mean();
        assert_eq!((t.n, t.grids), (3, 2));
        assert!((t.l1 - 1.0 / 3.0).abs() < 1e-12 && (t.cos - 1.0 / 3.0).abs() < 1e-12, "{t:?}");
    }

    #[test]
    fn held_out_seeds_are_a_half_open_range() {
        let s = HeldOutSeeds { seeds: 3, first_seed: 30_000 };
        assert_eq!(s.range().collect::<Vec<_>>(), vec![30_000, 30_001, 30_002]);
    }
}
