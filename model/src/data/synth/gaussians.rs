//! The tabletop made of Gaussians (deterministic from the seed): a wooden table top and the
//! seed's objects, surfaces covered by flat Gaussians oriented along the surface normal. World
//! frame: y up, table top at y = 0. It describes the same scene as the ray-cast dataset.

use super::scene::{Primitive, table_color, tabletop_objects};
use crate::GaussianCloud;
use crate::cloud::SH_C0;
use crate::rng::Rng;
use glam::{Quat, Vec3};

fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

struct Builder {
    cloud: GaussianCloud,
    rng: Rng,
}

impl Builder {
    fn splat(&mut self, p: Vec3, normal: Vec3, radius: f32, color: [f32; 3]) {
        let q = Quat::from_rotation_arc(Vec3::Z, normal.normalize_or(Vec3::Y));
        let jitter = self.rng.range(-0.04, 0.04);
        self.cloud.means.push(p.into());
        self.cloud.log_scales.push([radius.ln(), radius.ln(), (radius * 0.15).ln()]);
        self.cloud.quats.push([q.w, q.x, q.y, q.z]);
        self.cloud.opacity_logits.push(logit(0.95));
        self.cloud.sh_dc.push(color.map(|c| ((c + jitter).clamp(0.0, 1.0) - 0.5) / SH_C0));
    }
}

/// A tabletop of about `density^2 * 5` Gaussians (density 40 gives about 9,000).
pub fn tabletop(seed: u64, density: usize) -> (GaussianCloud, Vec<Primitive>) {
    let objects = tabletop_objects(seed);
    let mut b = Builder { cloud: GaussianCloud::default(), rng: Rng::new(seed) };
    // Table top: a 4 x 4 square with a wood-like stripe pattern.
    let d = density.max(4);
    let step = 4.0 / d as f32;
    for i in 0..d {
        for j in 0..d {
            let x = -2.0 + (i as f32 + 0.5) * step;
            let z = -2.0 + (j as f32 + 0.5) * step;
            b.splat(Vec3::new(x, 0.0, z), Vec3::Y, step * 0.7, table_color(x, z));
        }
    }
    for o in &objects {
        let s = o.size;
        let n = d * d / 4;
        for k in 0..n {
            // Fibonacci-like sampling on the unit sphere, mapped per shape.
            let t = (k as f32 + 0.5) / n as f32;
            let phi = k as f32 * 2.399_963;
            let (p, nrm) = match o.shape {
                "sphere" => {
                    let y = 1.0 - 2.0 * t;
                    let rr = (1.0 - y * y).sqrt();
                    let v = Vec3::new(rr * phi.cos(), y, rr * phi.sin());
                    (o.center + v * s, v)
                }
                "box" => {
                    let face = k % 6;
                    let (u, w) = (b.rng.range(-1.0, 1.0), b.rng.range(-1.0, 1.0));
                    let (v, nn) = match face {
                        0 => (Vec3::new(1.0, u, w), Vec3::X),
                        1 => (Vec3::new(-1.0, u, w), -Vec3::X),
                        2 => (Vec3::new(u, 1.0, w), Vec3::Y),
                        3 => (Vec3::new(u, -1.0, w), -Vec3::Y),
                        4 => (Vec3::new(u, w, 1.0), Vec3::Z),
                        _ => (Vec3::new(u, w, -1.0), -Vec3::Z),
                    };
                    (o.center + v * s * 0.85, nn)
                }
                "cylinder" => {
                    let y = -1.0 + 2.0 * t;
                    let v = Vec3::new(phi.cos(), 0.0, phi.sin());
                    if k % 5 == 0 {
                        let rr = b.rng.f().sqrt();
                        (o.center + Vec3::new(rr * phi.cos() * s * 0.7, s, rr * phi.sin() * s * 0.7), Vec3::Y)
                    } else {
                        (o.center + Vec3::new(v.x * s * 0.7, y * s, v.z * s * 0.7), v)
                    }
                }
                _ => {
                    // cone: apex up
                    let h = t;
                    let rr = (1.0 - h) * s * 0.8;
                    let v = Vec3::new(phi.cos(), 0.6, phi.sin());
                    (o.center + Vec3::new(rr * phi.cos(), -s + 2.0 * s * h, rr * phi.sin()), v)
                }
            };
            let shade = 0.85 + 0.15 * nrm.normalize_or(Vec3::Y).y;
            let col = o.color.map(|c| c * shade);
            b.splat(p, nrm, s * 3.2 / d as f32 * 2.0, col);
        }
    }
    (b.cloud, objects)
}
