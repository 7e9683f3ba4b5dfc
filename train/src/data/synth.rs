//! `chatsplat synth`: the built-in synthetic tabletop rendered analytically (ray casting) from
//! cameras around it, written as a nerfstudio-style dataset:
//!
//! ```text
//! DIR/transforms.json        fl_x, fl_y, cx, cy, w, h, camera_model, depth_unit_scale_factor,
//!                            frames[{file_path, transform_matrix (camera-to-world, OpenGL),
//!                                    instance_mask_path, depth_file_path}]
//! DIR/images/frame_XXXX.png  RGB, white background
//! DIR/masks/frame_XXXX.png   8-bit instance ids: 0 background, 1 table, 2.. objects
//! DIR/depth/frame_XXXX.png   16-bit camera-space depth in millimetres (0 = no surface)
//! DIR/scene.json             every object's id, name, shape, colour, position and size
//! DIR/questions.json         questions with reference answers for `chatsplat vqa` (view, object
//!                            and scene level; object questions click a pixel of a training view)
//! ```
//!
//! Deterministic from the seed; the objects are the same as the Gaussian tabletop of
//! `model::synthetic`, so both describe one scene.

use glam::{Mat4, Vec3};
use model::images;
use model::synthetic::{Primitive, TABLE_HALF, table_color, tabletop_objects};
use serde::Serialize;
use splat_kernels::Camera;
use std::path::Path;

/// Options of the generator.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    pub seed: u64,
    pub views: usize,
    pub width: u32,
    pub height: u32,
    /// Vertical field of view in degrees.
    pub fov_deg: f32,
}

impl Default for SynthOptions {
    fn default() -> Self {
        Self {
            seed: 7,
            views: 48,
            width: 200,
            height: 200,
            fov_deg: 50.0,
        }
    }
}

/// Where the cameras look.
pub const LOOK_AT: Vec3 = Vec3::new(0.0, 0.3, 0.0);
/// Mask id of the table top; objects start at `FIRST_OBJECT_ID`.
pub const TABLE_ID: u8 = 1;
pub const FIRST_OBJECT_ID: u8 = 2;
/// Depth PNG unit: metres per count.
pub const DEPTH_SCALE: f32 = 0.001;

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
    let hit = |t: f32, normal: Vec3| Hit {
        t,
        normal: normal.normalize(),
        id,
        albedo: p.color,
    };
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
            closer(
                &mut best,
                Hit {
                    t,
                    normal: Vec3::Y * o.y.signum(),
                    id: TABLE_ID,
                    albedo: table_color(q.x, q.z),
                },
            );
        }
    }
    for (k, p) in objects.iter().enumerate() {
        intersect(o, d, p, FIRST_OBJECT_ID + k as u8, &mut best);
    }
    best
}

/// The camera of view `i` of `n` (OpenCV convention).
pub fn view_camera(i: usize, opts: &SynthOptions) -> Camera {
    let n = opts.views.max(1);
    let az = i as f32 / n as f32 * std::f32::consts::TAU + 0.3;
    let el: f32 = if i % 2 == 0 { 25f32 } else { 45f32 }.to_radians();
    let radius = 4.6;
    let eye = LOOK_AT + Vec3::new(az.cos() * el.cos(), el.sin(), az.sin() * el.cos()) * radius;
    Camera::look_at(eye, LOOK_AT, Vec3::Y, opts.fov_deg, opts.width, opts.height)
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
    let mut v = SynthView {
        rgb: vec![1.0; w * h * 3],
        ids: vec![0; w * h],
        depth: vec![0.0; w * h],
    };
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

#[derive(Serialize)]
struct Frame {
    file_path: String,
    transform_matrix: [[f32; 4]; 4],
    instance_mask_path: String,
    depth_file_path: String,
}

#[derive(Serialize)]
struct Transforms {
    camera_model: &'static str,
    fl_x: f32,
    fl_y: f32,
    cx: f32,
    cy: f32,
    w: u32,
    h: u32,
    depth_unit_scale_factor: f32,
    frames: Vec<Frame>,
}

#[derive(Serialize)]
struct ObjectEntry {
    id: u8,
    name: String,
    shape: String,
    color: [f32; 3],
    position: [f32; 3],
    size: f32,
}

#[derive(Serialize)]
struct SceneJson {
    seed: u64,
    up: [f32; 3],
    table: ObjectEntry,
    objects: Vec<ObjectEntry>,
}

/// "red ball" -> "ball".
fn noun(name: &str) -> &str {
    name.split_whitespace().last().unwrap_or(name)
}

/// Questions with reference answers about the scene (the `chatsplat vqa` format).
fn questions(objects: &[Primitive], best: &[(usize, usize, [usize; 2])]) -> serde_json::Value {
    let mut qs = vec![
        serde_json::json!({"id": "view-count", "level": "view", "view": 0, "question": "How many objects are on the table?",
            "answer": format!("{}", objects.len()), "keywords": [format!("{}", objects.len())]}),
        serde_json::json!({"id": "scene-objects", "level": "scene", "question": "List the objects on the table.",
            "answer": objects.iter().map(|o| o.name).collect::<Vec<_>>().join(", "),
            "keywords": objects.iter().map(|o| noun(o.name)).collect::<Vec<_>>()}),
    ];
    for (k, (o, &(pixels, view, [x, y]))) in objects.iter().zip(best).enumerate() {
        if pixels == 0 {
            continue;
        }
        let colour = o.name.split_whitespace().next().unwrap_or("");
        qs.push(serde_json::json!({"id": format!("object-{k}-what"), "level": "object", "view": view, "object": [x, y],
            "question": "What is this object?", "answer": o.name, "keywords": [noun(o.name)]}));
        qs.push(serde_json::json!({"id": format!("object-{k}-colour"), "level": "object", "view": view, "object": [x, y],
            "question": "What colour is this object?", "answer": colour, "keywords": [colour]}));
    }
    serde_json::json!({"scene": "chatsplat synthetic tabletop", "questions": qs})
}

/// Camera-to-world in the OpenGL convention (x right, y up, z backwards), row-major.
pub fn opengl_c2w(cam: &Camera) -> [[f32; 4]; 4] {
    let flip = Mat4::from_diagonal(glam::Vec4::new(1.0, -1.0, -1.0, 1.0));
    let m = cam.world_to_cam.inverse() * flip;
    let c = m.to_cols_array_2d();
    std::array::from_fn(|r| std::array::from_fn(|k| c[k][r]))
}

/// Writes the dataset to `dir`, calling `progress(done, total)` after each view.
pub fn write_dataset(dir: &Path, opts: &SynthOptions, mut progress: impl FnMut(usize, usize)) -> Result<(), String> {
    if opts.views == 0 || opts.width == 0 || opts.height == 0 {
        return Err("synth: views, width and height must be positive".into());
    }
    let objects = tabletop_objects(opts.seed);
    for sub in ["images", "masks", "depth"] {
        std::fs::create_dir_all(dir.join(sub)).map_err(|e| format!("{}: cannot create: {e}", dir.join(sub).display()))?;
    }
    let mut frames = vec![];
    let cam0 = view_camera(0, opts);
    // per object: (pixels, training-view index, pixel) of the view that shows it largest
    let mut best: Vec<(usize, usize, [usize; 2])> = vec![(0, 0, [0, 0]); objects.len()];
    let holdout = crate::data::LoadOptions::default().holdout_every;
    let mut train_index = 0;
    for i in 0..opts.views {
        let cam = view_camera(i, opts);
        let v = render_view(&cam, &objects);
        if holdout == 0 || (i + 1) % holdout != 0 {
            for (k, b) in best.iter_mut().enumerate() {
                let id = FIRST_OBJECT_ID + k as u8;
                let px: Vec<usize> = (0..v.ids.len()).filter(|&p| v.ids[p] == id).collect();
                if px.len() > b.0 {
                    let p = px[px.len() / 2];
                    *b = (px.len(), train_index, [p % cam.width as usize, p / cam.width as usize]);
                }
            }
            train_index += 1;
        }
        let name = format!("frame_{i:04}.png");
        images::write_rgb(&dir.join("images").join(&name), cam.width, cam.height, &v.rgb)?;
        images::write_gray8(&dir.join("masks").join(&name), cam.width, cam.height, &v.ids)?;
        let mm: Vec<u16> = v.depth.iter().map(|&d| (d / DEPTH_SCALE).round().clamp(0.0, 65535.0) as u16).collect();
        images::write_gray16(&dir.join("depth").join(&name), cam.width, cam.height, &mm)?;
        frames.push(Frame {
            file_path: format!("images/{name}"),
            transform_matrix: opengl_c2w(&cam),
            instance_mask_path: format!("masks/{name}"),
            depth_file_path: format!("depth/{name}"),
        });
        progress(i + 1, opts.views);
    }
    let tf = Transforms {
        camera_model: "OPENCV",
        fl_x: cam0.fx,
        fl_y: cam0.fy,
        cx: cam0.cx,
        cy: cam0.cy,
        w: cam0.width,
        h: cam0.height,
        depth_unit_scale_factor: DEPTH_SCALE,
        frames,
    };
    let entry = |id: u8, p: &Primitive| ObjectEntry {
        id,
        name: p.name.to_string(),
        shape: p.shape.to_string(),
        color: p.color,
        position: p.center.into(),
        size: p.size,
    };
    let scene = SceneJson {
        seed: opts.seed,
        up: [0.0, 1.0, 0.0],
        table: ObjectEntry {
            id: TABLE_ID,
            name: "wooden table".into(),
            shape: "square slab".into(),
            color: table_color(0.0, 0.0),
            position: [0.0; 3],
            size: 2.0 * TABLE_HALF,
        },
        objects: objects.iter().enumerate().map(|(k, p)| entry(FIRST_OBJECT_ID + k as u8, p)).collect(),
    };
    write_json(&dir.join("transforms.json"), &tf)?;
    write_json(&dir.join("questions.json"), &questions(&objects, &best))?;
    write_json(&dir.join("scene.json"), &scene)
}

fn write_json<T: Serialize>(path: &Path, v: &T) -> Result<(), String> {
    let text = serde_json::to_string_pretty(v).map_err(|e| format!("{}: {e}", path.display()))?;
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, text).map_err(|e| format!("{}: cannot write: {e}", path.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| format!("{}: cannot write: {e}", path.display()))
}
