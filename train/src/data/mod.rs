//! Scene data: posed images (and masks, depth) from datasets or the built-in synthetic generator.

pub mod nerfstudio;
pub mod synth;
