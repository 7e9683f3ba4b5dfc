//! `x w + bias` for a linear layer at CPU inference, on host slices, into a fresh `Vec`: a few rows
//! (a decode step) through [`matvec`], many rows (a prefill, the vision tower) through one gemm call
//! that writes the output where it will stay.
//!
//! burn-flex's matmul allocates its output zeroed as bytes and then copies it once more to align it
//! (`FlexTensor::empty` -> `Bytes::from_bytes_vec`), and that 16-byte alignment makes every later
//! read of the output as a `Vec<f32>` copy it again: at 0.5B those copies and the zeroing were 8 %
//! of a prefill. Here the output is written once, by gemm (its first write, or onto the bias rows).
//!
//! `x` `[rows, k]` and the result `[rows, n]` are row-major f32; the weight holds `w[i][j]` (input
//! `i`, output `j`) in one of matvec's [`Order`]s, in f32 or f16 ([`Held`]: f16 is widened to f32
//! for a product of many rows, where gemm's f16 path is slower than its f32 one).

use super::convert::widened;
use super::matvec::{self, Held, Order};

/// Rows up to which a product runs in [`matvec`] (each weight read once) instead of gemm.
pub const FEW_ROWS: usize = 8;

/// Multiply-adds from which gemm splits a product over rayon's threads (burn-flex's threshold).
const PARALLEL_WORK: usize = 192 * 192 * 192;

/// `x w (+ bias)`: `x` `[rows, k]`, `w` `k x n` weights in `order`, `bias` `[n]`; returns
/// `[rows, n]`.
///
/// # Panics
/// When a slice's length does not match `rows`, `k` and `n`.
pub fn product(x: &[f32], w: Held, order: Order, rows: usize, k: usize, n: usize, bias: Option<&[f32]>) -> Vec<f32> {
    assert_eq!(x.len(), rows * k, "product: x is not [rows, k]");
    if let Some(b) = bias {
        assert_eq!(b.len(), n, "product: the bias is not [n]");
    }
    if rows <= FEW_ROWS {
        let mut out = vec![0f32; rows * n];
        matvec::matmul(x, w, order, rows, k, n, &mut out);
        if let Some(b) = bias {
            for row in out.chunks_exact_mut(n) {
                row.iter_mut().zip(b).for_each(|(y, b)| *y += b);
            }
        }
        return out;
    }
    let wide;
    let w = match w {
        Held::F32(w) => w,
        Held::F16(w) => {
            wide = widened(w);
            &wide
        }
    };
    assert_eq!(w.len(), k * n, "product: the weights are not k x n");
    gemm_product(x, w, order, rows, k, n, bias)
}

/// [`product`] of many rows with f32 weights, in one gemm call.
fn gemm_product(x: &[f32], w: &[f32], order: Order, rows: usize, k: usize, n: usize, bias: Option<&[f32]>) -> Vec<f32> {
    let len = rows * n;
    let mut out: Vec<f32> = Vec::with_capacity(len);
    if let Some(b) = bias {
        for _ in 0..rows {
            out.extend_from_slice(b);
        }
    }
    if len == 0 {
        return out;
    }
    if k == 0 {
        // nothing to add to the bias (gemm is not asked to write an empty sum)
        out.resize(len, 0.0);
        return out;
    }
    let (w_row, w_col) = match order {
        Order::InOut => (n as isize, 1),
        Order::OutIn => (1, k as isize),
    };
    let parallelism = if rows.saturating_mul(k).saturating_mul(n) >= PARALLEL_WORK {
        gemm::Parallelism::Rayon(0)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: `out` has room for `rows * n` values, written by gemm with row stride `n` (it reads
    // them first only with `read_dst`, when they hold the bias rows); `x` is `rows x k` with row
    // stride `k` and `w` `k x n` at the strides of `order` (lengths asserted by the caller).
    unsafe {
        gemm::gemm(
            rows,
            n,
            k,
            out.as_mut_ptr(),
            1,
            n as isize,
            bias.is_some(),
            x.as_ptr(),
            1,
            k as isize,
            w.as_ptr(),
            w_col,
            w_row,
            1.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
        out.set_len(len);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The plain twin: `x w + bias` in f64 loops.
    fn plain(x: &[f32], w: &[f32], order: Order, rows: usize, k: usize, n: usize, bias: Option<&[f32]>) -> Vec<f64> {
        let mut out = vec![0f64; rows * n];
        for r in 0..rows {
            for j in 0..n {
                let mut s = bias.map_or(0.0, |b| b[j] as f64);
                for i in 0..k {
                    let wij = match order {
                        Order::InOut => w[i * n + j],
                        Order::OutIn => w[j * k + i],
                    };
                    s += x[r * k + i] as f64 * wij as f64;
                }
                out[r * n + j] = s;
            }
        }
        out
    }

    fn values(len: usize, seed: u32) -> Vec<f32> {
        (0..len)
            .map(|i| ((i as u32).wrapping_mul(2654435761).wrapping_add(seed) % 2001) as f32 / 1000.0 - 1.0)
            .collect()
    }

    #[test]
    fn few_and_many_rows_match_the_plain_product_in_both_orders_with_and_without_bias() {
        // few rows (matvec), many rows single-threaded and many rows split over threads (gemm),
        // ragged widths and an empty product
        for &(rows, k, n) in &[(3, 37, 29), (9, 37, 29), (150, 96, 140), (40, 1, 3), (20, 5, 0), (12, 0, 4)] {
            for order in [Order::InOut, Order::OutIn] {
                let (x, w, b) = (values(rows * k, 1), values(k * n, 2), values(n, 3));
                for bias in [None, Some(&b[..])] {
                    let got = product(&x, Held::F32(&w), order, rows, k, n, bias);
                    let want = plain(&x, &w, order, rows, k, n, bias);
                    assert_eq!(got.len(), want.len());
                    for (g, e) in got.iter().zip(&want) {
                        assert!((*g as f64 - e).abs() < 1e-4 * (1.0 + e.abs()), "{rows}x{k}x{n} {order:?}: {g} vs {e}");
                    }
                }
            }
        }
    }

    #[test]
    fn half_weights_are_widened_for_many_rows() {
        let (rows, k, n) = (12, 33, 17);
        let (x, w) = (values(rows * k, 4), values(k * n, 5));
        let half: Vec<half::f16> = w.iter().map(|&v| half::f16::from_f32(v)).collect();
        let rounded: Vec<f32> = half.iter().map(|v| v.to_f32()).collect();
        let got = product(&x, Held::F16(&half), Order::InOut, rows, k, n, None);
        for (g, e) in got.iter().zip(plain(&x, &rounded, Order::InOut, rows, k, n, None)) {
            assert!((*g as f64 - e).abs() < 1e-4 * (1.0 + e.abs()), "{g} vs {e}");
        }
    }
}
