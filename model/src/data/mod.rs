//! Scene data: posed images (and masks, depth) from datasets or the built-in synthetic generator.
//!
//! Every loader produces the same [`Dataset`] of [`View`]s with OpenCV-convention
//! [`Camera`]s (x right, y down, z forward; pixel `(x, y)` covers `[x, x+1) x [y, y+1)`), RGB as
//! `[H, W, 3]` floats in [0, 1], optional `[H, W]` 8-bit instance ids (0 = background) and
//! optional `[H, W]` camera-space depth (0 = none). Errors are `String`s of the form
//! `"<path>: <problem>"`.
//!
//! | format | module | marker |
//! |---|---|---|
//! | nerfstudio / Blender | [`nerfstudio`] | `transforms.json`, `transforms_train.json` |
//! | COLMAP (undistorted) | [`colmap`] | `sparse/0/` or `sparse/` |
//! | LLFF | [`llff`] | `poses_bounds.npy` |
//! | Replica (Semantic-NeRF renders) | [`replica`] | `traj_w_c.txt` |
//!
//! [`load_any`] picks the loader from those markers.

pub mod colmap;
pub(crate) mod image;
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
    /// Instance masks from another tool (`--masks DIR`): `DIR/<image stem>.png` per image, 8-bit
    /// ids (0 = background) the size of the image, replacing the format's own masks.
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
    pub instance_ids: Option<Vec<u8>>,
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
    /// and size on disk, image size, intrinsics, pose and a sample of its pixels. Moving the dataset keeps it; other
    /// photos, poses, split or downscale change it. Runs and teacher directories store it so
    /// that resuming or training on other data is refused.
    pub fn fingerprint(&self) -> String {
        // FNV-1a, 64 bit
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        let mut eat = |bytes: &[u8]| {
            for b in bytes {
                h = (h ^ *b as u64).wrapping_mul(0x0100_0000_01b3);
            }
        };
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
            }
        }
        format!("{h:016x}")
    }
}

/// The instance-mask folder of a capture: `masks/`, else Gaussian Grouping's `object_mask/` (the
/// per-image instance-id PNGs that SAM + DEVA write beside `images/`).
pub(crate) fn mask_dir(dir: &Path) -> PathBuf {
    let ours = dir.join("masks");
    let grouping = dir.join("object_mask");
    if !ours.is_dir() && grouping.is_dir() { grouping } else { ours }
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
        let (mw, mh, ids) = image::read_ids8_any(&path)?;
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

/// Splits `views` (in order) into train and test: every `every`-th view is held out (0: none).
pub(crate) fn split(views: Vec<View>, every: usize) -> Dataset {
    let (mut train, mut test) = (vec![], vec![]);
    for (i, v) in views.into_iter().enumerate() {
        if every > 0 && i % every == every - 1 {
            test.push(v);
        } else {
            train.push(v);
        }
    }
    Dataset { train, test }
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
