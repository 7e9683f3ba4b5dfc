//! Evaluation helpers shared by the `chatsplat` tool and the benchmarks: PNG output, colour maps,
//! backend selection, benchmark scenes.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub use model::images;

use burn::tensor::{Device, DeviceKind};

/// The compute backends the tools can run on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BackendChoice {
    /// burn-ndarray on the CPU (the CPU rasterizer, rayon over tiles).
    Ndarray,
    /// burn-wgpu (CubeCL kernels): a GPU, or Mesa lavapipe on the CPU.
    Wgpu,
}

impl BackendChoice {
    pub fn device(self) -> Device {
        match self {
            BackendChoice::Ndarray => Device::ndarray(),
            BackendChoice::Wgpu => Device::wgpu(DeviceKind::DefaultDevice),
        }
    }
}

/// Runs `f`, turning a panic inside the backend (e.g. no wgpu adapter) into an error message.
pub fn catch_backend<T>(what: &str, f: impl FnOnce() -> T) -> Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).map_err(|e| {
        let msg = e
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "unknown panic".into());
        format!("{what} failed: {msg}")
    })
}

/// Draws a one-line progress bar on stderr: `label [#####     ] done/total unit, rate, eta`.
pub struct Progress {
    label: String,
    unit: &'static str,
    start: std::time::Instant,
}

impl Progress {
    pub fn new(label: impl Into<String>, unit: &'static str) -> Self {
        Self { label: label.into(), unit, start: std::time::Instant::now() }
    }

    pub fn update(&self, done: usize, total: usize) {
        self.update_with(done, total, "");
    }

    /// As [`update`](Self::update), with extra text (loss, PSNR...) after the counts.
    pub fn update_with(&self, done: usize, total: usize, extra: &str) {
        use std::io::Write;
        let total = total.max(1);
        let bar = 30 * done.min(total) / total;
        let secs = self.start.elapsed().as_secs_f64();
        let rate = done as f64 / secs.max(1e-9);
        let eta = if done > 0 { (total - done.min(total)) as f64 / rate } else { 0.0 };
        eprint!(
            "\r{} [{}{}] {done}/{total} {} ({rate:.2}/s, eta {eta:.0} s) {extra}   ",
            self.label,
            "#".repeat(bar),
            " ".repeat(30 - bar),
            self.unit
        );
        let _ = std::io::stderr().flush();
        if done >= total {
            eprintln!();
        }
    }
}
