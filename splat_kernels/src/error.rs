//! The op's one error type: bad shapes, non-finite inputs, bad cameras.

/// Errors of the splatting op: bad shapes, non-finite inputs, bad cameras.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SplatError {
    /// A tensor has the wrong shape.
    #[error("splat: bad input shape: {0}")]
    Shape(String),
    /// An input holds NaN or an infinity (policy: rejected with this error, never rendered).
    #[error("splat: {tensor} row {row} holds a non-finite value ({value})")]
    NonFinite { tensor: &'static str, row: usize, value: f32 },
    /// The camera cannot be used.
    #[error("splat: invalid camera: {0}")]
    InvalidCamera(String),
}
