//! Steps 2-4: the tile lists: prefix sum of the per-tile counts, (depth, id) entries emitted into
//! each touched tile's segment, and a bitonic sort per tile.

use super::layout::*;
use super::raster::loop_canary;
use crate::constants::TILE_PIXELS;
use cubecl::prelude::*;

/// One workgroup of 256: exclusive prefix sum of `counts[0..n]` into `offsets`, total into `total[0]`.
#[cube(launch)]
pub(super) fn scan_kernel(counts: &[u32], offsets: &mut [u32], total: &mut [u32], n: u32) {
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
pub(super) fn emit_kernel(
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
pub(super) fn tile_sort_kernel(
    keys: &mut [f32],
    gids: &mut [u32],
    offsets: &[u32],
    counts: &[u32],
    tiles_x: u32,
    canary: u32,
    truncated: &mut [u32],
) {
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
    loop_canary(canary, truncated);
}
