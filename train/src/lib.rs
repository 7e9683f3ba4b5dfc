//! Training stages of chatsplat: the geometry stage (3DGS with a 16-channel identity field) and the
//! language-field stage (view/object language features, encoder, scale/shift). Both render through
//! `splat_kernels::splat` and optimise with burn optimizers; see ARCHITECTURE.md.
