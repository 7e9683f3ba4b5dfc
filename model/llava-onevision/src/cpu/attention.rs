//! Softmax attention for CPU inference, on host slices.
//!
//! burn-flex's fused attention tiles the keys by 64, calls gemm with an inner dimension of 64 for
//! both products, runs the softmax one scalar `exp` at a time and reads an additive mask for every
//! score, so a causal prefill computes and masks every tile above the diagonal. This kernel takes
//! a block of query rows at a time: one gemm for the block's scores against the keys it may see
//! (a causal block stops at its last row's position), a vectorised softmax over each row, one gemm
//! of the probabilities with the values (inner dimension = the keys seen), then the rows' 1/sum.
//! Blocks of different query heads run on rayon's threads; each gemm stays on one.
//!
//! Layout (all row-major f32): `q` `[groups, rep * t, d]`, `k` `[groups, keys, d]`, `v`
//! `[groups, keys, dv]`, out `[groups, rep * t, dv]`: `rep` query heads share a key/value head
//! (grouped-query attention; 1 for plain multi-head), and row `h * t + i` of a group is query head
//! `h` at position `i`. Causal with `past` cached keys: position `i` sees keys `0..=past + i`.

use super::exp::softmax_numerators;
use super::matvec;
use rayon::prelude::*;

/// Query rows per block: a block's scores (`BLOCK x keys` f32) stay in L2 for a 2k-token prompt.
const BLOCK: usize = 64;

/// Rows below which a block's products are plain loops instead of gemm calls, which pack both
/// operands on every call (a ragged last block, or a call with a handful of rows).
pub const FEW_ROWS: usize = 16;

/// Multiply-adds below which a call runs on the calling thread (a decode step at a 2k context
/// splits its two key/value heads over the threads: 0.20 ms against 0.31 ms per layer at 0.5B).
const PARALLEL_WORK: usize = 1 << 20;

/// The shapes of one attention call (see the module docs for the layout).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shape {
    /// Key/value heads (or batch x heads).
    pub groups: usize,
    /// Query heads per key/value head.
    pub rep: usize,
    /// Query positions per head.
    pub t: usize,
    /// Keys (cached + new).
    pub keys: usize,
    /// Query/key width.
    pub d: usize,
    /// Value width.
    pub dv: usize,
}

/// `softmax(scale q k^T [+ causal mask]) v` into `out` (layout in the module docs). `causal_past`:
/// `Some(past)` for causal attention after `past` cached keys (`keys` must be `past + t`), `None`
/// for every query seeing every key.
///
/// # Panics
/// When a slice's length does not match `s`, or a causal call's `keys` is not `past + t`.
pub fn attend(q: &[f32], k: &[f32], v: &[f32], s: Shape, scale: f32, causal_past: Option<usize>, out: &mut [f32]) {
    assert_eq!(k.len(), s.groups * s.keys * s.d, "attention: k is not [groups, keys, d]");
    assert_eq!(v.len(), s.groups * s.keys * s.dv, "attention: v is not [groups, keys, dv]");
    attend_in(q, k, v, s, s.keys, scale, causal_past, out);
}

/// [`attend`] with each group's keys and values the first `keys` of `cap` rows: group `g`'s keys
/// start at `k[g * cap * d]` and its values at `v[g * cap * dv]` (a KV cache with room to grow,
/// read where it lies).
///
/// # Panics
/// As [`attend`], and when `cap < keys` or `k` / `v` end before the last group's keys / values.
#[allow(clippy::too_many_arguments)]
pub fn attend_in(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    s: Shape,
    cap: usize,
    scale: f32,
    causal_past: Option<usize>,
    out: &mut [f32],
) {
    let rows = s.rep * s.t;
    assert!(cap >= s.keys, "attention: {} keys in room for {cap}", s.keys);
    let span = |w: usize| if s.groups == 0 { 0 } else { (s.groups - 1) * cap * w + s.keys * w };
    assert_eq!(q.len(), s.groups * rows * s.d, "attention: q is not [groups, rep * t, d]");
    assert!(k.len() >= span(s.d), "attention: k ends before the last group's keys");
    assert!(v.len() >= span(s.dv), "attention: v ends before the last group's values");
    assert_eq!(out.len(), s.groups * rows * s.dv, "attention: out is not [groups, rep * t, dv]");
    if let Some(past) = causal_past {
        assert_eq!(s.keys, past + s.t, "attention: causal keys must be past + t");
    }
    if out.is_empty() {
        return;
    }
    // One task per query head (its `t` rows of q and out) when a head fills a block of rows;
    // otherwise (decode, short prompts) one per key/value head with all its `rep * t` rows, so
    // that its keys and values are read once, not `rep` times.
    let task_rows = if s.t >= BLOCK { s.t } else { rows };
    let per_group = rows / task_rows;
    let run = |scores: &mut Vec<f32>, (task, out): (usize, &mut [f32])| {
        let g = task / per_group;
        let q = &q[task * task_rows * s.d..(task + 1) * task_rows * s.d];
        let k = &k[g * cap * s.d..g * cap * s.d + s.keys * s.d];
        let v = &v[g * cap * s.dv..g * cap * s.dv + s.keys * s.dv];
        rows_attend(q, k, v, s, scale, causal_past, scores, out);
    };
    let scratch = || vec![0f32; BLOCK.min(task_rows) * s.keys];
    if s.groups * rows * s.keys * (s.d + s.dv) < PARALLEL_WORK {
        // small (a decode step): on the calling thread; waking rayon's workers for it would
        // leave them spinning beside the backend's own matmul threads (ndarray's)
        let mut scores = scratch();
        out.chunks_mut(task_rows * s.dv).enumerate().for_each(|t| run(&mut scores, t));
    } else {
        out.par_chunks_mut(task_rows * s.dv).enumerate().for_each_init(scratch, run);
    }
}

/// Rows of one group: `q` `[r, d]` (row `i` at position `i % t`), `k` `[keys, d]`, `v`
/// `[keys, dv]` -> `out` `[r, dv]`, `BLOCK` rows at a time through `scores`
/// (`>= min(BLOCK, r) * keys`).
fn rows_attend(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    s: Shape,
    scale: f32,
    causal_past: Option<usize>,
    scores: &mut [f32],
    out: &mut [f32],
) {
    let r = q.len() / s.d;
    let mut inv = [0f32; BLOCK];
    for start in (0..r).step_by(BLOCK) {
        let m = BLOCK.min(r - start);
        // keys row i of the block sees; the block computes scores for as many as any row sees
        let seen = |i: usize| causal_past.map_or(s.keys, |past| past + (start + i) % s.t + 1);
        let n = (0..m).map(seen).max().unwrap_or(0);
        let sc = &mut scores[..m * n];
        let qb = &q[start * s.d..(start + m) * s.d];
        if m < FEW_ROWS {
            scores_by_rows(qb, &k[..n * s.d], s.d, scale, sc);
        } else {
            // SAFETY: every pointer spans its matrix: qb m x d, k's first n rows of width d (read
            // transposed), scores m x n.
            unsafe {
                gemm::gemm(
                    m,
                    n,
                    s.d,
                    sc.as_mut_ptr(),
                    1,
                    n as isize,
                    false,
                    qb.as_ptr(),
                    1,
                    s.d as isize,
                    k.as_ptr(),
                    s.d as isize,
                    1,
                    0.0,
                    scale,
                    false,
                    false,
                    false,
                    gemm::Parallelism::None,
                );
            }
        }
        for i in 0..m {
            let row = &mut sc[i * n..(i + 1) * n];
            let (live, masked) = row.split_at_mut(seen(i));
            inv[i] = 1.0 / softmax_numerators(live);
            masked.fill(0.0);
        }
        let o = &mut out[start * s.dv..(start + m) * s.dv];
        if m < FEW_ROWS {
            weighted_values(sc, &v[..n * s.dv], s.dv, o);
        } else {
            // SAFETY: scores m x n, v's first n rows of width dv, o m x dv.
            unsafe {
                gemm::gemm(
                    m,
                    s.dv,
                    n,
                    o.as_mut_ptr(),
                    1,
                    s.dv as isize,
                    false,
                    sc.as_ptr(),
                    1,
                    n as isize,
                    v.as_ptr(),
                    1,
                    s.dv as isize,
                    0.0,
                    1.0,
                    false,
                    false,
                    false,
                    gemm::Parallelism::None,
                );
            }
        }
        for (row, w) in o.chunks_exact_mut(s.dv).zip(&inv[..m]) {
            row.iter_mut().for_each(|x| *x *= w);
        }
    }
}

/// Keys per block of the few-rows path: a block's keys or values (16 KB at width 64) stay in L1
/// while every row uses them.
const KEY_BLOCK: usize = 64;

/// `sc` `[m, n]` = `scale q k^T` for a few rows `q` `[m, d]` and keys `k` `[n, d]`, a block of keys
/// at a time for all rows through [`matvec::dot_rows`]: gemm packs both operands on every call,
/// which for a handful of rows costs more than the products.
fn scores_by_rows(q: &[f32], k: &[f32], d: usize, scale: f32, sc: &mut [f32]) {
    let n = k.len() / d;
    for j in (0..n).step_by(KEY_BLOCK) {
        let e = n.min(j + KEY_BLOCK);
        for (i, qi) in q.chunks_exact(d).enumerate() {
            let si = &mut sc[i * n + j..i * n + e];
            matvec::dot_rows(si, qi, &k[j * d..e * d]);
            si.iter_mut().for_each(|x| *x *= scale);
        }
    }
}

/// `o` `[m, dv]` = `p v` for a few rows of weights `p` `[m, n]` and values `v` `[n, dv]`, a block
/// of values at a time for all rows through [`matvec::axpy_rows`].
fn weighted_values(p: &[f32], v: &[f32], dv: usize, o: &mut [f32]) {
    let n = v.len() / dv;
    o.fill(0.0);
    for j in (0..n).step_by(KEY_BLOCK) {
        let e = n.min(j + KEY_BLOCK);
        for (i, oi) in o.chunks_exact_mut(dv).enumerate() {
            matvec::axpy_rows(oi, &p[i * n + j..i * n + e], &v[j * dv..e * dv]);
        }
    }
}
