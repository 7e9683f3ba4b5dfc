//! The analytic renderer of a synthetic [`SynthScene`]: one ray per pixel against the table and the
//! objects (closed forms for sphere, cube, cylinder, cone and pyramid; sphere tracing of the
//! torus's distance function), Lambert shading under the scene's light, instance ids and
//! camera-space depth.

use super::TABLE_ID;
use super::scene::{
    CONE_HEIGHT, CONE_RADIUS, CUBE_HALF, CYLINDER_HALF_HEIGHT, CYLINDER_RADIUS, Object, PYRAMID_HALF, PYRAMID_HEIGHT,
    Shape, SynthScene, TORUS_MAJOR, TORUS_MINOR,
};
use crate::ObjectId;
use glam::{Mat4, Quat, Vec3};
use splat_kernels::Camera;

/// A ray hit: distance along the (unnormalised) ray, unit normal, mask id, albedo.
#[derive(Clone, Copy, Debug)]
struct Hit {
    t: f32,
    normal: Vec3,
    id: ObjectId,
    albedo: [f32; 3],
}

fn closer(best: &mut Option<Hit>, h: Hit) {
    if h.t > 1e-4 && best.is_none_or(|b| h.t < b.t) {
        *best = Some(h);
    }
}

/// Smallest root above 1e-4 of a t^2 + b t + c accepted by `ok`.
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

/// Entry distance and outward normal of a ray into a convex solid given as half-spaces
/// `n . p <= d` (object frame).
fn convex(o: Vec3, d: Vec3, planes: &[(Vec3, f32)]) -> Option<(f32, Vec3)> {
    let (mut t_in, mut t_out, mut normal) = (f32::NEG_INFINITY, f32::INFINITY, Vec3::Y);
    for &(n, dist) in planes {
        let (denom, num) = (n.dot(d), dist - n.dot(o));
        if denom.abs() < 1e-12 {
            if num < 0.0 {
                return None;
            }
            continue;
        }
        let t = num / denom;
        if denom < 0.0 {
            if t > t_in {
                t_in = t;
                normal = n;
            }
        } else {
            t_out = t_out.min(t);
        }
    }
    (t_in <= t_out && t_in > 1e-4).then_some((t_in, normal))
}

/// The object's hit in its own frame: `o`, `d` relative to the bottom centre, y up, yaw undone.
fn hit_local(o: Vec3, d: Vec3, shape: Shape, s: f32) -> Option<(f32, Vec3)> {
    match shape {
        Shape::Sphere => {
            let c = Vec3::new(0.0, s, 0.0);
            let oc = o - c;
            quadratic(d.dot(d), 2.0 * oc.dot(d), oc.dot(oc) - s * s, |_| true).map(|t| (t, o + d * t - c))
        }
        Shape::Cube => {
            let h = CUBE_HALF * s;
            let planes =
                [(Vec3::X, h), (-Vec3::X, h), (Vec3::Z, h), (-Vec3::Z, h), (Vec3::Y, 2.0 * h), (-Vec3::Y, 0.0)];
            convex(o, d, &planes)
        }
        Shape::Pyramid => {
            let (a, hgt) = (PYRAMID_HALF * s, PYRAMID_HEIGHT * s);
            // side through the base edge x = a and the apex (0, hgt, 0): hgt x + a y <= hgt a
            let side = |n: Vec3| ((n * hgt + Vec3::Y * a).normalize(), hgt * a / (n * hgt + Vec3::Y * a).length());
            let planes = [side(Vec3::X), side(-Vec3::X), side(Vec3::Z), side(-Vec3::Z), (-Vec3::Y, 0.0)];
            convex(o, d, &planes)
        }
        Shape::Cylinder => {
            let (r, top) = (CYLINDER_RADIUS * s, 2.0 * CYLINDER_HALF_HEIGHT * s);
            let mut best: Option<(f32, Vec3)> = None;
            let mut keep = |t: f32, n: Vec3| {
                if t > 1e-4 && best.is_none_or(|b| t < b.0) {
                    best = Some((t, n));
                }
            };
            let side =
                quadratic(d.x * d.x + d.z * d.z, 2.0 * (o.x * d.x + o.z * d.z), o.x * o.x + o.z * o.z - r * r, |t| {
                    (0.0..=top).contains(&(o.y + t * d.y))
                });
            if let Some(t) = side {
                let q = o + d * t;
                keep(t, Vec3::new(q.x, 0.0, q.z));
            }
            if d.y.abs() > 1e-12 {
                for (y, n) in [(top, Vec3::Y), (0.0, -Vec3::Y)] {
                    let t = (y - o.y) / d.y;
                    let q = o + d * t;
                    if q.x * q.x + q.z * q.z <= r * r {
                        keep(t, n);
                    }
                }
            }
            best
        }
        Shape::Cone => {
            let (r, h) = (CONE_RADIUS * s, CONE_HEIGHT * s);
            let apex = Vec3::new(0.0, h, 0.0);
            let k2 = (r / h) * (r / h);
            let p0 = o - apex;
            let a = d.x * d.x + d.z * d.z - k2 * d.y * d.y;
            let b = 2.0 * (p0.x * d.x + p0.z * d.z - k2 * p0.y * d.y);
            let c = p0.x * p0.x + p0.z * p0.z - k2 * p0.y * p0.y;
            let mut best: Option<(f32, Vec3)> = None;
            if let Some(t) = quadratic(a, b, c, |t| (-h..=0.0).contains(&(p0.y + t * d.y))) {
                let q = o + d * t;
                best = Some((t, Vec3::new(q.x, k2 * (h - q.y), q.z)));
            }
            if d.y.abs() > 1e-12 {
                let t = -o.y / d.y;
                let q = o + d * t;
                if q.x * q.x + q.z * q.z <= r * r && t > 1e-4 && best.is_none_or(|b| t < b.0) {
                    best = Some((t, -Vec3::Y));
                }
            }
            best
        }
        Shape::Torus => {
            let (big, small) = (TORUS_MAJOR * s, TORUS_MINOR * s);
            let c = Vec3::new(0.0, small, 0.0);
            let sdf = |p: Vec3| {
                let q = p - c;
                (q.x.hypot(q.z) - big).hypot(q.y) - small
            };
            // Sphere tracing from where the ray enters the bounding sphere.
            let (len, dir) = (d.length(), d.normalize());
            let bound = big + small;
            let oc = o - c;
            let (bb, cc) = (oc.dot(dir), oc.dot(oc) - bound * bound);
            let disc = bb * bb - cc;
            if disc < 0.0 {
                return None;
            }
            let (mut t, t_end) = ((-bb - disc.sqrt()).max(0.0), -bb + disc.sqrt());
            for _ in 0..96 {
                let dist = sdf(o + dir * t);
                if dist < 1e-4 * bound {
                    let q = o + dir * t - c;
                    let ring = Vec3::new(q.x, 0.0, q.z).normalize_or_zero() * big;
                    return Some((t / len, q - ring));
                }
                t += dist;
                if t > t_end {
                    break;
                }
            }
            None
        }
    }
}

fn intersect(o: Vec3, d: Vec3, obj: &Object, best: &mut Option<Hit>) {
    let base = obj.center - Vec3::new(0.0, obj.shape.centre_height(obj.scale), 0.0);
    let undo = Quat::from_rotation_y(-obj.yaw);
    if let Some((t, n)) = hit_local(undo * (o - base), undo * d, obj.shape, obj.scale) {
        let normal = (Quat::from_rotation_y(obj.yaw) * n).normalize_or(Vec3::Y);
        closer(best, Hit { t, normal, id: obj.id, albedo: obj.color.rgb() });
    }
}

/// Casts one ray against the table and all objects.
fn trace(o: Vec3, d: Vec3, scene: &SynthScene) -> Option<Hit> {
    let mut best = None;
    if d.y.abs() > 1e-12 {
        let t = -o.y / d.y;
        let q = o + d * t;
        let half = scene.table.half;
        if q.x.abs() <= half && q.z.abs() <= half {
            let normal = Vec3::Y * o.y.signum();
            closer(&mut best, Hit { t, normal, id: TABLE_ID, albedo: scene.table.color(q.x, q.z) });
        }
    }
    for obj in &scene.objects {
        intersect(o, d, obj, &mut best);
    }
    best
}

/// One rendered view: RGB in [0, 1] (`[H, W, 3]`), instance ids, camera-space depth (0 = none).
pub struct SynthView {
    pub rgb: Vec<f32>,
    pub ids: Vec<ObjectId>,
    pub depth: Vec<f32>,
}

/// Ray-casts view `cam` of `scene`: one ray through each pixel's centre.
pub fn render_view(cam: &Camera, scene: &SynthScene) -> SynthView {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let c2w = cam.world_to_cam.inverse();
    let eye = c2w.transform_point3(Vec3::ZERO);
    let bg = scene.background;
    let mut v = SynthView { rgb: bg.repeat(w * h), ids: vec![0; w * h], depth: vec![0.0; w * h] };
    for y in 0..h {
        for x in 0..w {
            let d = pixel_ray(cam, c2w, x as f32 + 0.5, y as f32 + 0.5);
            if let Some(hit) = trace(eye, d, scene) {
                let o = y * w + x;
                // `d` has unit camera-space z, so `t` is the camera-space depth.
                v.depth[o] = hit.t;
                v.ids[o] = hit.id;
                v.rgb[o * 3..o * 3 + 3].copy_from_slice(&shade(&hit, d, scene));
            }
        }
    }
    v
}

/// As [`render_view`], with the colour of every pixel on an edge between objects, the table and
/// the background (a 4-neighbour of another id) the mean of `s` x `s` rays spread over the
/// pixel, as a camera's pixel integrates its area; ids and depths stay those of the centre ray.
/// `s` = 1 is [`render_view`].
pub fn render_view_supersampled(cam: &Camera, scene: &SynthScene, s: usize) -> SynthView {
    let mut v = render_view(cam, scene);
    if s <= 1 {
        return v;
    }
    let (w, h) = (cam.width as usize, cam.height as usize);
    let c2w = cam.world_to_cam.inverse();
    let eye = c2w.transform_point3(Vec3::ZERO);
    let edge = |x: usize, y: usize| {
        let id = v.ids[y * w + x];
        (x > 0 && v.ids[y * w + x - 1] != id)
            || (x + 1 < w && v.ids[y * w + x + 1] != id)
            || (y > 0 && v.ids[(y - 1) * w + x] != id)
            || (y + 1 < h && v.ids[(y + 1) * w + x] != id)
    };
    let edges: Vec<usize> =
        (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).filter(|&(x, y)| edge(x, y)).map(|(x, y)| y * w + x).collect();
    let step = 1.0 / s as f32;
    for o in edges {
        let (x, y) = ((o % w) as f32, (o / w) as f32);
        let mut sum = [0f32; 3];
        for j in 0..s {
            for i in 0..s {
                let d = pixel_ray(cam, c2w, x + (i as f32 + 0.5) * step, y + (j as f32 + 0.5) * step);
                let c = trace(eye, d, scene).map_or(scene.background, |hit| shade(&hit, d, scene));
                (0..3).for_each(|k| sum[k] += c[k]);
            }
        }
        let n = (s * s) as f32;
        (0..3).for_each(|k| v.rgb[o * 3 + k] = sum[k] / n);
    }
    v
}

/// The world-space ray (unit camera-space z) through pixel position `(px, py)` of `cam`.
fn pixel_ray(cam: &Camera, c2w: Mat4, px: f32, py: f32) -> Vec3 {
    c2w.transform_vector3(Vec3::new((px - cam.cx) / cam.fx, (py - cam.cy) / cam.fy, 1.0))
}

/// The colour of `hit` seen along `d`: its albedo under the scene's light and an ambient term.
fn shade(hit: &Hit, d: Vec3, scene: &SynthScene) -> [f32; 3] {
    let n = if hit.normal.dot(d) > 0.0 { -hit.normal } else { hit.normal };
    let k = 0.35 + 0.65 * n.dot(scene.light).max(0.0);
    [hit.albedo[0] * k, hit.albedo[1] * k, hit.albedo[2] * k]
}
