//! Replica sequences as rendered by Semantic-NeRF (`Replica_Dataset/<scene>/Sequence_N/`).
//!
//! * `dir/traj_w_c.txt`: one line per frame, 16 numbers: the row-major 4x4 camera-to-world
//!   matrix in the OpenCV convention (x right, y down, z forward). The number of lines is the
//!   number of frames.
//! * `dir/rgb/rgb_{i}.png`: the colour image of frame `i` (0-based).
//! * `dir/depth/depth_{i}.png` (optional directory): 16-bit camera-space depth in millimetres,
//!   loaded in metres (`value / 1000`; 0 = no depth).
//! * `dir/semantic_instance/semantic_instance_{i}.png` (optional directory): instance labels.
//!   8-bit label images are used as they are. 16-bit ones (sparse ids) are made dense over the
//!   whole sequence: id 0 stays 0 (background / void), every other id gets the next free value 1,
//!   2, ... in order of first appearance (frames in order, pixels in raster order, at full
//!   resolution, so the mapping does not depend on the downscale factor). More than
//!   [`MAX_INSTANCE_ID`](crate::MAX_INSTANCE_ID) distinct non-zero ids is an error, as is a
//!   sequence mixing 8- and 16-bit label images.
//! * `dir/intrinsics.json` (optional): `{"fx", "fy", "cx", "cy"}` in pixels of the full-size
//!   image, in [`Camera`]'s convention (the top-left pixel's centre is `(0.5, 0.5)`).
//!
//! Without `intrinsics.json` the Semantic-NeRF camera is used: a 90 degree horizontal field of
//! view, `fx = fy = (W/2) / tan(45 deg)`, and the principal point at the image centre. Semantic-NeRF
//! writes that centre as `((W-1)/2, (H-1)/2)` because it puts pixel centres at integer
//! coordinates; in [`Camera`]'s convention (centres at `+0.5`) the same point is `(W/2, H/2)`.
//!
//! Frames keep their index order before the holdout split.

use super::image::{check_size, decode, err, read_depth16, read_labels, subsample};
use super::{Dataset, LoadOptions, View, check_options, split};
use crate::error::Result;
use glam::{DMat4, DVec4};
use serde_json::Value;
use splat_kernels::Camera;
use std::collections::HashMap;
use std::path::Path;

/// Semantic-NeRF's horizontal field of view for Replica, in degrees.
pub const HFOV_DEG: f64 = 90.0;

/// Loads a Replica sequence (see the module docs).
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    check_options(opts)?;
    let traj = dir.join("traj_w_c.txt");
    let poses = read_trajectory(&traj)?;
    let intr_file = dir.join("intrinsics.json");
    let fixed = if intr_file.is_file() { Some(read_intrinsics(&intr_file)?) } else { None };
    let depth_dir = dir.join("depth");
    let label_dir = dir.join("semantic_instance");
    let (has_depth, has_labels) = (depth_dir.is_dir(), label_dir.is_dir());
    let mut compact = Compactor::default();
    let k = opts.downscale;
    let mut views = Vec::with_capacity(poses.len());
    for (i, c2w) in poses.iter().enumerate() {
        let path = dir.join("rgb").join(format!("rgb_{i}.png"));
        if !path.is_file() {
            return Err(err(
                &path,
                format!("image of frame {i} is missing ({} lists {} frames)", traj.display(), poses.len()),
            ));
        }
        let img = decode(&path)?;
        let (w, h) = (img.width, img.height);
        let [fx, fy, cx, cy] = fixed.unwrap_or_else(|| {
            let f = 0.5 * w as f64 / (0.5 * HFOV_DEG).to_radians().tan();
            [f, f, 0.5 * w as f64, 0.5 * h as f64]
        });
        let (dw, dh, rgb) = img.to_rgb(&path, k, opts.background)?;
        let s = k as f64;
        let mut camera = Camera::new(c2w.inverse().as_mat4(), (fx / s) as f32, (fy / s) as f32, dw, dh);
        camera.cx = (cx / s) as f32;
        camera.cy = (cy / s) as f32;
        let depth = if has_depth {
            let p = depth_dir.join(format!("depth_{i}.png"));
            if !p.is_file() {
                return Err(err(&p, format!("depth of frame {i} is missing")));
            }
            Some(read_depth16(&p, w, h, k, 1e-3)?)
        } else {
            None
        };
        let instance_ids = if has_labels {
            let p = label_dir.join(format!("semantic_instance_{i}.png"));
            if !p.is_file() {
                return Err(err(&p, format!("instance labels of frame {i} are missing")));
            }
            let (lw, lh, values, sixteen) = read_labels(&p)?;
            check_size(&p, (lw, lh), (w, h))?;
            let ids = compact.map(&p, &values, sixteen)?;
            Some(subsample(&ids, w, dw, dh, k))
        } else {
            None
        };
        views.push(View { image_path: path, camera, rgb, instance_ids, depth });
    }
    super::apply_masks(&mut views, opts)?;
    split(views, opts.holdout_every)
}

/// Sequence-wide mapping of 16-bit instance ids to dense ids 1..=N (see the module docs).
#[derive(Default)]
struct Compactor {
    sixteen: Option<bool>,
    ids: HashMap<u16, u16>,
}

impl Compactor {
    fn map(&mut self, path: &Path, values: &[u16], sixteen: bool) -> Result<Vec<u16>> {
        match self.sixteen {
            Some(s) if s != sixteen => {
                let bits = |s: bool| if s { 16 } else { 8 };
                return Err(err(
                    path,
                    format!("{}-bit labels in a sequence whose earlier labels are {}-bit", bits(sixteen), bits(s)),
                ));
            }
            _ => self.sixteen = Some(sixteen),
        }
        if !sixteen {
            return Ok(values.to_vec());
        }
        let mut out = Vec::with_capacity(values.len());
        for &v in values {
            let id = if v == 0 {
                0
            } else if let Some(&id) = self.ids.get(&v) {
                id
            } else {
                let next = self.ids.len() + 1;
                let id = u16::try_from(next).ok().filter(|&id| id <= crate::MAX_INSTANCE_ID).ok_or_else(|| {
                    err(
                        path,
                        format!(
                            "more than {} distinct non-zero instance ids in the sequence (the identity classifier \
                             has a class per id)",
                            crate::MAX_INSTANCE_ID
                        ),
                    )
                })?;
                self.ids.insert(v, id);
                id
            };
            out.push(id);
        }
        Ok(out)
    }
}

/// Camera-to-world matrices, one per non-empty line.
fn read_trajectory(path: &Path) -> Result<Vec<DMat4>> {
    let text = std::fs::read_to_string(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    let mut poses = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let at = |m: String| err(path, format!("line {}: {m}", i + 1));
        let vals = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|t| !t.is_empty())
            .map(|t| t.parse::<f64>().map_err(|_| at(format!("cannot parse `{t}` as a number"))))
            .collect::<Result<Vec<_>, _>>()?;
        let vals: [f64; 16] = vals.try_into().map_err(|v: Vec<f64>| {
            at(format!("{} numbers, expected 16 (a row-major 4x4 camera-to-world matrix)", v.len()))
        })?;
        let m = DMat4::from_cols_array(&vals).transpose();
        if !m.is_finite() || (m.row(3) - DVec4::W).abs().max_element() > 1e-6 || m.determinant().abs() < 1e-9 {
            return Err(at("not an invertible camera-to-world matrix with last row 0 0 0 1".into()));
        }
        poses.push(m);
    }
    if poses.is_empty() {
        return Err(err(path, "holds no poses"));
    }
    Ok(poses)
}

/// `[fx, fy, cx, cy]` from `intrinsics.json`.
fn read_intrinsics(path: &Path) -> Result<[f64; 4]> {
    let text = std::fs::read_to_string(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    let v: Value = serde_json::from_str(&text).map_err(|e| err(path, format!("invalid JSON: {e}")))?;
    let mut out = [0.0; 4];
    for (o, key) in out.iter_mut().zip(["fx", "fy", "cx", "cy"]) {
        *o = v
            .get(key)
            .and_then(Value::as_f64)
            .filter(|x| x.is_finite())
            .ok_or_else(|| err(path, format!("`{key}` is missing or not a finite number")))?;
    }
    if out[0] <= 0.0 || out[1] <= 0.0 {
        return Err(err(path, "fx and fy must be positive"));
    }
    Ok(out)
}
