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
