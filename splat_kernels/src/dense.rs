//! The same op written with ordinary burn tensor ops: what a naive port would do.
//!
//! Every pixel of a chunk meets every Gaussian (`[P, N]` intermediates), compositing is a
//! `cumprod` over the depth-sorted Gaussian axis, and burn's autodiff differentiates it. It exists
//! as the benchmark baseline (`splat-bench`) and is tested against the CPU kernel on small scenes.

use crate::api::Gaussians;
use crate::camera::Camera;
use crate::constants::{LOG_SCALE_MAX, LOG_SCALE_MIN, LOW_PASS, QUAT_MIN_NORM, RasterConfig, TILE_SIZE};
use burn::tensor::{Tensor, TensorData};

/// Depth-sorted projected Gaussians as `[N]` tensors (rows of the `[P, N]` products).
#[derive(Clone, Debug)]
pub struct DenseProjected {
    mx: Tensor<1>,
    my: Tensor<1>,
    ca: Tensor<1>,
    cb: Tensor<1>,
    cc: Tensor<1>,
    z: Tensor<1>,
    opacity: Tensor<1>,
    rect: [Tensor<1>; 4],
    features: Tensor<2>,
}

/// Projects and depth-sorts all Gaussians with tensor ops.
pub fn project(g: &Gaussians, cam: &Camera, cfg: &RasterConfig) -> DenseProjected {
    let col = |t: &Tensor<2>, k: usize| t.clone().narrow(1, k, 1).squeeze_dim::<1>(1);
    let rc = cam.rotation_rows();
    let tc = cam.translation();
    let (mx, my, mz) = (col(&g.means, 0), col(&g.means, 1), col(&g.means, 2));
    let p: Vec<Tensor<1>> =
        (0..3).map(|i| mx.clone() * rc[i][0] + my.clone() * rc[i][1] + mz.clone() * rc[i][2] + tc[i]).collect();
    let valid = p[2].clone().greater_equal_elem(cam.near).bool_and(p[2].clone().lower_equal_elem(cam.far));
    let z = p[2].clone().mask_where(valid.clone().bool_not(), Tensor::ones_like(&p[2]));
    // Quaternion -> rotation (identity policy below QUAT_MIN_NORM).
    let q: Vec<Tensor<1>> = (0..4).map(|k| col(&g.quats, k)).collect();
    let norm2 = q[0].clone().powi_scalar(2)
        + q[1].clone().powi_scalar(2)
        + q[2].clone().powi_scalar(2)
        + q[3].clone().powi_scalar(2);
    let tiny = norm2.clone().lower_elem(QUAT_MIN_NORM * QUAT_MIN_NORM);
    let inv = norm2.clamp_min(QUAT_MIN_NORM * QUAT_MIN_NORM).sqrt().recip();
    let qn: Vec<Tensor<1>> = q
        .iter()
        .enumerate()
        .map(|(k, qk)| {
            let v = qk.clone() * inv.clone();
            v.mask_fill(tiny.clone(), if k == 0 { 1.0 } else { 0.0 })
        })
        .collect();
    let (w, x, y, zq) = (qn[0].clone(), qn[1].clone(), qn[2].clone(), qn[3].clone());
    let two = |a: Tensor<1>| a * 2.0;
    let r = [
        [
            -two(y.clone() * y.clone() + zq.clone() * zq.clone()) + 1.0,
            two(x.clone() * y.clone() - w.clone() * zq.clone()),
            two(x.clone() * zq.clone() + w.clone() * y.clone()),
        ],
        [
            two(x.clone() * y.clone() + w.clone() * zq.clone()),
            -two(x.clone() * x.clone() + zq.clone() * zq.clone()) + 1.0,
            two(y.clone() * zq.clone() - w.clone() * x.clone()),
        ],
        [
            two(x.clone() * zq.clone() - w.clone() * y.clone()),
            two(y.clone() * zq.clone() + w.clone() * x.clone()),
            -two(x.clone() * x.clone() + y.clone() * y.clone()) + 1.0,
        ],
    ];
    let s: Vec<Tensor<1>> = (0..3).map(|k| col(&g.log_scales, k).clamp(LOG_SCALE_MIN, LOG_SCALE_MAX).exp()).collect();
    // E = R_c R S
    let m = |i: usize, k: usize| r[i][k].clone() * s[k].clone();
    let e: Vec<Vec<Tensor<1>>> = (0..3)
        .map(|i| (0..3).map(|k| m(0, k) * rc[i][0] + m(1, k) * rc[i][1] + m(2, k) * rc[i][2]).collect())
        .collect();
    let [lx, ly] = cam.clamp_limits();
    let uc = (p[0].clone() / z.clone()).clamp(-lx, lx);
    let vc = (p[1].clone() / z.clone()).clamp(-ly, ly);
    let j00 = z.clone().recip() * cam.fx;
    let j02 = -(uc * cam.fx) / z.clone();
    let j11 = z.clone().recip() * cam.fy;
    let j12 = -(vc * cam.fy) / z.clone();
    let t0: Vec<Tensor<1>> = (0..3).map(|k| j00.clone() * e[0][k].clone() + j02.clone() * e[2][k].clone()).collect();
    let t1: Vec<Tensor<1>> = (0..3).map(|k| j11.clone() * e[1][k].clone() + j12.clone() * e[2][k].clone()).collect();
    let dot = |a: &[Tensor<1>], b: &[Tensor<1>]| {
        a[0].clone() * b[0].clone() + a[1].clone() * b[1].clone() + a[2].clone() * b[2].clone()
    };
    let a = dot(&t0, &t0) + LOW_PASS;
    let b = dot(&t0, &t1);
    let c = dot(&t1, &t1) + LOW_PASS;
    let det = a.clone() * c.clone() - b.clone() * b.clone();
    let lambda = (a.clone() + c.clone()) * 0.5
        + ((a.clone() - c.clone()).powi_scalar(2) * 0.25 + b.clone().powi_scalar(2)).sqrt();
    let radius = (lambda.sqrt() * cfg.extent).ceil().detach();
    let cx2 = p[0].clone() / z.clone() * cam.fx + cam.cx;
    let cy2 = p[1].clone() / z.clone() * cam.fy + cam.cy;
    let ts = TILE_SIZE as f32;
    let [tx, ty] = cam.tiles();
    let lo = |c: Tensor<1>, n: u32| ((c - radius.clone()) / ts).floor().clamp(0.0, n as f32).detach();
    let hi = |c: Tensor<1>, n: u32| (((c + radius.clone()) / ts).floor() + 1.0).clamp(0.0, n as f32).detach();
    let rect = [lo(cx2.clone(), tx), lo(cy2.clone(), ty), hi(cx2.clone(), tx), hi(cy2.clone(), ty)];
    let opacity = burn::tensor::activation::sigmoid(g.opacity_logits.clone()) * valid.float();
    // Depth sort on the host (burn's sort reads back on most backends anyway).
    let depth_host = z.clone().into_data().to_vec::<f32>().expect("f32 depth");
    let mut order: Vec<usize> = (0..depth_host.len()).collect();
    order.sort_by(|&i, &j| depth_host[i].total_cmp(&depth_host[j]).then(i.cmp(&j)));
    let idx = Tensor::<1, burn::tensor::Int>::from_data(
        TensorData::new(order.iter().map(|&i| i as i64).collect::<Vec<_>>(), [order.len()]),
        &z.device(),
    );
    let sel = |t: Tensor<1>| t.select(0, idx.clone());
    DenseProjected {
        mx: sel(cx2),
        my: sel(cy2),
        ca: sel(c / det.clone()),
        cb: sel(-b / det.clone()),
        cc: sel(a / det),
        z: sel(z),
        opacity: sel(opacity),
        rect: rect.map(sel),
        features: g.features.clone().select(0, idx),
    }
}

/// Composites pixels `first..first + count` (row-major) against every Gaussian.
/// Returns `features [P, C]`, `alpha [P]`, `depth [P]`.
pub fn composite(
    proj: &DenseProjected,
    cam: &Camera,
    cfg: &RasterConfig,
    background: Tensor<1>,
    first: usize,
    count: usize,
) -> (Tensor<2>, Tensor<1>, Tensor<1>) {
    let device = proj.z.device();
    let w = cam.width as usize;
    let (mut px, mut py, mut tile_x, mut tile_y) = (vec![], vec![], vec![], vec![]);
    for o in first..first + count {
        px.push((o % w) as f32 + 0.5);
        py.push((o / w) as f32 + 0.5);
        tile_x.push(((o % w) as u32 / TILE_SIZE) as f32);
        tile_y.push(((o / w) as u32 / TILE_SIZE) as f32);
    }
    let colv = |v: Vec<f32>| Tensor::<1>::from_data(TensorData::new(v, [count]), &device).unsqueeze_dim::<2>(1);
    let row = |t: &Tensor<1>| t.clone().unsqueeze_dim::<2>(0);
    let (tx, ty) = (colv(tile_x), colv(tile_y));
    let inside = tx
        .clone()
        .greater_equal(row(&proj.rect[0]))
        .bool_and(tx.lower(row(&proj.rect[2])))
        .bool_and(ty.clone().greater_equal(row(&proj.rect[1])))
        .bool_and(ty.lower(row(&proj.rect[3])));
    let dx = colv(px) - row(&proj.mx);
    let dy = colv(py) - row(&proj.my);
    let power = (dx.clone().powi_scalar(2) * row(&proj.ca) + dy.clone().powi_scalar(2) * row(&proj.cc)) * -0.5
        - dx * dy * row(&proj.cb);
    let keep = power.clone().lower_equal_elem(0.0).bool_and(inside);
    let alpha = (power.exp() * row(&proj.opacity)).clamp_max(cfg.alpha_max);
    let keep = keep.bool_and(alpha.clone().greater_equal_elem(cfg.alpha_min));
    let alpha = alpha * keep.float();
    // Early stop: a Gaussian counts only while the transmittance after it stays >= t_min.
    let t_incl = (-alpha.clone() + 1.0).cumprod(1);
    let alpha = alpha * t_incl.greater_equal_elem(cfg.t_min).float().detach();
    let one_minus = -alpha.clone() + 1.0;
    let t_incl = one_minus.clone().cumprod(1);
    let t_excl = t_incl.clone() / one_minus;
    let weights = alpha * t_excl;
    let n = proj.z.dims()[0];
    let t_final = t_incl.narrow(1, n - 1, 1);
    let feats = weights.clone().matmul(proj.features.clone()) + t_final.clone() * background.unsqueeze_dim::<2>(0);
    let depth = weights.matmul(proj.z.clone().unsqueeze_dim::<2>(1)).squeeze_dim::<1>(1);
    let alpha_out = (-t_final + 1.0).squeeze_dim::<1>(1);
    (feats, alpha_out, depth)
}

/// Number of pixels per chunk so that one `[P, N]` intermediate holds about 2^24 values.
pub fn chunk_pixels(n: usize) -> usize {
    ((1usize << 24) / n.max(1)).clamp(1, 1 << 16)
}
