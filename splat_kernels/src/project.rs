//! Per-Gaussian projection (3D Gaussian -> screen-space conic) and its hand-written backward, in f32.
//!
//! Math (3DGS / EWA splatting):
//! * `q = quat / |quat|` as (w, x, y, z); `R(q)`; `S = diag(exp(clamp(log_scale)))`; `M = R S`,
//!   world covariance `Sigma3 = M M^T`.
//! * `p = R_c mean + t_c` (camera space), culled unless `near <= p.z <= far`.
//! * Jacobian of the perspective map at the clamped centre
//!   `J = [[fx/z, 0, -fx*uc/z], [0, fy/z, -fy*vc/z]]`, `uc = clamp(x/z, +-lim_x)`.
//! * `T = J R_c M` (2x3); `Sigma2 = T T^T + LOW_PASS * I`; the conic is `Sigma2^-1`.
//!   `det(Sigma2)` is evaluated as `sum of squared 2x2 minors of T + LOW_PASS tr(T T^T) + LOW_PASS^2`
//!   (Cauchy-Binet), which is positive by construction even for 1e4:1 anisotropy in f32.
//! * footprint radius `r = ceil(extent * sqrt(lambda_max))`, tiles touched by the square of side 2r.

use crate::camera::Camera;
use crate::constants::*;

/// A projected Gaussian as the compositor sees it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Projected {
    /// Screen-space centre in pixels.
    pub mean2d: [f32; 2],
    /// Inverse 2D covariance (a, b, c): `power = -0.5 (a dx^2 + c dy^2) - b dx dy`.
    pub conic: [f32; 3],
    /// Camera-space depth z.
    pub depth: f32,
    /// sigmoid(opacity logit).
    pub opacity: f32,
    /// Footprint radius in pixels.
    pub radius: f32,
    /// Touched tiles `[x0, y0, x1, y1)` (exclusive upper bounds).
    pub rect: [u32; 4],
}

impl Projected {
    pub fn num_tiles(&self) -> u32 {
        (self.rect[2] - self.rect[0]) * (self.rect[3] - self.rect[1])
    }
}

/// Gradient of the loss with respect to one projected Gaussian.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ProjectedGrad {
    pub mean2d: [f32; 2],
    pub conic: [f32; 3],
    pub depth: f32,
    pub opacity: f32,
}

/// Gradient with respect to one Gaussian's 3D parameters.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GaussianGrad {
    pub mean: [f32; 3],
    pub log_scale: [f32; 3],
    pub quat: [f32; 4],
    pub opacity_logit: f32,
}

type M3 = [[f32; 3]; 3];

/// Numerically stable logistic function.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    if x >= 0.0 {
        1.0 / (1.0 + (-x).exp())
    } else {
        let e = x.exp();
        e / (1.0 + e)
    }
}

/// Normalised quaternion and `1/|q|`; `None` under the identity policy (|q| < QUAT_MIN_NORM or
/// non-finite). Robust to denormals: the components are first divided by the largest magnitude.
#[inline]
pub fn normalize_quat(q: [f32; 4]) -> Option<([f32; 4], f32)> {
    let m = q.iter().fold(0.0f32, |a, v| a.max(v.abs()));
    if !(m.is_finite() && m > 0.0) {
        return None;
    }
    let s = [q[0] / m, q[1] / m, q[2] / m, q[3] / m];
    let n = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2] + s[3] * s[3]).sqrt();
    let norm = m * n;
    if !(norm >= QUAT_MIN_NORM) {
        return None;
    }
    Some(([s[0] / n, s[1] / n, s[2] / n, s[3] / n], 1.0 / norm))
}

/// Rotation matrix (row-major) of a unit quaternion (w, x, y, z).
#[inline]
pub fn quat_to_rot(q: [f32; 4]) -> M3 {
    let [w, x, y, z] = q;
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

#[inline]
fn matmul3(a: &M3, b: &M3) -> M3 {
    let mut o = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    o
}

/// Intermediate values of the projection, recomputed by the backward pass.
struct Fwd {
    qn: Option<([f32; 4], f32)>,
    rot: M3,
    scale: [f32; 3],
    scale_active: [bool; 3],
    p: [f32; 3],
    uc: f32,
    vc: f32,
    u_free: bool,
    v_free: bool,
    /// `R_c M`
    rcm: M3,
    /// `T = J R_c M`
    t: [[f32; 3]; 2],
    conic: [f32; 3],
    opacity: f32,
}

#[inline]
fn forward_parts(
    cam: &Camera,
    mean: [f32; 3],
    log_scale: [f32; 3],
    quat: [f32; 4],
    opacity_logit: f32,
) -> Option<(Fwd, Projected)> {
    let rc = cam.rotation_rows();
    let tc = cam.translation();
    let mut p = [0.0f32; 3];
    for i in 0..3 {
        p[i] = rc[i][0] * mean[0] + rc[i][1] * mean[1] + rc[i][2] * mean[2] + tc[i];
    }
    let z = p[2];
    if !(z >= cam.near && z <= cam.far) {
        return None;
    }
    let qn = normalize_quat(quat);
    let rot = match qn {
        Some((q, _)) => quat_to_rot(q),
        None => [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let mut scale = [0.0f32; 3];
    let mut scale_active = [true; 3];
    for j in 0..3 {
        let ls = log_scale[j];
        scale_active[j] = (LOG_SCALE_MIN..=LOG_SCALE_MAX).contains(&ls);
        scale[j] = ls.clamp(LOG_SCALE_MIN, LOG_SCALE_MAX).exp();
    }
    let mut m = rot;
    for row in m.iter_mut() {
        for j in 0..3 {
            row[j] *= scale[j];
        }
    }
    let rcm = matmul3(&rc, &m);
    let [lim_x, lim_y] = cam.clamp_limits();
    let u = p[0] / z;
    let v = p[1] / z;
    let uc = u.clamp(-lim_x, lim_x);
    let vc = v.clamp(-lim_y, lim_y);
    let j00 = cam.fx / z;
    let j02 = -cam.fx * uc / z;
    let j11 = cam.fy / z;
    let j12 = -cam.fy * vc / z;
    let mut t = [[0.0f32; 3]; 2];
    for k in 0..3 {
        t[0][k] = j00 * rcm[0][k] + j02 * rcm[2][k];
        t[1][k] = j11 * rcm[1][k] + j12 * rcm[2][k];
    }
    let ta = t[0][0] * t[0][0] + t[0][1] * t[0][1] + t[0][2] * t[0][2];
    let tc2 = t[1][0] * t[1][0] + t[1][1] * t[1][1] + t[1][2] * t[1][2];
    let a = ta + LOW_PASS;
    let b = t[0][0] * t[1][0] + t[0][1] * t[1][1] + t[0][2] * t[1][2];
    let c = tc2 + LOW_PASS;
    let m01 = t[0][0] * t[1][1] - t[0][1] * t[1][0];
    let m02 = t[0][0] * t[1][2] - t[0][2] * t[1][0];
    let m12 = t[0][1] * t[1][2] - t[0][2] * t[1][1];
    let det = m01 * m01 + m02 * m02 + m12 * m12 + LOW_PASS * (ta + tc2) + LOW_PASS * LOW_PASS;
    if !(det.is_finite() && det > 0.0 && a.is_finite() && c.is_finite() && b.is_finite()) {
        return None;
    }
    let conic = [c / det, -b / det, a / det];
    let half_diff = 0.5 * (a - c);
    let lambda_max = 0.5 * (a + c) + (half_diff * half_diff + b * b).sqrt();
    let radius = lambda_max.sqrt();
    let mean2d = [cam.fx * u + cam.cx, cam.fy * v + cam.cy];
    if !(mean2d[0].is_finite() && mean2d[1].is_finite() && radius.is_finite()) {
        return None;
    }
    let opacity = sigmoid(opacity_logit);
    let fwd = Fwd {
        qn,
        rot,
        scale,
        scale_active,
        p,
        uc,
        vc,
        u_free: u.abs() <= lim_x,
        v_free: v.abs() <= lim_y,
        rcm,
        t,
        conic,
        opacity,
    };
    let proj = Projected {
        mean2d,
        conic,
        depth: z,
        opacity,
        // sqrt(lambda_max); the caller scales it by `extent` and takes the tile rect.
        radius,
        rect: [0; 4],
    };
    Some((fwd, proj))
}

/// Tile rectangle `[x0, y0, x1, y1)` touched by a square of half-side `radius` around `center`.
#[inline]
pub fn tile_rect(center: [f32; 2], radius: f32, tiles: [u32; 2]) -> [u32; 4] {
    let ts = TILE_SIZE as f32;
    let lo = |c: f32, n: u32| ((c - radius) / ts).floor().clamp(0.0, n as f32) as u32;
    let hi = |c: f32, n: u32| (((c + radius) / ts).floor() + 1.0).clamp(0.0, n as f32) as u32;
    [lo(center[0], tiles[0]), lo(center[1], tiles[1]), hi(center[0], tiles[0]), hi(center[1], tiles[1])]
}

/// Projects one Gaussian; `None` when it is culled (behind the near plane, beyond the far plane,
/// degenerate, or with a footprint entirely outside the image).
#[inline]
pub fn project(
    cam: &Camera,
    cfg: &RasterConfig,
    mean: [f32; 3],
    log_scale: [f32; 3],
    quat: [f32; 4],
    opacity_logit: f32,
) -> Option<Projected> {
    let (_, mut p) = forward_parts(cam, mean, log_scale, quat, opacity_logit)?;
    p.radius = (cfg.extent * p.radius).ceil();
    p.rect = tile_rect(p.mean2d, p.radius, cam.tiles());
    if p.rect[0] >= p.rect[2] || p.rect[1] >= p.rect[3] {
        return None;
    }
    Some(p)
}

/// Backward of [`project`]: maps the gradient of one projected Gaussian to its 3D parameters.
/// Returns zeros for a Gaussian that the forward culls.
pub fn project_backward(
    cam: &Camera,
    mean: [f32; 3],
    log_scale: [f32; 3],
    quat: [f32; 4],
    opacity_logit: f32,
    g: &ProjectedGrad,
) -> GaussianGrad {
    let Some((f, _)) = forward_parts(cam, mean, log_scale, quat, opacity_logit) else {
        return GaussianGrad::default();
    };
    let mut out = GaussianGrad { opacity_logit: g.opacity * f.opacity * (1.0 - f.opacity), ..Default::default() };
    let z = f.p[2];
    // conic -> covariance: dL/dSigma = -Sigma^-1 G Sigma^-1 with G = [[ga, gb/2], [gb/2, gc]].
    let [ia, ib, ic] = f.conic;
    let (ga, gb, gc) = (g.conic[0], 0.5 * g.conic[1], g.conic[2]);
    // X = G * Sigma^-1
    let x00 = ga * ia + gb * ib;
    let x01 = ga * ib + gb * ic;
    let x10 = gb * ia + gc * ib;
    let x11 = gb * ib + gc * ic;
    // Y = Sigma^-1 * X, dSigma = -Y
    let d_a = -(ia * x00 + ib * x10);
    let d_b = -(ia * x01 + ib * x11); // symmetric off-diagonal entry (appears twice)
    let d_c = -(ib * x01 + ic * x11);
    // Sigma2 = T T^T: dT = (Gs + Gs^T) T with Gs = [[dA, dB], [dB, dC]] -> dT = 2 Gs T.
    let mut dt = [[0.0f32; 3]; 2];
    for k in 0..3 {
        dt[0][k] = 2.0 * (d_a * f.t[0][k] + d_b * f.t[1][k]);
        dt[1][k] = 2.0 * (d_b * f.t[0][k] + d_c * f.t[1][k]);
    }
    // T = J (R_c M): dJ = dT (R_c M)^T (only the 4 structurally non-zero entries), d(R_c M) = J^T dT.
    let rcm = &f.rcm;
    let dj00 = dt[0][0] * rcm[0][0] + dt[0][1] * rcm[0][1] + dt[0][2] * rcm[0][2];
    let dj02 = dt[0][0] * rcm[2][0] + dt[0][1] * rcm[2][1] + dt[0][2] * rcm[2][2];
    let dj11 = dt[1][0] * rcm[1][0] + dt[1][1] * rcm[1][1] + dt[1][2] * rcm[1][2];
    let dj12 = dt[1][0] * rcm[2][0] + dt[1][1] * rcm[2][1] + dt[1][2] * rcm[2][2];
    let j00 = cam.fx / z;
    let j02 = -cam.fx * f.uc / z;
    let j11 = cam.fy / z;
    let j12 = -cam.fy * f.vc / z;
    let mut drcm = [[0.0f32; 3]; 3];
    for k in 0..3 {
        drcm[0][k] = j00 * dt[0][k];
        drcm[1][k] = j11 * dt[1][k];
        drcm[2][k] = j02 * dt[0][k] + j12 * dt[1][k];
    }
    // J as a function of the camera-space point p.
    let mut dp = [0.0f32; 3];
    let z2 = z * z;
    dp[2] += dj00 * (-cam.fx / z2) + dj11 * (-cam.fy / z2);
    dp[2] += dj02 * (cam.fx * f.uc / z2) + dj12 * (cam.fy * f.vc / z2);
    if f.u_free {
        dp[0] += dj02 * (-cam.fx / z2);
        dp[2] += dj02 * (cam.fx * f.p[0] / (z2 * z));
    }
    if f.v_free {
        dp[1] += dj12 * (-cam.fy / z2);
        dp[2] += dj12 * (cam.fy * f.p[1] / (z2 * z));
    }
    // mean2d = (fx x/z + cx, fy y/z + cy), depth = z.
    dp[0] += g.mean2d[0] * cam.fx / z;
    dp[1] += g.mean2d[1] * cam.fy / z;
    dp[2] += -g.mean2d[0] * cam.fx * f.p[0] / z2 - g.mean2d[1] * cam.fy * f.p[1] / z2 + g.depth;
    // p = R_c mean + t_c.
    let rc = cam.rotation_rows();
    for j in 0..3 {
        out.mean[j] = rc[0][j] * dp[0] + rc[1][j] * dp[1] + rc[2][j] * dp[2];
    }
    // R_c M: dM = R_c^T d(R_c M).
    let mut dm = [[0.0f32; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            dm[i][k] = rc[0][i] * drcm[0][k] + rc[1][i] * drcm[1][k] + rc[2][i] * drcm[2][k];
        }
    }
    // M = R S.
    let mut dr = [[0.0f32; 3]; 3];
    for i in 0..3 {
        for k in 0..3 {
            dr[i][k] = dm[i][k] * f.scale[k];
        }
    }
    for k in 0..3 {
        if f.scale_active[k] {
            let ds = dm[0][k] * f.rot[0][k] + dm[1][k] * f.rot[1][k] + dm[2][k] * f.rot[2][k];
            out.log_scale[k] = ds * f.scale[k];
        }
    }
    if let Some((qn, inv_norm)) = f.qn {
        let [w, x, y, zq] = qn;
        let gq = [
            2.0 * (-zq * dr[0][1] + y * dr[0][2] + zq * dr[1][0] - x * dr[1][2] - y * dr[2][0] + x * dr[2][1]),
            2.0 * (y * dr[0][1] + zq * dr[0][2] + y * dr[1][0] - 2.0 * x * dr[1][1] - w * dr[1][2]
                + zq * dr[2][0]
                + w * dr[2][1]
                - 2.0 * x * dr[2][2]),
            2.0 * (-2.0 * y * dr[0][0] + x * dr[0][1] + w * dr[0][2] + x * dr[1][0] + zq * dr[1][2] - w * dr[2][0]
                + zq * dr[2][1]
                - 2.0 * y * dr[2][2]),
            2.0 * (-2.0 * zq * dr[0][0] - w * dr[0][1] + x * dr[0][2] + w * dr[1][0] - 2.0 * zq * dr[1][1]
                + y * dr[1][2]
                + x * dr[2][0]
                + y * dr[2][1]),
        ];
        let dot = gq[0] * qn[0] + gq[1] * qn[1] + gq[2] * qn[2] + gq[3] * qn[3];
        for k in 0..4 {
            out.quat[k] = (gq[k] - qn[k] * dot) * inv_norm;
        }
    }
    out
}
