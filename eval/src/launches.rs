//! Counting the CubeCL (wgpu) kernels a piece of work launches: a figure that, unlike a time, does
//! not depend on how fast the device is (Mesa lavapipe counts as a GPU would, up to the autotuner's
//! and fusion's choices), and what burn's kernel fusion (the `fusion` feature) and fused layers are
//! meant to lower. The benchmarks print it beside their timings.

use cubecl::logging::{LaunchObservation, LaunchObserver};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

#[derive(Default)]
struct Count(AtomicUsize);

impl LaunchObserver for Count {
    fn launched(&self, _kernel: &'static str) {
        self.0.fetch_add(1, Ordering::Relaxed);
    }
}

/// Runs `f` and counts the kernels issued on every CubeCL device meanwhile, from any thread
/// (fusion's server thread included). `f` must end by reading a result back, so that lazily
/// queued work has run by the time it returns. One count at a time per process: the observer
/// is global.
pub fn count_launches<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let count = Arc::new(Count::default());
    let watching = LaunchObservation::new(count.clone());
    let out = f();
    drop(watching);
    (out, count.0.load(Ordering::Relaxed))
}
