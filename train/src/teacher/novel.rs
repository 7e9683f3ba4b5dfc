//! Novel views: the frozen geometry rendered at cameras between the training cameras, taught like
//! photos.
use glam::{Mat3, Mat4, Quat};
use model::ObjectId;
use model::data::Dataset;
use model::error::{Error, Result};
use model::rng::Rng;
use model::run::{GeometryRun, NovelSource, StoredPath, TeacherDir};
use model::splats::{SplatModel, host};
use model::vlm::preprocess::RgbImage;
use splat_kernels::Camera;
use std::path::Path;

/// Novel views: `count` renders of the geometry run `run` at cameras between its training
/// cameras (seeded by `seed`), extracted after the photos.
#[derive(Clone, Debug, PartialEq)]
pub struct NovelViews {
    pub run: GeometryRun,
    pub count: usize,
    pub seed: u64,
}

/// A novel camera lies between a training camera and one of its this many nearest.
pub const NOVEL_NEIGHBOURS: usize = 2;
/// ... at a fraction of the way drawn from this range (never on either camera).
pub const NOVEL_BETWEEN: (f32, f32) = (0.25, 0.75);

/// `count` cameras between the training cameras `train` (seeded): each starts at a training
/// camera drawn at random, goes a fraction [`NOVEL_BETWEEN`] of the way to one of its
/// [`NOVEL_NEIGHBOURS`] nearest (by centre), its centre interpolated linearly and its rotation
/// spherically, with the first camera's intrinsics. Empty with fewer than two cameras.
pub fn novel_cameras(train: &[Camera], count: usize, seed: u64) -> Vec<Camera> {
    if train.len() < 2 {
        return Vec::new();
    }
    let to_world: Vec<Mat4> = train.iter().map(|c| c.world_to_cam.inverse()).collect();
    let centre = |i: usize| to_world[i].w_axis.truncate();
    let rotation = |m: &Mat4| {
        let r = Mat3::from_mat4(*m);
        (r.determinant() > 0.0).then(|| Quat::from_mat3(&r).normalize())
    };
    let mut rng = Rng::new(seed);
    (0..count)
        .map(|_| {
            let i = (rng.next_u64() % train.len() as u64) as usize;
            let mut others: Vec<usize> = (0..train.len()).filter(|&j| j != i).collect();
            let away = |j: usize| centre(j).distance_squared(centre(i));
            others.sort_by(|&a, &b| away(a).total_cmp(&away(b)));
            let j = others[(rng.next_u64() % others.len().min(NOVEL_NEIGHBOURS) as u64) as usize];
            let t = rng.range(NOVEL_BETWEEN.0, NOVEL_BETWEEN.1);
            let c = centre(i).lerp(centre(j), t);
            let to_world = match (rotation(&to_world[i]), rotation(&to_world[j])) {
                (Some(a), Some(b)) => Mat4::from_rotation_translation(a.slerp(b, t), c),
                // a pose with a reflection has no quaternion: the first camera's axes, moved
                _ => {
                    let mut m = to_world[i];
                    m.w_axis = c.extend(1.0);
                    m
                }
            };
            Camera { world_to_cam: to_world.inverse(), ..train[i] }
        })
        .collect()
}

/// A hash of a model's Gaussians (16 hex digits): novel views belong to the Gaussians that
/// rendered them.
pub fn gaussians_hash(splats: &SplatModel) -> String {
    let h = splats
        .tensors()
        .into_named()
        .into_iter()
        .fold(crate::dist::HASH_START, |h, (_, t)| crate::dist::hash_f32(h, &host(t)));
    format!("{h:016x}")
}

/// The novel views of one extraction: the geometry that renders them and their cameras.
pub(super) struct Novel {
    pub(super) splats: SplatModel,
    pub(super) sh_degree: usize,
    pub(super) background: [f32; 3],
    pub(super) cameras: Vec<Camera>,
    pub(super) source: NovelSource,
}

impl Novel {
    /// Loads `n.run` (trained on the dataset `ds` from `data`, of fingerprint `now`) and draws
    /// the cameras.
    pub(super) fn open(
        n: &NovelViews,
        ds: &Dataset,
        now: &str,
        data: &Path,
        out: &TeacherDir,
        device: &burn::tensor::Device,
    ) -> Result<Self> {
        let (splats, state) = n.run.load_model(device)?;
        if !state.data.fingerprint.is_empty() && state.data.fingerprint != now {
            return Err(Error::invalid(
                &n.run.dir,
                format!(
                    "novel views: this geometry run was trained on other data than {} (fingerprint {}, the \
                     dataset's is {now}): give the run trained on it",
                    data.display(),
                    state.data.fingerprint
                ),
            ));
        }
        let train: Vec<Camera> = ds.train.iter().map(|v| v.camera).collect();
        let cameras = novel_cameras(&train, n.count, n.seed);
        if cameras.len() != n.count {
            return Err(Error::invalid(
                data,
                "novel views lie between training cameras: the capture needs at least two",
            ));
        }
        let source = NovelSource {
            run: StoredPath::new(&n.run.dir, &out.dir),
            gaussians_hash: gaussians_hash(&splats),
            count: n.count,
            seed: n.seed,
        };
        Ok(Self { splats, sh_degree: state.sh_degree, background: state.background, cameras, source })
    }

    /// Novel view `k` rendered: its image and identity classes.
    pub(super) fn render(&self, k: usize) -> Result<(RgbImage, Vec<ObjectId>)> {
        let cam = &self.cameras[k];
        let r = self.splats.render(cam, self.sh_degree, self.background)?;
        let rgb: Vec<f32> = r.rgb.iter().map(|c| c.clamp(0.0, 1.0)).collect();
        Ok((RgbImage::from_f32(cam.width as usize, cam.height as usize, &rgb), r.ids))
    }

    /// The name a novel view goes by in the index and its file.
    pub(super) fn name(k: usize) -> String {
        format!("novel_{k:04}")
    }
}
#[cfg(test)]
mod tests {
    use super::*;
    use model::data::synth::{CAMERA_DISTANCE, LOOK_AT, orbit_camera};

    /// Twelve cameras on a ring around the look-at point.
    fn ring() -> Vec<Camera> {
        (0..12)
            .map(|i| orbit_camera(i as f32 * std::f32::consts::FRAC_PI_6, 0.5, CAMERA_DISTANCE, LOOK_AT, 40.0, 32, 32))
            .collect()
    }

    fn centre(c: &Camera) -> glam::Vec3 {
        c.world_to_cam.inverse().w_axis.truncate()
    }

    #[test]
    fn novel_cameras_lie_between_neighbouring_training_cameras() {
        let train = ring();
        let spacing = centre(&train[0]).distance(centre(&train[1]));
        let novel = novel_cameras(&train, 40, 3);
        assert_eq!(novel.len(), 40);
        assert_eq!(novel, novel_cameras(&train, 40, 3), "seeded");
        assert_ne!(novel, novel_cameras(&train, 40, 4));
        for c in &novel {
            let p = centre(c);
            let nearest = train.iter().map(|t| centre(t).distance(p)).fold(f32::MAX, f32::min);
            // a quarter to three quarters of the way to one of the two nearest (at most 2 spacings)
            assert!(nearest > 0.2 * spacing && nearest < 1.01 * spacing, "{nearest} vs spacing {spacing}");
            // a rigid pose that still looks at the ring's centre (within 3 degrees)
            let r = Mat3::from_mat4(c.world_to_cam);
            assert!((r.determinant() - 1.0).abs() < 1e-4);
            let forward = r.transpose() * glam::Vec3::Z;
            let to_target = (LOOK_AT - p).normalize();
            assert!(forward.angle_between(to_target).to_degrees() < 3.0);
            assert_eq!((c.fx, c.width), (train[0].fx, train[0].width));
        }
        assert!(novel_cameras(&train[..1], 5, 0).is_empty(), "one camera has no neighbour");
    }
}
