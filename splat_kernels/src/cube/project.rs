//! Steps 1 and 7: projection (forward: centre, conic, depth, opacity, tile rectangle, per-tile
//! counts) and its backward (screen-space gradients -> the 3D parameters'), thread per Gaussian.

use super::layout::*;
use crate::constants::{LOG_SCALE_MAX, LOG_SCALE_MIN, LOW_PASS, QUAT_MIN_NORM, TILE_SIZE};
use cubecl::prelude::*;

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
pub(super) fn project_kernel(
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

/// Thread per Gaussian: screen-space gradients -> gradients of the 3D parameters.
// #[cube] code has no `RangeInclusive::contains`.
#[allow(clippy::manual_range_contains)]
#[cube(launch)]
pub(super) fn project_bwd_kernel(
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
