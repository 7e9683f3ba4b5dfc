//! Steps 3-4 the global way ([`crate::TileSort::Radix`]): the Gaussians sorted once by depth,
//! their tile entries written in that order, then one stable sort of all entries by tile. Both
//! sorts are the same stable least-significant-digit radix sort of (key, value) pairs, 4 bits a
//! pass: a histogram per block of [`BLOCK_ITEMS`] pairs, one scan of every block's digit counts,
//! and a scatter that keeps each block's order. Ties in depth keep the ids' order, so a tile's
//! list is in the same (depth, id) total order as the CPU's and the bitonic sort's.
//!
//! Kernels here, their launches in [`tile_lists`], [`sort_pairs`] and [`scan`].
//!
//! The kernels launch unchecked (no bounds test on each access); every index is in range:
//! - an item index `i` is read only under `i < n`, and every item buffer holds at least `n`;
//! - a block `b` past the last one leaves at once ([`block_index`]), so `hist`, `starts` and
//!   `sums` indices `digit * blocks + b` and `b` stay below their `DIGITS * blocks` and `blocks`;
//!   the shared arrays are indexed by `digit * TILE_PIXELS + UNIT_POS` or a row's cells (of
//!   `DIGITS * TILE_PIXELS`), or by `UNIT_POS` and `TILE_PIXELS` (of `TILE_PIXELS + 1`) and
//!   `UNIT_POS + k` for a row's first thread, `k < ROW_THREADS` (of `TILE_PIXELS`);
//! - a scatter's target is its digit's start (the exclusive scan of the very histogram this pass
//!   counted from the same keys) plus the items of that digit before it in its block: below `n`;
//! - a Gaussian's entries are written from the scan of the tiles its rectangle touches, whose
//!   total is the projection's count of entries from the same rectangles: the entry buffers' length;
//!   `order` is a permutation of the Gaussian ids, below `n`.

use super::layout::*;
use super::sort::scan_kernel;
use super::{alloc, buf, groups};
use crate::camera::Camera;
use crate::constants::TILE_PIXELS;
use burn::backend::wgpu::CubeTensor;
use burn::tensor::DType;
use cubecl::prelude::*;

/// Bits of the key sorted per pass, and the digits they make.
const DIGIT_BITS: u32 = 4;
const DIGITS: u32 = 16;
/// Pairs each thread of a block handles, consecutively: thread order is item order.
const PER_THREAD: u32 = 8;
/// Pairs per block of [`TILE_PIXELS`] threads.
const BLOCK_ITEMS: usize = (TILE_PIXELS * PER_THREAD) as usize;

/// The block's index (the grid may be two-dimensional, [`block_grid`]); the whole block leaves
/// when it is past the last one.
#[cube]
fn block_index(blocks: u32) -> u32 {
    let b = CUBE_POS as u32;
    if b >= blocks {
        terminate!();
    }
    b
}

/// The first of this thread's [`PER_THREAD`] items.
#[cube]
fn first_item(block: u32) -> u32 {
    (block * TILE_PIXELS + UNIT_POS) * PER_THREAD
}

/// Counts this thread's items per digit into `counts[digit * TILE_PIXELS + UNIT_POS]` (cells
/// only this thread touches).
#[cube]
fn count_digits(keys: &[u32], counts: &mut Shared<[u32]>, n: u32, shift: u32, first: u32) {
    for d in 0..DIGITS {
        counts[(d * TILE_PIXELS + UNIT_POS) as usize] = 0u32;
    }
    for k in 0..PER_THREAD {
        let i = first + k;
        if i < n {
            let d = (keys[i as usize] >> shift) & (DIGITS - 1);
            counts[(d * TILE_PIXELS + UNIT_POS) as usize] += 1u32;
        }
    }
}

/// Cells of a digit's row (one cell per thread of the block) each thread sums or scans: the block's
/// threads work the [`DIGITS`] rows together, [`ROW_THREADS`] to a row.
const ROW_CELLS: u32 = TILE_PIXELS / DIGITS;
const ROW_THREADS: u32 = TILE_PIXELS / ROW_CELLS;

/// Every thread sums its [`ROW_CELLS`] consecutive cells of one digit's row of `counts` into
/// `part[UNIT_POS]`; returns the row's total to the row's first thread (0 to the others). About
/// 32 dependent steps where one thread per row took 256.
#[cube]
fn row_parts(counts: &mut Shared<[u32]>, part: &mut Shared<[u32]>) -> u32 {
    let first = (UNIT_POS / ROW_THREADS) * TILE_PIXELS + (UNIT_POS % ROW_THREADS) * ROW_CELLS;
    let mut s = 0u32;
    for k in 0..ROW_CELLS {
        s += counts[(first + k) as usize];
    }
    part[UNIT_POS as usize] = s;
    sync_cube();
    let mut total = 0u32;
    let lane = UNIT_POS % ROW_THREADS;
    if lane == 0 {
        for k in 0..ROW_THREADS {
            total += part[(UNIT_POS + k) as usize];
        }
    }
    total
}

/// Turns every digit's row of `counts` into its exclusive scan (per digit, the items of the
/// threads before each thread), all threads working.
#[cube]
fn scan_rows(counts: &mut Shared<[u32]>, part: &mut Shared<[u32]>) {
    let first = (UNIT_POS / ROW_THREADS) * TILE_PIXELS + (UNIT_POS % ROW_THREADS) * ROW_CELLS;
    row_parts(counts, part);
    // the row's first thread scans the row's parts in place
    let lane = UNIT_POS % ROW_THREADS;
    if lane == 0 {
        let mut running = 0u32;
        for k in 0..ROW_THREADS {
            let i = (UNIT_POS + k) as usize;
            let v = part[i];
            part[i] = running;
            running += v;
        }
    }
    sync_cube();
    let mut running = part[UNIT_POS as usize];
    for k in 0..ROW_CELLS {
        let i = (first + k) as usize;
        let v = counts[i];
        counts[i] = running;
        running += v;
    }
}

/// Block per [`BLOCK_ITEMS`] pairs: how many of its keys have each digit at `shift`, into
/// `hist[digit * blocks + block]` (digit-major, so one exclusive scan gives every block's start
/// for every digit).
#[cube(launch_unchecked)]
fn radix_hist_kernel(keys: &[u32], hist: &mut [u32], n: u32, shift: u32, blocks: u32) {
    let b = block_index(blocks);
    let mut counts = Shared::<[u32]>::new_slice((DIGITS * TILE_PIXELS) as usize);
    let mut part = Shared::<[u32]>::new_slice(TILE_PIXELS as usize);
    count_digits(keys, &mut counts, n, shift, first_item(b));
    sync_cube();
    let total = row_parts(&mut counts, &mut part);
    let lane = UNIT_POS % ROW_THREADS;
    if lane == 0 {
        hist[((UNIT_POS / ROW_THREADS) * blocks + b) as usize] = total;
    }
}

/// Block per [`BLOCK_ITEMS`] pairs: each pair moved to its place, `starts` being the exclusive
/// scan of [`radix_hist_kernel`]'s counts. Within a digit a block keeps its pairs' order, and the
/// blocks keep theirs: the sort is stable.
#[cube(launch_unchecked)]
fn radix_scatter_kernel(
    keys: &[u32],
    vals: &[u32],
    starts: &[u32],
    keys_out: &mut [u32],
    vals_out: &mut [u32],
    n: u32,
    shift: u32,
    blocks: u32,
) {
    let b = block_index(blocks);
    let first = first_item(b);
    let mut counts = Shared::<[u32]>::new_slice((DIGITS * TILE_PIXELS) as usize);
    let mut part = Shared::<[u32]>::new_slice(TILE_PIXELS as usize);
    count_digits(keys, &mut counts, n, shift, first);
    sync_cube();
    // per digit, the threads before this one: an exclusive scan along each digit's row
    scan_rows(&mut counts, &mut part);
    sync_cube();
    for k in 0..PER_THREAD {
        let i = first + k;
        if i < n {
            let key = keys[i as usize];
            let d = (key >> shift) & (DIGITS - 1);
            let cell = (d * TILE_PIXELS + UNIT_POS) as usize;
            let at = (starts[(d * blocks + b) as usize] + counts[cell]) as usize;
            counts[cell] += 1u32;
            keys_out[at] = key;
            vals_out[at] = vals[i as usize];
        }
    }
}

/// Thread per Gaussian: its depth as a key whose unsigned order is `f32::total_cmp`'s (the sign
/// bit flipped on positives, every bit on negatives), and its id as the value.
#[cube(launch_unchecked)]
fn depth_keys_kernel(proj: &[f32], keys: &mut [u32], ids: &mut [u32], n: u32) {
    let i = ABSOLUTE_POS as u32;
    if i >= n {
        terminate!();
    }
    let bits = u32::reinterpret(proj[i as usize * PROJ + P_DEPTH]);
    let mut key = bits | 0x8000_0000u32;
    if bits >= 0x8000_0000u32 {
        key = bits ^ 0xFFFF_FFFFu32;
    }
    keys[i as usize] = key;
    ids[i as usize] = i;
}

/// Thread per depth-sorted Gaussian: how many tiles its rectangle touches.
#[cube(launch_unchecked)]
fn tile_counts_kernel(rects: &[u32], order: &[u32], counts: &mut [u32], n: u32) {
    let k = ABSOLUTE_POS as u32;
    if k >= n {
        terminate!();
    }
    let g = order[k as usize] as usize;
    counts[k as usize] = (rects[g * 4 + 2] - rects[g * 4]) * (rects[g * 4 + 3] - rects[g * 4 + 1]);
}

/// Thread per depth-sorted Gaussian: (tile, id) for each tile it touches, from `starts[k]` on
/// (the exclusive scan of [`tile_counts_kernel`]), so the entries are in depth order.
#[cube(launch_unchecked)]
fn emit_sorted_kernel(
    rects: &[u32],
    order: &[u32],
    starts: &[u32],
    tiles: &mut [u32],
    gids: &mut [u32],
    n: u32,
    tiles_x: u32,
) {
    let k = ABSOLUTE_POS as u32;
    if k >= n {
        terminate!();
    }
    let g = order[k as usize];
    let gu = g as usize;
    let mut at = starts[k as usize] as usize;
    for ty in rects[gu * 4 + 1]..rects[gu * 4 + 3] {
        for tx in rects[gu * 4]..rects[gu * 4 + 2] {
            tiles[at] = ty * tiles_x + tx;
            gids[at] = g;
            at += 1;
        }
    }
}

/// Sums this thread's [`PER_THREAD`] values into `partial[UNIT_POS]`, then (one thread) turns
/// `partial` into its exclusive scan; returns the block's total.
#[cube]
fn block_partials(vals: &[u32], partial: &mut Shared<[u32]>, n: u32, first: u32) -> u32 {
    let mut s = 0u32;
    for k in 0..PER_THREAD {
        if first + k < n {
            s += vals[(first + k) as usize];
        }
    }
    partial[UNIT_POS as usize] = s;
    sync_cube();
    if UNIT_POS == 0 {
        let mut running = 0u32;
        for t in 0..TILE_PIXELS {
            let v = partial[t as usize];
            partial[t as usize] = running;
            running += v;
        }
        partial[TILE_PIXELS as usize] = running;
    }
    sync_cube();
    partial[TILE_PIXELS as usize]
}

/// Block per [`BLOCK_ITEMS`] values: their sum into `sums[block]`.
#[cube(launch_unchecked)]
fn block_sum_kernel(vals: &[u32], sums: &mut [u32], n: u32, blocks: u32) {
    let b = block_index(blocks);
    let mut partial = Shared::<[u32]>::new_slice(TILE_PIXELS as usize + 1);
    let total = block_partials(vals, &mut partial, n, first_item(b));
    if UNIT_POS == 0 {
        sums[b as usize] = total;
    }
}

/// Block per [`BLOCK_ITEMS`] values: their exclusive scan, each block starting at its `base`.
#[cube(launch_unchecked)]
fn block_scan_kernel(vals: &[u32], base: &[u32], out: &mut [u32], n: u32, blocks: u32) {
    let b = block_index(blocks);
    let first = first_item(b);
    let mut partial = Shared::<[u32]>::new_slice(TILE_PIXELS as usize + 1);
    block_partials(vals, &mut partial, n, first);
    let mut running = base[b as usize] + partial[UNIT_POS as usize];
    for k in 0..PER_THREAD {
        let i = first + k;
        if i < n {
            out[i as usize] = running;
            running += vals[i as usize];
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Host side.

/// A grid of `blocks` workgroups (two-dimensional past 65,535; `CUBE_POS` linearises it).
fn block_grid(blocks: usize) -> CubeCount {
    let g = blocks.max(1) as u32;
    if g <= 65535 { CubeCount::Static(g, 1, 1) } else { CubeCount::Static(65535, g.div_ceil(65535), 1) }
}

/// The exclusive prefix sum of `vals[0..n]` (u32) on the device: one workgroup's scan where that
/// is at most [`BLOCK_ITEMS`] values (8 a thread), else [`scan_blocks`]. One workgroup over more
/// reads serially from global memory: at 10M tile entries a pass's digit counts are 78,000 values,
/// 305 a thread.
fn scan(client: &Client, vals: &CubeTensor, n: usize) -> CubeTensor {
    if n > BLOCK_ITEMS {
        return scan_blocks(client, vals, n);
    }
    let out = alloc(vals, vec![n.max(1)], DType::I32);
    let total = alloc(vals, vec![1], DType::I32);
    let dim = CubeDim::new_1d(TILE_PIXELS);
    scan_kernel::launch(client, CubeCount::Static(1, 1, 1), dim, buf(vals), buf(&out), buf(&total), n as u32);
    out
}

/// The exclusive prefix sum of `vals[0..n]` (u32) on the device: block sums, one scan of them,
/// then each block's own scan.
fn scan_blocks(client: &Client, vals: &CubeTensor, n: usize) -> CubeTensor {
    let blocks = n.div_ceil(BLOCK_ITEMS).max(1);
    let sums = alloc(vals, vec![blocks], DType::I32);
    let base = alloc(vals, vec![blocks], DType::I32);
    let total = alloc(vals, vec![1], DType::I32);
    let out = alloc(vals, vec![n.max(1)], DType::I32);
    let dim = CubeDim::new_1d(TILE_PIXELS);
    let (n32, b32) = (n as u32, blocks as u32);
    // SAFETY: every index is in range (the module docs say why).
    unsafe {
        block_sum_kernel::launch_unchecked(client, block_grid(blocks), dim, buf(vals), buf(&sums), n32, b32);
    }
    scan_kernel::launch(client, CubeCount::Static(1, 1, 1), dim, buf(&sums), buf(&base), buf(&total), b32);
    // SAFETY: every index is in range (the module docs say why).
    unsafe {
        block_scan_kernel::launch_unchecked(
            client,
            block_grid(blocks),
            dim,
            buf(vals),
            buf(&base),
            buf(&out),
            n32,
            b32,
        );
    }
    out
}

/// Sorts the `n` (key, value) pairs by the keys' low `bits` bits, stably (pairs with equal keys
/// keep their order); returns the sorted keys and values. Values are carried, never read.
fn sort_pairs(client: &Client, keys: CubeTensor, vals: CubeTensor, n: usize, bits: u32) -> (CubeTensor, CubeTensor) {
    let blocks = n.div_ceil(BLOCK_ITEMS).max(1);
    let hist = alloc(&keys, vec![blocks * DIGITS as usize], DType::I32);
    let (mut keys, mut vals) = (keys, vals);
    let (mut keys_to, mut vals_to) =
        (alloc(&keys, vec![n.max(1)], DType::I32), alloc(&keys, vec![n.max(1)], DType::I32));
    let dim = CubeDim::new_1d(TILE_PIXELS);
    let (n32, b32) = (n as u32, blocks as u32);
    for pass in 0..bits.div_ceil(DIGIT_BITS) {
        let shift = pass * DIGIT_BITS;
        // SAFETY: every index is in range (the module docs say why).
        unsafe {
            radix_hist_kernel::launch_unchecked(
                client,
                block_grid(blocks),
                dim,
                buf(&keys),
                buf(&hist),
                n32,
                shift,
                b32,
            );
        }
        let starts = scan(client, &hist, blocks * DIGITS as usize);
        // SAFETY: every index is in range (the module docs say why).
        unsafe {
            radix_scatter_kernel::launch_unchecked(
                client,
                block_grid(blocks),
                dim,
                buf(&keys),
                buf(&vals),
                buf(&starts),
                buf(&keys_to),
                buf(&vals_to),
                n32,
                shift,
                b32,
            );
        }
        std::mem::swap(&mut keys, &mut keys_to);
        std::mem::swap(&mut vals, &mut vals_to);
    }
    (keys, vals)
}

/// Every tile's list of Gaussian ids, tile after tile in (depth, id) order ([`crate::TileSort::Radix`]):
/// the `n` Gaussians sorted by depth, their `n_isect` tile entries written in that order, then
/// sorted by tile. A tile's list then starts at its offset (the scan of its count), as the
/// bitonic path's does.
pub(super) fn tile_lists(
    proj: &CubeTensor,
    rects: &CubeTensor,
    n: usize,
    n_isect: usize,
    camera: &Camera,
) -> CubeTensor {
    let client = &proj.client;
    let dim = CubeDim::new_1d(TILE_PIXELS);
    let [tx, ty] = camera.tiles();
    let keys = alloc(proj, vec![n], DType::I32);
    let ids = alloc(proj, vec![n], DType::I32);
    // SAFETY: every index is in range (the module docs say why).
    unsafe {
        depth_keys_kernel::launch_unchecked(client, groups(n), dim, buf(proj), buf(&keys), buf(&ids), n as u32);
    }
    let (_, order) = sort_pairs(client, keys, ids, n, 32);
    let touched = alloc(proj, vec![n], DType::I32);
    // SAFETY: every index is in range (the module docs say why).
    unsafe {
        tile_counts_kernel::launch_unchecked(client, groups(n), dim, buf(rects), buf(&order), buf(&touched), n as u32);
    }
    let starts = scan(client, &touched, n);
    let tiles = alloc(proj, vec![n_isect], DType::I32);
    let gids = alloc(proj, vec![n_isect], DType::I32);
    // SAFETY: every index is in range (the module docs say why).
    unsafe {
        emit_sorted_kernel::launch_unchecked(
            client,
            groups(n),
            dim,
            buf(rects),
            buf(&order),
            buf(&starts),
            buf(&tiles),
            buf(&gids),
            n as u32,
            tx,
        );
    }
    // the tile ids' significant bits only: 12 for 1280x720's 3,600 tiles (three passes)
    let tile_bits = u32::BITS - (tx * ty).saturating_sub(1).leading_zeros();
    sort_pairs(client, tiles, gids, n_isect, tile_bits).1
}
