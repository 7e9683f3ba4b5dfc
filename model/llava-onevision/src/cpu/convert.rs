//! f32 <-> f16 on host slices, with F16C vector instructions where the CPU has them (burn-flex's
//! own cast goes element by element through f64 in software).

use half::f16;
use half::slice::HalfFloatSliceExt;

/// `src` rounded to f16.
pub fn narrowed(src: &[f32]) -> Vec<f16> {
    let mut out = vec![f16::ZERO; src.len()];
    out.convert_from_f32_slice(src);
    out
}

/// `src` widened to f32.
pub fn widened(src: &[f16]) -> Vec<f32> {
    let mut out = vec![0f32; src.len()];
    src.convert_to_f32_slice(&mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn narrowing_rounds_to_nearest_and_widening_is_exact() {
        // halfway between two f16 values rounds to the even one; beyond f16's range becomes infinite
        let src = [0.0f32, -1.5, 1.0 + 1.0 / 2048.0, 1.0 + 3.0 / 2048.0, 65520.0, -1e-8, 3.0e-5];
        let h = narrowed(&src);
        let want: Vec<f16> = src.iter().map(|&v| f16::from_f32(v)).collect();
        assert_eq!(h, want);
        assert_eq!(h[2], f16::ONE);
        assert_eq!(h[4], f16::INFINITY);
        assert_eq!(widened(&h), want.iter().map(|v| v.to_f32()).collect::<Vec<_>>());
        // lengths that are not a multiple of the vector width
        let long: Vec<f32> = (0..37).map(|i| i as f32 * 0.37 - 5.0).collect();
        let back = widened(&narrowed(&long));
        assert!(long.iter().zip(&back).all(|(a, b)| (a - b).abs() <= a.abs() / 1024.0));
    }
}
