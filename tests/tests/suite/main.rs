//! The integration tests as one binary (one link, and one process that compiles wgpu's kernels
//! once), in data-flow order. Run one part with e.g. `cargo test -p chatsplat-tests --test suite vlm::`.

// The splatting op: CPU kernels against the f64 oracle, hard and fuzzed inputs, burn backends.
mod cpu_kernel;

mod cpu_hard_cases;

mod cpu_fuzz;

mod dense_baseline;

mod backends;

mod optimize;

// Captures: loaders of every format, .ply files.
mod loaders;

mod loaders_formats;

mod ply;

// Geometry, the synthetic scenes and their questions, the VLM, the language stage.
mod geometry;

mod synth;

mod vlm;

mod tabletop_vlm;

mod language;
