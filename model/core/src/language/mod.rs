//! ChatSplat's language field (CVPR 2025, Sec. 3.2-3.4): per-Gaussian view-level and
//! object-level language features, the encoder that turns a rendered feature map into the
//! teacher's token grid, and the scaling adjustment.
//!
//! Data flow for one view (shapes for the paper's settings, grid 27, patch 14, D = 1152):
//!
//! ```text
//! features [N, C] --splat--> map [27*14, 27*14, C] --lift (1x1 convs C -> hidden -> D)-->
//!   [378, 378, D] --14x14 stride-14 conv--> tokens [729, D] (--token mixer, optional-->)
//!   --* a + b--> tokens [729, D]
//! ```
//!
//! The 1x1 convolutions are per-pixel matrix products and the non-overlapping 14x14 convolution is
//! a matrix product over flattened patches, so both are written as `matmul`s (identical maths,
//! and no convolution kernel is needed on any backend). [`export`] writes them in PyTorch's
//! `Conv2d` layout.
//!
//! Modules: [`config`] (shapes and the token cameras), [`crop`] (the object crop rule shared with
//! the teacher), `init` (the weights' initial values), [`mix`] (the optional token mixer after the
//! patch convolution), [`field`] (the burn modules), [`frozen`] (the encoder at inference, its fold
//! formed once), [`export`] (Conv2d-layout weights).

pub mod config;
pub mod crop;
pub mod export;
pub mod field;
pub mod frozen;
mod init;
pub mod mix;

pub use config::LanguageConfig;
pub use crop::{CROP_MARGIN, ObjectCrop, object_box, object_image, objects_in, pixel_counts};
pub use field::{Encoder, LanguageField, mask_out};
pub use frozen::FrozenEncoder;
pub use mix::TokenMixer;
