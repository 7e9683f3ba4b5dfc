//! The burn backend extension: one trait, implemented for NdArray (CPU rasterizer in [`crate::cpu`]),
//! Cube (wgpu; CubeCL kernels in [`crate::cube`]) and Autodiff (hand-written backward).
//!
//! Tensor shapes (N Gaussians, C channels, H x W image):
//!
//! | input            | shape    | output      | shape          |
//! |------------------|----------|-------------|----------------|
//! | `means`          | `[N, 3]` | `packed`    | `[H, W, C+2]` (features, alpha, blend-weighted depth) |
//! | `log_scales`     | `[N, 3]` | `top_id`    | `[H, W]` int   |
//! | `quats`          | `[N, 4]` | `final_t`   | `[H, W]`       |
//! | `opacity_logits` | `[N]`    | `n_visited` | `[H, W]` int   |
//! | `features`       | `[N, C]` |             |                |
//! | `background`     | `[C]`    |             |                |
//! | `screen_offsets` | `[N, 2]` |             |                |
//!
//! Only `packed` is differentiable; its gradient flows to all seven inputs.

use crate::camera::Camera;
use crate::constants::RasterConfig;
use crate::cpu::{self, SplatInputs};
use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::{
    Backend, ExtensionType, Flex, NdArray, TensorMetadata, backend_extension,
    tensor::{FloatTensor, IntTensor},
};
use burn::tensor::{Shape, TensorData};

/// The seven differentiable inputs of the op, as backend primitives.
#[derive(ExtensionType, Debug, Clone)]
pub struct SplatPrims<B: Backend> {
    pub means: FloatTensor<B>,
    pub log_scales: FloatTensor<B>,
    pub quats: FloatTensor<B>,
    pub opacity_logits: FloatTensor<B>,
    pub features: FloatTensor<B>,
    pub background: FloatTensor<B>,
    pub screen_offsets: FloatTensor<B>,
}

/// Forward outputs, as backend primitives.
#[derive(ExtensionType, Debug, Clone)]
pub struct SplatFwdPrims<B: Backend> {
    /// `[H, W, C+2]`: features, alpha, blend-weighted depth.
    pub packed: FloatTensor<B>,
    /// `[H, W]` id of the Gaussian with the largest blend weight, -1 where empty.
    pub top_id: IntTensor<B>,
    /// `[H, W]` final transmittance.
    pub final_t: FloatTensor<B>,
    /// `[H, W]` number of tile-list entries visited.
    pub n_visited: IntTensor<B>,
    /// The binning, for the backward.
    #[extension_type]
    pub bins: SplatBins<B>,
}

/// The forward's binning, kept for the backward so that it neither projects, sorts nor reads the
/// intersection count back again. The wgpu forward fills it (`[N, PROJ]` projected Gaussians,
/// `[N, 4]` tile rectangles, `[tiles]` tile offsets, `[intersections]` depth-sorted ids); the CPU
/// backends bin again in the backward and hand 1-element placeholders
/// ([`SplatBins::placeholder`]). A backward handed bins of another shape bins again.
#[derive(ExtensionType, Debug, Clone)]
pub struct SplatBins<B: Backend> {
    pub proj: FloatTensor<B>,
    pub rects: IntTensor<B>,
    pub offsets: IntTensor<B>,
    pub ids: IntTensor<B>,
}

impl<B: Backend> SplatBins<B> {
    /// What a backend that keeps no binning hands on.
    pub fn placeholder(device: &B::Device) -> Self {
        Self {
            proj: float_prim::<B>(vec![0.0], vec![1], device),
            rects: int_prim::<B>(vec![0], vec![1], device),
            offsets: int_prim::<B>(vec![0], vec![1], device),
            ids: int_prim::<B>(vec![0], vec![1], device),
        }
    }
}

/// Saved forward state handed to the backward pass.
#[derive(ExtensionType, Debug, Clone)]
pub struct SplatSaved<B: Backend> {
    pub final_t: FloatTensor<B>,
    pub n_visited: IntTensor<B>,
    /// Upstream gradient of `packed`, `[H, W, C+2]`.
    pub grad_packed: FloatTensor<B>,
    /// The forward's binning.
    #[extension_type]
    pub bins: SplatBins<B>,
}

/// Splatting as a backend operation.
#[backend_extension(Cube, NdArray, Flex, Autodiff)]
pub trait SplatBackend: Backend {
    /// Renders the Gaussians (see the module docs for shapes).
    fn splat_forward(
        #[extension_type] inputs: SplatPrims<Self>,
        camera: Camera,
        config: RasterConfig,
    ) -> SplatFwdPrims<Self>;

    /// Hand-written backward: gradients of all seven inputs, same shapes as the inputs.
    fn splat_backward(
        #[extension_type] inputs: SplatPrims<Self>,
        #[extension_type] saved: SplatSaved<Self>,
        camera: Camera,
        config: RasterConfig,
    ) -> SplatPrims<Self>;
}

// ---------------------------------------------------------------------------------------------
// CPU backends: read to host slices, run `cpu`, wrap the results.

/// Reads a float primitive into a host vector (synchronously).
///
/// burn-ndarray hands over a tensor's buffer without copying only when nothing else holds it; a
/// tensor the caller still holds (a parameter, the frozen geometry) it copies element by element
/// through a dynamic-rank iterator, which took 42 % of a language-stage step (85k Gaussians,
/// seven reads per render). An element-wise op first makes a fresh contiguous array in one
/// vectorised pass, which is then handed over as is.
pub fn read_floats<B: Backend>(t: FloatTensor<B>) -> Vec<f32> {
    let t = B::float_add_scalar(t, 0.0f32.into());
    let data = burn::backend::try_read_sync(B::float_into_data(t))
        .expect("synchronous read is supported")
        .expect("tensor read succeeds");
    data.convert::<f32>().into_vec::<f32>().expect("f32 data")
}

/// Reads an int primitive into a host vector (synchronously).
pub fn read_ints<B: Backend>(t: IntTensor<B>) -> Vec<i32> {
    let data = burn::backend::try_read_sync(B::int_into_data(t))
        .expect("synchronous read is supported")
        .expect("tensor read succeeds");
    data.convert::<i32>().into_vec::<i32>().expect("i32 data")
}

pub(crate) fn float_prim<B: Backend>(v: Vec<f32>, shape: Vec<usize>, device: &B::Device) -> FloatTensor<B> {
    B::float_from_data(TensorData::new(v, Shape::from(shape)), device)
}

fn int_prim<B: Backend>(v: Vec<i32>, shape: Vec<usize>, device: &B::Device) -> IntTensor<B> {
    B::int_from_data(TensorData::new(v, Shape::from(shape)), device)
}

/// Host copies of the seven inputs.
pub type HostInputs = SplatInputs<Vec<f32>>;

impl<B: Backend> SplatPrims<B> {
    /// The seven primitives as [`SplatInputs`].
    pub fn into_inputs(self) -> SplatInputs<FloatTensor<B>> {
        SplatInputs {
            means: self.means,
            log_scales: self.log_scales,
            quats: self.quats,
            opacity_logits: self.opacity_logits,
            features: self.features,
            background: self.background,
            screen_offsets: self.screen_offsets,
        }
    }

    /// The seven primitives of [`SplatInputs`].
    pub fn from_inputs(i: SplatInputs<FloatTensor<B>>) -> Self {
        Self {
            means: i.means,
            log_scales: i.log_scales,
            quats: i.quats,
            opacity_logits: i.opacity_logits,
            features: i.features,
            background: i.background,
            screen_offsets: i.screen_offsets,
        }
    }

    /// Host copies of the seven (synchronous reads).
    pub fn read(self) -> HostInputs {
        self.into_inputs().map(read_floats::<B>)
    }
}

/// Forward on any backend through the CPU rasterizer (host round trip).
pub fn cpu_forward<B: Backend>(inputs: SplatPrims<B>, camera: &Camera, config: &RasterConfig) -> SplatFwdPrims<B> {
    let device = inputs.means.device();
    let host = inputs.read();
    let c = host.channels();
    let out = cpu::forward(&host.as_slices(), camera, config);
    let (h, w) = (camera.height as usize, camera.width as usize);
    let mut packed = Vec::with_capacity(h * w * (c + 2));
    for o in 0..h * w {
        packed.extend_from_slice(&out.image[o * c..(o + 1) * c]);
        packed.push(out.alpha[o]);
        packed.push(out.depth[o]);
    }
    SplatFwdPrims {
        packed: float_prim::<B>(packed, vec![h, w, c + 2], &device),
        top_id: int_prim::<B>(out.top_id, vec![h, w], &device),
        final_t: float_prim::<B>(out.final_t, vec![h, w], &device),
        n_visited: int_prim::<B>(out.n_visited, vec![h, w], &device),
        bins: SplatBins::placeholder(&device),
    }
}

/// Backward on any backend through the CPU rasterizer (host round trip).
pub fn cpu_backward<B: Backend>(
    inputs: SplatPrims<B>,
    saved: SplatSaved<B>,
    camera: &Camera,
    config: &RasterConfig,
) -> SplatPrims<B> {
    let device = inputs.means.device();
    let host = inputs.read();
    let (n, c) = (host.len(), host.channels());
    let final_t = read_floats::<B>(saved.final_t);
    let n_visited = read_ints::<B>(saved.n_visited);
    let gp = read_floats::<B>(saved.grad_packed);
    let hw = final_t.len();
    let mut g_image = Vec::with_capacity(hw * c);
    let mut g_alpha = Vec::with_capacity(hw);
    let mut g_depth = Vec::with_capacity(hw);
    for o in 0..hw {
        g_image.extend_from_slice(&gp[o * (c + 2)..o * (c + 2) + c]);
        g_alpha.push(gp[o * (c + 2) + c]);
        g_depth.push(gp[o * (c + 2) + c + 1]);
    }
    let g = cpu::backward(&host.as_slices(), camera, config, &final_t, &n_visited, &g_image, &g_alpha, &g_depth);
    SplatPrims {
        means: float_prim::<B>(g.means, vec![n, 3], &device),
        log_scales: float_prim::<B>(g.log_scales, vec![n, 3], &device),
        quats: float_prim::<B>(g.quats, vec![n, 4], &device),
        opacity_logits: float_prim::<B>(g.opacity_logits, vec![n], &device),
        features: float_prim::<B>(g.features, vec![n, c], &device),
        background: float_prim::<B>(g.background, vec![c], &device),
        screen_offsets: float_prim::<B>(g.screen_offsets, vec![n, 2], &device),
    }
}

/// The CPU backends share the host rasterizer.
macro_rules! cpu_splat_backend {
    ($($backend:ty),+) => {$(
        impl SplatBackend for $backend {
            fn splat_forward(inputs: SplatPrims<Self>, camera: Camera, config: RasterConfig) -> SplatFwdPrims<Self> {
                cpu_forward::<Self>(inputs, &camera, &config)
            }

            fn splat_backward(
                inputs: SplatPrims<Self>,
                saved: SplatSaved<Self>,
                camera: Camera,
                config: RasterConfig,
            ) -> SplatPrims<Self> {
                cpu_backward::<Self>(inputs, saved, &camera, &config)
            }
        }
    )+};
}

cpu_splat_backend!(NdArray, Flex);

// ---------------------------------------------------------------------------------------------
// Autodiff: forward on the inner backend, backward through `splat_backward`.

#[derive(Debug)]
struct SplatBackwardOp;

#[derive(Debug, Clone)]
struct SplatState<B: Backend> {
    inputs: SplatPrims<B>,
    final_t: FloatTensor<B>,
    n_visited: IntTensor<B>,
    bins: SplatBins<B>,
    camera: Camera,
    config: RasterConfig,
}

impl<B: Backend + SplatBackend> Backward<B, 7> for SplatBackwardOp {
    type State = SplatState<B>;

    fn backward(self, ops: Ops<Self::State, 7>, grads: &mut Gradients, _checkpointer: &mut Checkpointer) {
        let grad_packed = grads.consume::<B>(&ops.node);
        let s = ops.state;
        let g = B::splat_backward(
            s.inputs,
            SplatSaved { final_t: s.final_t, n_visited: s.n_visited, grad_packed, bins: s.bins },
            s.camera,
            s.config,
        );
        let [means, log_scales, quats, opacity_logits, features, background, screen_offsets] = ops.parents;
        for (node, grad) in [
            (means, g.means),
            (log_scales, g.log_scales),
            (quats, g.quats),
            (opacity_logits, g.opacity_logits),
            (features, g.features),
            (background, g.background),
            (screen_offsets, g.screen_offsets),
        ] {
            if let Some(node) = node {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

fn strip<B: Backend, C: CheckpointStrategy>(p: SplatPrims<Autodiff<B, C>>) -> SplatPrims<B> {
    SplatPrims::from_inputs(p.into_inputs().map(|t| t.into_primitive()))
}

fn untracked<B: Backend, C: CheckpointStrategy>(t: FloatTensor<B>) -> FloatTensor<Autodiff<B, C>> {
    <Autodiff<B, C> as burn::backend::AutodiffBackend>::from_inner(t)
}

/// The inner backend's bins as the autodiff backend's (untracked).
fn lift_bins<B: Backend, C: CheckpointStrategy>(b: SplatBins<B>) -> SplatBins<Autodiff<B, C>> {
    SplatBins { proj: untracked::<B, C>(b.proj), rects: b.rects, offsets: b.offsets, ids: b.ids }
}

impl<B: Backend + SplatBackend, C: CheckpointStrategy> SplatBackend for Autodiff<B, C> {
    fn splat_forward(inputs: SplatPrims<Self>, camera: Camera, config: RasterConfig) -> SplatFwdPrims<Self> {
        let nodes = [
            inputs.means.node(),
            inputs.log_scales.node(),
            inputs.quats.node(),
            inputs.opacity_logits.node(),
            inputs.features.node(),
            inputs.background.node(),
            inputs.screen_offsets.node(),
        ];
        let prims = strip(inputs);
        match SplatBackwardOp.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let out = B::splat_forward(prims.clone(), camera, config);
                let state = SplatState {
                    inputs: prims,
                    final_t: out.final_t.clone(),
                    n_visited: out.n_visited.clone(),
                    bins: out.bins.clone(),
                    camera,
                    config,
                };
                SplatFwdPrims {
                    packed: prep.finish(state, out.packed),
                    top_id: out.top_id,
                    final_t: untracked::<B, C>(out.final_t),
                    n_visited: out.n_visited,
                    bins: lift_bins::<B, C>(out.bins),
                }
            }
            OpsKind::UnTracked(prep) => {
                let out = B::splat_forward(prims, camera, config);
                SplatFwdPrims {
                    packed: prep.finish(out.packed),
                    top_id: out.top_id,
                    final_t: untracked::<B, C>(out.final_t),
                    n_visited: out.n_visited,
                    bins: lift_bins::<B, C>(out.bins),
                }
            }
        }
    }

    fn splat_backward(
        inputs: SplatPrims<Self>,
        saved: SplatSaved<Self>,
        camera: Camera,
        config: RasterConfig,
    ) -> SplatPrims<Self> {
        // Second-order gradients are not supported: the backward runs untracked.
        let g = B::splat_backward(
            strip(inputs),
            SplatSaved {
                final_t: saved.final_t.into_primitive(),
                n_visited: saved.n_visited,
                grad_packed: saved.grad_packed.into_primitive(),
                bins: SplatBins {
                    proj: saved.bins.proj.into_primitive(),
                    rects: saved.bins.rects,
                    offsets: saved.bins.offsets,
                    ids: saved.bins.ids,
                },
            },
            camera,
            config,
        );
        SplatPrims::from_inputs(g.into_inputs().map(untracked::<B, C>))
    }
}
