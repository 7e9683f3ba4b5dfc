//! chatsplat's files and scene data, below the model: the error type that names the file
//! ([`error`]), atomic writes, JSON and safetensors ([`io`]), PNG ([`images`]), question files
//! ([`question_file`]), the host Gaussian cloud ([`cloud`]), and posed images (and masks, depth)
//! from datasets or the built-in synthetic generator ([`synth`]). The `model` crate re-exports
//! every module here (`model::data` is this crate); inference never needs the loaders.
//!
//! Every loader produces the same [`Dataset`] of [`View`]s with OpenCV-convention
//! [`Camera`]s (x right, y down, z forward; pixel `(x, y)` covers `[x, x+1) x [y, y+1)`), RGB as
//! `[H, W, 3]` floats in [0, 1], optional `[H, W]` 8-bit instance ids (0 = background) and
//! optional `[H, W]` camera-space depth (0 = none). Errors name the file and the problem.
//!
//! | format | module | marker |
//! |---|---|---|
//! | nerfstudio / Blender | [`nerfstudio`] | `transforms.json`, `transforms_train.json` |
//! | COLMAP (undistorted) | [`colmap`] | `sparse/0/` or `sparse/` |
//! | LLFF | [`llff`] | `poses_bounds.npy` |
//! | Replica (Semantic-NeRF renders) | [`replica`] | `traj_w_c.txt` |
//!
//! [`load_any`] picks the loader from those markers.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub mod cloud;
pub mod error;
pub mod guard;
pub mod images;
pub mod io;
pub mod question_file;

pub mod colmap;
pub(crate) mod image;
/// A PNG or JPEG as the VLM port's RGB image.
pub use image::read_rgb_any;
/// An instance-id PNG of any segmenter (8- or 16-bit grayscale, a palette's index, or gray saved
/// as RGB): its width, height and `[h, w]` ids (0 = none).
pub use image::{MAX_INSTANCE_ID, read_ids16_any};

/// An object's id in masks, identity renders, questions and the API (0 = background).
pub type ObjectId = u16;
pub mod llff;
pub mod nerfstudio;
pub mod replica;
pub mod synth;

use crate::error::{Error, Result};
use splat_kernels::Camera;
use std::path::{Path, PathBuf};

/// How RGBA images are flattened.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Background {
    White,
    Black,
}

impl Background {
    /// The background intensity in [0, 1].
    pub fn value(self) -> f32 {
        match self {
            Background::White => 1.0,
            Background::Black => 0.0,
        }
    }
}

/// Loader options (shared by every format).
#[derive(Clone, Debug)]
pub struct LoadOptions {
    /// Integer downscale factor (box filter for colours, nearest sample for ids and depth);
    /// 1 keeps the full resolution. Intrinsics are divided by it.
    pub downscale: u32,
    /// Background for RGBA images.
    pub background: Background,
    /// Without a test split on disk, every `holdout_every`-th view is held out (0: none): views
    /// `every-1, 2*every-1, ...` in the loader's view order.
    pub holdout_every: usize,
    /// Instance masks from another tool (`--masks DIR`): `DIR/<image stem>.png` per image, 8- or
    /// 16-bit ids (0 = background, at most [`MAX_INSTANCE_ID`]) the size of the image, replacing
    /// the format's own masks.
    pub masks: Option<PathBuf>,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self { downscale: 1, background: Background::White, holdout_every: 8, masks: None }
    }
}

/// One posed view.
#[derive(Clone, Debug)]
pub struct View {
    pub image_path: PathBuf,
    pub camera: Camera,
    /// `[H, W, 3]` in [0, 1].
    pub rgb: Vec<f32>,
    /// `[H, W]` instance ids, when the dataset has masks.
    pub instance_ids: Option<Vec<u16>>,
    /// `[H, W]` camera-space depth in scene units (0 = none), when the dataset has depth.
    pub depth: Option<Vec<f32>>,
}

/// A loaded dataset.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub train: Vec<View>,
    pub test: Vec<View>,
}

impl Dataset {
    /// A fingerprint of what was loaded (16 hex digits): per view, in split order, its file name
    /// and size on disk, image size, intrinsics, pose, a sample of its pixels and of its instance
    /// ids. Moving the dataset keeps it; other photos, poses, split, masks or downscale change it.
    /// Runs and teacher directories store it so that resuming or training on other data is
    /// refused.
    pub fn fingerprint(&self) -> String {
        let mut h = Fnv::default();
        let mut eat = |bytes: &[u8]| h.eat(bytes);
        for (split, views) in [(0u8, &self.train), (1, &self.test)] {
            eat(&[split]);
            eat(&(views.len() as u64).to_le_bytes());
            for v in views {
                let name = v.image_path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                eat(name.as_bytes());
                eat(&std::fs::metadata(&v.image_path).map(|m| m.len()).unwrap_or(0).to_le_bytes());
                let c = &v.camera;
                eat(&c.width.to_le_bytes());
                eat(&c.height.to_le_bytes());
                for x in [c.fx, c.fy, c.cx, c.cy].into_iter().chain(c.world_to_cam.to_cols_array()) {
                    // poses rounded to 1e-5 so that re-parsing the same file cannot differ
                    eat(&((x as f64 * 1e5).round() as i64).to_le_bytes());
                }
                for x in v.rgb.iter().step_by(61) {
                    eat(&[(x * 255.0).round() as u8]);
                }
                // masks change which objects a run learns: a run resumed with other masks, or
                // without them, is another run (nothing is eaten without masks, so mask-less
                // fingerprints are as before)
                if let Some(ids) = &v.instance_ids {
                    eat(b"ids");
                    for &i in ids.iter().step_by(7) {
                        // one byte for the ids a byte holds: fingerprints of 8-bit masks as before
                        match u8::try_from(i) {
                            Ok(b) => eat(&[b]),
                            Err(_) => eat(&i.to_le_bytes()),
                        }
                    }
                }
            }
        }
        h.hex()
    }
}

/// FNV-1a, 64 bit: the hash of the fingerprints, the same on every machine and run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Fnv(pub u64);

impl Default for Fnv {
    fn default() -> Self {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
}

impl Fnv {
    pub fn eat(&mut self, bytes: &[u8]) {
        for b in bytes {
            self.0 = (self.0 ^ *b as u64).wrapping_mul(0x0100_0000_01b3);
        }
    }

    /// 16 hex digits.
    pub fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }
}

/// The instance-mask folder of a capture: `masks/`, else Gaussian Grouping's `object_mask/` (the
/// per-image instance-id PNGs that SAM + DEVA write beside `images/`).
pub(crate) fn mask_dir(dir: &Path) -> PathBuf {
    let ours = dir.join("masks");
    let grouping = dir.join("object_mask");
    if !ours.is_dir() && grouping.is_dir() { grouping } else { ours }
}

/// The capture's own mask of one view at `path`, read by `read`: `None` under `--masks` (which
/// replaces it later) or when the file is missing (noted in `missing` for [`check_own_masks`]).
pub(crate) fn own_mask(
    opts: &LoadOptions,
    path: PathBuf,
    missing: &mut Vec<PathBuf>,
    read: impl FnOnce(&Path) -> Result<Vec<u16>>,
) -> Result<Option<Vec<u16>>> {
    if opts.masks.is_some() {
        Ok(None)
    } else if path.is_file() {
        read(&path).map(Some)
    } else {
        missing.push(path);
        Ok(None)
    }
}

/// A capture's own masks cover every view or none. `missing` are the mask files not found in
/// `folder` for `total` views: some missing is refused, naming the first (a scene trained with
/// masks for part of its views would learn no objects in the others); all missing while
/// `folder` exists is a warning (the folder is not used).
pub(crate) fn check_own_masks(folder: &Path, missing: &[PathBuf], total: usize) -> Result<()> {
    if missing.is_empty() {
        return Ok(());
    }
    if missing.len() < total {
        return Err(image::err(
            &missing[0],
            format!(
                "is missing: {} has masks for {} of the {total} images and every image needs one (or move the \
                 folder away to load the scene without masks)",
                folder.display(),
                total - missing.len()
            ),
        ));
    }
    if folder.is_dir() {
        crate::error::warn(format!(
            "{}: holds no mask for any of the {total} images (looked for <image name>.png, e.g. {}): the scene is \
             loaded without masks",
            folder.display(),
            missing[0].file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
        ));
    }
    Ok(())
}

/// Replaces every view's instance ids with `opts.masks`' (nothing without it): for each image
/// `DIR/<image stem>.png` must exist, the size of the full-resolution image, and is downscaled by
/// nearest sample like the format's own masks. The loaders without lens distortion call it on
/// their views; nerfstudio reads `--masks` through its own mask path (undistorting them).
pub(crate) fn apply_masks(views: &mut [View], opts: &LoadOptions) -> Result<()> {
    if opts.masks.is_none() {
        return Ok(());
    }
    let k = opts.downscale.max(1);
    for v in views {
        let path = given_mask(opts, &v.image_path)?.expect("--masks is set");
        let (mw, mh, ids) = image::read_ids_any(&path)?;
        let (w, h) = (v.camera.width, v.camera.height);
        if mw / k != w || mh / k != h {
            return Err(image::err(
                &path,
                format!("is {mw}x{mh} but its image {} is {}x{} (after downscale {k})", v.image_path.display(), w, h),
            ));
        }
        v.instance_ids = Some(image::subsample(&ids, mw, w, h, k));
    }
    Ok(())
}

/// The `--masks` file of `image` (`DIR/<image stem>.png`), which must exist; `None` without
/// `--masks`.
pub(crate) fn given_mask(opts: &LoadOptions, image: &Path) -> Result<Option<PathBuf>> {
    let Some(dir) = &opts.masks else { return Ok(None) };
    if !dir.is_dir() {
        return Err(image::err(dir, "is not a directory (--masks: a folder of per-image instance-id PNGs)"));
    }
    let mut name = image.file_stem().map(|s| s.to_os_string()).unwrap_or_default();
    name.push(".png");
    let path = dir.join(name);
    if !path.is_file() {
        return Err(image::err(&path, format!("is missing: every image needs a mask (image {})", image.display())));
    }
    Ok(Some(path))
}

/// Splits `views` (in order) into train and test: every `every`-th view is held out (0: none),
/// then [`check_capture`]s the result.
pub(crate) fn split(views: Vec<View>, every: usize) -> Result<Dataset> {
    let (mut train, mut test) = (vec![], vec![]);
    for (i, v) in views.into_iter().enumerate() {
        if every > 0 && i % every == every - 1 {
            test.push(v);
        } else {
            train.push(v);
        }
    }
    check_capture(Dataset { train, test })
}

/// Widest and narrowest field of view (degrees) a camera may have before its focal length is
/// called absurd (a focal length in the wrong unit: millimetres, or normalised by the width).
const FOV_DEGREES: (f32, f32) = (0.1, 170.0);

/// Refuses a capture no reconstruction can come from, and warns about a legal but suspicious
/// one, so that nothing trains on it with a normal summary:
///
/// * errors: a focal length giving a field of view outside [`FOV_DEGREES`] or pixels more than
///   10x wider than tall; a principal point more than half the image outside it; an image that
///   is both a training and a held-out view (held-out figures would be measured on training
///   data); several views that all share one pose, or all the same pixels;
/// * warnings: a principal point outside the image (inside that margin); an image listed twice
///   among the training views; every view taken from one point (rotation only: no parallax).
pub(crate) fn check_capture(ds: Dataset) -> Result<Dataset> {
    let all: Vec<&View> = ds.train.iter().chain(&ds.test).collect();
    for v in &all {
        let c = &v.camera;
        let (w, h) = (c.width as f32, c.height as f32);
        for (f, size, axis) in [(c.fx, w, "fx"), (c.fy, h, "fy")] {
            let fov = 2.0 * (0.5 * size / f).atan().to_degrees();
            if !(f.is_finite() && f > 0.0 && fov >= FOV_DEGREES.0 && fov <= FOV_DEGREES.1) {
                return Err(image::err(
                    &v.image_path,
                    format!(
                        "focal length {axis} = {f} px gives a field of view of {fov:.3} degrees over its {size} \
                         pixels; expected {}..{} (is the focal length in another unit, e.g. mm or normalised?)",
                        FOV_DEGREES.0, FOV_DEGREES.1
                    ),
                ));
            }
        }
        if c.fx / c.fy > 10.0 || c.fy / c.fx > 10.0 {
            return Err(image::err(
                &v.image_path,
                format!(
                    "focal lengths fx = {} and fy = {} differ more than tenfold: pixels that shape are not a camera's",
                    c.fx, c.fy
                ),
            ));
        }
        let inside =
            |p: f32, size: f32, margin: f32| p.is_finite() && p >= -margin * size && p <= (1.0 + margin) * size;
        if !inside(c.cx, w, 0.5) || !inside(c.cy, h, 0.5) {
            return Err(image::err(
                &v.image_path,
                format!(
                    "principal point ({}, {}) is far outside the {}x{} image (cx, cy are in pixels from the top-left \
                     corner)",
                    c.cx, c.cy, c.width, c.height
                ),
            ));
        }
        if !inside(c.cx, w, 0.0) || !inside(c.cy, h, 0.0) {
            crate::error::warn(format!(
                "{}: principal point ({}, {}) is outside the {}x{} image: used as given",
                v.image_path.display(),
                c.cx,
                c.cy,
                c.width,
                c.height
            ));
        }
    }
    // the same photo twice
    let key = |v: &View| std::fs::canonicalize(&v.image_path).unwrap_or_else(|_| v.image_path.clone());
    let train_paths: std::collections::HashMap<PathBuf, usize> =
        ds.train.iter().fold(Default::default(), |mut m, v| {
            *m.entry(key(v)).or_insert(0) += 1;
            m
        });
    if let Some(v) = ds.test.iter().find(|v| train_paths.contains_key(&key(v))) {
        return Err(image::err(
            &v.image_path,
            "is both a training view and a held-out view: held-out figures would be measured on a photo the \
             scene was trained on (list each frame once, or keep the held-out split apart)",
        ));
    }
    if let Some((p, n)) = train_paths.iter().filter(|(_, n)| **n > 1).min_by(|a, b| a.0.cmp(b.0)) {
        crate::error::warn(format!(
            "{}: listed {n} times among the training views: it weighs {n}x in training",
            p.display()
        ));
    }
    if all.len() > 1 {
        let first = all[0];
        let same_pose = |v: &&View| {
            let (a, b) = (v.camera.world_to_cam.to_cols_array(), first.camera.world_to_cam.to_cols_array());
            a.iter().zip(&b).all(|(x, y)| (x - y).abs() <= 1e-6 * (1.0 + y.abs()))
        };
        if all.iter().all(same_pose) {
            return Err(image::err(
                &first.image_path,
                format!(
                    "all {} views have the same camera pose: a scene needs photos taken from different places",
                    all.len()
                ),
            ));
        }
        if all.iter().all(|v| v.rgb == first.rgb) {
            return Err(image::err(
                &first.image_path,
                format!("all {} views have the same pixels: a scene needs different photos of it", all.len()),
            ));
        }
        let centre = |v: &View| v.camera.world_to_cam.inverse().w_axis.truncate();
        let c0 = centre(first);
        let extent = all.iter().map(|v| v.camera.world_to_cam.w_axis.truncate().length()).fold(0.0f32, f32::max);
        if all.iter().all(|v| (centre(v) - c0).length() <= 1e-5 * (1.0 + extent)) {
            crate::error::warn(format!(
                "{}: all {} views are taken from one point (the camera only turns): without parallax the \
                 Gaussians' depth is not constrained",
                first.image_path.parent().unwrap_or(&first.image_path).display(),
                all.len()
            ));
        }
    }
    Ok(ds)
}

/// Rejects a zero downscale factor.
pub(crate) fn check_options(opts: &LoadOptions) -> Result<()> {
    if opts.downscale == 0 { Err(Error::input("downscale must be at least 1")) } else { Ok(()) }
}

/// Loads a scene directory in whichever supported format it holds, checking for (in this order):
///
/// 1. `transforms.json` or `transforms_train.json`: [`nerfstudio`];
/// 2. `poses_bounds.npy`: [`llff`] (LLFF scenes usually also carry the COLMAP model they were
///    made from, with the original, distorted cameras, so this marker wins over `sparse/`);
/// 3. a `sparse/` directory: [`colmap`] (its sparse points are dropped; call
///    [`colmap::load`] to keep them);
/// 4. `traj_w_c.txt`: [`replica`].
///
/// Every loader honours `opts.masks`.
pub fn load_any(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    if nerfstudio::is_here(dir) {
        nerfstudio::load(dir, opts)
    } else if dir.join("poses_bounds.npy").is_file() {
        llff::load(dir, opts)
    } else if dir.join("sparse").is_dir() {
        colmap::load(dir, opts).map(|(ds, _)| ds)
    } else if dir.join("traj_w_c.txt").is_file() {
        replica::load(dir, opts)
    } else if !dir.is_dir() {
        Err(image::err(dir, "not a directory"))
    } else {
        Err(image::err(
            dir,
            "no known scene format: looked for transforms.json or transforms_train.json (nerfstudio), \
             poses_bounds.npy (LLFF), sparse/ (COLMAP) and traj_w_c.txt (Replica)",
        ))
    }
}
