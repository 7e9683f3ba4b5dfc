//! The language stage (ChatSplat, Sec. 3.5): with the geometry, opacity and identity frozen,
//! train the per-Gaussian view- and object-level language features, the encoder and the scaling
//! adjustment so that encoded rendered maps reproduce the teacher's SigLIP tokens.
//!
//! Loss per training view: `L1(Encoder(view map), teacher(view))` + mean over the view's objects
//! of `L1(Encoder(MaskOut(object map, rendered identity mask)), teacher(masked object image))`.
//! The object map is rendered with a camera that frames the same square crop the teacher saw
//! (the one crop rule of `model::language::crop`), so each token covers the same part of the
//! picture, and only the tiles of that crop are rasterised. Parameters are stepped with burn's
//! `Adam`, one state per named tensor (paper: lr 0.05 for features and encoder).
//!
//! Modules: [`config`] (the knobs, the short recipe), [`trainer`] (one step), [`compact`]
//! (the fewest Gaussians that keep the tokens), `fit` (the stage: checkpoints, metrics).

pub mod compact;
pub mod config;
mod fit;
pub mod trainer;

pub use config::*;
pub use fit::*;
pub use trainer::*;
