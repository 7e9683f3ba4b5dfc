//! Evaluation helpers shared by the `chatsplat` tool and the benchmarks: PNG output, colour maps,
//! backend selection, benchmark scenes.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub use model::images;

pub mod chat;
pub mod plot;
pub mod vqa;

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

/// A progress bar on stderr (indicatif): `label [#####     ] done/total unit, rate, eta, extra`.
/// Hidden automatically when stderr is not a terminal.
pub struct Progress {
    bar: indicatif::ProgressBar,
}

impl Progress {
    pub fn new(label: impl Into<String>, unit: &'static str) -> Self {
        let bar = indicatif::ProgressBar::new(1);
        let style = indicatif::ProgressStyle::with_template(&format!(
            "{{prefix}} [{{bar:30}}] {{pos}}/{{len}} {unit} ({{per_sec}}, eta {{eta}}) {{msg}}"
        ))
        .expect("valid template")
        .progress_chars("#> ");
        bar.set_style(style);
        bar.set_prefix(label.into());
        Self { bar }
    }

    pub fn update(&self, done: usize, total: usize) {
        self.update_with(done, total, "");
    }

    /// As [`update`](Self::update), with extra text (loss, PSNR...) after the counts.
    pub fn update_with(&self, done: usize, total: usize, extra: &str) {
        self.bar.set_length(total.max(1) as u64);
        self.bar.set_position(done as u64);
        self.bar.set_message(extra.to_string());
        if done >= total {
            self.bar.finish();
        }
    }
}
