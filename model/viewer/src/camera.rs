//! The camera contract between the page and chatsplat: a three.js `PerspectiveCamera` (position,
//! quaternion, vertical field of view; it looks down its -z axis with +y up, OpenGL's convention)
//! and the canvas size become the project's pinhole [`Camera`] (OpenCV: +z forward, +y down).
//!
//! `camera = {position: [x, y, z], quaternion: [x, y, z, w], fov: degrees, width, height}`, plus
//! optional exact intrinsics `fx, fy, cx, cy` (pixels): without them the principal point is the
//! image centre and `fx = fy = height / 2 / tan(fov / 2)`, as three.js projects. Every training
//! camera of the scene is listed in this form (`GET /api/scene`), intrinsics included, so a camera
//! sent back renders exactly the training view.

use crate::error::ApiError;
use glam::{Mat3, Mat4, Quat, Vec3};
use serde::{Deserialize, Serialize};
use splat_kernels::Camera;

/// Largest image side a request may ask for (the server renders it on the CPU).
pub const MAX_SIDE: u32 = 2048;
/// Smallest image side.
pub const MIN_SIDE: u32 = 8;
/// Vertical field of view limits, degrees.
pub const FOV_RANGE: (f32, f32) = (1.0, 170.0);

/// A camera as the page sends it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ViewCamera {
    pub position: [f32; 3],
    /// Camera-to-world rotation of the three.js camera, `[x, y, z, w]` (need not be normalised).
    pub quaternion: [f32; 4],
    /// Vertical field of view in degrees.
    pub fov: f32,
    pub width: u32,
    pub height: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fx: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fy: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cx: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cy: Option<f32>,
}

/// OpenGL camera axes (x right, y up, looking down -z) to OpenCV's (x right, y down, +z forward).
const GL_TO_CV: Mat3 = Mat3::from_cols(Vec3::X, Vec3::NEG_Y, Vec3::NEG_Z);

impl ViewCamera {
    /// The page form of `cam`, exact intrinsics included.
    pub fn from_camera(cam: &Camera) -> Self {
        let c2w = cam.world_to_cam.inverse();
        let rot_cv = Mat3::from_mat4(c2w);
        let q = Quat::from_mat3(&(rot_cv * GL_TO_CV)).normalize();
        let p = c2w.w_axis.truncate();
        Self {
            position: p.to_array(),
            quaternion: q.to_array(),
            fov: 2.0 * (0.5 * cam.height as f32 / cam.fy).atan().to_degrees(),
            width: cam.width,
            height: cam.height,
            fx: Some(cam.fx),
            fy: Some(cam.fy),
            cx: Some(cam.cx),
            cy: Some(cam.cy),
        }
    }

    /// The project's camera, or an error naming the field at fault (`what` names the request
    /// field holding this camera, e.g. `camera`).
    pub fn to_camera(&self, what: &str) -> Result<Camera, ApiError> {
        let bad = |field: &str, problem: String| ApiError::field(format!("{what}.{field}"), problem);
        if let Some(i) = self.position.iter().position(|v| !v.is_finite()) {
            return Err(bad("position", format!("component {i} is not a finite number")));
        }
        if let Some(i) = self.quaternion.iter().position(|v| !v.is_finite()) {
            return Err(bad("quaternion", format!("component {i} is not a finite number")));
        }
        let q = Quat::from_array(self.quaternion);
        let norm = q.length();
        if !(norm > 1e-6) {
            return Err(bad("quaternion", "has zero length".into()));
        }
        for (field, side) in [("width", self.width), ("height", self.height)] {
            if !(MIN_SIDE..=MAX_SIDE).contains(&side) {
                return Err(bad(field, format!("{side} is outside {MIN_SIDE}..={MAX_SIDE} pixels")));
            }
        }
        let (lo, hi) = FOV_RANGE;
        if !(self.fov.is_finite() && self.fov >= lo && self.fov <= hi) {
            return Err(bad("fov", format!("{} is outside {lo}..={hi} degrees", self.fov)));
        }
        let (w, h) = (self.width as f32, self.height as f32);
        let focal = 0.5 * h / (0.5 * self.fov.to_radians()).tan();
        let positive = |field: &str, v: Option<f32>, default: f32| match v {
            None => Ok(default),
            Some(v) if v.is_finite() && v > 0.0 && v < 1e6 => Ok(v),
            Some(v) => Err(bad(field, format!("{v} is not a focal length in pixels (0 < f < 1e6)"))),
        };
        let centre = |field: &str, v: Option<f32>, size: f32| match v {
            None => Ok(0.5 * size),
            Some(v) if v.is_finite() && (-size..=2.0 * size).contains(&v) => Ok(v),
            Some(v) => Err(bad(field, format!("{v} lies far outside the {size}-pixel image"))),
        };
        let rot_cv = Mat3::from_quat(q / norm) * GL_TO_CV;
        let p = Vec3::from_array(self.position);
        let rot = rot_cv.transpose();
        let t = -(rot * p);
        let w2c =
            Mat4::from_cols(rot.x_axis.extend(0.0), rot.y_axis.extend(0.0), rot.z_axis.extend(0.0), t.extend(1.0));
        let mut cam =
            Camera::new(w2c, positive("fx", self.fx, focal)?, positive("fy", self.fy, focal)?, self.width, self.height);
        cam.cx = centre("cx", self.cx, w)?;
        cam.cy = centre("cy", self.cy, h)?;
        Ok(cam)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_camera_survives_the_round_trip_and_three_js_conventions_hold() {
        let cam = Camera::look_at(Vec3::new(2.0, 1.5, -3.0), Vec3::new(0.1, 0.2, 0.0), Vec3::Y, 40.0, 120, 90);
        let back = ViewCamera::from_camera(&cam).to_camera("camera").unwrap();
        let (a, b) = (cam.world_to_cam.to_cols_array(), back.world_to_cam.to_cols_array());
        assert!(a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-5), "{a:?} vs {b:?}");
        assert_eq!((back.fx, back.fy, back.cx, back.cy), (cam.fx, cam.fy, cam.cx, cam.cy));
        // three.js: the identity quaternion looks down -z with +y up; a point ahead and above the
        // camera lands above the image centre (smaller y in OpenCV pixels)
        let v = ViewCamera {
            position: [0.0, 0.0, 5.0],
            quaternion: [0.0, 0.0, 0.0, 1.0],
            fov: 90.0,
            width: 100,
            height: 100,
            fx: None,
            fy: None,
            cx: None,
            cy: None,
        };
        let c = v.to_camera("camera").unwrap();
        let p = c.world_to_cam.transform_point3(Vec3::new(1.0, 1.0, 0.0));
        assert!((p.z - 5.0).abs() < 1e-5, "depth {}", p.z);
        let (x, y) = (c.fx * p.x / p.z + c.cx, c.fy * p.y / p.z + c.cy);
        assert!((x - 60.0).abs() < 1e-3 && (y - 40.0).abs() < 1e-3, "({x}, {y})");
        assert!((c.fy - 50.0).abs() < 1e-3);
    }

    #[test]
    fn bad_cameras_name_the_field() {
        let good = ViewCamera::from_camera(&Camera::look_at(Vec3::Z, Vec3::ZERO, Vec3::Y, 50.0, 64, 48));
        let err = |f: fn(&mut ViewCamera)| {
            let mut c = good;
            f(&mut c);
            c.to_camera("camera").unwrap_err().to_string()
        };
        assert!(err(|c| c.position[1] = f32::NAN).contains("camera.position"));
        assert!(err(|c| c.quaternion = [0.0; 4]).contains("zero length"));
        assert!(err(|c| c.fov = 0.0).contains("camera.fov"));
        assert!(err(|c| c.fov = 179.5).contains("camera.fov"));
        assert!(err(|c| c.width = 0).contains("camera.width"));
        assert!(err(|c| c.height = 100_000).contains("camera.height"));
        assert!(err(|c| c.fx = Some(f32::INFINITY)).contains("camera.fx"));
        assert!(err(|c| c.cy = Some(-1e9)).contains("camera.cy"));
    }
}
