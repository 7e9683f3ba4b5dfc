//! nerfstudio `transforms.json` and its Blender/NeRF-synthetic variant
//! (`transforms_train.json` / `transforms_test.json`, `camera_angle_x`, extension-less paths,
//! RGBA images whose alpha is the foreground).
//!
//! Poses are camera-to-world in the OpenGL convention and become OpenCV world-to-camera
//! [`Camera`]s. Images are 8-bit PNG or JPEG; masks (`instance_mask_path` or `mask_path`) are
//! 8-bit id images; depth (`depth_file_path`) is 16-bit PNG scaled by `depth_unit_scale_factor`.
//! [`LoadOptions`], [`View`] and [`Dataset`] are shared with the other loaders (this crate).
//!
//! # Lens distortion
//!
//! OpenCV radial-tangential distortion (`camera_model` `"OPENCV"`: `k1`, `k2`, optional `k3`,
//! `p1`, `p2`, at the top level or per frame, a frame's own value winning) is removed while
//! loading: every view becomes an ideal pinhole image with the *same* `fl_x`, `fl_y`, `cx`, `cy`
//! and size. With pixel `(i, j)` centred at `(u, v) = (i + 0.5, j + 0.5)` (the [`Camera`]
//! convention, which `cx`, `cy` follow):
//!
//! ```text
//! x = (u - cx) / fx,  y = (v - cy) / fy,  r2 = x² + y²
//! radial = 1 + k1 r2 + k2 r2² + k3 r2³
//! xd = x radial + 2 p1 x y + p2 (r2 + 2 x²)
//! yd = y radial + p1 (r2 + 2 y²) + 2 p2 x y
//! (ud, vd) = (fx xd + cx, fy yd + cy)
//! ```
//!
//! and the output colour is the source image sampled bilinearly at array coordinates
//! `(ud - 0.5, vd - 0.5)`, positions outside the source taking the nearest edge pixel. Masks and
//! depth maps take the source pixel containing `(ud, vd)` (nearest sample, so ids stay exact),
//! or 0 outside the source. This happens at full resolution, before the box downscale, and the
//! source positions are computed once per distinct (intrinsics, distortion, size) and reused for
//! every frame sharing them. All-zero coefficients skip the resampling entirely (the images are
//! bit-identical to a file without them). Fisheye distortion (`camera_model`
//! `"OPENCV_FISHEYE"`, or a non-zero `k4`) and equirectangular cameras are refused with a clear
//! message (undistort those images first).

use super::image::{Remap, decode, err, read_depth16_full, read_ids_full, subsample};
pub use super::{Background, Dataset, LoadOptions, View};
use super::{check_options, split};
use crate::error::Result;
use glam::{Mat4, Vec4};
use serde_json::Value;
use splat_kernels::Camera;
use std::path::Path;

fn num(v: &Value, key: &str) -> Option<f32> {
    v.get(key).and_then(Value::as_f64).map(|x| x as f32)
}

/// OpenCV radial-tangential ("OPENCV") lens distortion coefficients.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Distortion {
    k1: f64,
    k2: f64,
    k3: f64,
    p1: f64,
    p2: f64,
}

impl Distortion {
    fn is_zero(&self) -> bool {
        *self == Self::default()
    }

    /// The distorted normalised coordinates of the ideal pinhole point `(x, y)`.
    fn apply(&self, x: f64, y: f64) -> (f64, f64) {
        let Self { k1, k2, k3, p1, p2 } = *self;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }
}

/// At most this many undistortion maps are kept (a fox-sized map is about 33 MB).
const MAX_MAPS: usize = 4;

/// Undistortion maps by (fx, fy, cx, cy, k1, k2, k3, p1, p2, width, height) bit patterns, the
/// most recently used last; shared by the train and test files of a dataset.
#[derive(Default)]
struct Maps(Vec<([u64; 11], Remap)>);

impl Maps {
    /// The map undistorting a `w x h` image with these pinhole intrinsics (full resolution).
    fn get(&mut self, w: u32, h: u32, [fx, fy, cx, cy]: [f64; 4], d: Distortion) -> &Remap {
        let key = [fx, fy, cx, cy, d.k1, d.k2, d.k3, d.p1, d.p2, w as f64, h as f64].map(f64::to_bits);
        if let Some(p) = self.0.iter().position(|(k, _)| *k == key) {
            let hit = self.0.remove(p);
            self.0.push(hit);
        } else {
            if self.0.len() >= MAX_MAPS {
                self.0.remove(0);
            }
            let remap = Remap::new(w, h, |u, v| {
                let (xd, yd) = d.apply((u - cx) / fx, (v - cy) / fy);
                (fx * xd + cx, fy * yd + cy)
            });
            self.0.push((key, remap));
        }
        &self.0.last().expect("just pushed").1
    }
}

/// Nearest-sample undistortion (if any) at full resolution, then the nearest downscale by `k`.
fn resample<T: Copy + Default>(full: Vec<T>, remap: Option<&Remap>, w: u32, h: u32, k: u32) -> Vec<T> {
    let full = match remap {
        Some(r) => r.nearest(&full),
        None => full,
    };
    subsample(&full, w, w / k, h / k, k)
}

/// `; undistort the images first ...` advice for refused camera models.
const UNDISTORT_FIRST: &str = "undistort the images first (e.g. COLMAP image_undistorter)";

/// Whether `dir` holds a nerfstudio/Blender dataset (`transforms.json` or `transforms_train.json`).
pub fn is_here(dir: &Path) -> bool {
    dir.join("transforms.json").is_file() || dir.join("transforms_train.json").is_file()
}

/// Loads `dir/transforms.json`, or the Blender split files `transforms_train.json` (+ `_test`).
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    check_options(opts)?;
    let single = dir.join("transforms.json");
    let train_file = dir.join("transforms_train.json");
    let test_file = dir.join("transforms_test.json");
    let mut maps = Maps::default();
    if single.is_file() {
        let views = load_file(&single, dir, opts, &mut maps)?;
        split(views, opts.holdout_every)
    } else if train_file.is_file() {
        let train = load_file(&train_file, dir, opts, &mut maps)?;
        if test_file.is_file() {
            super::check_capture(Dataset { train, test: load_file(&test_file, dir, opts, &mut maps)? })
        } else {
            split(train, opts.holdout_every)
        }
    } else {
        Err(err(dir, "no transforms.json or transforms_train.json here"))
    }
}

fn load_file(file: &Path, dir: &Path, opts: &LoadOptions, maps: &mut Maps) -> Result<Vec<View>> {
    let text = std::fs::read_to_string(file).map_err(|e| err(file, format!("cannot read: {e}")))?;
    let root: Value = serde_json::from_str(&text).map_err(|e| err(file, format!("invalid JSON: {e}")))?;
    let frames = root.get("frames").and_then(Value::as_array).ok_or_else(|| err(file, "no `frames` array"))?;
    if frames.is_empty() {
        return Err(err(file, "`frames` is empty"));
    }
    let depth_scale = num(&root, "depth_unit_scale_factor").unwrap_or(1.0);
    if !(depth_scale.is_finite() && depth_scale > 0.0) {
        return Err(err(
            file,
            format!("depth_unit_scale_factor is {depth_scale}: it must be a positive scale (metres per depth unit)"),
        ));
    }
    let mut views = Vec::with_capacity(frames.len());
    let mut warned_binary = false;
    for (i, f) in frames.iter().enumerate() {
        let at = |m: &str| err(file, format!("frame {i}: {m}"));
        let coef = |key: &str| {
            let v = |o: &Value| o.get(key).and_then(Value::as_f64);
            v(f).or_else(|| v(&root)).unwrap_or(0.0)
        };
        let model = f.get("camera_model").or_else(|| root.get("camera_model")).and_then(Value::as_str);
        if let Some(model) = model {
            let upper = model.to_ascii_uppercase();
            if upper.contains("FISHEYE") {
                return Err(at(&format!("fisheye camera model `{model}` is not supported; {UNDISTORT_FIRST}")));
            }
            if upper.contains("EQUIRECTANGULAR") {
                return Err(at(&format!("camera model `{model}` is not supported (pinhole cameras only)")));
            }
        }
        let k4 = coef("k4");
        if k4 != 0.0 {
            return Err(at(&format!("fisheye lens distortion (k4 = {k4}) is not supported; {UNDISTORT_FIRST}")));
        }
        let distortion = Distortion { k1: coef("k1"), k2: coef("k2"), k3: coef("k3"), p1: coef("p1"), p2: coef("p2") };
        let rel = f.get("file_path").and_then(Value::as_str).ok_or_else(|| at("no `file_path`"))?;
        let mut path = dir.join(rel);
        if path.extension().is_none() {
            path.set_extension("png");
        }
        if !path.is_file() {
            return Err(at(&format!("image {} is missing", path.display())));
        }
        let img = decode(&path)?;
        let (w, h) = (img.width, img.height);
        let get = |key: &str| num(f, key).or_else(|| num(&root, key));
        if let (Some(ew), Some(eh)) = (get("w"), get("h"))
            && (ew as u32 != w || eh as u32 != h)
        {
            return Err(err(&path, format!("image is {w}x{h} but the transforms say {ew}x{eh}")));
        }
        let fx = match get("fl_x") {
            Some(v) => v,
            None => {
                let angle = get("camera_angle_x").ok_or_else(|| at("neither `fl_x` nor `camera_angle_x` is given"))?;
                0.5 * w as f32 / (0.5 * angle).tan()
            }
        };
        let fy = get("fl_y").unwrap_or(fx);
        let cx = get("cx").unwrap_or(0.5 * w as f32);
        let cy = get("cy").unwrap_or(0.5 * h as f32);
        if !(fx.is_finite() && fx > 0.0 && fy.is_finite() && fy > 0.0 && cx.is_finite() && cy.is_finite()) {
            return Err(at(&format!(
                "intrinsics fl_x {fx}, fl_y {fy}, cx {cx}, cy {cy}: focal lengths must be positive"
            )));
        }
        let m = f
            .get("transform_matrix")
            .and_then(Value::as_array)
            .filter(|rows| rows.len() >= 3)
            .ok_or_else(|| at("no 4x4 `transform_matrix`"))?;
        let mut c2w = [[0.0f32; 4]; 4];
        c2w[3][3] = 1.0;
        for (r, row) in m.iter().take(4).enumerate() {
            let row =
                row.as_array().filter(|r| r.len() == 4).ok_or_else(|| at("`transform_matrix` rows need 4 numbers"))?;
            for (c, v) in row.iter().enumerate() {
                c2w[r][c] = v.as_f64().ok_or_else(|| at("`transform_matrix` holds a non-number"))? as f32;
            }
        }
        let gl = Mat4::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|r| c2w[r][c])));
        let cv = gl * Mat4::from_diagonal(Vec4::new(1.0, -1.0, -1.0, 1.0));
        if !cv.is_finite() || cv.determinant().abs() < 1e-12 {
            return Err(at("`transform_matrix` is not an invertible pose"));
        }
        let k = opts.downscale;
        // Undistortion (module docs) at full resolution, before the downscale.
        let remap =
            if distortion.is_zero() { None } else { Some(maps.get(w, h, [fx, fy, cx, cy].map(f64::from), distortion)) };
        let (dw, dh, rgb) = match remap {
            Some(r) => img.to_rgb_remapped(&path, k, opts.background, r)?,
            None => img.to_rgb(&path, k, opts.background)?,
        };
        let mut camera = Camera::new(cv.inverse(), fx / k as f32, fy / k as f32, dw, dh);
        camera.cx = cx / k as f32;
        camera.cy = cy / k as f32;
        // Masks and depth: same size as the image, undistorted and downscaled by nearest sample.
        // `--masks` replaces the file's own
        let own =
            f.get("instance_mask_path").or_else(|| f.get("mask_path")).and_then(Value::as_str).map(|r| dir.join(r));
        let given = super::given_mask(opts, &path)?;
        let from_mask_path = given.is_none() && f.get("instance_mask_path").is_none() && own.is_some();
        let instance_ids = match given.or(own) {
            Some(p) => {
                let ids = read_ids_full(&p, w, h)?;
                // nerfstudio's own `mask_path` is a 0/255 validity mask, not instance ids
                if from_mask_path && !warned_binary && ids.contains(&255) && ids.iter().all(|&v| v == 0 || v == 255) {
                    crate::error::warn(format!(
                        "{}: frame {i}'s mask_path {} holds only 0 and 255, like nerfstudio's validity masks: read as \
                         instance ids (one object, id 255); give instance ids as instance_mask_path",
                        file.display(),
                        p.display()
                    ));
                    warned_binary = true;
                }
                Some(resample(ids, remap, w, h, k))
            }
            None => None,
        };
        let depth = match f.get("depth_file_path").and_then(Value::as_str) {
            Some(rel) => Some(resample(read_depth16_full(&dir.join(rel), w, h, depth_scale)?, remap, w, h, k)),
            None => None,
        };
        views.push(View { image_path: path, camera, rgb, instance_ids, depth });
    }
    // masks for every frame or none (as `--masks` requires): a scene trained with masks for part
    // of its views would learn no objects in the others
    let with = views.iter().filter(|v| v.instance_ids.is_some()).count();
    if let Some(v) = views.iter().find(|v| v.instance_ids.is_none()).filter(|_| with > 0) {
        return Err(err(
            file,
            format!(
                "the frame of {} has no instance_mask_path while {with} of the {} frames have one: every frame \
                 needs a mask, or none",
                v.image_path.display(),
                views.len()
            ),
        ));
    }
    Ok(views)
}
