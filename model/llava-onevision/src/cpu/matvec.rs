//! Products of a few activation rows with a weight matrix, on host slices: a decode step's linear
//! layers and its logits.
//!
//! With one row a product does one multiply-add per weight it reads, so it runs at the speed the
//! weights stream from memory. gemm's general path packs and tiles for reuse a single row never
//! gets, and at 0.5B streamed the weights at 12-29 GB/s where torch reaches 28-50 (the 151,936 x
//! 896 logits matrix: 43 ms against 20 ms per token). Here each weight is read once, in memory
//! order, on all threads, four weight rows per pass, and f16 weights are widened in registers (F16C)
//! as they are read: half the bytes per token.
//!
//! `x` `[rows, k]` and `out` `[rows, n]` are row-major f32. The weight holds `w[i][j]` (input `i`,
//! output `j`) in one of two orders ([`Order`]).

use half::f16;
use rayon::prelude::*;

/// Where the weight of input `i` and output `j` lies.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Order {
    /// `w[i * n + j]`: burn's `Linear` weight `[in, out]`. Threads take runs of inputs and add
    /// their partial outputs.
    InOut,
    /// `w[j * k + i]`: a `[out, in]` matrix, as the token embedding read as the tied `lm_head`.
    /// Threads take runs of outputs, each a dot product over a contiguous weight row.
    OutIn,
}

/// The weights, in the precision they are held in.
#[derive(Clone, Copy, Debug)]
pub enum Held<'a> {
    F32(&'a [f32]),
    F16(&'a [f16]),
}

/// Multiply-adds below which a product runs on the calling thread.
const PARALLEL_WORK: usize = 1 << 16;

/// `out = x w` for `x` `[rows, k]`, `w` holding `k x n` weights in `order`, `out` `[rows, n]`.
///
/// # Panics
/// When a slice's length does not match `rows`, `k` and `n`.
pub fn matmul(x: &[f32], w: Held, order: Order, rows: usize, k: usize, n: usize, out: &mut [f32]) {
    assert_eq!(x.len(), rows * k, "matvec: x is not [rows, k]");
    assert_eq!(out.len(), rows * n, "matvec: out is not [rows, n]");
    let held = match w {
        Held::F32(w) => w.len(),
        Held::F16(w) => w.len(),
    };
    assert_eq!(held, k * n, "matvec: the weights are not k x n");
    if out.is_empty() {
        return;
    }
    match w {
        Held::F32(w) => run(x, w, order, rows, k, n, out),
        Held::F16(w) => run(x, w, order, rows, k, n, out),
    }
}

/// A weight element, read as f32.
pub trait Weight: Copy + Sync {
    fn f32(self) -> f32;
}

impl Weight for f32 {
    fn f32(self) -> f32 {
        self
    }
}

impl Weight for f16 {
    fn f32(self) -> f32 {
        self.to_f32()
    }
}

fn run<W: Weight + Lanes>(x: &[f32], w: &[W], order: Order, rows: usize, k: usize, n: usize, out: &mut [f32]) {
    let threads = if rows * k * n < PARALLEL_WORK { 1 } else { rayon::current_num_threads() };
    match order {
        Order::InOut => {
            // each thread a run of inputs, into its own partial outputs, then summed
            let parts = threads.min(k.div_ceil(64)).max(1);
            let part = |p: usize| {
                let (lo, hi) = (p * k / parts, (p + 1) * k / parts);
                let mut acc = vec![0f32; rows * n];
                for r in 0..rows {
                    axpy_rows(&mut acc[r * n..(r + 1) * n], &x[r * k + lo..r * k + hi], &w[lo * n..hi * n]);
                }
                acc
            };
            if parts == 1 {
                out.copy_from_slice(&part(0));
                return;
            }
            let partials: Vec<Vec<f32>> = (0..parts).into_par_iter().map(part).collect();
            out.copy_from_slice(&partials[0]);
            for p in &partials[1..] {
                out.iter_mut().zip(p).for_each(|(a, b)| *a += b);
            }
        }
        Order::OutIn => {
            // each thread a run of outputs, written as [n, rows] and then transposed when rows > 1
            let chunk = n.div_ceil(threads * 4).max(4);
            let mut t = vec![0f32; n * rows];
            let body = |(c, o): (usize, &mut [f32])| {
                let (first, count) = (c * chunk, o.len() / rows);
                for r in 0..rows {
                    let mut col = vec![0f32; count];
                    dot_rows(&mut col, &x[r * k..(r + 1) * k], &w[first * k..(first + count) * k]);
                    col.iter().enumerate().for_each(|(j, v)| o[j * rows + r] = *v);
                }
            };
            if threads == 1 {
                t.chunks_mut(chunk * rows).enumerate().for_each(body);
            } else {
                t.par_chunks_mut(chunk * rows).enumerate().for_each(body);
            }
            for (j, vals) in t.chunks_exact(rows).enumerate() {
                for (r, v) in vals.iter().enumerate() {
                    out[r * n + j] = *v;
                }
            }
        }
    }
}

/// `y += sum_i x[i] w[i]` over the rows `w[i]` (`[x.len(), y.len()]`).
pub fn axpy_rows<W: Weight + Lanes>(y: &mut [f32], x: &[f32], w: &[W]) {
    #[cfg(target_arch = "x86_64")]
    if simd() {
        // SAFETY: the features it is compiled for were just detected.
        return unsafe { avx2::axpy_rows(y, x, w) };
    }
    let n = y.len();
    for (i, a) in x.iter().enumerate() {
        for (yj, wj) in y.iter_mut().zip(&w[i * n..(i + 1) * n]) {
            *yj += a * wj.f32();
        }
    }
}

/// `y[j] = sum_i w[j][i] x[i]` over the rows `w[j]` (`[y.len(), x.len()]`).
pub fn dot_rows<W: Weight + Lanes>(y: &mut [f32], x: &[f32], w: &[W]) {
    #[cfg(target_arch = "x86_64")]
    if simd() {
        // SAFETY: the features it is compiled for were just detected.
        return unsafe { avx2::dot_rows(y, x, w) };
    }
    for (j, yj) in y.iter_mut().enumerate() {
        *yj = w[j * x.len()..(j + 1) * x.len()].iter().zip(x).map(|(a, b)| a.f32() * b).sum();
    }
}

/// Whether the CPU has AVX2, FMA and F16C (the vector kernels' features).
#[cfg(target_arch = "x86_64")]
fn simd() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
        && std::arch::is_x86_feature_detected!("f16c")
}

#[cfg(target_arch = "x86_64")]
pub use avx2::Lanes;

/// Without x86 vector kernels every weight type is "vectorised" trivially.
#[cfg(not(target_arch = "x86_64"))]
pub trait Lanes {}
#[cfg(not(target_arch = "x86_64"))]
impl<T> Lanes for T {}

/// The AVX2 + FMA (+ F16C to widen f16) twins of [`axpy_rows`] and [`dot_rows`], 8 lanes.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use half::f16;
    use std::arch::x86_64::*;

    /// Eight weights widened to f32 lanes.
    pub trait Lanes: Copy {
        /// # Safety
        /// `p..p + 8` must be readable; the CPU must have AVX2, FMA and F16C.
        unsafe fn load8(p: *const Self) -> __m256;
    }

    impl Lanes for f32 {
        #[inline]
        #[target_feature(enable = "avx2,fma,f16c")]
        unsafe fn load8(p: *const f32) -> __m256 {
            // SAFETY: as the trait says.
            unsafe { _mm256_loadu_ps(p) }
        }
    }

    impl Lanes for f16 {
        #[inline]
        #[target_feature(enable = "avx2,fma,f16c")]
        unsafe fn load8(p: *const f16) -> __m256 {
            // SAFETY: as the trait says (8 f16 are the 16 bytes read).
            unsafe { _mm256_cvtph_ps(_mm_loadu_si128(p.cast())) }
        }
    }

    /// Rows `first..first + b` (`b` in 1..=4) of `w`, each `len` long, as four slices (the last
    /// repeated where `b < 4`, so a kernel's four lanes always read valid rows).
    fn block_of_rows<W>(w: &[W], first: usize, b: usize, len: usize) -> [&[W]; 4] {
        std::array::from_fn(|q| {
            let r = first + q.min(b - 1);
            &w[r * len..(r + 1) * len]
        })
    }

    /// [`super::axpy_rows`]: four weight rows per pass over `y`, 8 lanes at a time.
    ///
    /// # Safety
    /// The CPU must have AVX2, FMA and F16C.
    #[target_feature(enable = "avx2,fma,f16c")]
    pub unsafe fn axpy_rows<W: Lanes + super::Weight>(y: &mut [f32], x: &[f32], w: &[W]) {
        let n = y.len();
        assert_eq!(w.len(), x.len() * n);
        let vec_n = n - n % 8;
        let mut i = 0;
        while i < x.len() {
            let b = 4.min(x.len() - i);
            let rows = block_of_rows(w, i, b, n);
            let a: [f32; 4] = std::array::from_fn(|q| if q < b { x[i + q] } else { 0.0 });
            let av = a.map(|v| _mm256_set1_ps(v));
            let mut j = 0;
            while j < vec_n {
                // SAFETY: j + 8 <= n and every row holds n weights; the features are the caller's.
                unsafe {
                    let mut acc = _mm256_loadu_ps(y.as_ptr().add(j));
                    for q in 0..4 {
                        acc = _mm256_fmadd_ps(av[q], W::load8(rows[q].as_ptr().add(j)), acc);
                    }
                    _mm256_storeu_ps(y.as_mut_ptr().add(j), acc);
                }
                j += 8;
            }
            for j in vec_n..n {
                y[j] += (0..b).map(|q| a[q] * rows[q][j].f32()).sum::<f32>();
            }
            i += b;
        }
    }

    /// [`super::dot_rows`]: four weight rows per pass over `x`, 8 lanes at a time.
    ///
    /// # Safety
    /// The CPU must have AVX2, FMA and F16C.
    #[target_feature(enable = "avx2,fma,f16c")]
    pub unsafe fn dot_rows<W: Lanes + super::Weight>(y: &mut [f32], x: &[f32], w: &[W]) {
        let k = x.len();
        assert_eq!(w.len(), y.len() * k);
        let vec_k = k - k % 8;
        let mut j = 0;
        while j < y.len() {
            let b = 4.min(y.len() - j);
            let rows = block_of_rows(w, j, b, k);
            let mut acc = [_mm256_setzero_ps(); 4];
            let mut i = 0;
            while i < vec_k {
                // SAFETY: i + 8 <= k and x and every row hold k values; the features are the caller's.
                unsafe {
                    let xv = _mm256_loadu_ps(x.as_ptr().add(i));
                    for q in 0..4 {
                        acc[q] = _mm256_fmadd_ps(W::load8(rows[q].as_ptr().add(i)), xv, acc[q]);
                    }
                }
                i += 8;
            }
            for q in 0..b {
                let mut lanes = [0f32; 8];
                // SAFETY: `lanes` holds 8 floats.
                unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), acc[q]) };
                let tail: f32 = (vec_k..k).map(|i| rows[q][i].f32() * x[i]).sum();
                y[j + q] = lanes.iter().sum::<f32>() + tail;
            }
            j += b;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The plain twin: `out[r][j] = sum_i x[r][i] w[i][j]` in f64.
    fn plain(x: &[f32], w: &[f32], order: Order, rows: usize, k: usize, n: usize) -> Vec<f64> {
        let at = |i: usize, j: usize| match order {
            Order::InOut => w[i * n + j],
            Order::OutIn => w[j * k + i],
        } as f64;
        (0..rows * n).map(|o| (0..k).map(|i| x[(o / n) * k + i] as f64 * at(i, o % n)).sum()).collect()
    }

    fn values(len: usize, seed: u32) -> Vec<f32> {
        (0..len).map(|i| (((i as u32).wrapping_mul(2_654_435_761) ^ seed) % 2001) as f32 / 1000.0 - 1.0).collect()
    }

    /// Both orders, f32 and f16 weights, one row and several, on one thread and on all: the same
    /// products as the f64 loop, on sizes that leave ragged blocks and vector tails (k = 203 is
    /// not a multiple of 4 or 32, n = 1001 not of 8), and empty ones (no rows, no inputs: zeros).
    #[test]
    fn few_row_products_match_the_plain_loop() {
        for (rows, k, n) in [(1, 203, 1001), (3, 203, 1001), (1, 896, 8), (2, 5, 3), (0, 5, 3), (2, 0, 3)] {
            let x = values(rows * k, 7);
            let w32 = values(k * n, 11);
            let w16: Vec<f16> = w32.iter().map(|&v| f16::from_f32(v)).collect();
            let w16_wide: Vec<f32> = w16.iter().map(|v| v.to_f32()).collect();
            for order in [Order::InOut, Order::OutIn] {
                for (held, exact) in [(Held::F32(&w32), &w32), (Held::F16(&w16), &w16_wide)] {
                    let want = plain(&x, exact, order, rows, k, n);
                    let mut got = vec![f32::NAN; rows * n];
                    matmul(&x, held, order, rows, k, n, &mut got);
                    for (o, (g, w)) in got.iter().zip(&want).enumerate() {
                        assert!(
                            (*g as f64 - w).abs() < 1e-4 * (1.0 + w.abs()),
                            "{order:?} rows {rows} k {k} n {n} out {o}: {g} vs {w}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    #[should_panic(expected = "not k x n")]
    fn a_weight_of_the_wrong_size_is_refused() {
        let mut out = vec![0.0; 4];
        matmul(&[0.0; 3], Held::F32(&[0.0; 11]), Order::InOut, 1, 3, 4, &mut out);
    }
}
