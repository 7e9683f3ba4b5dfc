//! COLMAP, LLFF and Replica loaders and `load_any`: every test writes its own tiny fixture (8x6
//! images, hand-encoded .bin / .npy files) and checks geometry against independently computed
//! projections, plus the error messages for malformed inputs.
//!
//! One file per format ([`colmap`], [`llff`], [`replica`]) and [`any`] (format detection, masks
//! from other tools, the teacher stage on every format); the helpers they share are here.

mod any;
mod colmap;
mod llff;
mod replica;

pub(crate) use colmap::colmap_dir;
pub(crate) use llff::llff_dir;
pub(crate) use replica::replica_dir;

use chatsplat_tests::{Scratch, temp_dir};
use glam::Vec3;
use model::data::{LoadOptions, load_any};
use model::images::{write_gray8, write_gray16, write_rgb};
use splat_kernels::Camera;
use std::path::Path;

const W: u32 = 8;
const H: u32 = 6;

fn opts(downscale: u32, holdout_every: usize) -> LoadOptions {
    LoadOptions { downscale, holdout_every, ..Default::default() }
}

/// Pixel position of world point `p` through the loaded camera (`u = fx * x / z + cx`).
fn project(c: &Camera, p: [f64; 3]) -> (f32, f32) {
    let q = c.world_to_cam.transform_point3(Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32));
    assert!(q.z > 0.0, "point behind the camera");
    (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy)
}

/// World-space camera axes (right, down, forward) and centre.
fn axes(c: &Camera) -> [Vec3; 4] {
    let c2w = c.world_to_cam.inverse();
    [
        c2w.transform_vector3(Vec3::X),
        c2w.transform_vector3(Vec3::Y),
        c2w.transform_vector3(Vec3::Z),
        c2w.transform_point3(Vec3::ZERO),
    ]
}

fn close3(a: Vec3, b: [f32; 3], tol: f32) -> bool {
    (a - Vec3::from_array(b)).abs().max_element() < tol
}

fn names(views: &[model::data::View]) -> Vec<String> {
    views.iter().map(|v| v.image_path.file_name().unwrap().to_string_lossy().into_owned()).collect()
}

fn expect_err<T: std::fmt::Debug>(r: model::Result<T>, needles: &[&str]) -> String {
    let e = r.expect_err("expected an error").to_string();
    for n in needles {
        assert!(e.contains(n), "expected `{n}` in: {e}");
    }
    e
}

/// An 8x6 image whose pixel (x, y) is `(x / 7, y / 5, tag)`.
fn gradient(tag: f32, w: u32, h: u32) -> Vec<f32> {
    (0..h).flat_map(|y| (0..w).flat_map(move |x| [x as f32 / 7.0, y as f32 / 5.0, tag])).collect()
}

fn q8(v: f32) -> f32 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5).floor() / 255.0
}
