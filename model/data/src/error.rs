//! The error type of the chatsplat libraries. Every variant names what it is about: the file and
//! the problem (`Io`, `Invalid`), the argument (`Input`), or the stage (`Backend`, `Diverged`).

use std::path::{Path, PathBuf};

/// An error of the chatsplat libraries.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file or directory could not be opened, read, written, created or renamed.
    #[error("{}: {action}: {source}", path.display())]
    Io {
        path: PathBuf,
        /// What was attempted, e.g. "cannot read".
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
    /// A file (or directory) holds something wrong: format, shape, value, or it does not fit the
    /// rest of the run.
    #[error("{}: {problem}", path.display())]
    Invalid { path: PathBuf, problem: String },
    /// An argument or setting is out of range, or a request cannot be met (no file involved).
    #[error("{0}")]
    Input(String),
    /// The splatting op refused its inputs.
    #[error(transparent)]
    Splat(#[from] splat_kernels::SplatError),
    /// The LLaVA-OneVision port refused a model directory or a prompt.
    #[error(transparent)]
    Vlm(#[from] llava_onevision::VlmError),
    /// The compute backend failed (a panic inside burn or wgpu, e.g. no adapter); see
    /// `model::catch_backend`.
    #[error("{what} failed: {message}")]
    Backend { what: String, message: String },
    /// Training stopped because the loss became non-finite or rose far above its start; `detail`
    /// says how and what to change (empty or starting with "; ").
    #[error("training diverged: the loss became {loss} at iteration {iter}{detail}")]
    Diverged { iter: usize, loss: f32, detail: String },
}

/// Says on standard error that an input is legal but suspicious and what was assumed
/// (`warning: <msg>`); counted for [`warnings`].
pub fn warn(msg: impl std::fmt::Display) {
    WARNINGS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    eprintln!("warning: {msg}");
}

/// How many [`warn`]ings this process has given.
pub fn warnings() -> usize {
    WARNINGS.load(std::sync::atomic::Ordering::Relaxed)
}

static WARNINGS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// `Result` with [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    /// `path: action: source`, e.g. `Error::io(p, "cannot read", e)`.
    pub fn io(path: impl AsRef<Path>, action: &'static str, source: std::io::Error) -> Self {
        Error::Io { path: path.as_ref().to_path_buf(), action, source }
    }

    /// `path: problem`.
    pub fn invalid(path: impl AsRef<Path>, problem: impl Into<String>) -> Self {
        Error::Invalid { path: path.as_ref().to_path_buf(), problem: problem.into() }
    }

    /// A problem with an argument or setting.
    pub fn input(problem: impl Into<String>) -> Self {
        Error::Input(problem.into())
    }
}

/// Short form of `.map_err(|e| Error::io(path, action, e))`.
pub trait IoContext<T> {
    fn at(self, path: impl AsRef<Path>, action: &'static str) -> Result<T>;
}

impl<T> IoContext<T> for std::io::Result<T> {
    fn at(self, path: impl AsRef<Path>, action: &'static str) -> Result<T> {
        self.map_err(|e| Error::io(path, action, e))
    }
}
