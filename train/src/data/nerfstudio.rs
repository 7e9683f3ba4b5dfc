//! nerfstudio `transforms.json` and its Blender/NeRF-synthetic variant
//! (`transforms_train.json` / `transforms_test.json`, `camera_angle_x`, extension-less paths,
//! RGBA images whose alpha is the foreground).
//!
//! Poses are camera-to-world in the OpenGL convention and become OpenCV world-to-camera
//! [`Camera`]s. Lens distortion is refused with a clear message (undistort the images first).
//! Images are 8-bit PNG or JPEG; masks (`instance_mask_path` or `mask_path`) are 8-bit id
//! images; depth (`depth_file_path`) is 16-bit PNG scaled by `depth_unit_scale_factor`.
//! [`LoadOptions`], [`View`] and [`Dataset`] are shared with the other loaders (`crate::data`).

use super::image::{decode, err, read_depth16, read_ids8};
pub use super::{Background, Dataset, LoadOptions, View};
use super::{check_options, split};
use glam::{Mat4, Vec4};
use serde_json::Value;
use splat_kernels::Camera;
use std::path::Path;

fn num(v: &Value, key: &str) -> Option<f32> {
    v.get(key).and_then(Value::as_f64).map(|x| x as f32)
}

/// Loads `dir/transforms.json`, or the Blender split files `transforms_train.json` (+ `_test`).
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset, String> {
    check_options(opts)?;
    let single = dir.join("transforms.json");
    let train_file = dir.join("transforms_train.json");
    let test_file = dir.join("transforms_test.json");
    if single.is_file() {
        let views = load_file(&single, dir, opts)?;
        Ok(split(views, opts.holdout_every))
    } else if train_file.is_file() {
        let train = load_file(&train_file, dir, opts)?;
        if test_file.is_file() {
            Ok(Dataset {
                train,
                test: load_file(&test_file, dir, opts)?,
            })
        } else {
            Ok(split(train, opts.holdout_every))
        }
    } else {
        Err(err(dir, "no transforms.json or transforms_train.json here"))
    }
}

fn load_file(file: &Path, dir: &Path, opts: &LoadOptions) -> Result<Vec<View>, String> {
    let text = std::fs::read_to_string(file).map_err(|e| err(file, format!("cannot read: {e}")))?;
    let root: Value = serde_json::from_str(&text).map_err(|e| err(file, format!("invalid JSON: {e}")))?;
    let frames = root
        .get("frames")
        .and_then(Value::as_array)
        .ok_or_else(|| err(file, "no `frames` array"))?;
    if frames.is_empty() {
        return Err(err(file, "`frames` is empty"));
    }
    let depth_scale = num(&root, "depth_unit_scale_factor").unwrap_or(1.0);
    let mut views = Vec::with_capacity(frames.len());
    for (i, f) in frames.iter().enumerate() {
        let at = |m: &str| err(file, format!("frame {i}: {m}"));
        for key in ["k1", "k2", "k3", "k4", "p1", "p2"] {
            let k = num(f, key).or_else(|| num(&root, key)).unwrap_or(0.0);
            if k != 0.0 {
                return Err(at(&format!(
                    "lens distortion ({key} = {k}) is not supported; undistort the images first (e.g. COLMAP image_undistorter)"
                )));
            }
        }
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
        if let (Some(ew), Some(eh)) = (get("w"), get("h")) {
            if ew as u32 != w || eh as u32 != h {
                return Err(err(&path, format!("image is {w}x{h} but the transforms say {ew}x{eh}")));
            }
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
        let m = f
            .get("transform_matrix")
            .and_then(Value::as_array)
            .filter(|rows| rows.len() >= 3)
            .ok_or_else(|| at("no 4x4 `transform_matrix`"))?;
        let mut c2w = [[0.0f32; 4]; 4];
        c2w[3][3] = 1.0;
        for (r, row) in m.iter().take(4).enumerate() {
            let row = row.as_array().filter(|r| r.len() == 4).ok_or_else(|| at("`transform_matrix` rows need 4 numbers"))?;
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
        let (dw, dh, rgb) = img.to_rgb(&path, k, opts.background)?;
        let mut camera = Camera::new(cv.inverse(), fx / k as f32, fy / k as f32, dw, dh);
        camera.cx = cx / k as f32;
        camera.cy = cy / k as f32;
        // Masks and depth: same size as the image, downscaled by nearest sample.
        let instance_ids = match f.get("instance_mask_path").or_else(|| f.get("mask_path")).and_then(Value::as_str) {
            Some(rel) => Some(read_ids8(&dir.join(rel), w, h, k)?),
            None => None,
        };
        let depth = match f.get("depth_file_path").and_then(Value::as_str) {
            Some(rel) => Some(read_depth16(&dir.join(rel), w, h, k, depth_scale)?),
            None => None,
        };
        views.push(View {
            image_path: path,
            camera,
            rgb,
            instance_ids,
            depth,
        });
    }
    Ok(views)
}
