//! `chatsplat synth`: a synthetic tabletop (from a seed: 1-6 objects of 6 shapes x 8 colours x
//! 2 sizes on a varied table and background) rendered analytically (ray casting) from cameras
//! around it, written as a nerfstudio-style dataset:
//!
//! ```text
//! DIR/transforms.json        fl_x, fl_y, cx, cy, w, h, camera_model, depth_unit_scale_factor,
//!                            frames[{file_path, transform_matrix (camera-to-world, OpenGL),
//!                                    instance_mask_path, depth_file_path}]
//! DIR/images/frame_XXXX.png  RGB over the scene's background
//! DIR/masks/frame_XXXX.png   8-bit instance ids: 0 background, 1 table, 2.. objects
//! DIR/depth/frame_XXXX.png   16-bit camera-space depth in millimetres (0 = no surface)
//! DIR/scene.json             the scene: table, background, light, every object's id, shape,
//!                            colour, size, position, scale and yaw
//! DIR/questions.json         questions with reference answers for `chatsplat vqa`: view and
//!                            object level on the held-out views (novel views), scene level on
//!                            training views that together see every object, and phrases to
//!                            find (each colour, shape and name, present and absent)
//! ```
//!
//! Deterministic from the seed. One module owns the synthetic scene: [`scene`] (what a seed
//! places on the table), [`raycast`] (the analytic renderer), [`gaussians`] (the same scene as
//! 3D Gaussians, for `chatsplat render`) and [`questions`] (questions with answers true by
//! construction).

pub mod forms;
pub mod gaussians;
pub mod questions;
pub mod raycast;
pub mod scene;

use crate::ObjectId;
use crate::error::{Error, Result};
use crate::images;
use crate::io;
use crate::question_file::{Level, Question, QuestionFile};
use base::rng::Rng;
use glam::{Mat4, Vec3};
use questions::{
    CLICK_FRACTION, FollowUp, ViewFacts, covering_views, find_queries, object_follow_ups, object_questions,
    scene_questions, view_follow_ups, view_questions,
};
use raycast::render_view;
use scene::SynthScene;
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
        Self { seed: DEFAULT_SEED, views: 48, width: 96, height: 96, fov_deg: FOV_DEG }
    }
}

/// The seed of the demo's scene.
pub const DEFAULT_SEED: u64 = 46;
/// Largest image side `synth` writes.
pub const MAX_SIDE: u32 = 4096;
pub use crate::question_file::SCENE_VIEWS;
/// Where the cameras look.
pub const LOOK_AT: Vec3 = Vec3::new(0.0, 0.25, 0.0);
/// Vertical field of view of every synthetic camera (degrees): narrow enough that the objects
/// fill the frame, wide enough that every object on the table is in it from every orbit camera.
pub const FOV_DEG: f32 = 40.0;
/// Distance of the dataset cameras from [`LOOK_AT`].
pub const CAMERA_DISTANCE: f32 = 3.4;
/// Mask id of the table top; objects start at `FIRST_OBJECT_ID`.
pub const TABLE_ID: ObjectId = 1;
pub const FIRST_OBJECT_ID: ObjectId = 2;
/// Depth PNG unit: metres per count.
pub const DEPTH_SCALE: f32 = 0.001;

/// The camera of view `i` of `n` (OpenCV convention).
pub fn view_camera(i: usize, opts: &SynthOptions) -> Camera {
    let n = opts.views.max(1);
    let az = i as f32 / n as f32 * std::f32::consts::TAU + 0.3;
    let el: f32 = if i.is_multiple_of(2) { 25f32 } else { 45f32 }.to_radians();
    orbit_camera(az, el, CAMERA_DISTANCE, LOOK_AT, opts.fov_deg, opts.width, opts.height)
}

/// A camera at azimuth `az` and elevation `el` (radians), `distance` from `target`, looking at it.
pub fn orbit_camera(az: f32, el: f32, distance: f32, target: Vec3, fov_deg: f32, width: u32, height: u32) -> Camera {
    let eye = target + Vec3::new(az.cos() * el.cos(), el.sin(), az.sin() * el.cos()) * distance;
    Camera::look_at(eye, target, Vec3::Y, fov_deg, width, height)
}

/// A random camera around a scene (VLM training data): azimuth anywhere, elevation 20-50°,
/// about [`CAMERA_DISTANCE`] away, the target jittered around [`LOOK_AT`].
pub fn random_camera(rng: &mut Rng, fov_deg: f32, width: u32, height: u32) -> Camera {
    let az = rng.range(0.0, std::f32::consts::TAU);
    let el = rng.range(20.0f32, 50.0).to_radians();
    let target = LOOK_AT + Vec3::new(rng.range(-0.1, 0.1), rng.range(-0.05, 0.05), rng.range(-0.1, 0.1));
    let d = CAMERA_DISTANCE * rng.range(0.97, 1.03);
    orbit_camera(az, el, d, target, fov_deg, width, height)
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

/// Camera-to-world in the OpenGL convention (x right, y up, z backwards), row-major.
pub fn opengl_c2w(cam: &Camera) -> [[f32; 4]; 4] {
    let flip = Mat4::from_diagonal(glam::Vec4::new(1.0, -1.0, -1.0, 1.0));
    let m = cam.world_to_cam.inverse() * flip;
    let c = m.to_cols_array_2d();
    std::array::from_fn(|r| std::array::from_fn(|k| c[k][r]))
}

/// Whether frame `i` is held out by the loaders' default split (every 8th view).
pub fn held_out(i: usize) -> bool {
    let every = super::LoadOptions::default().holdout_every;
    every > 0 && i % every == every - 1
}

/// The pixel of object `id` deepest inside its mask: the largest city-block distance to a pixel
/// of another id or to the image border (first in reading order among equals). A click there
/// still lands on the object when a reconstruction's identity map is a pixel or two off at the
/// edges, where a centroid of a ring, a cone seen edge-on or a partly hidden object may not be
/// on the object at all. `ids` `[H, W]` row-major.
pub fn click_pixel(ids: &[ObjectId], width: usize, id: ObjectId) -> Option<[usize; 2]> {
    if width == 0 {
        return None;
    }
    let height = ids.len() / width;
    // two-pass distance transform: d = 1 on the mask's outer pixels, growing inwards
    let mut d: Vec<u32> = ids.iter().map(|&v| if v == id { u32::MAX } else { 0 }).collect();
    let at = |d: &[u32], x: isize, y: isize| -> u32 {
        if x < 0 || y < 0 || x >= width as isize || y >= height as isize {
            0
        } else {
            d[y as usize * width + x as usize]
        }
    };
    for y in 0..height as isize {
        for x in 0..width as isize {
            let i = y as usize * width + x as usize;
            if d[i] > 0 {
                d[i] = d[i].min(at(&d, x - 1, y) + 1).min(at(&d, x, y - 1) + 1); // finite: left and up came first
            }
        }
    }
    for y in (0..height as isize).rev() {
        for x in (0..width as isize).rev() {
            let i = y as usize * width + x as usize;
            if d[i] > 0 {
                d[i] = d[i].min(at(&d, x + 1, y) + 1).min(at(&d, x, y + 1) + 1);
            }
        }
    }
    let (best, depth) = d.iter().enumerate().fold((0, 0), |(b, bd), (i, &v)| if v > bd { (i, v) } else { (b, bd) });
    (depth > 0).then_some([best % width, best / width])
}

/// Writes the dataset to `dir`, calling `progress(done, total)` after each view.
pub fn write_dataset(dir: &Path, opts: &SynthOptions, mut progress: impl FnMut(usize, usize)) -> Result<()> {
    if opts.views == 0 || opts.width == 0 || opts.height == 0 {
        return Err(Error::input("synth: views, width and height must be positive"));
    }
    for (name, v, max) in
        [("width", opts.width, MAX_SIDE), ("height", opts.height, MAX_SIDE), ("views", opts.views as u32, 10_000)]
    {
        if v > max {
            return Err(Error::input(format!("synth: --{name} {v} is out of range (at most {max})")));
        }
    }
    // a folder the user had: only an earlier synthetic tabletop is written over
    let holds_something = std::fs::read_dir(dir).is_ok_and(|mut d| d.next().is_some());
    if holds_something && io::read_json::<SynthScene>(&dir.join("scene.json")).is_err() {
        return Err(Error::invalid(
            dir,
            "holds files and is not a synthetic tabletop (`chatsplat synth` writes scene.json): nothing was \
             written over it; give a new or empty --out",
        ));
    }
    let scene = SynthScene::from_seed(opts.seed);
    for sub in ["images", "masks", "depth"] {
        io::create_dir(&dir.join(sub))?;
    }
    let (w, h) = (opts.width as usize, opts.height as usize);
    let mut frames = vec![];
    let mut facts = vec![];
    let mut clicks = vec![];
    let cam0 = view_camera(0, opts);
    for i in 0..opts.views {
        let cam = view_camera(i, opts);
        let v = render_view(&cam, &scene);
        let f = ViewFacts::of(&scene, &v.ids, &v.depth, w, h);
        let area = (w * h) as f32;
        let big: Vec<(ObjectId, [usize; 2])> = f
            .seen
            .iter()
            .filter(|s| s.pixels as f32 >= CLICK_FRACTION * area)
            .filter_map(|s| click_pixel(&v.ids, w, s.id).map(|p| (s.id, p)))
            .collect();
        facts.push(f);
        clicks.push(big);
        let name = format!("frame_{i:04}.png");
        images::write_rgb(&dir.join("images").join(&name), cam.width, cam.height, &v.rgb)?;
        images::write_ids(&dir.join("masks").join(&name), cam.width, cam.height, &v.ids)?;
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
    let qf = question_file(&scene, &facts, &clicks, &tf.frames.iter().map(|f| f.file_path.clone()).collect::<Vec<_>>());
    io::write_json(&dir.join("transforms.json"), &tf)?;
    io::write_json(&dir.join("questions.json"), &qf)?;
    io::write_json(&dir.join("scene.json"), &scene)
}

/// The dataset's question file: view- and object-level questions on the held-out views, scene-level
/// questions on training views that together see every object (`views` index the frames).
fn question_file(
    scene: &SynthScene,
    facts: &[ViewFacts],
    clicks: &[Vec<(ObjectId, [usize; 2])>],
    frames: &[String],
) -> QuestionFile {
    let mut rng = Rng::new(scene.seed ^ 0x0935_7105);
    let mut qs = Vec::new();
    let q =
        |id: String, qa: &questions::Qa, view: Option<usize>, object: Option<[f32; 2]>, views: Option<Vec<usize>>| {
            Question {
                id,
                level: qa.kind.level(),
                kind: Some(qa.kind.as_str().to_string()),
                view,
                object,
                views,
                question: qa.question.clone(),
                answer: qa.answer.clone(),
                keywords: vec![],
                items: qa.items(),
                objects: None,
                follows: None,
                spelled: None,
            }
        };
    // a follow-up goes on the conversation of the question it follows (its id `first`)
    let follow_up = |f: &FollowUp, first: &Question, twin: &str| Question {
        id: format!("{twin}-{}", f.kind),
        kind: Some(f.kind.to_string()),
        question: f.question.clone(),
        answer: f.answer.clone(),
        follows: Some(first.id.clone()),
        spelled: Some(twin.to_string()),
        ..first.clone()
    };
    let mut follow_ups = Vec::new();
    for (i, f) in facts.iter().enumerate().filter(|(i, _)| held_out(*i)) {
        let at = qs.len();
        let view_qas = view_questions(scene, f, &mut rng);
        for (n, qa) in view_qas.iter().enumerate() {
            qs.push(q(format!("v{i}-{n}-{}", qa.kind.as_str()), qa, Some(i), None, None));
        }
        for fu in view_follow_ups(&view_qas) {
            follow_ups.push(follow_up(&fu, &qs[at + fu.first], &qs[at + fu.twin].id));
        }
        if f.ambiguous {
            continue;
        }
        for &(id, [x, y]) in &clicks[i] {
            let o = scene.object(id).expect("clicked objects exist");
            let (at, object_qas) = (qs.len(), object_questions(o));
            for qa in &object_qas {
                let click = Some([x as f32, y as f32]);
                qs.push(q(format!("o{i}-{id}-{}", qa.kind.as_str()), qa, Some(i), click, None));
            }
            for fu in object_follow_ups(&object_qas) {
                follow_ups.push(follow_up(&fu, &qs[at + fu.first], &qs[at + fu.twin].id));
            }
        }
    }
    let train: Vec<usize> = (0..facts.len()).filter(|&i| !held_out(i)).collect();
    let train_facts: Vec<ViewFacts> = train.iter().map(|&i| facts[i].clone()).collect();
    if let Some(chosen) = covering_views(scene, &train_facts, SCENE_VIEWS.min(train.len())) {
        let views: Vec<usize> = chosen.iter().map(|&k| train[k]).collect();
        for (n, qa) in scene_questions(scene).iter().enumerate() {
            qs.push(q(format!("s-{n}-{}", qa.kind.as_str()), qa, None, None, Some(views.clone())));
        }
    }
    // follow-ups after the questions asked on their own (which stay those of earlier datasets)
    qs.extend(follow_ups);
    // find: its own draws, so the questions above stay those of earlier datasets
    let mut rng = Rng::new(scene.seed ^ 0x0f1d_0f1d);
    for (n, f) in find_queries(scene, &mut rng).into_iter().enumerate() {
        let names: Vec<String> = f.objects.iter().filter_map(|&id| scene.object(id)).map(|o| o.name()).collect();
        qs.push(Question {
            id: format!("f-{n}-{}", f.kind),
            level: Level::Find,
            kind: Some(f.kind),
            view: None,
            object: None,
            views: None,
            question: f.phrase,
            answer: if names.is_empty() { "none".into() } else { names.join(" ") },
            keywords: vec![],
            items: None,
            objects: Some(f.objects),
            follows: None,
            spelled: None,
        });
    }
    QuestionFile {
        scene: Some(format!("synthetic tabletop, seed {}", scene.seed)),
        views: Some(frames.to_vec()),
        questions: qs,
    }
}
