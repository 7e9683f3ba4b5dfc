//! Replaying kept blend weights ([`crate::blend`]) as a differentiable burn op: a burn backend
//! extension with a hand-written backward, for NdArray, Flex and Cube (wgpu: a host round trip
//! through the same loops) and Autodiff.
//!
//! | input      | shape    | output | shape       |
//! |------------|----------|--------|-------------|
//! | `features` | `[N, C]` | map    | `[H, W, C]` |
//!
//! The weights are constants (the geometry is frozen); only the features get a gradient.

use crate::blend::BlendWeights;
use crate::error::SplatError;
use crate::ext::{float_prim, read_floats};
use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::wgpu::CubeBackend;
use burn::backend::{Backend, Dispatch, Flex, NdArray, TensorMetadata, backend_extension, tensor::FloatTensor};
use burn::tensor::Tensor;
use std::sync::Arc;

/// Blending kept weights as a backend operation.
#[backend_extension(Cube, NdArray, Flex, Autodiff)]
pub trait BlendBackend: Backend {
    /// The `[H, W, C]` map of `features` `[N, C]` over a zero background.
    fn blend_forward(features: FloatTensor<Self>, weights: Arc<BlendWeights>) -> FloatTensor<Self>;

    /// Hand-written backward: the `[N, C]` feature gradient from the map's gradient `[H, W, C]`.
    fn blend_backward(grad: FloatTensor<Self>, weights: Arc<BlendWeights>) -> FloatTensor<Self>;
}

/// Forward on any backend through the host loops.
fn host_forward<B: Backend>(features: FloatTensor<B>, w: &BlendWeights) -> FloatTensor<B> {
    let device = features.device();
    let c = features.shape().dims::<2>()[1];
    let map = w.render(&read_floats::<B>(features), c);
    float_prim::<B>(map, vec![w.height, w.width, c], &device)
}

/// Backward on any backend through the host loops.
fn host_backward<B: Backend>(grad: FloatTensor<B>, w: &BlendWeights) -> FloatTensor<B> {
    let device = grad.device();
    let c = grad.shape().dims::<3>()[2];
    let g = w.features_grad(&read_floats::<B>(grad), c);
    float_prim::<B>(g, vec![w.gaussians, c], &device)
}

macro_rules! host_blend_backend {
    ($($backend:ty),+) => {$(
        impl BlendBackend for $backend {
            fn blend_forward(features: FloatTensor<Self>, weights: Arc<BlendWeights>) -> FloatTensor<Self> {
                host_forward::<Self>(features, &weights)
            }

            fn blend_backward(grad: FloatTensor<Self>, weights: Arc<BlendWeights>) -> FloatTensor<Self> {
                host_backward::<Self>(grad, &weights)
            }
        }
    )+};
}

host_blend_backend!(NdArray, Flex, CubeBackend);
// with the `fusion` feature, `Cube` is the fusion backend over CubeBackend
#[cfg(feature = "fusion")]
host_blend_backend!(burn::backend::fusion::Fusion<CubeBackend>);

#[derive(Debug)]
struct BlendBackwardOp;

impl<B: Backend + BlendBackend> Backward<B, 1> for BlendBackwardOp {
    type State = Arc<BlendWeights>;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let [features] = ops.parents;
        if let Some(node) = features {
            grads.register::<B>(node.id, B::blend_backward(grad, ops.state));
        }
    }
}

impl<B: Backend + BlendBackend, C: CheckpointStrategy> BlendBackend for Autodiff<B, C> {
    fn blend_forward(features: FloatTensor<Self>, weights: Arc<BlendWeights>) -> FloatTensor<Self> {
        let node = features.node();
        let features = features.into_primitive();
        match BlendBackwardOp.prepare::<C>([node]).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let out = B::blend_forward(features, weights.clone());
                prep.finish(weights, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::blend_forward(features, weights)),
        }
    }

    fn blend_backward(grad: FloatTensor<Self>, weights: Arc<BlendWeights>) -> FloatTensor<Self> {
        // second-order gradients are not supported: the backward runs untracked
        <Autodiff<B, C> as burn::backend::AutodiffBackend>::from_inner(B::blend_backward(
            grad.into_primitive(),
            weights,
        ))
    }
}

/// The `[H, W, C]` map of `features` `[N, C]` with kept `weights` (over a zero background),
/// differentiable in the features on any backend, under autodiff or not.
pub fn blend(features: Tensor<2>, weights: &Arc<BlendWeights>) -> Result<Tensor<3>, SplatError> {
    let [n, c] = features.dims();
    if n != weights.gaussians || c == 0 {
        return Err(SplatError::Shape(format!(
            "blend: features are [{n}, {c}] but the weights were made for {} Gaussians (and C must be > 0)",
            weights.gaussians
        )));
    }
    let out = <Dispatch as BlendBackend>::blend_forward(features.into_dispatch(), weights.clone());
    Ok(Tensor::<3>::from_dispatch(out))
}
