//! The scene model: a host-side Gaussian cloud, its Inria-layout `.ply` I/O, and the built-in
//! synthetic scenes used by demos and tests, and the LLaVA-OneVision port ([`vlm`]).

pub mod cloud;
pub mod images;
pub mod language;
pub mod ply;
pub mod rng;
pub mod splats;
pub mod synthetic;
pub mod vlm;

pub use cloud::GaussianCloud;

/// An error that names the file (or input) and what is wrong with it.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelError {
    pub source: String,
    pub message: String,
}

impl ModelError {
    pub fn new(source: impl Into<String>, message: impl Into<String>) -> Self {
        Self {
            source: source.into(),
            message: message.into(),
        }
    }
}

impl std::fmt::Display for ModelError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.source, self.message)
    }
}

impl std::error::Error for ModelError {}
