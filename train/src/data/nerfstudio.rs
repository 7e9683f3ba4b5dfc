//! nerfstudio `transforms.json` and its Blender/NeRF-synthetic variant
//! (`transforms_train.json` / `transforms_test.json`, `camera_angle_x`, extension-less paths,
//! RGBA images whose alpha is the foreground).
//!
//! Poses are camera-to-world in the OpenGL convention and become OpenCV world-to-camera
//! [`Camera`]s. Lens distortion is refused with a clear message (undistort the images first).
//! Images are 8-bit PNG; masks (`instance_mask_path` or `mask_path`) are 8-bit id images;
//! depth (`depth_file_path`) is 16-bit PNG scaled by `depth_unit_scale_factor`.

use glam::{Mat4, Vec4};
use model::images::{read_gray16, read_png8};
use serde_json::Value;
use splat_kernels::Camera;
use std::path::{Path, PathBuf};

/// How RGBA images are flattened.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Background {
    White,
    Black,
}

/// Loader options.
#[derive(Clone, Debug)]
pub struct LoadOptions {
    /// Integer downscale factor (box filter); 1 keeps the full resolution.
    pub downscale: u32,
    /// Background for RGBA images.
    pub background: Background,
    /// Without a test split on disk, every `holdout_every`-th view is held out (0: none).
    pub holdout_every: usize,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self {
            downscale: 1,
            background: Background::White,
            holdout_every: 8,
        }
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

fn err(path: &Path, msg: impl std::fmt::Display) -> String {
    format!("{}: {msg}", path.display())
}

fn num(v: &Value, key: &str) -> Option<f32> {
    v.get(key).and_then(Value::as_f64).map(|x| x as f32)
}

/// Loads `dir/transforms.json`, or the Blender split files `transforms_train.json` (+ `_test`).
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset, String> {
    if opts.downscale == 0 {
        return Err("downscale must be at least 1".into());
    }
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

fn split(views: Vec<View>, every: usize) -> Dataset {
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
        if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("jpg") || e.eq_ignore_ascii_case("jpeg")) {
            return Err(err(&path, "JPEG images are not supported yet; convert to PNG"));
        }
        let (w, h, ch, bytes) = read_png8(&path)?;
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
        let (dw, dh) = (w / k, h / k);
        if dw == 0 || dh == 0 {
            return Err(err(&path, format!("{w}x{h} is smaller than the downscale factor {k}")));
        }
        let bg = match opts.background {
            Background::White => 1.0,
            Background::Black => 0.0,
        };
        let mut rgb = vec![0.0f32; (dw * dh * 3) as usize];
        let norm = 1.0 / (k * k) as f32;
        for y in 0..dh {
            for x in 0..dw {
                let mut acc = [0.0f32; 3];
                for sy in 0..k {
                    for sx in 0..k {
                        let o = (((y * k + sy) * w + x * k + sx) as usize) * ch;
                        let px = &bytes[o..o + ch];
                        let (c, a) = match ch {
                            1 => ([px[0]; 3], 255),
                            2 => ([px[0]; 3], px[1]),
                            3 => ([px[0], px[1], px[2]], 255),
                            _ => ([px[0], px[1], px[2]], px[3]),
                        };
                        let a = a as f32 / 255.0;
                        for q in 0..3 {
                            acc[q] += c[q] as f32 / 255.0 * a + bg * (1.0 - a);
                        }
                    }
                }
                let o = ((y * dw + x) * 3) as usize;
                for q in 0..3 {
                    rgb[o + q] = acc[q] * norm;
                }
            }
        }
        let mut camera = Camera::new(cv.inverse(), fx / k as f32, fy / k as f32, dw, dh);
        camera.cx = cx / k as f32;
        camera.cy = cy / k as f32;
        // Masks and depth: same size as the image, downscaled by nearest sample (top-left of each
        // block) so that ids stay exact.
        let check_size = |p: &Path, sw: u32, sh: u32| -> Result<(), String> {
            if (sw, sh) == (w, h) {
                Ok(())
            } else {
                Err(err(p, format!("is {sw}x{sh} but its image is {w}x{h}")))
            }
        };
        let instance_ids = match f.get("instance_mask_path").or_else(|| f.get("mask_path")).and_then(Value::as_str) {
            Some(rel) => {
                let p = dir.join(rel);
                let (mw, mh, mc, bytes) = read_png8(&p)?;
                check_size(&p, mw, mh)?;
                let ids: Vec<u8> = bytes.chunks(mc).map(|c| c[0]).collect();
                Some(subsample(&ids, w, dw, dh, k))
            }
            None => None,
        };
        let depth = match f.get("depth_file_path").and_then(Value::as_str) {
            Some(rel) => {
                let p = dir.join(rel);
                let (dw16, dh16, mm) = read_gray16(&p)?;
                check_size(&p, dw16, dh16)?;
                let full: Vec<f32> = mm.into_iter().map(|d| d as f32 * depth_scale).collect();
                Some(subsample(&full, w, dw, dh, k))
            }
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

/// Nearest-sample downscale of a `[h, w]` map (row stride `w`) to `[dh, dw]` by factor `k`.
fn subsample<T: Copy>(full: &[T], w: u32, dw: u32, dh: u32, k: u32) -> Vec<T> {
    (0..dh)
        .flat_map(|y| (0..dw).map(move |x| full[((y * k) * w + x * k) as usize]))
        .collect()
}
