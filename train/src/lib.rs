//! The training stages of chatsplat, in data-flow order: [`geometry`] (3DGS with a 16-channel
//! identity field, from posed photos), [`teacher`] (LLaVA-OneVision's SigLIP tokens of every
//! training view and masked object) and [`language`] (the per-Gaussian language field, the
//! encoder and the scaling adjustment against those tokens). All render through
//! `splat_kernels::splat` and optimise with burn's Adam; [`adam_state`] keeps the optimizer state by
//! parameter name; [`pipeline`] runs one scene through the three. Inference (chat) lives in `model`
//! and does not depend on this crate.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub mod adam_state;
pub mod dist;
pub mod geometry;
pub mod guard;
pub mod language;
pub mod manifest;
pub mod masks;
pub use language::compact;
pub mod pipeline;
pub mod schedule;
pub mod teacher;
pub mod vlm;
