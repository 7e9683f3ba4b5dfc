//! Hand-written CPU kernels for inference on host slices (f32, row-major), used by the port on
//! burn-flex and burn-ndarray where burn's composed ops pass over memory many times: softmax
//! attention, the gated / tanh-approximated activations, and the linear layers' products (a decode
//! step's few rows read each weight once; many rows in one gemm call into the output's buffer).
//! Each has a plain twin in the tests. `convert`: f32 <-> f16 on slices.

pub mod activation;
pub mod attention;
pub mod convert;
pub mod exp;
pub mod matvec;
pub mod product;
