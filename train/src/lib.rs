//! Training stages of chatsplat and their scene data: the geometry stage (3DGS with a 16-channel
//! identity field) and the language-field stage render through `splat_kernels::splat` and
//! optimise with burn optimizers (see ARCHITECTURE.md). `data` holds the scene sources; `teacher` extracts LLaVA-OneVision teacher tokens.

pub mod ckpt;
pub mod data;
pub mod export;
pub mod geometry;
pub mod language;
pub mod teacher;
