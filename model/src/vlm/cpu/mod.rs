//! Hand-written CPU kernels for inference on host slices (f32, row-major), used by the port on
//! burn-flex and burn-ndarray where burn's composed ops pass over memory many times: softmax
//! attention, the gated / tanh-approximated activations, and a decode step's few-row products.
//! Each has a plain twin in the tests.

pub mod activation;
pub mod attention;
pub mod exp;
pub mod matvec;
