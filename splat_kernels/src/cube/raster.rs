//! Steps 5 and 6: compositing (workgroup per 16x16 tile, thread per pixel), forward front to back
//! and backward back to front with atomic float adds.

use super::layout::*;
use crate::constants::{TILE_PIXELS, TILE_SIZE};
use cubecl::prelude::*;

/// Mesa lavapipe (llvmpipe) silently ends every loop of an invocation once that invocation has
/// run 65,535 loop iterations in all (its `LP_MAX_TGSI_LOOP_ITERATIONS`, shared by every loop
/// of the shader): a tile with many Gaussians then loses contributions without a sign. Called
/// last, this loop with a runtime trip count of [`CANARY_TRIPS`] runs once instead when the
/// limit was reached, and marks `truncated[0]`; GPUs have no such limit and never mark it.
#[cube]
pub(super) fn loop_canary(canary: u32, truncated: &mut [u32]) {
    let mut trips = 0u32;
    for _ in 0..canary {
        trips += 1;
    }
    if trips != canary {
        truncated[0] = 1;
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

/// Where a raster kernel's thread is and what it reads first: its tile (one workgroup), its pixel
/// (one thread), whether that pixel is inside the image, the channel counts and the alpha limits.
/// The forward and backward kernels start alike.
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
    /// `C` and `C + 2` (a pixel's stride in `packed`).
    ch_n: usize,
    c2: usize,
    alpha_max: f32,
    alpha_min: f32,
}

#[cube]
fn tile_pixel(width: u32, height: u32, tiles_x: u32, channels: u32, cam: &[f32]) -> TilePixel {
    let px = CUBE_POS_X * TILE_SIZE + UNIT_POS % TILE_SIZE;
    let py = CUBE_POS_Y * TILE_SIZE + UNIT_POS / TILE_SIZE;
    TilePixel {
        tile: (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize,
        pix: (py * width + px) as usize,
        inside: px < width && py < height,
        pxf: f32::cast_from(px) + 0.5,
        pyf: f32::cast_from(py) + 0.5,
        ch_n: channels as usize,
        c2: (channels + 2) as usize,
        alpha_max: cam[C_ALPHA_MAX],
        alpha_min: cam[C_ALPHA_MIN],
    }
}

/// A staged Gaussian's falloff at a pixel centre: the offset from its centre, its conic
/// (`ca`, `cb`, `cc`) and `power` = -(ca dx^2 + cc dy^2) / 2 - cb dx dy (`<= 0` inside).
#[derive(CubeType)]
struct Falloff {
    dx: f32,
    dy: f32,
    ca: f32,
    cb: f32,
    cc: f32,
    power: f32,
}

#[cube]
fn falloff(s_p: &Shared<[f32]>, ju: usize, pxf: f32, pyf: f32) -> Falloff {
    let dx = pxf - s_p[ju * STAGED + P_MX];
    let dy = pyf - s_p[ju * STAGED + P_MY];
    let ca = s_p[ju * STAGED + P_CA];
    let cb = s_p[ju * STAGED + P_CB];
    let cc = s_p[ju * STAGED + P_CC];
    let power = 0.0f32 - 0.5f32 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
    Falloff { dx, dy, ca, cb, cc, power }
}

/// Workgroup per tile, thread per pixel: front-to-back compositing.
///
/// With `reg_channels` > 0 (a bucket of at least the channel count, [`super::reg_channels`]) a
/// pixel's features are summed in registers and written once; with 0 they are summed in `packed`
/// in global memory, one read and write per channel and contact (any channel count).
///
/// Launched unchecked (no bounds test on each index): the tile comes from the launch grid (`tx` x
/// `ty`), every tile-list read stays inside the tile's `offsets`/`counts` segment that the binning
/// kernels wrote, every id in it is below N (`emit_kernel`), feature reads stay below the channel
/// count, and every write to a per-pixel output is under `inside`.
#[cube(launch_unchecked)]
pub(super) fn raster_fwd_kernel(
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
    canary: u32,
    truncated: &mut [u32],
    #[comptime] reg_channels: usize,
) {
    // Shared staging for one batch: TILE_PIXELS ids and STAGED floats each (256 x 7: sizes must be literals).
    let mut s_gid = Shared::<[u32]>::new_slice(256usize);
    let mut s_p = Shared::<[f32]>::new_slice(1792usize);
    let mut acc = Array::<f32>::new(comptime![usize::max(reg_channels, 1)]);
    let at = tile_pixel(width, height, tiles_x, channels, cam);
    let (pix, c2, ch_n) = (at.pix, at.c2, at.ch_n);
    let t_min = cam[C_T_MIN];
    let start = offsets[at.tile];
    let count = counts[at.tile];
    let mut t = 1.0f32;
    let mut done = !at.inside;
    let mut depth_acc = 0.0f32;
    let mut best = 0.0f32;
    let mut top = i32::new(-1);
    let mut nv = 0i32;
    if comptime![reg_channels > 0] {
        #[unroll]
        for ch in 0..reg_channels {
            acc[ch] = 0.0;
        }
    } else if at.inside {
        for ch in 0usize..ch_n {
            packed[pix * c2 + ch] = 0.0;
        }
    }
    // The tile stops early once every pixel is saturated (or outside the image): each pixel
    // counts itself into `s_done` once when it is done, and the count is read uniformly.
    let s_done = Shared::<[Atomic<u32>]>::new_slice(1usize);
    if UNIT_POS == 0 {
        s_done[0].store(0u32);
    }
    sync_cube();
    if done {
        s_done[0].fetch_add(1u32);
    }
    let mut base = 0u32;
    while base < count {
        if workgroup_uniform_load_atomic(&s_done[0]) >= TILE_PIXELS {
            break;
        }
        stage_batch(gids, proj, &mut s_gid, &mut s_p, start + base, count - base);
        sync_cube();
        let batch = u32::min(TILE_PIXELS, count - base);
        let was_done = done;
        for j in 0u32..batch {
            if !done {
                let ju = j as usize;
                let power = falloff(&s_p, ju, at.pxf, at.pyf).power;
                if power <= 0.0 {
                    let alpha = f32::min(at.alpha_max, s_p[ju * STAGED + P_OPACITY] * f32::exp(power));
                    if alpha >= at.alpha_min {
                        let next_t = t * (1.0 - alpha);
                        if next_t < t_min {
                            done = true;
                        } else {
                            let w = alpha * t;
                            let g = s_gid[ju];
                            let fo = (g * channels) as usize;
                            if comptime![reg_channels > 0] {
                                #[unroll]
                                for ch in 0..reg_channels {
                                    if ch < ch_n {
                                        acc[ch] += w * features[fo + ch];
                                    }
                                }
                            } else {
                                for ch in 0usize..ch_n {
                                    packed[pix * c2 + ch] += w * features[fo + ch];
                                }
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
        if done && !was_done {
            s_done[0].fetch_add(1u32);
        }
        sync_cube();
        base += TILE_PIXELS;
    }
    if at.inside {
        if comptime![reg_channels > 0] {
            #[unroll]
            for ch in 0..reg_channels {
                if ch < ch_n {
                    packed[pix * c2 + ch] = acc[ch] + t * background[ch];
                }
            }
        } else {
            for ch in 0usize..ch_n {
                packed[pix * c2 + ch] += t * background[ch];
            }
        }
        packed[pix * c2 + ch_n] = 1.0 - t;
        packed[pix * c2 + ch_n + 1] = depth_acc;
        top_id[pix] = top;
        final_t[pix] = t;
        n_visited[pix] = nv;
    }
    loop_canary(canary, truncated);
}

/// How a kernel adds an `f32` into a gradient slot. [`NativeAdd`] where the adapter has float
/// atomic add (Vulkan's `shaderBufferFloat32AtomicAdd`: NVIDIA, AMD), else [`CasAdd`]; the host
/// picks one at launch from the adapter's properties ([`super::native_float_add`]).
#[cube]
pub(super) trait FloatAdd: Send + Sync + 'static {
    /// The word the slots are bound as: `f32` (native) or the bits in `u32` (compare-and-swap).
    type Word: Numeric;
    fn add_to(slot: &Atomic<Self::Word>, val: f32);
}

/// One hardware atomic add per call.
#[derive(CubeType)]
pub(super) struct NativeAdd;

/// A compare-and-swap loop on the bits: two dependent round trips per try, retried while
/// another unit wrote the slot in between. Runs on every adapter (Mesa lavapipe included).
#[derive(CubeType)]
pub(super) struct CasAdd;

#[cube]
impl FloatAdd for NativeAdd {
    type Word = f32;
    fn add_to(slot: &Atomic<f32>, val: f32) {
        slot.fetch_add(val);
    }
}

#[cube]
impl FloatAdd for CasAdd {
    type Word = u32;
    fn add_to(slot: &Atomic<u32>, val: f32) {
        let mut old = slot.load();
        loop {
            let new_bits = u32::reinterpret(f32::reinterpret(old) + val);
            let prev = slot.compare_exchange_weak(old, new_bits);
            if prev == old {
                break;
            }
            old = prev;
        }
    }
}

/// `buf[idx] += val`. With `plane`, the sum of `val` over the plane (subgroup) is added by the
/// plane's first unit, one atomic instead of one per unit; then every unit of the plane must
/// call it (uniform control flow per plane).
#[cube]
fn add_grad<A: FloatAdd>(buf: &[Atomic<A::Word>], idx: usize, val: f32, #[comptime] plane: bool) {
    if plane {
        let s = plane_sum(val);
        if UNIT_POS_PLANE == 0 && s != 0.0 {
            A::add_to(&buf[idx], s);
        }
    } else {
        A::add_to(&buf[idx], val);
    }
}

/// Workgroup per tile, thread per pixel: back-to-front walk, atomic accumulation of screen-space
/// and feature gradients per Gaussian.
///
/// All units of a tile visit the same Gaussian at the same step, so its gradient slots are the
/// target of up to 256 atomics at once. With `plane` the units of each plane (subgroup, 32 on
/// NVIDIA) first sum their contributions and one of them adds the sum: 8 atomics per slot and
/// tile instead of 256 (the launch picks it where the adapter reports plane operations).
///
/// No per-pixel, per-channel record of the colour behind the current Gaussian is kept: the
/// alpha gradient needs only its dot product with the pixel's feature gradient `gf`,
/// `gf . (f - behind)`, so one scalar `behind_dot = gf . behind` per pixel carries it
/// (`behind' = alpha f + (1 - alpha) behind`, hence `behind_dot' = alpha gf.f + (1 - alpha)
/// behind_dot`), in a register. The CPU twin keeps the vector (`crate::cpu`); the two agree to
/// rounding. With `reg_channels` > 0 (a bucket of at least the channel count) the pixel's feature gradient is read
/// once into registers; with 0 it is read from `grad_packed` at every contact.
///
/// Launched unchecked for the forward's reasons; in addition a pixel walks at most its own
/// `n_visited` entries, which the forward counted inside the same tile segment (the bins are
/// the forward's own, `super::reuse_bins`), and reads the per-pixel buffers only when `inside`.
#[cube(launch_unchecked)]
pub(super) fn raster_bwd_kernel<A: FloatAdd>(
    proj: &[f32],
    features: &[f32],
    background: &[f32],
    offsets: &[u32],
    gids: &[u32],
    cam: &[f32],
    final_t: &[f32],
    n_visited: &[i32],
    grad_packed: &[f32],
    g2d: &[Atomic<A::Word>],
    gfeat: &[Atomic<A::Word>],
    width: u32,
    height: u32,
    tiles_x: u32,
    channels: u32,
    canary: u32,
    truncated: &mut [u32],
    #[comptime] plane: bool,
    #[comptime] reg_channels: usize,
) {
    let mut gf = Array::<f32>::new(comptime![usize::max(reg_channels, 1)]);
    // Shared staging for one batch: TILE_PIXELS ids and STAGED floats each (256 x 7: sizes must be literals).
    let mut s_gid = Shared::<[u32]>::new_slice(256usize);
    let mut s_p = Shared::<[f32]>::new_slice(1792usize);
    let mut s_max = Shared::<[u32]>::new_slice(256usize);
    let at = tile_pixel(width, height, tiles_x, channels, cam);
    let (pix, c2, ch_n, inside) = (at.pix, at.c2, at.ch_n, at.inside);
    let (alpha_max, alpha_min) = (at.alpha_max, at.alpha_min);
    let start = offsets[at.tile];
    let mut tt = 1.0f32;
    let mut tf = 1.0f32;
    let mut last = 0u32;
    let mut rec_z = 0.0f32;
    let mut behind_dot = 0.0f32;
    let mut g_a = 0.0f32;
    let mut g_z = 0.0f32;
    if inside {
        tt = final_t[pix];
        tf = tt;
        // never past the intersection list, whatever `n_visited` a caller hands in
        last = u32::min(u32::cast_from(n_visited[pix]), gids.len() as u32 - start);
        g_a = grad_packed[pix * c2 + ch_n];
        g_z = grad_packed[pix * c2 + ch_n + 1];
        if comptime![reg_channels > 0] {
            #[unroll]
            for ch in 0..reg_channels {
                gf[ch] = 0.0;
                if ch < ch_n {
                    gf[ch] = grad_packed[pix * c2 + ch];
                    behind_dot += gf[ch] * background[ch];
                }
            }
        } else {
            for ch in 0usize..ch_n {
                behind_dot += grad_packed[pix * c2 + ch] * background[ch];
            }
        }
    } else if comptime![reg_channels > 0] {
        #[unroll]
        for ch in 0..reg_channels {
            gf[ch] = 0.0;
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
            let ju = j as usize;
            // The Gaussian is the same for every unit of the tile at this step.
            let g = s_gid[ju];
            let fo = (g * channels) as usize;
            let go = g as usize * G2D;
            // This pixel's contributions: `hit` when the Gaussian blends into it (blend weight `w`),
            // `screen` when its alpha is also below the clamp (the screen-space gradients flow).
            let mut hit = false;
            let mut screen = false;
            let mut w = 0.0f32;
            let mut c_opacity = 0.0f32;
            let mut c_mx = 0.0f32;
            let mut c_my = 0.0f32;
            let mut c_ca = 0.0f32;
            let mut c_cb = 0.0f32;
            let mut c_cc = 0.0f32;
            if inside && k < last {
                let fall = falloff(&s_p, ju, at.pxf, at.pyf);
                let (dx, dy, ca, cb, cc) = (fall.dx, fall.dy, fall.ca, fall.cb, fall.cc);
                if fall.power <= 0.0 {
                    let gexp = f32::exp(fall.power);
                    let op = s_p[ju * STAGED + P_OPACITY];
                    let raw = op * gexp;
                    let alpha = f32::min(alpha_max, raw);
                    if alpha >= alpha_min {
                        hit = true;
                        let depth = s_p[ju * STAGED + P_DEPTH];
                        let t_k = tt / (1.0 - alpha);
                        w = alpha * t_k;
                        let mut gf_f = 0.0f32;
                        if comptime![reg_channels > 0] {
                            #[unroll]
                            for ch in 0..reg_channels {
                                if ch < ch_n {
                                    gf_f += gf[ch] * features[fo + ch];
                                }
                            }
                        } else {
                            for ch in 0usize..ch_n {
                                gf_f += grad_packed[pix * c2 + ch] * features[fo + ch];
                            }
                        }
                        let mut d_alpha = gf_f - behind_dot;
                        behind_dot = alpha * gf_f + (1.0 - alpha) * behind_dot;
                        d_alpha += g_z * (depth - rec_z);
                        d_alpha *= t_k;
                        d_alpha += g_a * tf / (1.0 - alpha);
                        rec_z = alpha * depth + (1.0 - alpha) * rec_z;
                        tt = t_k;
                        if raw < alpha_max {
                            screen = true;
                            c_opacity = d_alpha * gexp;
                            let d_power = d_alpha * op * gexp;
                            c_mx = d_power * (ca * dx + cb * dy);
                            c_my = d_power * (cc * dy + cb * dx);
                            c_ca = d_power * (0.0f32 - 0.5f32 * dx * dx);
                            c_cb = d_power * (0.0f32 - dx * dy);
                            c_cc = d_power * (0.0f32 - 0.5f32 * dy * dy);
                        }
                    }
                }
            }
            // With `plane`, whole planes enter together (plane sums need every unit of the plane).
            let mut adding = hit;
            if plane {
                adding = plane_any(hit);
            }
            if adding {
                if comptime![reg_channels > 0] {
                    #[unroll]
                    for ch in 0..reg_channels {
                        if ch < ch_n {
                            let mut v = 0.0f32;
                            if hit {
                                v = w * gf[ch];
                            }
                            add_grad::<A>(gfeat, fo + ch, v, plane);
                        }
                    }
                } else {
                    for ch in 0usize..ch_n {
                        let mut v = 0.0f32;
                        if hit {
                            v = w * grad_packed[pix * c2 + ch];
                        }
                        add_grad::<A>(gfeat, fo + ch, v, plane);
                    }
                }
                add_grad::<A>(g2d, go + G_DEPTH, w * g_z, plane);
                let mut adding_screen = screen;
                if plane {
                    adding_screen = plane_any(screen);
                }
                if adding_screen {
                    add_grad::<A>(g2d, go + G_OPACITY, c_opacity, plane);
                    add_grad::<A>(g2d, go + G_MX, c_mx, plane);
                    add_grad::<A>(g2d, go + G_MY, c_my, plane);
                    add_grad::<A>(g2d, go + G_CA, c_ca, plane);
                    add_grad::<A>(g2d, go + G_CB, c_cb, plane);
                    add_grad::<A>(g2d, go + G_CC, c_cc, plane);
                }
            }
        }
        sync_cube();
        end = begin;
    }
    loop_canary(canary, truncated);
}
