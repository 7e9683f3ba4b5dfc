//! The compute backends and the one place where a panic inside a backend becomes an [`Error`].

use crate::error::{Error, Result};
use burn::tensor::Device;

/// The compute backends chatsplat runs on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// burn-ndarray on the CPU (the CPU rasterizer, rayon over tiles).
    #[default]
    Ndarray,
    /// burn-wgpu (CubeCL kernels): a GPU, or Mesa lavapipe on the CPU.
    Wgpu,
    /// burn-flex on the CPU (burn-ndarray's successor: gemm matmuls, SIMD element-wise ops on all
    /// threads, fused attention); the same CPU rasterizer as ndarray.
    Flex,
}

impl Backend {
    /// Whether this backend can hold a model's weights in f16 (`--half`): flex (gemm's f16
    /// matmuls, accumulated in f32), and wgpu where the adapter's shaders take f16 (asked of the
    /// adapter: most GPUs, Mesa lavapipe too); burn-ndarray holds only f32 and f64.
    pub fn holds_half(self) -> bool {
        match self {
            Backend::Flex => true,
            // no adapter at all: no f16 either (the command's own use of wgpu then says why)
            Backend::Wgpu => self
                .device()
                .and_then(|d| catch_backend("wgpu", || splat_kernels::cube::f16_on(&d)))
                .is_ok_and(|f16| f16 == Some(true)),
            Backend::Ndarray => false,
        }
    }

    /// The burn device of this backend. For wgpu, the adapter burn picks, once per process, where
    /// the splatting op can run on it; else [`Error::Backend`] naming the adapter, its graphics API
    /// and what to install or use instead (`splat_kernels::cube::adapter`).
    pub fn device(self) -> Result<Device> {
        match self {
            Backend::Ndarray => Ok(Device::ndarray()),
            Backend::Wgpu => splat_kernels::cube::adapter::device()
                .map_err(|message| Error::Backend { what: "wgpu".into(), message }),
            Backend::Flex => Ok(Device::flex()),
        }
    }
}

impl std::str::FromStr for Backend {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "ndarray" => Ok(Backend::Ndarray),
            "wgpu" => Ok(Backend::Wgpu),
            "flex" => Ok(Backend::Flex),
            other => Err(format!("unknown backend `{other}` (expected ndarray, wgpu or flex)")),
        }
    }
}

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Backend::Ndarray => "ndarray",
            Backend::Wgpu => "wgpu",
            Backend::Flex => "flex",
        })
    }
}

use base::panic::panic_message;
pub use base::panic::quietly;

/// Runs `f`, turning a panic inside the backend (e.g. no wgpu adapter, a kernel that fails to
/// compile) into [`Error::Backend`]. The panic message is still printed by the default hook.
pub fn catch_backend<T>(what: &str, f: impl FnOnce() -> T) -> Result<T> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f))
        .map_err(|e| Error::Backend { what: what.to_string(), message: panic_message(&*e) })
}
