//! Differentiable N-channel Gaussian splatting as a burn backend extension.
//!
//! Layers, from the bottom:
//! * [`constants`] — every numeric constant of the op, in one place.
//! * [`camera`] — the pinhole camera.
//! * [`project`] — per-Gaussian projection and its hand-written backward (f32).
//! * [`cpu`] — tile binning, compositing and the backward pass on slices (rayon over tiles).
//! * [`blend`] — rendering with the geometry frozen: one camera's blend weights, kept and replayed.
//! * [`reference`] — a dense f64 twin of the whole op: the test oracle.
//! * [`cube`] — the same op as CubeCL kernels for the wgpu backend.
//! * [`ext`] — the burn backend extension trait, its NdArray / Cube / Autodiff implementations.
//! * [`blend_ext`] — the kept weights as a differentiable burn op ([`blend_ext::blend`]).
//! * [`api`] — the tensor-level entry point [`api::splat`].
//! * [`dense`] — the same math written with ordinary burn tensor ops (benchmark baseline).
//! * [`error`] — [`SplatError`], what every layer returns.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub mod api;
pub mod blend;
pub mod blend_ext;
pub mod camera;
pub mod constants;
pub mod cpu;
pub mod cube;
pub mod dense;
pub mod error;
pub mod ext;
pub mod project;
pub mod reference;

pub use api::{Gaussians, SplatRender, splat};
pub use camera::Camera;
pub use constants::{FloatAdd, GradReduce, RasterConfig, TileSort};
pub use error::SplatError;
