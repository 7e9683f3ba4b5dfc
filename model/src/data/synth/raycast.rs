//! The analytic renderer of the synthetic tabletop: one ray per pixel against the table and the
//! objects, Lambert shading, instance ids and camera-space depth.

use super::scene::{Primitive, TABLE_HALF, table_color};
use super::{FIRST_OBJECT_ID, TABLE_ID};
use glam::Vec3;
use splat_kernels::Camera;

const LIGHT: Vec3 = Vec3::new(0.4, 1.0, 0.3);

/// A ray hit: distance along the (unnormalised) ray, unit normal, mask id, albedo.
#[derive(Clone, Copy, Debug)]
struct Hit {
    t: f32,
    normal: Vec3,
    id: u8,
    albedo: [f32; 3],
}

fn closer(best: &mut Option<Hit>, h: Hit) {
    if h.t > 1e-4 && best.is_none_or(|b| h.t < b.t) {
        *best = Some(h);
    }
}

/// Smallest root above 1e-4 of a t^2 + b t + c, tested by `ok`.
fn quadratic(a: f32, b: f32, c: f32, ok: impl Fn(f32) -> bool) -> Option<f32> {
    if a.abs() < 1e-12 {
        return None;
    }
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return None;
    }
    let sq = disc.sqrt();
    let (mut t0, mut t1) = ((-b - sq) / (2.0 * a), (-b + sq) / (2.0 * a));
    if t0 > t1 {
        std::mem::swap(&mut t0, &mut t1);
    }
    [t0, t1].into_iter().find(|&t| t > 1e-4 && ok(t))
}

fn intersect(o: Vec3, d: Vec3, p: &Primitive, id: u8, best: &mut Option<Hit>) {
    let s = p.size;
    let c = p.center;
    let hit = |t: f32, normal: Vec3| Hit { t, normal: normal.normalize(), id, albedo: p.color };
    match p.shape {
        "sphere" => {
            let oc = o - c;
            if let Some(t) = quadratic(d.dot(d), 2.0 * oc.dot(d), oc.dot(oc) - s * s, |_| true) {
                closer(best, hit(t, o + d * t - c));
            }
        }
        "box" => {
            let half = Vec3::splat(0.85 * s);
            let (lo, hi) = (c - half, c + half);
            let inv = d.recip();
            let t1 = (lo - o) * inv;
            let t2 = (hi - o) * inv;
            let tmin = t1.min(t2);
            let tmax = t1.max(t2);
            let t_near = tmin.max_element();
            let t_far = tmax.min_element();
            if t_near <= t_far && t_near > 1e-4 {
                let axis = if t_near == tmin.x {
                    Vec3::X
                } else if t_near == tmin.y {
                    Vec3::Y
                } else {
                    Vec3::Z
                };
                closer(best, hit(t_near, -axis * d.dot(axis).signum()));
            }
        }
        "cylinder" => {
            let r = 0.7 * s;
            let (y0, y1) = (c.y - s, c.y + s);
            let (px, pz) = (o.x - c.x, o.z - c.z);
            let side = quadratic(d.x * d.x + d.z * d.z, 2.0 * (px * d.x + pz * d.z), px * px + pz * pz - r * r, |t| {
                (y0..=y1).contains(&(o.y + t * d.y))
            });
            if let Some(t) = side {
                let q = o + d * t;
                closer(best, hit(t, Vec3::new(q.x - c.x, 0.0, q.z - c.z)));
            }
            for (y, n) in [(y1, Vec3::Y), (y0, -Vec3::Y)] {
                if d.y.abs() > 1e-12 {
                    let t = (y - o.y) / d.y;
                    let q = o + d * t;
                    if (q.x - c.x).powi(2) + (q.z - c.z).powi(2) <= r * r {
                        closer(best, hit(t, n));
                    }
                }
            }
        }
        _ => {
            // Cone: apex at c + (0, s, 0), base radius 0.8 s at c.y - s.
            let apex = c + Vec3::new(0.0, s, 0.0);
            let h = 2.0 * s;
            let k = 0.8 * s / h;
            let p0 = o - apex;
            let k2 = k * k;
            let a = d.x * d.x + d.z * d.z - k2 * d.y * d.y;
            let b = 2.0 * (p0.x * d.x + p0.z * d.z - k2 * p0.y * d.y);
            let cc = p0.x * p0.x + p0.z * p0.z - k2 * p0.y * p0.y;
            if let Some(t) = quadratic(a, b, cc, |t| (-h..=0.0).contains(&(p0.y + t * d.y))) {
                let q = o + d * t;
                closer(best, hit(t, Vec3::new(q.x - c.x, k2 * (apex.y - q.y), q.z - c.z)));
            }
            if d.y.abs() > 1e-12 {
                let t = (c.y - s - o.y) / d.y;
                let q = o + d * t;
                if (q.x - c.x).powi(2) + (q.z - c.z).powi(2) <= (0.8 * s).powi(2) {
                    closer(best, hit(t, -Vec3::Y));
                }
            }
        }
    }
}

/// Casts one ray against the table and all objects.
fn trace(o: Vec3, d: Vec3, objects: &[Primitive]) -> Option<Hit> {
    let mut best = None;
    if d.y.abs() > 1e-12 {
        let t = -o.y / d.y;
        let q = o + d * t;
        if q.x.abs() <= TABLE_HALF && q.z.abs() <= TABLE_HALF {
            closer(&mut best, Hit { t, normal: Vec3::Y * o.y.signum(), id: TABLE_ID, albedo: table_color(q.x, q.z) });
        }
    }
    for (k, p) in objects.iter().enumerate() {
        intersect(o, d, p, FIRST_OBJECT_ID + k as u8, &mut best);
    }
    best
}

/// One rendered view: RGB in [0, 1] (`[H, W, 3]`), instance ids, camera-space depth (0 = none).
pub struct SynthView {
    pub rgb: Vec<f32>,
    pub ids: Vec<u8>,
    pub depth: Vec<f32>,
}

/// Ray-casts view `cam` of the objects.
pub fn render_view(cam: &Camera, objects: &[Primitive]) -> SynthView {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let c2w = cam.world_to_cam.inverse();
    let eye = c2w.transform_point3(Vec3::ZERO);
    let light = LIGHT.normalize();
    let mut v = SynthView { rgb: vec![1.0; w * h * 3], ids: vec![0; w * h], depth: vec![0.0; w * h] };
    for y in 0..h {
        for x in 0..w {
            let dc = Vec3::new((x as f32 + 0.5 - cam.cx) / cam.fx, (y as f32 + 0.5 - cam.cy) / cam.fy, 1.0);
            let d = c2w.transform_vector3(dc);
            if let Some(hit) = trace(eye, d, objects) {
                let o = y * w + x;
                // `d` has unit camera-space z, so `t` is the camera-space depth.
                v.depth[o] = hit.t;
                v.ids[o] = hit.id;
                let n = if hit.normal.dot(d) > 0.0 { -hit.normal } else { hit.normal };
                let shade = 0.35 + 0.65 * n.dot(light).max(0.0);
                for k in 0..3 {
                    v.rgb[o * 3 + k] = hit.albedo[k] * shade;
                }
            }
        }
    }
    v
}
