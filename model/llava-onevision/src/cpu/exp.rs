//! `exp` of non-positive arguments (softmax numerators, sigmoids), scalar and with AVX2 + FMA:
//! the one transcendental the CPU kernels need, branch-free so that eight lanes run at once.

/// Replaces each score `x` of a row by `exp(x - max)` and returns their sum (>= 1: the max gives
/// exp(0)). Eight lanes at a time with AVX2 + FMA where the CPU has them.
pub fn softmax_numerators(row: &mut [f32]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the features it is compiled for were just detected.
        return unsafe { avx2::softmax_numerators(row) };
    }
    let max = row.iter().fold(f32::NEG_INFINITY, |a, &b| if b > a { b } else { a });
    let mut sum = 0.0;
    for x in row.iter_mut() {
        *x = exp_nonpositive(*x - max);
        sum += *x;
    }
    sum
}

/// The AVX2 twin of [`softmax_numerators`] and [`exp_nonpositive`] (the same steps, 8 lanes).
#[cfg(target_arch = "x86_64")]
pub mod avx2 {
    use std::arch::x86_64::*;

    /// [`super::softmax_numerators`] in 8 lanes.
    ///
    /// # Safety
    /// The CPU must have AVX2 and FMA (a `target_feature` function: callers without those
    /// features enabled need `unsafe` and a runtime check).
    #[target_feature(enable = "avx2,fma")]
    pub fn softmax_numerators(row: &mut [f32]) -> f32 {
        let mut chunks = row.chunks_exact_mut(8);
        let mut vmax = _mm256_set1_ps(f32::NEG_INFINITY);
        for c in &mut chunks {
            // SAFETY: `c` holds 8 floats.
            vmax = _mm256_max_ps(vmax, unsafe { _mm256_loadu_ps(c.as_ptr()) });
        }
        let mut lanes = [0f32; 8];
        // SAFETY: `lanes` holds 8 floats.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), vmax) };
        let max = lanes.iter().chain(chunks.into_remainder().iter()).fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        let vm = _mm256_set1_ps(max);
        let mut vsum = _mm256_setzero_ps();
        let mut chunks = row.chunks_exact_mut(8);
        for c in &mut chunks {
            // SAFETY: `c` holds 8 floats.
            let e = exp8(_mm256_sub_ps(unsafe { _mm256_loadu_ps(c.as_ptr()) }, vm));
            // SAFETY: `c` holds 8 floats and is borrowed mutably.
            unsafe { _mm256_storeu_ps(c.as_mut_ptr(), e) };
            vsum = _mm256_add_ps(vsum, e);
        }
        // SAFETY: `lanes` holds 8 floats.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), vsum) };
        let mut sum: f32 = lanes.iter().sum();
        for x in chunks.into_remainder() {
            *x = super::exp_nonpositive(*x - max);
            sum += *x;
        }
        sum
    }

    /// [`super::exp_nonpositive`] of 8 lanes.
    ///
    /// # Safety
    /// As [`softmax_numerators`]: AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    pub fn exp8(x: __m256) -> __m256 {
        let floor = _mm256_set1_ps(super::EXP_FLOOR);
        let below = _mm256_cmp_ps::<_CMP_LT_OQ>(x, floor);
        let x = _mm256_max_ps(x, floor);
        let round = _mm256_set1_ps(super::ROUND);
        let shifted = _mm256_fmadd_ps(x, _mm256_set1_ps(std::f32::consts::LOG2_E), round);
        let n = _mm256_sub_ps(shifted, round);
        let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(super::LN2_HI), x);
        let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(super::LN2_LO), r);
        let mut p = _mm256_set1_ps(super::TAYLOR[0]);
        for c in &super::TAYLOR[1..] {
            p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(*c));
        }
        let n_bits = _mm256_sub_epi32(_mm256_castps_si256(shifted), _mm256_set1_epi32(super::ROUND.to_bits() as i32));
        let two_n = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(n_bits, _mm256_set1_epi32(127))));
        _mm256_andnot_ps(below, _mm256_mul_ps(p, two_n))
    }
}

/// Below this `exp` is flushed to 0 (f32's exp leaves the normal range near -87.3).
const EXP_FLOOR: f32 = -87.3;
/// ln 2 split so that `n * LN2_HI` is exact for |n| < 2^9.
const LN2_HI: f32 = 0.693_145_75;
const LN2_LO: f32 = 1.428_606_8e-6;
/// Adding 1.5 * 2^23 rounds to an integer `n` held in the low mantissa bits: the sum's bits are
/// `ROUND`'s bits + n, for |n| < 2^22.
const ROUND: f32 = 12_582_912.0;
/// exp(r)'s Taylor coefficients from r^7 down to r^0 (Horner order).
const TAYLOR: [f32; 8] = [1.0 / 5040.0, 1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0];

/// `exp(x)` for `x <= 0` (a score minus its row's max) within 2 ulp, and 0 below [`EXP_FLOOR`]
/// (such a term is below 1e-38 of the row's largest, which is 1): `x = n ln2 + r`,
/// `|r| <= ln2 / 2`, `exp(r)` by its Taylor series to r^7, times `2^n` written into the exponent
/// bits (n >= -126 here).
#[inline(always)]
pub fn exp_nonpositive(x: f32) -> f32 {
    if x < EXP_FLOOR {
        return 0.0;
    }
    let shifted = x * std::f32::consts::LOG2_E + ROUND;
    let n = shifted - ROUND;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let p = TAYLOR[1..].iter().fold(TAYLOR[0], |p, c| p * r + c);
    let two_n = f32::from_bits(shifted.to_bits().wrapping_sub(ROUND.to_bits()).wrapping_add(127) << 23);
    p * two_n
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_matches_std_to_two_ulp_and_flushes_far_below_zero() {
        let mut worst = 0f32;
        for i in 0..=200_000 {
            let x = -87.0 * i as f32 / 200_000.0;
            let (got, want) = (exp_nonpositive(x), x.exp());
            worst = worst.max(((got - want) / want).abs());
        }
        assert!(worst < 2.5e-7, "worst relative error {worst}");
        assert_eq!(exp_nonpositive(-100.0), 0.0);
        assert_eq!(exp_nonpositive(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp_nonpositive(0.0), 1.0);
    }

    /// The vector path (when the CPU has it) and the scalar one give the same numerators to 1 ulp
    /// and the same sums, on a row whose length is not a multiple of 8 and spans the flush.
    #[test]
    fn softmax_numerators_agree_with_the_scalar_exp() {
        let row: Vec<f32> = (0..203).map(|i| 3.0 - (i as f32 * 0.731) % 95.0).collect();
        let max = row.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
        let want: Vec<f32> = row.iter().map(|x| exp_nonpositive(x - max)).collect();
        let mut got = row.clone();
        let sum = softmax_numerators(&mut got);
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() <= w.abs() * 1.2e-7, "{g} vs {w}");
        }
        assert!(want.contains(&0.0) && want.contains(&1.0));
        assert!((sum - want.iter().sum::<f32>()).abs() < 1e-5);
    }
}
