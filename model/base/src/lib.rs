//! The leaf of the crate graph: what both the LLaVA-OneVision port (`llava-onevision`) and the
//! rest of `model` need and nothing else provides.

pub mod panic;
pub mod rng;

pub use rng::Rng;
