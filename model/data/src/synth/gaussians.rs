//! A synthetic [`SynthScene`] made of Gaussians (for `chatsplat render` and tests): the table top and
//! every object's surface covered by flat Gaussians oriented along the surface normal, coloured
//! with the albedo. It describes the same scene as the ray-cast dataset.

use super::scene::{
    CONE_HEIGHT, CONE_RADIUS, CUBE_HALF, CYLINDER_HALF_HEIGHT, CYLINDER_RADIUS, Object, PYRAMID_HALF, PYRAMID_HEIGHT,
    Shape, SynthScene, TORUS_MAJOR, TORUS_MINOR,
};
use crate::cloud::GaussianCloud;
use crate::cloud::SH_C0;
use base::rng::Rng;
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

/// A point and normal on the surface of a unit-proportioned shape (object frame: bottom centre at
/// the origin, scale 1), for sample `k` of `n` (a Fibonacci-like spread) and two uniforms `u, v`.
fn surface(shape: Shape, k: usize, n: usize, u: f32, v: f32) -> (Vec3, Vec3) {
    let t = (k as f32 + 0.5) / n as f32;
    let phi = k as f32 * 2.399_963;
    let ring = Vec3::new(phi.cos(), 0.0, phi.sin());
    let (a, b) = (2.0 * u - 1.0, 2.0 * v - 1.0);
    match shape {
        Shape::Sphere => {
            let y = 1.0 - 2.0 * t;
            let dir = ring * (1.0 - y * y).sqrt() + Vec3::Y * y;
            (Vec3::Y + dir, dir)
        }
        Shape::Cube => {
            let h = CUBE_HALF;
            let (p, nrm) = match k % 6 {
                0 => (Vec3::new(1.0, a, b), Vec3::X),
                1 => (Vec3::new(-1.0, a, b), -Vec3::X),
                2 => (Vec3::new(a, 1.0, b), Vec3::Y),
                3 => (Vec3::new(a, -1.0, b), -Vec3::Y),
                4 => (Vec3::new(a, b, 1.0), Vec3::Z),
                _ => (Vec3::new(a, b, -1.0), -Vec3::Z),
            };
            (p * h + Vec3::Y * h, nrm)
        }
        Shape::Cylinder => {
            let (r, top) = (CYLINDER_RADIUS, 2.0 * CYLINDER_HALF_HEIGHT);
            if k.is_multiple_of(5) {
                (ring * r * u.sqrt() + Vec3::Y * top, Vec3::Y)
            } else {
                (ring * r + Vec3::Y * (t * top), ring)
            }
        }
        Shape::Cone => {
            let (r, h) = (CONE_RADIUS, CONE_HEIGHT);
            let y = h * (1.0 - u.sqrt());
            let nrm = (ring * h + Vec3::Y * r).normalize();
            (ring * r * (1.0 - y / h) + Vec3::Y * y, nrm)
        }
        Shape::Pyramid => {
            let (half, h) = (PYRAMID_HALF, PYRAMID_HEIGHT);
            // one of the four faces; (u, v) -> a point of the triangle
            let (mut s, mut w) = (u, v);
            if s + w > 1.0 {
                (s, w) = (1.0 - s, 1.0 - w);
            }
            let out = [Vec3::X, Vec3::Z, -Vec3::X, -Vec3::Z][k % 4];
            let side = Vec3::Y.cross(out);
            let (c0, c1, apex) = (out * half + side * half, out * half - side * half, Vec3::Y * h);
            let p = c0 + (c1 - c0) * s + (apex - c0) * w;
            (p, (out * h + Vec3::Y * half).normalize())
        }
        Shape::Torus => {
            let (big, small) = (TORUS_MAJOR, TORUS_MINOR);
            let theta = std::f32::consts::TAU * u;
            let tube = ring * theta.cos() + Vec3::Y * theta.sin();
            (ring * big + tube * small + Vec3::Y * small, tube)
        }
    }
}

fn object(b: &mut Builder, o: &Object, d: usize) {
    let n = d * d / 4;
    let base = o.center - Vec3::new(0.0, o.shape.centre_height(o.scale), 0.0);
    let rot = Quat::from_rotation_y(o.yaw);
    for k in 0..n {
        let (u, v) = (b.rng.f(), b.rng.f());
        let (p, nrm) = surface(o.shape, k, n, u, v);
        let shade = 0.85 + 0.15 * nrm.normalize_or(Vec3::Y).y;
        let col = o.color.rgb().map(|c| c * shade);
        b.splat(base + rot * (p * o.scale), rot * nrm, o.scale * 3.2 / d as f32 * 2.0, col);
    }
}

/// The scene of `seed` as about `density^2 * (1 + objects / 4)` Gaussians, and the scene.
pub fn tabletop(seed: u64, density: usize) -> (GaussianCloud, SynthScene) {
    let scene = SynthScene::from_seed(seed);
    let mut b = Builder { cloud: GaussianCloud::default(), rng: Rng::new(seed) };
    let d = density.max(4);
    let half = scene.table.half;
    let step = 2.0 * half / d as f32;
    for i in 0..d {
        for j in 0..d {
            let x = -half + (i as f32 + 0.5) * step;
            let z = -half + (j as f32 + 0.5) * step;
            b.splat(Vec3::new(x, 0.0, z), Vec3::Y, step * 0.7, scene.table.color(x, z));
        }
    }
    for o in &scene.objects {
        object(&mut b, o, d);
    }
    (b.cloud, scene)
}
