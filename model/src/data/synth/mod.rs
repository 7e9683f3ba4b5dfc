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
//! Deterministic from the seed. One module owns the synthetic scene: [`scene`] (what a seed
//! places on the table), [`raycast`] (the analytic renderer), [`gaussians`] (the same scene as
//! 3D Gaussians, for `chatsplat render`) and [`questions`] (questions with reference answers).

pub mod gaussians;
pub mod questions;
pub mod raycast;
pub mod scene;

use crate::error::{Error, Result};
use crate::images;
use crate::io;
use glam::{Mat4, Vec3};
use raycast::render_view;
use scene::{Primitive, TABLE_HALF, table_color, tabletop_objects};
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
        Self { seed: 7, views: 48, width: 200, height: 200, fov_deg: 50.0 }
    }
}

/// Where the cameras look.
pub const LOOK_AT: Vec3 = Vec3::new(0.0, 0.3, 0.0);
/// Mask id of the table top; objects start at `FIRST_OBJECT_ID`.
pub const TABLE_ID: u8 = 1;
pub const FIRST_OBJECT_ID: u8 = 2;
/// Depth PNG unit: metres per count.
pub const DEPTH_SCALE: f32 = 0.001;

/// The camera of view `i` of `n` (OpenCV convention).
pub fn view_camera(i: usize, opts: &SynthOptions) -> Camera {
    let n = opts.views.max(1);
    let az = i as f32 / n as f32 * std::f32::consts::TAU + 0.3;
    let el: f32 = if i.is_multiple_of(2) { 25f32 } else { 45f32 }.to_radians();
    let radius = 4.6;
    let eye = LOOK_AT + Vec3::new(az.cos() * el.cos(), el.sin(), az.sin() * el.cos()) * radius;
    Camera::look_at(eye, LOOK_AT, Vec3::Y, opts.fov_deg, opts.width, opts.height)
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

/// Camera-to-world in the OpenGL convention (x right, y up, z backwards), row-major.
pub fn opengl_c2w(cam: &Camera) -> [[f32; 4]; 4] {
    let flip = Mat4::from_diagonal(glam::Vec4::new(1.0, -1.0, -1.0, 1.0));
    let m = cam.world_to_cam.inverse() * flip;
    let c = m.to_cols_array_2d();
    std::array::from_fn(|r| std::array::from_fn(|k| c[k][r]))
}

/// Writes the dataset to `dir`, calling `progress(done, total)` after each view.
pub fn write_dataset(dir: &Path, opts: &SynthOptions, mut progress: impl FnMut(usize, usize)) -> Result<()> {
    if opts.views == 0 || opts.width == 0 || opts.height == 0 {
        return Err(Error::input("synth: views, width and height must be positive"));
    }
    let objects = tabletop_objects(opts.seed);
    for sub in ["images", "masks", "depth"] {
        io::create_dir(&dir.join(sub))?;
    }
    let mut frames = vec![];
    let cam0 = view_camera(0, opts);
    // per object: (pixels, training-view index, pixel) of the view that shows it largest
    let mut best: Vec<(usize, usize, [usize; 2])> = vec![(0, 0, [0, 0]); objects.len()];
    let holdout = super::LoadOptions::default().holdout_every;
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
    io::write_json(&dir.join("transforms.json"), &tf)?;
    io::write_json(&dir.join("questions.json"), &questions::questions(&objects, &best))?;
    io::write_json(&dir.join("scene.json"), &scene)
}
