//! The test oracle: a dense, obviously-correct f64 implementation of the same math.
//!
//! Every pixel walks every Gaussian in (depth, id) order; nothing is tiled or cached. The only
//! tile-related rule kept is the definition of which pixels a Gaussian reaches (the tiles touched by
//! its `extent`-sigma square), because it is part of the op's semantics.

use crate::camera::Camera;
use crate::constants::*;
use crate::cpu::{ForwardOut, SplatInputsRef};
use glam::{DMat3, DVec3};

struct RefGaussian {
    id: usize,
    mean2d: [f64; 2],
    conic: [f64; 3],
    depth: f64,
    opacity: f64,
    rect: [i64; 4],
    /// Rectangles for the footprint shrunk / grown by f32 rounding: tiles between them may or may
    /// not be touched by an f32 implementation.
    rect_inner: [i64; 4],
    rect_outer: [i64; 4],
}

fn in_rect(r: &[i64; 4], tx: i64, ty: i64) -> bool {
    tx >= r[0] && tx < r[2] && ty >= r[1] && ty < r[3]
}

fn project_one(inp: &SplatInputsRef, cam: &Camera, cfg: &RasterConfig, i: usize) -> Option<RefGaussian> {
    let f = |v: f32| v as f64;
    let mean = DVec3::new(f(inp.means[3 * i]), f(inp.means[3 * i + 1]), f(inp.means[3 * i + 2]));
    let w2c = cam.world_to_cam.as_dmat4();
    let p = w2c.transform_point3(mean);
    if !(p.z >= f(cam.near) && p.z <= f(cam.far)) {
        return None;
    }
    let q: Vec<f64> = inp.quats[4 * i..4 * i + 4].iter().map(|&v| v as f64).collect();
    let qnorm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let rot = if qnorm < QUAT_MIN_NORM as f64 {
        DMat3::IDENTITY
    } else {
        let (w, x, y, z) = (q[0] / qnorm, q[1] / qnorm, q[2] / qnorm, q[3] / qnorm);
        // glam's quaternion is (x, y, z, w); it yields the same matrix as `project::quat_to_rot`.
        DMat3::from_quat(glam::DQuat::from_xyzw(x, y, z, w))
    };
    let s = DVec3::new(
        f(inp.log_scales[3 * i].clamp(LOG_SCALE_MIN, LOG_SCALE_MAX)).exp(),
        f(inp.log_scales[3 * i + 1].clamp(LOG_SCALE_MIN, LOG_SCALE_MAX)).exp(),
        f(inp.log_scales[3 * i + 2].clamp(LOG_SCALE_MIN, LOG_SCALE_MAX)).exp(),
    );
    let m = rot * DMat3::from_diagonal(s);
    let cov3 = m * m.transpose();
    let rc = DMat3::from_mat4(w2c);
    let cov_cam = rc * cov3 * rc.transpose();
    let lim_x = f(FRUSTUM_CLAMP) * 0.5 * f(cam.width as f32) / f(cam.fx);
    let lim_y = f(FRUSTUM_CLAMP) * 0.5 * f(cam.height as f32) / f(cam.fy);
    let uc = (p.x / p.z).clamp(-lim_x, lim_x);
    let vc = (p.y / p.z).clamp(-lim_y, lim_y);
    let (fx, fy) = (f(cam.fx), f(cam.fy));
    // 2x3 Jacobian rows.
    let j0 = DVec3::new(fx / p.z, 0.0, -fx * uc / p.z);
    let j1 = DVec3::new(0.0, fy / p.z, -fy * vc / p.z);
    let a = j0.dot(cov_cam * j0) + f(LOW_PASS);
    let b = j0.dot(cov_cam * j1);
    let c = j1.dot(cov_cam * j1) + f(LOW_PASS);
    let det = a * c - b * b;
    if !(det > 0.0 && det.is_finite()) {
        return None;
    }
    let lambda_max = 0.5 * (a + c) + (0.25 * (a - c) * (a - c) + b * b).sqrt();
    let radius_raw = f(cfg.extent) * lambda_max.sqrt();
    let radius = radius_raw.ceil();
    let mean2d = [
        fx * p.x / p.z + f(cam.cx) + f(inp.screen_offsets[2 * i]),
        fy * p.y / p.z + f(cam.cy) + f(inp.screen_offsets[2 * i + 1]),
    ];
    let ts = TILE_SIZE as f64;
    let [tx, ty] = cam.tiles();
    let rect_of = |radius: f64, slack: f64| {
        [
            ((mean2d[0] - radius + slack) / ts).floor().clamp(0.0, tx as f64) as i64,
            ((mean2d[1] - radius + slack) / ts).floor().clamp(0.0, ty as f64) as i64,
            (((mean2d[0] + radius - slack) / ts).floor() + 1.0).clamp(0.0, tx as f64) as i64,
            (((mean2d[1] + radius - slack) / ts).floor() + 1.0).clamp(0.0, ty as f64) as i64,
        ]
    };
    let rect = rect_of(radius, 0.0);
    // f32 rounding of the radius (relative ~1e-5) and of the centre (~1e-3 px).
    let rtol = 2e-5 * radius_raw.max(1.0);
    let ptol = 1e-3 + 1e-6 * (mean2d[0].abs() + mean2d[1].abs());
    let rect_inner = rect_of((radius_raw - rtol).ceil(), ptol);
    let rect_outer = rect_of((radius_raw + rtol).ceil(), -ptol);
    if rect[0] >= rect[2] || rect[1] >= rect[3] {
        return None;
    }
    let l = f(inp.opacity_logits[i]);
    Some(RefGaussian {
        id: i,
        mean2d,
        conic: [c / det, -b / det, a / det],
        depth: p.z,
        opacity: 1.0 / (1.0 + (-l).exp()),
        rect,
        rect_inner,
        rect_outer,
    })
}

/// f64 outputs of the reference.
pub struct RefOut {
    pub image: Vec<f64>,
    pub alpha: Vec<f64>,
    pub depth: Vec<f64>,
    pub top_id: Vec<i32>,
    /// Pixels whose result hinges on a threshold decision (alpha vs `alpha_min`, transmittance vs
    /// `t_min`, the sign of `power`, a tile-rectangle edge) within f32 rounding: an f32
    /// implementation may legitimately take the other branch there.
    pub ambiguous: Vec<bool>,
}

impl RefOut {
    /// Converts to the f32 layout of the fast implementations (no saved state).
    pub fn to_forward_out(&self) -> ForwardOut {
        ForwardOut {
            image: self.image.iter().map(|&v| v as f32).collect(),
            alpha: self.alpha.iter().map(|&v| v as f32).collect(),
            depth: self.depth.iter().map(|&v| v as f32).collect(),
            top_id: self.top_id.clone(),
            ..Default::default()
        }
    }
}

/// Dense f64 forward pass.
pub fn render(inp: &SplatInputsRef, cam: &Camera, cfg: &RasterConfig) -> RefOut {
    let c = inp.channels();
    let mut gs: Vec<RefGaussian> = (0..inp.len()).filter_map(|i| project_one(inp, cam, cfg, i)).collect();
    gs.sort_by(|a, b| (a.depth as f32).total_cmp(&(b.depth as f32)).then(a.id.cmp(&b.id)));
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut out = RefOut {
        image: vec![0.0; w * h * c],
        alpha: vec![0.0; w * h],
        depth: vec![0.0; w * h],
        top_id: vec![EMPTY_ID; w * h],
        ambiguous: vec![false; w * h],
    };
    let ts = TILE_SIZE as i64;
    for y in 0..h {
        for x in 0..w {
            let (tile_x, tile_y) = (x as i64 / ts, y as i64 / ts);
            let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
            let mut t = 1.0f64;
            let mut best = 0.0f64;
            let o = y * w + x;
            for g in &gs {
                if !in_rect(&g.rect_outer, tile_x, tile_y) {
                    continue;
                }
                let dx = px - g.mean2d[0];
                let dy = py - g.mean2d[1];
                let power = -0.5 * (g.conic[0] * dx * dx + g.conic[2] * dy * dy) - g.conic[1] * dx * dy;
                let alpha = (g.opacity * power.exp()).min(cfg.alpha_max as f64);
                let amin = cfg.alpha_min as f64;
                let tmin = cfg.t_min as f64;
                let membership_unsure = !in_rect(&g.rect_inner, tile_x, tile_y) && power <= 0.0 && alpha >= amin;
                if membership_unsure {
                    out.ambiguous[o] = true;
                }
                if !in_rect(&g.rect, tile_x, tile_y) {
                    continue;
                }
                if (alpha - amin).abs() <= 1e-5 * amin
                    || (t * (1.0 - alpha) - tmin).abs() <= 1e-4 * tmin
                    || (power.abs() < 1e-6 && g.opacity >= amin)
                {
                    out.ambiguous[o] = true;
                }
                if power > 0.0 {
                    continue;
                }
                if alpha < amin {
                    continue;
                }
                let next_t = t * (1.0 - alpha);
                if next_t < cfg.t_min as f64 {
                    break;
                }
                let wgt = alpha * t;
                for ch in 0..c {
                    out.image[o * c + ch] += wgt * inp.features[g.id * c + ch] as f64;
                }
                out.depth[o] += wgt * g.depth;
                if wgt > best {
                    best = wgt;
                    out.top_id[o] = g.id as i32;
                }
                t = next_t;
            }
            out.alpha[o] = 1.0 - t;
            for ch in 0..c {
                out.image[o * c + ch] += t * inp.background[ch] as f64;
            }
        }
    }
    out
}
