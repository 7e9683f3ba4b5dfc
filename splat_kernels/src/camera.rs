//! Pinhole camera in the OpenCV convention (x right, y down, z forward).

use crate::constants::{DEFAULT_FAR, DEFAULT_NEAR, FRUSTUM_CLAMP};
use glam::{Mat3, Mat4, Vec3};

/// A pinhole camera.
///
/// * `world_to_cam` maps world points to camera space: `p_cam = R p + t`, with the camera looking
///   down +z, x to the right and y down (OpenCV). Data loaders convert OpenGL/Blender poses.
/// * Pixel `(x, y)` covers `[x, x+1) x [y, y+1)`; its centre is `(x + 0.5, y + 0.5)`; a camera-space
///   point projects to `(fx * X/Z + cx, fy * Y/Z + cy)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub world_to_cam: Mat4,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
    pub near: f32,
    pub far: f32,
}

impl Camera {
    /// A camera with the principal point at the image centre and default near/far planes.
    pub fn new(world_to_cam: Mat4, fx: f32, fy: f32, width: u32, height: u32) -> Self {
        Self {
            world_to_cam,
            fx,
            fy,
            cx: width as f32 * 0.5,
            cy: height as f32 * 0.5,
            width,
            height,
            near: DEFAULT_NEAR,
            far: DEFAULT_FAR,
        }
    }

    /// A camera at `eye` looking at `target` (world up is -y in OpenCV terms: `up` is the world
    /// direction that should appear at the top of the image).
    pub fn look_at(eye: Vec3, target: Vec3, up: Vec3, fov_y_deg: f32, width: u32, height: u32) -> Self {
        let f = (target - eye).normalize();
        let r = f.cross(up).normalize();
        let d = f.cross(r); // image "down"
        // Rows of the world->camera rotation are the camera axes in world coordinates.
        let rot = Mat3::from_cols(r, d, f).transpose();
        let t = -(rot * eye);
        let w2c =
            Mat4::from_cols(rot.x_axis.extend(0.0), rot.y_axis.extend(0.0), rot.z_axis.extend(0.0), t.extend(1.0));
        let fy = 0.5 * height as f32 / (0.5 * fov_y_deg.to_radians()).tan();
        Self::new(w2c, fy, fy, width, height)
    }

    /// Rotation part of `world_to_cam` as a row-major 3x3 array.
    pub fn rotation_rows(&self) -> [[f32; 3]; 3] {
        let m = self.world_to_cam;
        [
            [m.x_axis.x, m.y_axis.x, m.z_axis.x],
            [m.x_axis.y, m.y_axis.y, m.z_axis.y],
            [m.x_axis.z, m.y_axis.z, m.z_axis.z],
        ]
    }

    /// Translation part of `world_to_cam`.
    pub fn translation(&self) -> [f32; 3] {
        let t = self.world_to_cam.w_axis;
        [t.x, t.y, t.z]
    }

    /// Limits of the Jacobian clamp: `FRUSTUM_CLAMP * tan(fov/2)` in x and y.
    pub fn clamp_limits(&self) -> [f32; 2] {
        [FRUSTUM_CLAMP * 0.5 * self.width as f32 / self.fx, FRUSTUM_CLAMP * 0.5 * self.height as f32 / self.fy]
    }

    /// Number of tiles in x and y.
    pub fn tiles(&self) -> [u32; 2] {
        let t = crate::constants::TILE_SIZE;
        [self.width.div_ceil(t), self.height.div_ceil(t)]
    }

    /// Checks the intrinsics; every op calls this before doing any work.
    pub fn validate(&self) -> Result<(), crate::error::SplatError> {
        let bad = |what: String| Err(crate::error::SplatError::InvalidCamera(what));
        if self.width == 0 || self.height == 0 {
            return bad(format!("image size {}x{} must be at least 1x1", self.width, self.height));
        }
        if self.width > 16384 || self.height > 16384 {
            return bad(format!("image size {}x{} exceeds 16384", self.width, self.height));
        }
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("{name} = {v} must be finite and positive"));
            }
        }
        for (name, v) in [("cx", self.cx), ("cy", self.cy)] {
            if !v.is_finite() {
                return bad(format!("{name} = {v} must be finite"));
            }
        }
        if !(self.near.is_finite() && self.near > 0.0 && self.far > self.near) {
            return bad(format!("near = {} and far = {} must satisfy 0 < near < far", self.near, self.far));
        }
        if !self.world_to_cam.is_finite() {
            return bad("world_to_cam has a non-finite entry".into());
        }
        Ok(())
    }
}
