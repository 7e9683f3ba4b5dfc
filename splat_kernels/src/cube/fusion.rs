//! The op on burn's fusion backend (cargo feature `fusion`, where `Cube` is
//! `Fusion<CubeBackend>`), kept outside fusion: the operations queued before it run, its inputs
//! are resolved to CubeCL tensors, the [`CubeBackend`] op runs as it does without fusion, and its
//! outputs come back as fresh fusion tensors that the operations after it fuse over.
//!
//! Why not lazily, as burn's `#[fusion(...)]` attributes would register it: a lazy operation
//! states every output's shape before it runs, and the forward's tile list
//! ([`SplatBins::ids`], one entry per tile a Gaussian touches) has a length that only the
//! projection finds out (the op's one host read). The element-wise work around the op (the
//! activations before it, the losses after it) is what fusion joins, and it still does.

use super::CubeBackend;
use crate::camera::Camera;
use crate::constants::RasterConfig;
use crate::ext::{SplatBackend, SplatBins, SplatFwdPrims, SplatPrims, SplatSaved};
use burn::backend::TensorMetadata;
use burn::backend::fusion::client::GlobalFusionClient;
use burn::backend::fusion::stream::StreamId;
use burn::backend::fusion::{Fusion, FusionBackend, FusionTensor, NoOp};
use burn::backend::ir::{BackendIr, InitOperationIr, OperationIr};
use burn::backend::wgpu::CubeTensor;

type Runtime = <CubeBackend as FusionBackend>::FusionRuntime;
type Client = GlobalFusionClient<Runtime>;
type Tensor = FusionTensor<Runtime>;

/// Runs what is queued before `t` and hands over its CubeCL tensor.
fn float_in(t: Tensor) -> CubeTensor {
    let client = t.client.clone();
    client.resolve_tensor_float::<CubeBackend>(t)
}

fn int_in(t: Tensor) -> CubeTensor {
    let client = t.client.clone();
    client.resolve_tensor_int::<CubeBackend>(t)
}

/// Registers a CubeCL tensor the op made as a fusion tensor (an initialised handle, as
/// `float_from_data` registers uploaded data).
fn out(client: &Client, t: CubeTensor, int: bool) -> Tensor {
    let (shape, dtype) = (t.shape(), t.dtype());
    let handle =
        if int { <CubeBackend as BackendIr>::int_tensor_handle(t) } else { CubeBackend::float_tensor_handle(t) };
    let desc = InitOperationIr::create(shape, dtype, || client.register_tensor_handle(handle));
    let mut made = client.register(StreamId::current(), OperationIr::Init(desc), NoOp::<CubeBackend>::new());
    made.pop().expect("an initialisation has one output")
}

fn prims_in(p: SplatPrims<Fusion<CubeBackend>>) -> SplatPrims<CubeBackend> {
    SplatPrims {
        means: float_in(p.means),
        log_scales: float_in(p.log_scales),
        quats: float_in(p.quats),
        opacity_logits: float_in(p.opacity_logits),
        features: float_in(p.features),
        background: float_in(p.background),
        screen_offsets: float_in(p.screen_offsets),
    }
}

fn prims_out(c: &Client, p: SplatPrims<CubeBackend>) -> SplatPrims<Fusion<CubeBackend>> {
    SplatPrims {
        means: out(c, p.means, false),
        log_scales: out(c, p.log_scales, false),
        quats: out(c, p.quats, false),
        opacity_logits: out(c, p.opacity_logits, false),
        features: out(c, p.features, false),
        background: out(c, p.background, false),
        screen_offsets: out(c, p.screen_offsets, false),
    }
}

fn bins_in(b: SplatBins<Fusion<CubeBackend>>) -> SplatBins<CubeBackend> {
    SplatBins { proj: float_in(b.proj), rects: int_in(b.rects), offsets: int_in(b.offsets), ids: int_in(b.ids) }
}

fn bins_out(c: &Client, b: SplatBins<CubeBackend>) -> SplatBins<Fusion<CubeBackend>> {
    SplatBins {
        proj: out(c, b.proj, false),
        rects: out(c, b.rects, true),
        offsets: out(c, b.offsets, true),
        ids: out(c, b.ids, true),
    }
}

impl SplatBackend for Fusion<CubeBackend> {
    fn splat_forward(inputs: SplatPrims<Self>, camera: Camera, config: RasterConfig) -> SplatFwdPrims<Self> {
        let client = inputs.means.client.clone();
        let f = CubeBackend::splat_forward(prims_in(inputs), camera, config);
        SplatFwdPrims {
            packed: out(&client, f.packed, false),
            top_id: out(&client, f.top_id, true),
            final_t: out(&client, f.final_t, false),
            n_visited: out(&client, f.n_visited, true),
            bins: bins_out(&client, f.bins),
        }
    }

    fn splat_backward(
        inputs: SplatPrims<Self>,
        saved: SplatSaved<Self>,
        camera: Camera,
        config: RasterConfig,
    ) -> SplatPrims<Self> {
        let client = inputs.means.client.clone();
        let saved = SplatSaved {
            final_t: float_in(saved.final_t),
            n_visited: int_in(saved.n_visited),
            grad_packed: float_in(saved.grad_packed),
            bins: bins_in(saved.bins),
        };
        let g = CubeBackend::splat_backward(prims_in(inputs), saved, camera, config);
        prims_out(&client, g)
    }
}
