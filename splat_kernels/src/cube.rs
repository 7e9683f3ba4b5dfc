//! The op as CubeCL kernels (the wgpu backend; any CubeCL runtime works).
//!
//! Pipeline, all on the device; the only host read is the number of tile intersections, which
//! sizes the intersection buffers:
//!
//! 1. `project_kernel` (thread per Gaussian): screen-space centre, conic, depth, opacity, tile
//!    rectangle; atomically counts Gaussians per tile.
//! 2. `scan_kernel` (one workgroup): exclusive prefix sum of the tile counts -> tile offsets, total.
//! 3. `emit_kernel` (thread per Gaussian): writes (depth, id) into each touched tile's segment.
//! 4. `tile_sort_kernel` (workgroup per tile): bitonic sort of the segment by (depth, id), so the
//!    order is the same total order as on the CPU.
//! 5. `raster_fwd_kernel` (workgroup per 16x16 tile, thread per pixel): front-to-back compositing
//!    with Gaussians staged through shared memory in batches of 256.
//!
//! Backward: steps 1-4 again, then `raster_bwd_kernel` walks each pixel's list back to front and
//! adds per-Gaussian screen-space gradients with atomic float adds (compare-and-swap on the bits),
//! then `project_bwd_kernel` maps them to the 3D parameters. Float atomics make the wgpu gradients
//! order-dependent in the last bits (the CPU path is bitwise deterministic).
//!
//! The math mirrors [`crate::project`] and [`crate::cpu`] line for line; see there for derivations.

use crate::camera::Camera;
use crate::constants::{LOG_SCALE_MAX, LOG_SCALE_MIN, LOW_PASS, QUAT_MIN_NORM, RasterConfig, TILE_PIXELS, TILE_SIZE};
use crate::ext::{SplatBackend, SplatFwdPrims, SplatPrims, SplatSaved};
use burn::backend::ops::FloatTensorOps;
use burn::backend::try_read_sync;
use burn::backend::wgpu::{CubeBackend, CubeTensor};
use burn::tensor::{DType, Shape, TensorData};
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::{empty_device_dtype, zeros_client};
use cubecl::prelude::*;

// The packed buffers the kernels share, by named offset.

/// Floats per projected Gaussian (`proj`): the fields `P_*`.
const PROJ: usize = 8;
/// Projected screen-space centre x, y.
const P_MX: usize = 0;
const P_MY: usize = 1;
/// Projected conic (inverse 2D covariance) a, b, c.
const P_CA: usize = 2;
const P_CB: usize = 3;
const P_CC: usize = 4;
const P_DEPTH: usize = 5;
const P_OPACITY: usize = 6;
const P_RADIUS: usize = 7;
/// Floats per Gaussian staged in shared memory by the raster kernels: `proj`'s first fields, up
/// to the opacity (the radius stays behind).
const STAGED: usize = 7;

/// Per-Gaussian screen-space gradient slots (`g2d`): the fields `G_*`.
const G2D: usize = 7;
const G_MX: usize = 0;
const G_MY: usize = 1;
const G_CA: usize = 2;
const G_CB: usize = 3;
const G_CC: usize = 4;
const G_OPACITY: usize = 5;
const G_DEPTH: usize = 6;

/// Camera parameter block (`cam`), built by `cam_block`: the fields `C_*`.
const CAM: usize = 24;
/// World-to-camera rotation, 9 floats row-major (`C_R + 3 * row + col`).
const C_R: usize = 0;
/// World-to-camera translation, 3 floats.
const C_T: usize = 9;
const C_FX: usize = 12;
const C_FY: usize = 13;
const C_CX: usize = 14;
const C_CY: usize = 15;
/// The clamp limits of the normalised image coordinates x/z and y/z (`Camera::clamp_limits`).
const C_LIM_X: usize = 16;
const C_LIM_Y: usize = 17;
const C_NEAR: usize = 18;
const C_FAR: usize = 19;
/// The Gaussian extent in standard deviations (`RasterConfig::extent`).
const C_EXTENT: usize = 20;
const C_ALPHA_MAX: usize = 21;
const C_ALPHA_MIN: usize = 22;
const C_T_MIN: usize = 23;

#[cube]
fn sigmoid(x: f32) -> f32 {
    // exp of a non-positive argument only: no overflow for any finite logit.
    let e = f32::exp(-f32::abs(x));
    let mut r = e / (1.0 + e);
    if x >= 0.0 {
        r = 1.0 / (1.0 + e);
    }
    r
}

/// Per-Gaussian projection intermediates shared by the forward and backward kernels.
#[derive(CubeType)]
struct Covar {
    /// Camera-space centre.
    p0: f32,
    p1: f32,
    z: f32,
    /// Normalised quaternion and 1/|q| (0 under the identity policy).
    qw: f32,
    qx: f32,
    qy: f32,
    qz: f32,
    inv_norm: f32,
    r00: f32,
    r01: f32,
    r02: f32,
    r10: f32,
    r11: f32,
    r12: f32,
    r20: f32,
    r21: f32,
    r22: f32,
    s0: f32,
    s1: f32,
    s2: f32,
    /// `R_c R S`
    c00: f32,
    c01: f32,
    c02: f32,
    c10: f32,
    c11: f32,
    c12: f32,
    c20: f32,
    c21: f32,
    c22: f32,
    u: f32,
    v: f32,
    uc: f32,
    vc: f32,
    j00: f32,
    j02: f32,
    j11: f32,
    j12: f32,
    /// `T = J R_c R S`
    t00: f32,
    t01: f32,
    t02: f32,
    t10: f32,
    t11: f32,
    t12: f32,
}

#[cube]
fn covar(means: &[f32], log_scales: &[f32], quats: &[f32], cam: &[f32], iu: usize) -> Covar {
    let mx = means[iu * 3];
    let my = means[iu * 3 + 1];
    let mz = means[iu * 3 + 2];
    let p0 = cam[C_R] * mx + cam[C_R + 1] * my + cam[C_R + 2] * mz + cam[C_T];
    let p1 = cam[C_R + 3] * mx + cam[C_R + 4] * my + cam[C_R + 5] * mz + cam[C_T + 1];
    let z = cam[C_R + 6] * mx + cam[C_R + 7] * my + cam[C_R + 8] * mz + cam[C_T + 2];
    let fx = cam[C_FX];
    let fy = cam[C_FY];
    // Quaternion (w, x, y, z) -> rotation, identity policy for tiny norms.
    let q0 = quats[iu * 4];
    let q1 = quats[iu * 4 + 1];
    let q2 = quats[iu * 4 + 2];
    let q3 = quats[iu * 4 + 3];
    let m = f32::max(f32::max(f32::abs(q0), f32::abs(q1)), f32::max(f32::abs(q2), f32::abs(q3)));
    let mut qw = 1.0f32;
    let mut qx = 0.0f32;
    let mut qy = 0.0f32;
    let mut qz = 0.0f32;
    let mut inv_norm = 0.0f32;
    if m > 0.0 {
        let a0 = q0 / m;
        let a1 = q1 / m;
        let a2 = q2 / m;
        let a3 = q3 / m;
        let nn = f32::sqrt(a0 * a0 + a1 * a1 + a2 * a2 + a3 * a3);
        if m * nn >= QUAT_MIN_NORM {
            qw = a0 / nn;
            qx = a1 / nn;
            qy = a2 / nn;
            qz = a3 / nn;
            inv_norm = 1.0 / (m * nn);
        }
    }
    let r00 = 1.0 - 2.0 * (qy * qy + qz * qz);
    let r01 = 2.0 * (qx * qy - qw * qz);
    let r02 = 2.0 * (qx * qz + qw * qy);
    let r10 = 2.0 * (qx * qy + qw * qz);
    let r11 = 1.0 - 2.0 * (qx * qx + qz * qz);
    let r12 = 2.0 * (qy * qz - qw * qx);
    let r20 = 2.0 * (qx * qz - qw * qy);
    let r21 = 2.0 * (qy * qz + qw * qx);
    let r22 = 1.0 - 2.0 * (qx * qx + qy * qy);
    let s0 = f32::exp(f32::clamp(log_scales[iu * 3], LOG_SCALE_MIN, LOG_SCALE_MAX));
    let s1 = f32::exp(f32::clamp(log_scales[iu * 3 + 1], LOG_SCALE_MIN, LOG_SCALE_MAX));
    let s2 = f32::exp(f32::clamp(log_scales[iu * 3 + 2], LOG_SCALE_MIN, LOG_SCALE_MAX));
    let c00 = cam[C_R] * r00 * s0 + cam[C_R + 1] * r10 * s0 + cam[C_R + 2] * r20 * s0;
    let c01 = cam[C_R] * r01 * s1 + cam[C_R + 1] * r11 * s1 + cam[C_R + 2] * r21 * s1;
    let c02 = cam[C_R] * r02 * s2 + cam[C_R + 1] * r12 * s2 + cam[C_R + 2] * r22 * s2;
    let c10 = cam[C_R + 3] * r00 * s0 + cam[C_R + 4] * r10 * s0 + cam[C_R + 5] * r20 * s0;
    let c11 = cam[C_R + 3] * r01 * s1 + cam[C_R + 4] * r11 * s1 + cam[C_R + 5] * r21 * s1;
    let c12 = cam[C_R + 3] * r02 * s2 + cam[C_R + 4] * r12 * s2 + cam[C_R + 5] * r22 * s2;
    let c20 = cam[C_R + 6] * r00 * s0 + cam[C_R + 7] * r10 * s0 + cam[C_R + 8] * r20 * s0;
    let c21 = cam[C_R + 6] * r01 * s1 + cam[C_R + 7] * r11 * s1 + cam[C_R + 8] * r21 * s1;
    let c22 = cam[C_R + 6] * r02 * s2 + cam[C_R + 7] * r12 * s2 + cam[C_R + 8] * r22 * s2;
    let u = p0 / z;
    let v = p1 / z;
    let uc = f32::clamp(u, 0.0f32 - cam[C_LIM_X], cam[C_LIM_X]);
    let vc = f32::clamp(v, 0.0f32 - cam[C_LIM_Y], cam[C_LIM_Y]);
    let j00 = fx / z;
    let j02 = 0.0f32 - fx * uc / z;
    let j11 = fy / z;
    let j12 = 0.0f32 - fy * vc / z;
    Covar {
        p0,
        p1,
        z,
        qw,
        qx,
        qy,
        qz,
        inv_norm,
        r00,
        r01,
        r02,
        r10,
        r11,
        r12,
        r20,
        r21,
        r22,
        s0,
        s1,
        s2,
        c00,
        c01,
        c02,
        c10,
        c11,
        c12,
        c20,
        c21,
        c22,
        u,
        v,
        uc,
        vc,
        j00,
        j02,
        j11,
        j12,
        t00: j00 * c00 + j02 * c20,
        t01: j00 * c01 + j02 * c21,
        t02: j00 * c02 + j02 * c22,
        t10: j11 * c10 + j12 * c20,
        t11: j11 * c11 + j12 * c21,
        t12: j11 * c12 + j12 * c22,
    }
}

/// Thread per Gaussian: projection, culling, tile rectangle and per-tile counts.
// `x - x == 0.0` is the finiteness test (false for NaN and infinities): #[cube] has no is_finite.
#[allow(clippy::eq_op)]
#[cube(launch)]
fn project_kernel(
    means: &[f32],
    log_scales: &[f32],
    quats: &[f32],
    logits: &[f32],
    offsets: &[f32],
    cam: &[f32],
    proj: &mut [f32],
    rects: &mut [u32],
    tile_counts: &[Atomic<u32>],
    n: u32,
    tiles_x: u32,
    tiles_y: u32,
) {
    let i = ABSOLUTE_POS as u32;
    if i >= n {
        terminate!();
    }
    // `rects` and `proj` arrive zeroed: a culled Gaussian keeps an empty rectangle.
    let iu = i as usize;
    let k = covar(means, log_scales, quats, cam, iu);
    let z = k.z;
    let fx = cam[C_FX];
    let fy = cam[C_FY];
    let u = k.u;
    let v = k.v;
    let mut visible = z >= cam[C_NEAR] && z <= cam[C_FAR];
    let t00 = k.t00;
    let t01 = k.t01;
    let t02 = k.t02;
    let t10 = k.t10;
    let t11 = k.t11;
    let t12 = k.t12;
    let ta = t00 * t00 + t01 * t01 + t02 * t02;
    let tc = t10 * t10 + t11 * t11 + t12 * t12;
    let a = ta + LOW_PASS;
    let b = t00 * t10 + t01 * t11 + t02 * t12;
    let c = tc + LOW_PASS;
    let n01 = t00 * t11 - t01 * t10;
    let n02 = t00 * t12 - t02 * t10;
    let n12 = t01 * t12 - t02 * t11;
    let det = n01 * n01 + n02 * n02 + n12 * n12 + LOW_PASS * (ta + tc) + LOW_PASS * LOW_PASS;
    // `x - x == 0` is false for infinities and NaN: a finiteness test without intrinsics.
    let finite = det - det == 0.0 && a - a == 0.0 && c - c == 0.0 && b - b == 0.0;
    visible = visible && finite && det > 0.0;
    let hd = 0.5 * (a - c);
    let lambda_max = 0.5 * (a + c) + f32::sqrt(hd * hd + b * b);
    let radius = f32::ceil(cam[C_EXTENT] * f32::sqrt(lambda_max));
    let cx2 = fx * u + cam[C_CX] + offsets[iu * 2];
    let cy2 = fy * v + cam[C_CY] + offsets[iu * 2 + 1];
    visible = visible && cx2 - cx2 == 0.0 && cy2 - cy2 == 0.0 && radius - radius == 0.0;
    let ts = f32::cast_from(TILE_SIZE);
    let tx0 = f32::clamp(f32::floor((cx2 - radius) / ts), 0.0, f32::cast_from(tiles_x));
    let ty0 = f32::clamp(f32::floor((cy2 - radius) / ts), 0.0, f32::cast_from(tiles_y));
    let tx1 = f32::clamp(f32::floor((cx2 + radius) / ts) + 1.0, 0.0, f32::cast_from(tiles_x));
    let ty1 = f32::clamp(f32::floor((cy2 + radius) / ts) + 1.0, 0.0, f32::cast_from(tiles_y));
    visible = visible && tx0 < tx1 && ty0 < ty1;
    if visible {
        let x0 = u32::cast_from(tx0);
        let y0 = u32::cast_from(ty0);
        let x1 = u32::cast_from(tx1);
        let y1 = u32::cast_from(ty1);
        rects[iu * 4] = x0;
        rects[iu * 4 + 1] = y0;
        rects[iu * 4 + 2] = x1;
        rects[iu * 4 + 3] = y1;
        proj[iu * PROJ + P_MX] = cx2;
        proj[iu * PROJ + P_MY] = cy2;
        proj[iu * PROJ + P_CA] = c / det;
        proj[iu * PROJ + P_CB] = -b / det;
        proj[iu * PROJ + P_CC] = a / det;
        proj[iu * PROJ + P_DEPTH] = z;
        proj[iu * PROJ + P_OPACITY] = sigmoid(logits[iu]);
        proj[iu * PROJ + P_RADIUS] = radius;
        for ty in y0..y1 {
            for tx in x0..x1 {
                tile_counts[(ty * tiles_x + tx) as usize].fetch_add(1u32);
            }
        }
    }
}

/// One workgroup of 256: exclusive prefix sum of `counts[0..n]` into `offsets`, total into `total[0]`.
#[cube(launch)]
fn scan_kernel(counts: &[u32], offsets: &mut [u32], total: &mut [u32], n: u32) {
    let mut partial = Shared::<[u32]>::new_slice(256usize);
    let per = n.div_ceil(TILE_PIXELS);
    let begin = u32::min(UNIT_POS * per, n);
    let end = u32::min(begin + per, n);
    let mut s = 0u32;
    for k in begin..end {
        s += counts[k as usize];
    }
    partial[UNIT_POS as usize] = s;
    sync_cube();
    if UNIT_POS == 0 {
        let mut running = 0u32;
        for k in 0..TILE_PIXELS {
            let v = partial[k as usize];
            partial[k as usize] = running;
            running += v;
        }
        total[0] = running;
    }
    sync_cube();
    let mut acc = partial[UNIT_POS as usize];
    for k in begin..end {
        offsets[k as usize] = acc;
        acc += counts[k as usize];
    }
}

/// Thread per Gaussian: writes (depth, id) into the segments of the tiles it touches.
#[cube(launch)]
fn emit_kernel(
    proj: &[f32],
    rects: &[u32],
    offsets: &[u32],
    cursors: &[Atomic<u32>],
    keys: &mut [f32],
    gids: &mut [u32],
    n: u32,
    tiles_x: u32,
) {
    let i = ABSOLUTE_POS as u32;
    if i >= n {
        terminate!();
    }
    let iu = i as usize;
    let depth = proj[iu * PROJ + P_DEPTH];
    for ty in rects[iu * 4 + 1]..rects[iu * 4 + 3] {
        for tx in rects[iu * 4]..rects[iu * 4 + 2] {
            let t = (ty * tiles_x + tx) as usize;
            let slot = (offsets[t] + cursors[t].fetch_add(1u32)) as usize;
            keys[slot] = depth;
            gids[slot] = i;
        }
    }
}

#[cube]
fn compare_swap(keys: &mut [f32], gids: &mut [u32], lo: usize, hi: usize) {
    let ka = keys[lo];
    let kb = keys[hi];
    let ga = gids[lo];
    let gb = gids[hi];
    if kb < ka || (kb == ka && gb < ga) {
        keys[lo] = kb;
        keys[hi] = ka;
        gids[lo] = gb;
        gids[hi] = ga;
    }
}

/// Workgroup per tile: bitonic sort (the variant whose comparators all point the same way, so a
/// length that is not a power of two is padded with implicit +inf) of the tile's segment.
#[cube(launch)]
fn tile_sort_kernel(keys: &mut [f32], gids: &mut [u32], offsets: &[u32], counts: &[u32], tiles_x: u32) {
    let tile = (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize;
    let start = offsets[tile] as usize;
    let n = counts[tile];
    let mut m = 1u32;
    while m < n {
        m *= 2;
    }
    let pairs = m / 2;
    let mut size = 2u32;
    while size <= m {
        let half = size / 2;
        let mut i = UNIT_POS;
        while i < pairs {
            let blk = i / half;
            let off = i % half;
            let lo = blk * size + off;
            let hi = blk * size + size - 1 - off;
            if hi < n {
                compare_swap(keys, gids, start + lo as usize, start + hi as usize);
            }
            i += TILE_PIXELS;
        }
        sync_storage();
        let mut stride = half / 2;
        while stride > 0 {
            let mut j = UNIT_POS;
            while j < pairs {
                let blk = j / stride;
                let off = j % stride;
                let lo = blk * 2 * stride + off;
                let hi = lo + stride;
                if hi < n {
                    compare_swap(keys, gids, start + lo as usize, start + hi as usize);
                }
                j += TILE_PIXELS;
            }
            sync_storage();
            stride /= 2;
        }
        size *= 2;
    }
}

/// Each thread of the workgroup copies one tile-list entry (`first + UNIT_POS`, if below
/// `first + len`) into shared memory: its id and the first 7 projected floats.
#[cube]
fn stage_batch(gids: &[u32], proj: &[f32], s_gid: &mut Shared<[u32]>, s_p: &mut Shared<[f32]>, first: u32, len: u32) {
    if UNIT_POS < len {
        let u = UNIT_POS as usize;
        let g = gids[(first + UNIT_POS) as usize];
        let gu = g as usize;
        s_gid[u] = g;
        for k in 0usize..STAGED {
            s_p[u * STAGED + k] = proj[gu * PROJ + k];
        }
    }
}

/// Where a raster kernel's thread is: its tile (one workgroup), its pixel (one thread) and
/// whether that pixel is inside the image. The forward and backward kernels start alike.
#[derive(CubeType)]
struct TilePixel {
    /// The tile's index, row-major over `tiles_x` columns.
    tile: usize,
    /// The pixel's row-major index in the image (meaningful when `inside`).
    pix: usize,
    inside: bool,
    /// The pixel's centre.
    pxf: f32,
    pyf: f32,
}

#[cube]
fn tile_pixel(width: u32, height: u32, tiles_x: u32) -> TilePixel {
    let px = CUBE_POS_X * TILE_SIZE + UNIT_POS % TILE_SIZE;
    let py = CUBE_POS_Y * TILE_SIZE + UNIT_POS / TILE_SIZE;
    TilePixel {
        tile: (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize,
        pix: (py * width + px) as usize,
        inside: px < width && py < height,
        pxf: f32::cast_from(px) + 0.5,
        pyf: f32::cast_from(py) + 0.5,
    }
}

/// Workgroup per tile, thread per pixel: front-to-back compositing.
#[cube(launch)]
fn raster_fwd_kernel(
    proj: &[f32],
    features: &[f32],
    background: &[f32],
    offsets: &[u32],
    counts: &[u32],
    gids: &[u32],
    cam: &[f32],
    packed: &mut [f32],
    top_id: &mut [i32],
    final_t: &mut [f32],
    n_visited: &mut [i32],
    width: u32,
    height: u32,
    tiles_x: u32,
    channels: u32,
) {
    // Shared staging for one batch: TILE_PIXELS ids and STAGED floats each (256 x 7: sizes must be literals).
    let mut s_gid = Shared::<[u32]>::new_slice(256usize);
    let mut s_p = Shared::<[f32]>::new_slice(1792usize);
    let at = tile_pixel(width, height, tiles_x);
    let tile = at.tile;
    let pix = at.pix;
    let inside = at.inside;
    let pxf = at.pxf;
    let pyf = at.pyf;
    let c2 = (channels + 2) as usize;
    let ch_n = channels as usize;
    let alpha_max = cam[C_ALPHA_MAX];
    let alpha_min = cam[C_ALPHA_MIN];
    let t_min = cam[C_T_MIN];
    let start = offsets[tile];
    let count = counts[tile];
    let mut t = 1.0f32;
    let mut done = !inside;
    let mut depth_acc = 0.0f32;
    let mut best = 0.0f32;
    let mut top = i32::new(-1);
    let mut nv = 0i32;
    if inside {
        for ch in 0usize..ch_n {
            packed[pix * c2 + ch] = 0.0;
        }
    }
    let mut base = 0u32;
    while base < count {
        stage_batch(gids, proj, &mut s_gid, &mut s_p, start + base, count - base);
        sync_cube();
        let batch = u32::min(TILE_PIXELS, count - base);
        for j in 0u32..batch {
            if !done {
                let ju = j as usize;
                let dx = pxf - s_p[ju * STAGED + P_MX];
                let dy = pyf - s_p[ju * STAGED + P_MY];
                let power = 0.0f32
                    - 0.5f32 * (s_p[ju * STAGED + P_CA] * dx * dx + s_p[ju * STAGED + P_CC] * dy * dy)
                    - s_p[ju * STAGED + P_CB] * dx * dy;
                if power <= 0.0 {
                    let alpha = f32::min(alpha_max, s_p[ju * STAGED + P_OPACITY] * f32::exp(power));
                    if alpha >= alpha_min {
                        let next_t = t * (1.0 - alpha);
                        if next_t < t_min {
                            done = true;
                        } else {
                            let w = alpha * t;
                            let g = s_gid[ju];
                            let fo = (g * channels) as usize;
                            for ch in 0usize..ch_n {
                                packed[pix * c2 + ch] += w * features[fo + ch];
                            }
                            depth_acc += w * s_p[ju * STAGED + P_DEPTH];
                            if w > best {
                                best = w;
                                top = i32::cast_from(g);
                            }
                            t = next_t;
                            nv = i32::cast_from(base + j) + 1;
                        }
                    }
                }
            }
        }
        sync_cube();
        base += TILE_PIXELS;
    }
    if inside {
        for ch in 0usize..ch_n {
            packed[pix * c2 + ch] += t * background[ch];
        }
        packed[pix * c2 + ch_n] = 1.0 - t;
        packed[pix * c2 + ch_n + 1] = depth_acc;
        top_id[pix] = top;
        final_t[pix] = t;
        n_visited[pix] = nv;
    }
}

/// `buf[idx] += val` on f32 bits stored in u32 atomics (compare-and-swap loop).
#[cube]
fn atomic_add_f32(buf: &[Atomic<u32>], idx: usize, val: f32) {
    let mut old = buf[idx].load();
    loop {
        let new_bits = u32::reinterpret(f32::reinterpret(old) + val);
        let prev = buf[idx].compare_exchange_weak(old, new_bits);
        if prev == old {
            break;
        }
        old = prev;
    }
}

/// Workgroup per tile, thread per pixel: back-to-front walk, atomic accumulation of screen-space
/// and feature gradients per Gaussian.
#[cube(launch)]
fn raster_bwd_kernel(
    proj: &[f32],
    features: &[f32],
    background: &[f32],
    offsets: &[u32],
    gids: &[u32],
    cam: &[f32],
    final_t: &[f32],
    n_visited: &[i32],
    grad_packed: &[f32],
    rec: &mut [f32],
    g2d: &[Atomic<u32>],
    gfeat: &[Atomic<u32>],
    width: u32,
    height: u32,
    tiles_x: u32,
    channels: u32,
) {
    // Shared staging for one batch: TILE_PIXELS ids and STAGED floats each (256 x 7: sizes must be literals).
    let mut s_gid = Shared::<[u32]>::new_slice(256usize);
    let mut s_p = Shared::<[f32]>::new_slice(1792usize);
    let mut s_max = Shared::<[u32]>::new_slice(256usize);
    let at = tile_pixel(width, height, tiles_x);
    let tile = at.tile;
    let pix = at.pix;
    let inside = at.inside;
    let pxf = at.pxf;
    let pyf = at.pyf;
    let c2 = (channels + 2) as usize;
    let ch_n = channels as usize;
    let alpha_max = cam[C_ALPHA_MAX];
    let alpha_min = cam[C_ALPHA_MIN];
    let start = offsets[tile];
    let mut tt = 1.0f32;
    let mut tf = 1.0f32;
    let mut last = 0u32;
    let mut rec_z = 0.0f32;
    let mut g_a = 0.0f32;
    let mut g_z = 0.0f32;
    if inside {
        tt = final_t[pix];
        tf = tt;
        last = u32::cast_from(n_visited[pix]);
        g_a = grad_packed[pix * c2 + ch_n];
        g_z = grad_packed[pix * c2 + ch_n + 1];
        for ch in 0usize..ch_n {
            rec[pix * ch_n + ch] = background[ch];
        }
    }
    s_max[UNIT_POS as usize] = last;
    sync_cube();
    if UNIT_POS == 0 {
        let mut mx = 0u32;
        for k in 0..TILE_PIXELS {
            mx = u32::max(mx, s_max[k as usize]);
        }
        s_max[0] = mx;
    }
    sync_cube();
    let max_last = s_max[0];
    let mut end = max_last;
    while end > 0 {
        let begin = end - u32::min(TILE_PIXELS, end);
        stage_batch(gids, proj, &mut s_gid, &mut s_p, start + begin, end - begin);
        sync_cube();
        let batch = end - begin;
        for jj in 0u32..batch {
            let j = batch - 1 - jj;
            let k = begin + j;
            if inside && k < last {
                let ju = j as usize;
                let dx = pxf - s_p[ju * STAGED + P_MX];
                let dy = pyf - s_p[ju * STAGED + P_MY];
                let ca = s_p[ju * STAGED + P_CA];
                let cb = s_p[ju * STAGED + P_CB];
                let cc = s_p[ju * STAGED + P_CC];
                let power = 0.0f32 - 0.5f32 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
                if power <= 0.0 {
                    let gexp = f32::exp(power);
                    let op = s_p[ju * STAGED + P_OPACITY];
                    let raw = op * gexp;
                    let alpha = f32::min(alpha_max, raw);
                    if alpha >= alpha_min {
                        let g = s_gid[ju];
                        let fo = (g * channels) as usize;
                        let depth = s_p[ju * STAGED + P_DEPTH];
                        let t_k = tt / (1.0 - alpha);
                        let w = alpha * t_k;
                        let mut d_alpha = 0.0f32;
                        for ch in 0usize..ch_n {
                            let gf = grad_packed[pix * c2 + ch];
                            let f = features[fo + ch];
                            let r = rec[pix * ch_n + ch];
                            d_alpha += gf * (f - r);
                            atomic_add_f32(gfeat, fo + ch, w * gf);
                            rec[pix * ch_n + ch] = alpha * f + (1.0 - alpha) * r;
                        }
                        d_alpha += g_z * (depth - rec_z);
                        d_alpha *= t_k;
                        d_alpha += g_a * tf / (1.0 - alpha);
                        let go = g as usize * G2D;
                        atomic_add_f32(g2d, go + G_DEPTH, w * g_z);
                        rec_z = alpha * depth + (1.0 - alpha) * rec_z;
                        tt = t_k;
                        if raw < alpha_max {
                            atomic_add_f32(g2d, go + G_OPACITY, d_alpha * gexp);
                            let d_power = d_alpha * op * gexp;
                            atomic_add_f32(g2d, go + G_MX, d_power * (ca * dx + cb * dy));
                            atomic_add_f32(g2d, go + G_MY, d_power * (cc * dy + cb * dx));
                            atomic_add_f32(g2d, go + G_CA, d_power * (0.0f32 - 0.5f32 * dx * dx));
                            atomic_add_f32(g2d, go + G_CB, d_power * (0.0f32 - dx * dy));
                            atomic_add_f32(g2d, go + G_CC, d_power * (0.0f32 - 0.5f32 * dy * dy));
                        }
                    }
                }
            }
        }
        sync_cube();
        end = begin;
    }
}

/// Thread per Gaussian: screen-space gradients -> gradients of the 3D parameters.
// #[cube] code has no `RangeInclusive::contains`.
#[allow(clippy::manual_range_contains)]
#[cube(launch)]
fn project_bwd_kernel(
    means: &[f32],
    log_scales: &[f32],
    quats: &[f32],
    proj: &[f32],
    rects: &[u32],
    g2d: &[f32],
    cam: &[f32],
    g_means: &mut [f32],
    g_scales: &mut [f32],
    g_quats: &mut [f32],
    g_logits: &mut [f32],
    g_offsets: &mut [f32],
    n: u32,
) {
    let i = ABSOLUTE_POS as u32;
    if i >= n {
        terminate!();
    }
    let iu = i as usize;
    for k in 0usize..3usize {
        g_means[iu * 3 + k] = 0.0;
        g_scales[iu * 3 + k] = 0.0;
    }
    for k in 0usize..4usize {
        g_quats[iu * 4 + k] = 0.0;
    }
    g_logits[iu] = 0.0;
    g_offsets[iu * 2] = 0.0;
    g_offsets[iu * 2 + 1] = 0.0;
    // Culled Gaussians have an empty rectangle and keep zero gradients.
    if rects[iu * 4] < rects[iu * 4 + 2] {
        let gm0 = g2d[iu * G2D + G_MX];
        let gm1 = g2d[iu * G2D + G_MY];
        let gca = g2d[iu * G2D + G_CA];
        let gcb = g2d[iu * G2D + G_CB];
        let gcc = g2d[iu * G2D + G_CC];
        let gop = g2d[iu * G2D + G_OPACITY];
        let gdepth = g2d[iu * G2D + G_DEPTH];
        let opacity = proj[iu * PROJ + P_OPACITY];
        g_logits[iu] = gop * opacity * (1.0 - opacity);
        g_offsets[iu * 2] = gm0;
        g_offsets[iu * 2 + 1] = gm1;
        // Recompute the forward intermediates.
        let k = covar(means, log_scales, quats, cam, iu);
        let (p0, p1, z) = (k.p0, k.p1, k.z);
        let fx = cam[C_FX];
        let fy = cam[C_FY];
        let (qw, qx, qy, qz, inv_norm) = (k.qw, k.qx, k.qy, k.qz, k.inv_norm);
        let (r00, r01, r02, r10, r11, r12, r20, r21, r22) =
            (k.r00, k.r01, k.r02, k.r10, k.r11, k.r12, k.r20, k.r21, k.r22);
        let (s0, s1, s2) = (k.s0, k.s1, k.s2);
        let (c00, c01, c02, c10, c11, c12, c20, c21, c22) =
            (k.c00, k.c01, k.c02, k.c10, k.c11, k.c12, k.c20, k.c21, k.c22);
        let (u, v, uc, vc) = (k.u, k.v, k.uc, k.vc);
        let (j00, j02, j11, j12) = (k.j00, k.j02, k.j11, k.j12);
        let (t00, t01, t02, t10, t11, t12) = (k.t00, k.t01, k.t02, k.t10, k.t11, k.t12);
        let l0 = log_scales[iu * 3];
        let l1 = log_scales[iu * 3 + 1];
        let l2 = log_scales[iu * 3 + 2];
        // conic -> covariance
        let ia = proj[iu * PROJ + P_CA];
        let ib = proj[iu * PROJ + P_CB];
        let ic = proj[iu * PROJ + P_CC];
        let ga = gca;
        let gb = 0.5 * gcb;
        let gc = gcc;
        let x00 = ga * ia + gb * ib;
        let x01 = ga * ib + gb * ic;
        let x10 = gb * ia + gc * ib;
        let x11 = gb * ib + gc * ic;
        let d_a = 0.0f32 - (ia * x00 + ib * x10);
        let d_b = 0.0f32 - (ia * x01 + ib * x11);
        let d_c = 0.0f32 - (ib * x01 + ic * x11);
        let dt00 = 2.0 * (d_a * t00 + d_b * t10);
        let dt01 = 2.0 * (d_a * t01 + d_b * t11);
        let dt02 = 2.0 * (d_a * t02 + d_b * t12);
        let dt10 = 2.0 * (d_b * t00 + d_c * t10);
        let dt11 = 2.0 * (d_b * t01 + d_c * t11);
        let dt12 = 2.0 * (d_b * t02 + d_c * t12);
        let dj00 = dt00 * c00 + dt01 * c01 + dt02 * c02;
        let dj02 = dt00 * c20 + dt01 * c21 + dt02 * c22;
        let dj11 = dt10 * c10 + dt11 * c11 + dt12 * c12;
        let dj12 = dt10 * c20 + dt11 * c21 + dt12 * c22;
        let e00 = j00 * dt00;
        let e01 = j00 * dt01;
        let e02 = j00 * dt02;
        let e10 = j11 * dt10;
        let e11 = j11 * dt11;
        let e12 = j11 * dt12;
        let e20 = j02 * dt00 + j12 * dt10;
        let e21 = j02 * dt01 + j12 * dt11;
        let e22 = j02 * dt02 + j12 * dt12;
        let z2 = z * z;
        let mut dp0 = gm0 * fx / z;
        let mut dp1 = gm1 * fy / z;
        let mut dp2 =
            dj00 * (0.0f32 - fx / z2) + dj11 * (0.0f32 - fy / z2) + dj02 * (fx * uc / z2) + dj12 * (fy * vc / z2);
        if f32::abs(u) <= cam[C_LIM_X] {
            dp0 += dj02 * (0.0f32 - fx / z2);
            dp2 += dj02 * (fx * p0 / (z2 * z));
        }
        if f32::abs(v) <= cam[C_LIM_Y] {
            dp1 += dj12 * (0.0f32 - fy / z2);
            dp2 += dj12 * (fy * p1 / (z2 * z));
        }
        dp2 += 0.0f32 - gm0 * fx * p0 / z2 - gm1 * fy * p1 / z2 + gdepth;
        g_means[iu * 3] = cam[C_R] * dp0 + cam[C_R + 3] * dp1 + cam[C_R + 6] * dp2;
        g_means[iu * 3 + 1] = cam[C_R + 1] * dp0 + cam[C_R + 4] * dp1 + cam[C_R + 7] * dp2;
        g_means[iu * 3 + 2] = cam[C_R + 2] * dp0 + cam[C_R + 5] * dp1 + cam[C_R + 8] * dp2;
        // dM = R_c^T dE
        let dm00 = cam[C_R] * e00 + cam[C_R + 3] * e10 + cam[C_R + 6] * e20;
        let dm01 = cam[C_R] * e01 + cam[C_R + 3] * e11 + cam[C_R + 6] * e21;
        let dm02 = cam[C_R] * e02 + cam[C_R + 3] * e12 + cam[C_R + 6] * e22;
        let dm10 = cam[C_R + 1] * e00 + cam[C_R + 4] * e10 + cam[C_R + 7] * e20;
        let dm11 = cam[C_R + 1] * e01 + cam[C_R + 4] * e11 + cam[C_R + 7] * e21;
        let dm12 = cam[C_R + 1] * e02 + cam[C_R + 4] * e12 + cam[C_R + 7] * e22;
        let dm20 = cam[C_R + 2] * e00 + cam[C_R + 5] * e10 + cam[C_R + 8] * e20;
        let dm21 = cam[C_R + 2] * e01 + cam[C_R + 5] * e11 + cam[C_R + 8] * e21;
        let dm22 = cam[C_R + 2] * e02 + cam[C_R + 5] * e12 + cam[C_R + 8] * e22;
        if l0 >= LOG_SCALE_MIN && l0 <= LOG_SCALE_MAX {
            g_scales[iu * 3] = (dm00 * r00 + dm10 * r10 + dm20 * r20) * s0;
        }
        if l1 >= LOG_SCALE_MIN && l1 <= LOG_SCALE_MAX {
            g_scales[iu * 3 + 1] = (dm01 * r01 + dm11 * r11 + dm21 * r21) * s1;
        }
        if l2 >= LOG_SCALE_MIN && l2 <= LOG_SCALE_MAX {
            g_scales[iu * 3 + 2] = (dm02 * r02 + dm12 * r12 + dm22 * r22) * s2;
        }
        if inv_norm > 0.0 {
            let d00 = dm00 * s0;
            let d01 = dm01 * s1;
            let d02 = dm02 * s2;
            let d10 = dm10 * s0;
            let d11 = dm11 * s1;
            let d12 = dm12 * s2;
            let d20 = dm20 * s0;
            let d21 = dm21 * s1;
            let d22 = dm22 * s2;
            let gw = 2.0 * (0.0f32 - qz * d01 + qy * d02 + qz * d10 - qx * d12 - qy * d20 + qx * d21);
            let gx = 2.0
                * (qy * d01 + qz * d02 + qy * d10 - 2.0 * qx * d11 - qw * d12 + qz * d20 + qw * d21 - 2.0 * qx * d22);
            let gy = 2.0
                * (0.0f32 - 2.0 * qy * d00 + qx * d01 + qw * d02 + qx * d10 + qz * d12 - qw * d20 + qz * d21
                    - 2.0 * qy * d22);
            let gz = 2.0
                * (0.0f32 - 2.0 * qz * d00 - qw * d01 + qx * d02 + qw * d10 - 2.0 * qz * d11
                    + qy * d12
                    + qx * d20
                    + qy * d21);
            let dot = gw * qw + gx * qx + gy * qy + gz * qz;
            g_quats[iu * 4] = (gw - qw * dot) * inv_norm;
            g_quats[iu * 4 + 1] = (gx - qx * dot) * inv_norm;
            g_quats[iu * 4 + 2] = (gy - qy * dot) * inv_norm;
            g_quats[iu * 4 + 3] = (gz - qz * dot) * inv_norm;
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Host-side orchestration.

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
    let keys = alloc(like, vec![n_isect.max(1)], DType::F32);
    let gids = zeros(like, vec![n_isect.max(1)], DType::I32);
    if n > 0 && n_isect > 0 {
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
        );
    }
    DeviceBins { proj, rects, offsets, counts, gids, cam }
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
        raster_fwd_kernel::launch(
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
        );
        SplatFwdPrims { packed, top_id, final_t, n_visited }
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
        let b = bin(&p, &camera, &config);
        let (w, h) = (camera.width as usize, camera.height as usize);
        let [tx, ty] = camera.tiles();
        let final_t = into_contiguous(saved.final_t);
        let n_visited = into_contiguous(saved.n_visited);
        let grad_packed = into_contiguous(saved.grad_packed);
        let rec = alloc(&p.means, vec![h * w * c], DType::F32);
        let g2d = zeros(&p.means, vec![n.max(1), G2D], DType::F32);
        let gfeat = zeros(&p.means, vec![n.max(1), c], DType::F32);
        let client = p.means.client.clone();
        raster_bwd_kernel::launch(
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
            buf(&rec),
            buf(&g2d),
            buf(&gfeat),
            camera.width,
            camera.height,
            tx,
            c as u32,
        );
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
