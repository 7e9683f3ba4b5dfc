//! The chatsplat model and its inference path, in the order data flows through them:
//!
//! 1. [`data`] (the `data` crate, model/data, re-exported) — posed photos (nerfstudio/Blender,
//!    COLMAP, LLFF, Replica), the built-in synthetic scenes ([`data::synth`]: objects, ray caster,
//!    questions) and [`question_file`]s about a scene.
//! 2. [`splats`] — the 3D Gaussians (`SplatModel`, a burn `Module`), [`cloud`], [`ply`] and
//!    [`spz`] (Niantic's compressed splats).
//! 3. [`language`] — per-Gaussian language features, the encoder that turns a rendered feature
//!    map into tokens, and the token cameras (one crop rule for teacher and field).
//! 4. [`vlm`] — LLaVA-OneVision (SigLIP, projector, Qwen2, tokenizer, generation): the
//!    `llava-onevision` crate (model/llava-onevision), re-exported.
//! 5. [`scene`] and [`chat`] — a trained scene answering questions at view, object and scene
//!    level: frozen Gaussians + language field -> tokens -> prompt -> LLM; [`vqa`] runs a
//!    question file through it; [`find`] scores the scene's objects against a phrase; [`known`]
//!    says which questions a model trained on the synthetic forms knows.
//!
//! Around them: [`run`] (the files of a run directory, typed), [`io`] (atomic writes, JSON,
//! safetensors), [`error`] and [`images`] (PNG), all three from the `data` crate; [`backend`]
//! (ndarray / wgpu, backend panics as errors) and [`rng`] (from the `base` crate, model/base, which
//! the port shares). Nothing here
//! depends on training (`train` depends on this crate).
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub mod alloc;
pub mod backend;
pub use base::rng;
// Files and scene data (the `data` crate, model/data): re-exported under their old paths.
pub use ::data;
pub use ::data::ObjectId;
pub use ::data::{cloud, error, guard, images, io, question_file};

pub mod ply;
pub mod splats;
pub mod spz;

pub mod language;

pub use llava_onevision as vlm;

pub mod chat;
pub mod find;
pub mod known;
pub mod run;
pub mod scene;
pub mod vqa;

pub use backend::{Backend, catch_backend};
pub use cloud::GaussianCloud;
pub use error::{Error, Result};
