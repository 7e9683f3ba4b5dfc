//! The op as CubeCL kernels (the wgpu backend; any CubeCL runtime works).
//!
//! Pipeline, all on the device; the only host read is the number of tile intersections, which
//! sizes the intersection buffers:
//!
//! 1. `project_kernel` (thread per Gaussian): screen-space centre, conic, depth, opacity, tile
//!    rectangle; atomically counts Gaussians per tile.
//! 2. `scan_kernel` (one workgroup): exclusive prefix sum of the tile counts -> tile offsets, total.
//! 3. Each tile's list of Gaussians in (depth, id) order, the same total order as on the CPU, one
//!    of two ways ([`TileSort`]). By default (`radix`, [`radix`]) the Gaussians are sorted once by
//!    depth, their tile entries written in that order and then sorted by tile, both with a global,
//!    stable radix sort.
//! 4. Or (`bitonic`): `emit_kernel` (thread per Gaussian) writes (depth, id) into each touched
//!    tile's segment and `tile_sort_kernel` (workgroup per tile) sorts it.
//! 5. `raster_fwd_kernel` (workgroup per 16x16 tile, thread per pixel): front-to-back compositing
//!    with Gaussians staged through shared memory in batches of 256, a pixel's features summed in
//!    registers (up to [`MAX_REG_CHANNELS`] channels), the tile stopped once every pixel is
//!    saturated.
//!
//! Backward: the forward's bins (steps 1-4 are not run again, nor the host read;
//! [`crate::ext::SplatBins`]), then (6) `raster_bwd_kernel` walks each pixel's list back to front
//! and adds per-Gaussian screen-space gradients with atomic float adds (the adapter's native add
//! where it has one, else compare-and-swap on the bits, [`crate::FloatAdd`]; where the adapter
//! has plane operations each plane sums its pixels' contributions first, [`crate::GradReduce`]),
//! then (7) `project_bwd_kernel` maps them to the 3D parameters.
//! Float atomics make the wgpu gradients order-dependent in the last bits (the CPU path is
//! bitwise deterministic).
//!
//! The math mirrors [`crate::project`] and [`crate::cpu`] line for line; see there for derivations.
//! Files by pipeline stage: `project` (1, 7), `sort` (2, 4), `radix` (3), `raster` (5, 6),
//! `layout` (the packed buffers' named offsets); this module launches them (host side); `fusion`
//! (cargo feature `fusion`) runs the op on burn's fusion backend, outside fusion.

pub mod adapter;
#[cfg(feature = "fusion")]
mod fusion;
mod layout;
mod project;
mod radix;
mod raster;
mod sort;

use crate::camera::Camera;
use crate::constants::{FloatAdd, GradReduce, RasterConfig, TILE_PIXELS, TileSort};
use crate::ext::{SplatBackend, SplatBins, SplatFwdPrims, SplatPrims, SplatSaved};
pub use adapter::{adapter_report, f16_on, native_float_add_on};
use adapter::{cube_client, native_float_add};
use burn::backend::ops::FloatTensorOps;
use burn::backend::try_read_sync;
use burn::backend::wgpu::{CubeBackend, CubeTensor};
use burn::tensor::{DType, Shape, TensorData};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::{empty_device_dtype, zeros_client};
use cubecl::features::Plane;
use cubecl::prelude::*;
use layout::{CAM, CANARY_TRIPS, G2D, PROJ};
use project::{project_bwd_kernel, project_kernel};
use raster::{CasAdd, NativeAdd, raster_bwd_kernel, raster_fwd_kernel};
use sort::{emit_kernel, scan_kernel, tile_sort_kernel};

// ---------------------------------------------------------------------------------------------
// Host-side orchestration.

/// Overrides [`GradReduce::Auto`]'s choice for the whole process: `atomic` or `plane`.
pub const GRAD_REDUCE_ENV: &str = "CHATSPLAT_WGPU_GRAD_REDUCE";

/// Channel counts up to this are compiled into the raster kernels, rounded up to a bucket of 4,
/// 8, 16, 32 or 64 (one kernel per bucket): a pixel's features (forward) and feature gradient
/// (backward) then live in registers. Above it the kernels keep them in global memory, for any
/// count.
pub const MAX_REG_CHANNELS: usize = 64;

/// The raster kernels' `reg_channels` for `c` channels: its bucket, or 0 above the largest.
pub(super) fn reg_channels(c: usize) -> usize {
    if c <= MAX_REG_CHANNELS { c.next_power_of_two().max(4) } else { 0 }
}

/// Overrides [`TileSort::Auto`]'s choice for the whole process: `radix` or `bitonic`.
pub const TILE_SORT_ENV: &str = "CHATSPLAT_WGPU_SORT";

/// Whether the forward orders the tiles' lists with the global radix sorts ([`TileSort`]).
fn use_radix(choice: TileSort) -> bool {
    static CELL: std::sync::OnceLock<Option<bool>> = std::sync::OnceLock::new();
    match choice {
        TileSort::Auto => forced(TILE_SORT_ENV, "radix", "bitonic", &CELL).unwrap_or(true),
        TileSort::Radix => true,
        TileSort::Bitonic => false,
    }
}

/// Overrides [`FloatAdd::Auto`]'s choice for the whole process: `native` or `cas`.
pub const FLOAT_ADD_ENV: &str = "CHATSPLAT_WGPU_FLOAT_ADD";

/// An environment variable's two-way choice, read once per variable: `Some(true)` for `yes`,
/// `Some(false)` for `no`, `None` when unset or anything else.
fn forced(var: &'static str, yes: &str, no: &str, cell: &'static std::sync::OnceLock<Option<bool>>) -> Option<bool> {
    *cell.get_or_init(|| match std::env::var(var).as_deref() {
        Ok(v) if v == yes => Some(true),
        Ok(v) if v == no => Some(false),
        _ => None,
    })
}

/// Whether the backward sums per plane ([`GradReduce`]); a forced plane path on an adapter
/// without subgroup operations panics with its name ([`adapter::subgroups_or_refuse`]).
fn use_plane(client: &Client, choice: GradReduce) -> bool {
    static CELL: std::sync::OnceLock<Option<bool>> = std::sync::OnceLock::new();
    match choice {
        GradReduce::Auto => match forced(GRAD_REDUCE_ENV, "plane", "atomic", &CELL) {
            Some(true) => adapter::subgroups_or_refuse(),
            Some(false) => false,
            None => client.properties().features.plane.contains(Plane::Ops),
        },
        GradReduce::Atomic => false,
        GradReduce::Plane => adapter::subgroups_or_refuse(),
    }
}

/// Which paths the op takes on `device` under `config`, each `Auto` resolved as the kernels will
/// (adapter and `CHATSPLAT_WGPU_*` overrides): "tile lists by radix sort, backward with plane sums
/// and the native float add", and "; burn's fusion on, the op outside it" in a `fusion` build.
/// `None` for a host device.
pub fn paths(device: &burn::tensor::Device, config: &RasterConfig) -> Option<String> {
    let client = cube_client(device)?;
    Some(format!(
        "tile lists by {}, backward with {} and the {} float add{}",
        if use_radix(config.tile_sort) { "radix sort" } else { "bitonic sort" },
        if use_plane(&client, config.grad_reduce) { "plane sums" } else { "an atomic per pixel" },
        if use_native_add(&client, config.float_add) { "native" } else { "compare-and-swap" },
        if cfg!(feature = "fusion") { "; burn's fusion on, the op outside it" } else { "" },
    ))
}

/// Whether the backward adds with the native float atomic ([`FloatAdd`]).
fn use_native_add(client: &Client, choice: FloatAdd) -> bool {
    static CELL: std::sync::OnceLock<Option<bool>> = std::sync::OnceLock::new();
    match choice {
        FloatAdd::Auto => forced(FLOAT_ADD_ENV, "native", "cas", &CELL).unwrap_or_else(|| native_float_add(client)),
        FloatAdd::Native => true,
        FloatAdd::Cas => false,
    }
}

fn buf(t: &CubeTensor) -> BufferArg {
    let len = t.meta.shape().num_elements().max(1);
    // SAFETY: every tensor handed to a kernel is contiguous and holds `len` 4-byte elements.
    unsafe { BufferArg::from_raw_parts(t.handle.clone(), len) }
}

fn alloc(like: &CubeTensor, shape: Vec<usize>, dtype: DType) -> CubeTensor {
    empty_device_dtype(like.client.clone(), like.device.clone(), Shape::from(shape), dtype)
}

fn zeros(like: &CubeTensor, shape: Vec<usize>, dtype: DType) -> CubeTensor {
    zeros_client(like.client.clone(), like.device.clone(), Shape::from(shape), dtype)
}

/// A 1-element placeholder for empty inputs (wgpu does not bind zero-sized buffers).
fn non_empty(t: CubeTensor) -> CubeTensor {
    if t.meta.shape().num_elements() == 0 { zeros(&t, vec![1], DType::F32) } else { into_contiguous(t) }
}

fn cam_block(like: &CubeTensor, camera: &Camera, config: &RasterConfig) -> CubeTensor {
    let r = camera.rotation_rows();
    let t = camera.translation();
    let [lx, ly] = camera.clamp_limits();
    let mut v = Vec::with_capacity(CAM);
    for row in r {
        v.extend_from_slice(&row);
    }
    v.extend_from_slice(&t);
    v.extend_from_slice(&[
        camera.fx,
        camera.fy,
        camera.cx,
        camera.cy,
        lx,
        ly,
        camera.near,
        camera.far,
        config.extent,
        config.alpha_max,
        config.alpha_min,
        config.t_min,
    ]);
    CubeBackend::float_from_data(TensorData::new(v, [CAM]), &like.device)
}

fn groups(n: usize) -> CubeCount {
    let g = n.div_ceil(TILE_PIXELS as usize).max(1) as u32;
    if g <= 65535 {
        CubeCount::Static(g, 1, 1)
    } else {
        // ABSOLUTE_POS linearises a 2D grid as well.
        CubeCount::Static(65535, g.div_ceil(65535), 1)
    }
}

/// Projected and binned Gaussians on the device.
struct DeviceBins {
    proj: CubeTensor,
    rects: CubeTensor,
    offsets: CubeTensor,
    counts: CubeTensor,
    gids: CubeTensor,
    cam: CubeTensor,
    /// One flag: a kernel of this call reached lavapipe's loop limit ([`check_loops`]).
    truncated: CubeTensor,
}

fn bin(p: &SplatPrims<CubeBackend>, camera: &Camera, config: &RasterConfig) -> DeviceBins {
    let like = &p.means;
    let client = &like.client;
    let n = p.opacity_logits.meta.shape().num_elements();
    let [tx, ty] = camera.tiles();
    let num_tiles = (tx * ty) as usize;
    let cam = cam_block(like, camera, config);
    let proj = zeros(like, vec![n.max(1), PROJ], DType::F32);
    let rects = zeros(like, vec![n.max(1), 4], DType::I32);
    let counts = zeros(like, vec![num_tiles], DType::I32);
    let dim = CubeDim::new_1d(TILE_PIXELS);
    if n > 0 {
        project_kernel::launch(
            client,
            groups(n),
            dim,
            buf(&p.means),
            buf(&p.log_scales),
            buf(&p.quats),
            buf(&p.opacity_logits),
            buf(&p.screen_offsets),
            buf(&cam),
            buf(&proj),
            buf(&rects),
            buf(&counts),
            n as u32,
            tx,
            ty,
        );
    }
    let offsets = alloc(like, vec![num_tiles], DType::I32);
    let total = alloc(like, vec![1], DType::I32);
    let truncated = zeros(like, vec![1], DType::I32);
    scan_kernel::launch(
        client,
        CubeCount::Static(1, 1, 1),
        dim,
        buf(&counts),
        buf(&offsets),
        buf(&total),
        num_tiles as u32,
    );
    // The one host read of the pipeline: how many intersections to allocate.
    let total_data =
        try_read_sync(<CubeBackend as burn::backend::ops::IntTensorOps<CubeBackend>>::int_into_data(total))
            .expect("synchronous read is supported")
            .expect("tensor read succeeds");
    let n_isect = total_data.convert::<i64>().into_vec::<i64>().expect("int data")[0] as usize;
    let gids = if n > 0 && n_isect > 0 && use_radix(config.tile_sort) {
        radix::tile_lists(&proj, &rects, n, n_isect, camera)
    } else {
        let gids = zeros(like, vec![n_isect.max(1)], DType::I32);
        if n > 0 && n_isect > 0 {
            let keys = alloc(like, vec![n_isect.max(1)], DType::F32);
            let cursors = zeros(like, vec![num_tiles], DType::I32);
            emit_kernel::launch(
                client,
                groups(n),
                dim,
                buf(&proj),
                buf(&rects),
                buf(&offsets),
                buf(&cursors),
                buf(&keys),
                buf(&gids),
                n as u32,
                tx,
            );
            tile_sort_kernel::launch(
                client,
                CubeCount::Static(tx, ty, 1),
                dim,
                buf(&keys),
                buf(&gids),
                buf(&offsets),
                buf(&counts),
                tx,
                CANARY_TRIPS,
                buf(&truncated),
            );
        }
        gids
    };
    DeviceBins { proj, rects, offsets, counts, gids, cam, truncated }
}

/// The forward's bins for the backward: no projection, sort or host read again. Bins of another
/// shape than these inputs' (handed by a caller other than this crate's autodiff) are made anew.
fn reuse_bins(
    saved: SplatBins<CubeBackend>,
    p: &SplatPrims<CubeBackend>,
    camera: &Camera,
    config: &RasterConfig,
) -> DeviceBins {
    let n = p.opacity_logits.meta.shape().num_elements();
    let [tx, ty] = camera.tiles();
    let fits = saved.proj.meta.shape().num_elements() == n.max(1) * PROJ
        && saved.rects.meta.shape().num_elements() == n.max(1) * 4
        && saved.offsets.meta.shape().num_elements() == (tx * ty) as usize;
    if !fits {
        return bin(p, camera, config);
    }
    let like = &p.means;
    DeviceBins {
        proj: into_contiguous(saved.proj),
        rects: into_contiguous(saved.rects),
        offsets: into_contiguous(saved.offsets),
        // the backward reads no tile counts (each pixel's own count bounds its walk)
        counts: zeros(like, vec![1], DType::I32),
        gids: into_contiguous(saved.ids),
        cam: cam_block(like, camera, config),
        truncated: zeros(like, vec![1], DType::I32),
    }
}

/// Mesa lavapipe ends every loop of a shader invocation, silently, once it has run 65,535 loop
/// iterations in all; the kernels mark `truncated` when that happened (`raster::loop_canary`).
/// Read back on software adapters only (no physical card: a GPU has no such limit, and the read
/// would stall its queue). Panics rather than hand on results that lost Gaussians.
fn check_loops(truncated: &CubeTensor, pass: &str) {
    let props = truncated.client.properties();
    if props.identity.physical.is_some() {
        return;
    }
    let data =
        try_read_sync(<CubeBackend as burn::backend::ops::IntTensorOps<CubeBackend>>::int_into_data(truncated.clone()))
            .expect("synchronous read is supported")
            .expect("tensor read succeeds");
    if data.convert::<i64>().into_vec::<i64>().expect("int data")[0] != 0 {
        panic!(
            "the splatting {pass} on `{}` reached the software rasterizer's limit of 65,535 loop iterations per \
             shader invocation (a tile holds too many Gaussians or channels for it), so its result would be \
             silently wrong: use the ndarray backend on a CPU, or a GPU",
            props.identity.name
        );
    }
}

fn contiguous_inputs(p: SplatPrims<CubeBackend>) -> SplatPrims<CubeBackend> {
    SplatPrims {
        means: non_empty(p.means),
        log_scales: non_empty(p.log_scales),
        quats: non_empty(p.quats),
        opacity_logits: into_contiguous(p.opacity_logits),
        features: non_empty(p.features),
        background: into_contiguous(p.background),
        screen_offsets: non_empty(p.screen_offsets),
    }
}

impl SplatBackend for CubeBackend {
    fn splat_forward(inputs: SplatPrims<Self>, camera: Camera, config: RasterConfig) -> SplatFwdPrims<Self> {
        let c = inputs.background.meta.shape().num_elements();
        let p = contiguous_inputs(inputs);
        let b = bin(&p, &camera, &config);
        let (w, h) = (camera.width as usize, camera.height as usize);
        let [tx, ty] = camera.tiles();
        let packed = alloc(&p.means, vec![h, w, c + 2], DType::F32);
        let top_id = alloc(&p.means, vec![h, w], DType::I32);
        let final_t = alloc(&p.means, vec![h, w], DType::F32);
        let n_visited = alloc(&p.means, vec![h, w], DType::I32);
        // SAFETY: every index of the kernel is in range (see its docs).
        unsafe {
            raster_fwd_kernel::launch_unchecked(
                &p.means.client,
                CubeCount::Static(tx, ty, 1),
                CubeDim::new_1d(TILE_PIXELS),
                buf(&b.proj),
                buf(&p.features),
                buf(&p.background),
                buf(&b.offsets),
                buf(&b.counts),
                buf(&b.gids),
                buf(&b.cam),
                buf(&packed),
                buf(&top_id),
                buf(&final_t),
                buf(&n_visited),
                camera.width,
                camera.height,
                tx,
                c as u32,
                CANARY_TRIPS,
                buf(&b.truncated),
                reg_channels(c),
            );
        }
        check_loops(&b.truncated, "forward");
        let bins = SplatBins { proj: b.proj, rects: b.rects, offsets: b.offsets, ids: b.gids };
        SplatFwdPrims { packed, top_id, final_t, n_visited, bins }
    }

    fn splat_backward(
        inputs: SplatPrims<Self>,
        saved: SplatSaved<Self>,
        camera: Camera,
        config: RasterConfig,
    ) -> SplatPrims<Self> {
        let c = inputs.background.meta.shape().num_elements();
        let n = inputs.opacity_logits.meta.shape().num_elements();
        let p = contiguous_inputs(inputs);
        let b = reuse_bins(saved.bins, &p, &camera, &config);
        let (w, h) = (camera.width as usize, camera.height as usize);
        let [tx, ty] = camera.tiles();
        let final_t = into_contiguous(saved.final_t);
        let n_visited = into_contiguous(saved.n_visited);
        let grad_packed = into_contiguous(saved.grad_packed);
        let g2d = zeros(&p.means, vec![n.max(1), G2D], DType::F32);
        let gfeat = zeros(&p.means, vec![n.max(1), c], DType::F32);
        let client = p.means.client.clone();
        let plane = use_plane(&client, config.grad_reduce);
        let native = use_native_add(&client, config.float_add);
        if native && !native_float_add(&client) {
            panic!(
                "FloatAdd::Native was asked for, but `{}` has no atomic float add (use FloatAdd::Auto or Cas)",
                client.properties().identity.name
            );
        }
        // One launch, the atomic chosen at run time: the kernel is generic over it.
        macro_rules! launch_bwd {
            ($add:ty) => {
                // SAFETY: every index of the kernel is in range (see its docs).
                unsafe {
                    raster_bwd_kernel::launch_unchecked::<$add>(
                        &client,
                        CubeCount::Static(tx, ty, 1),
                        CubeDim::new_1d(TILE_PIXELS),
                        buf(&b.proj),
                        buf(&p.features),
                        buf(&p.background),
                        buf(&b.offsets),
                        buf(&b.gids),
                        buf(&b.cam),
                        buf(&final_t),
                        buf(&n_visited),
                        buf(&grad_packed),
                        buf(&g2d),
                        buf(&gfeat),
                        camera.width,
                        camera.height,
                        tx,
                        c as u32,
                        CANARY_TRIPS,
                        buf(&b.truncated),
                        plane,
                        reg_channels(c),
                    )
                }
            };
        }
        if native {
            launch_bwd!(NativeAdd)
        } else {
            launch_bwd!(CasAdd)
        }
        check_loops(&b.truncated, "backward");
        let g_means = alloc(&p.means, vec![n.max(1), 3], DType::F32);
        let g_scales = alloc(&p.means, vec![n.max(1), 3], DType::F32);
        let g_quats = alloc(&p.means, vec![n.max(1), 4], DType::F32);
        let g_logits = alloc(&p.means, vec![n.max(1)], DType::F32);
        let g_offsets = alloc(&p.means, vec![n.max(1), 2], DType::F32);
        if n > 0 {
            project_bwd_kernel::launch(
                &client,
                groups(n),
                CubeDim::new_1d(TILE_PIXELS),
                buf(&p.means),
                buf(&p.log_scales),
                buf(&p.quats),
                buf(&b.proj),
                buf(&b.rects),
                buf(&g2d),
                buf(&b.cam),
                buf(&g_means),
                buf(&g_scales),
                buf(&g_quats),
                buf(&g_logits),
                buf(&g_offsets),
                n as u32,
            );
        }
        // Background: sum over pixels of grad_image * final_t (plain tensor ops on the device).
        let gi = CubeBackend::float_reshape(grad_packed, Shape::from(vec![h * w, c + 2]));
        let gi = CubeBackend::float_slice(gi, &[burn::tensor::Slice::from(0..h * w), burn::tensor::Slice::from(0..c)]);
        let ft = CubeBackend::float_reshape(final_t, Shape::from(vec![h * w, 1]));
        let g_bg = CubeBackend::float_sum_dim(CubeBackend::float_mul(gi, ft), 0);
        let g_bg = CubeBackend::float_reshape(g_bg, Shape::from(vec![c]));
        let shape_n = |t: CubeTensor, cols: Option<usize>| -> CubeTensor {
            let shape = match cols {
                Some(k) => vec![n, k],
                None => vec![n],
            };
            if n == 0 { zeros(&t, shape, DType::F32) } else { t }
        };
        SplatPrims {
            means: shape_n(g_means, Some(3)),
            log_scales: shape_n(g_scales, Some(3)),
            quats: shape_n(g_quats, Some(4)),
            opacity_logits: shape_n(g_logits, None),
            features: shape_n(gfeat, Some(c)),
            background: g_bg,
            screen_offsets: shape_n(g_offsets, Some(2)),
        }
    }
}
