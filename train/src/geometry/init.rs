//! Where a geometry run starts: the scene's extent from its cameras and the initial Gaussians
//! (sparse SfM points, back-projected depth, or random points around what the cameras look at).

use super::GeometryConfig;
use model::GaussianCloud;
use model::data::View;
use model::data::colmap::SparsePoints;
use model::rng::Rng;
use model::run::Extent;
use splat_kernels::Camera;

/// Scene bounds used for initialisation and densification.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneExtent {
    /// Mean of the camera centres.
    pub center: glam::Vec3,
    /// 1.1 x the largest camera distance from `center` (3DGS's `cameras_extent`): scales the
    /// means' learning rate and the clone/split size threshold.
    pub radius: f32,
    /// The point closest (least squares) to every camera's optical axis: what they look at.
    pub focus: glam::Vec3,
}

impl SceneExtent {
    pub fn from_cameras(cams: &[&Camera]) -> Self {
        let centers: Vec<glam::Vec3> = cams.iter().map(|c| c.world_to_cam.inverse().w_axis.truncate()).collect();
        let mean = centers.iter().fold(glam::Vec3::ZERO, |a, b| a + *b) / centers.len().max(1) as f32;
        let r = centers.iter().map(|c| (*c - mean).length()).fold(0.0f32, f32::max);
        // Least-squares point nearest to all optical axes: sum (I - d d^T) p = sum (I - d d^T) c.
        let (mut a, mut b) = (glam::DMat3::ZERO, glam::DVec3::ZERO);
        for (cam, c) in cams.iter().zip(&centers) {
            let d = cam.world_to_cam.inverse().z_axis.truncate().normalize().as_dvec3();
            let m = glam::DMat3::IDENTITY - glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z);
            a += m;
            b += m * c.as_dvec3();
        }
        let focus = if a.determinant().abs() > 1e-6 { (a.inverse() * b).as_vec3() } else { mean };
        let focus = if focus.is_finite() { focus } else { mean };
        Self { center: mean, radius: (1.1 * r).max(1e-3), focus }
    }

    /// As stored in a run's state.
    pub fn stored(&self) -> Extent {
        Extent { center: self.center.to_array(), radius: self.radius, focus: self.focus.to_array() }
    }

    pub fn from_stored(e: &Extent) -> Self {
        Self { center: e.center.into(), radius: e.radius, focus: e.focus.into() }
    }
}

pub(crate) fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// Initial Gaussians: the sparse SfM points when given (COLMAP), else back-projected depth pixels
/// when the views have depth, else `cfg.init_points`
/// random points in a box around the cameras' look-at region with random colours.
pub fn initial_cloud(
    views: &[View],
    points: Option<&SparsePoints>,
    extent: &SceneExtent,
    cfg: &GeometryConfig,
) -> GaussianCloud {
    let mut rng = Rng::new(cfg.seed ^ 0x1517);
    let mut cloud = GaussianCloud::default();
    let push = |p: glam::Vec3, rgb: [f32; 3], cloud: &mut GaussianCloud| {
        cloud.means.push(p.to_array());
        cloud.sh_dc.push(rgb.map(|c| (c - 0.5) / model::cloud::SH_C0));
    };
    let with_depth = views.iter().any(|v| v.depth.is_some());
    if let Some(sp) = points.filter(|p| !p.xyz.is_empty()) {
        for (p, c) in sp.xyz.iter().zip(&sp.rgb) {
            push(glam::Vec3::from(*p), c.map(|v| v as f32 / 255.0), &mut cloud);
        }
    } else if with_depth {
        for v in views {
            let Some(depth) = &v.depth else { continue };
            let c = &v.camera;
            let c2w = c.world_to_cam.inverse();
            let (w, h) = (c.width as usize, c.height as usize);
            for _ in 0..cfg.init_per_view {
                let x = (rng.f() * w as f32) as usize % w;
                let y = (rng.f() * h as f32) as usize % h;
                let d = depth[y * w + x];
                if d <= 0.0 {
                    continue;
                }
                let pc = glam::Vec3::new((x as f32 + 0.5 - c.cx) / c.fx * d, (y as f32 + 0.5 - c.cy) / c.fy * d, d);
                let p = c2w.transform_point3(pc);
                let o = (y * w + x) * 3;
                push(p, [v.rgb[o], v.rgb[o + 1], v.rgb[o + 2]], &mut cloud);
            }
        }
    }
    if cloud.means.is_empty() {
        // A box around what the cameras look at; the content sits well inside their ring.
        let half = extent.radius * 0.35;
        for _ in 0..cfg.init_points {
            let p =
                extent.focus + glam::Vec3::new(rng.range(-half, half), rng.range(-half, half), rng.range(-half, half));
            push(p, [rng.f(), rng.f(), rng.f()], &mut cloud);
        }
    }
    let n = cloud.means.len();
    // Isotropic size ~ the mean spacing of n points in the scene box.
    let (lo, hi) = cloud.bounds().unwrap_or((glam::Vec3::ZERO, glam::Vec3::ONE));
    let vol = ((hi - lo).max(glam::Vec3::splat(1e-3))).element_product();
    let s = (vol / n.max(1) as f32).cbrt().max(1e-4) * 0.5;
    cloud.log_scales = vec![[s.ln(); 3]; n];
    cloud.quats = vec![[1.0, 0.0, 0.0, 0.0]; n];
    cloud.opacity_logits = vec![logit(0.1); n];
    cloud.rest_per_gaussian = 45;
    cloud.sh_rest = vec![0.0; n * 45];
    cloud
}
