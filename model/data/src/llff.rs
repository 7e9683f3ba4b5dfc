//! LLFF scenes (`poses_bounds.npy` + `images/`), as produced by LLFF's `imgs2poses.py` and used by
//! the original NeRF forward-facing scenes.
//!
//! * `dir/poses_bounds.npy`: a NumPy array of shape `(N, 17)`, dtype `<f8` or `<f4`, C order.
//!   Row `i` is a row-major 3x5 matrix `[R | t | (h, w, f)]` followed by the `near` and `far`
//!   scene bounds. `R`'s columns are the camera's axes in world coordinates in LLFF's
//!   convention `[down, right, backwards]`, `t` is the camera centre, `(h, w)` the image size the
//!   poses were computed at and `f` the focal length in those pixels.
//! * `dir/images/`: the `N` images (PNG or JPEG), matched to the rows in file-name order.
//! * `dir/images_{k}/`: pre-downscaled copies; with `downscale = k` they are used instead of
//!   box-filtering `images/` when they exist with `N` images and there are no masks.
//! * `dir/masks/<image stem>.png` (optional): 8-bit instance ids (0 = background) the size of
//!   the image in `images/`; Gaussian Grouping's `dir/object_mask/` is read the same way when
//!   there is no `masks/`.
//!
//! Cameras: OpenCV camera-to-world axes `[right, down, forward] = [R1, R0, -R2]`, inverted to
//! `world_to_cam`. The focal length is scaled by `image width / w` when the images on disk have
//! another size than `(h, w)`; the principal point is the image centre. `near`/`far` are only
//! validated (`0 < near < far`). Views keep the file-name order before the holdout split.

use super::image::{decode, err, list_images, read_ids};
use super::{Dataset, LoadOptions, View, check_options, split};
use crate::error::Result;
use glam::{DMat4, DVec3};
use splat_kernels::Camera;
use std::path::Path;

/// Values per row of `poses_bounds.npy`.
const COLS: usize = 17;

/// Loads an LLFF scene (see the module docs).
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    check_options(opts)?;
    let npy = dir.join("poses_bounds.npy");
    let rows = read_npy(&npy)?;
    let n = rows.len();
    let k = opts.downscale;
    let masks = super::mask_dir(dir);
    let small = dir.join(format!("images_{k}"));
    let mut box_k = k;
    let mut images_dir = dir.join("images");
    if k > 1 && small.is_dir() && !masks.is_dir() && list_images(&small)?.len() == n {
        images_dir = small;
        box_k = 1;
    }
    if !images_dir.is_dir() {
        return Err(err(&images_dir, "image directory is missing"));
    }
    let files = list_images(&images_dir)?;
    if files.len() != n {
        return Err(err(&images_dir, format!("holds {} images but {} has {n} poses", files.len(), npy.display())));
    }
    let mut missing_masks = vec![];
    let mut views = Vec::with_capacity(n);
    for (i, (row, path)) in rows.iter().zip(files).enumerate() {
        let at = |m: String| err(&npy, format!("row {i}: {m}"));
        let m = |r: usize, c: usize| row[r * 5 + c];
        let (h, w, f) = (m(0, 4), m(1, 4), m(2, 4));
        if !(h.is_finite() && h > 0.0 && w.is_finite() && w > 0.0 && f.is_finite() && f > 0.0) {
            return Err(at(format!("(h, w, f) = ({h}, {w}, {f}) must be positive")));
        }
        let (near, far) = (row[15], row[16]);
        if !(near.is_finite() && far.is_finite() && near > 0.0 && near < far) {
            return Err(at(format!("near = {near} and far = {far} must satisfy 0 < near < far")));
        }
        let col = |c: usize| DVec3::new(m(0, c), m(1, c), m(2, c));
        // LLFF [down, right, back] -> OpenCV [right, down, forward].
        let c2w = DMat4::from_cols(col(1).extend(0.0), col(0).extend(0.0), (-col(2)).extend(0.0), col(3).extend(1.0));
        if !c2w.is_finite() || c2w.determinant().abs() < 1e-9 {
            return Err(at("the pose is not an invertible rotation and translation".into()));
        }
        let img = decode(&path)?;
        let (iw, ih) = (img.width, img.height);
        let s = iw as f64 / w;
        if (ih as f64 - h * s).abs() > (0.01 * ih as f64).max(1.0) {
            return Err(err(
                &path,
                format!("image is {iw}x{ih}, which is not a rescaled {w}x{h} as {} says (row {i})", npy.display()),
            ));
        }
        let (dw, dh, rgb) = img.to_rgb(&path, box_k, opts.background)?;
        let fk = (f * s / box_k as f64) as f32;
        let mut camera = Camera::new(c2w.inverse().as_mat4(), fk, fk, dw, dh);
        camera.cx = iw as f32 * 0.5 / box_k as f32;
        camera.cy = ih as f32 * 0.5 / box_k as f32;
        let mut mask_name = path.file_stem().map(|s| s.to_os_string()).unwrap_or_default();
        mask_name.push(".png");
        let mask = masks.join(mask_name);
        let instance_ids = super::own_mask(opts, mask, &mut missing_masks, |m| read_ids(m, iw, ih, box_k))?;
        views.push(View { image_path: path, camera, rgb, instance_ids, depth: None });
    }
    super::check_own_masks(&masks, &missing_masks, views.len())?;
    super::apply_masks(&mut views, opts)?;
    split(views, opts.holdout_every)
}

/// Reads a `(N, 17)` little-endian float array from a NumPy `.npy` file (format versions 1-3).
fn read_npy(path: &Path) -> Result<Vec<[f64; COLS]>> {
    let data = std::fs::read(path).map_err(|e| err(path, format!("cannot read: {e}")))?;
    if data.len() < 10 || &data[..6] != b"\x93NUMPY" {
        return Err(err(path, "not a NumPy .npy file (bad magic)"));
    }
    let (hlen, start): (usize, usize) = match data[6] {
        1 => (u16::from_le_bytes([data[8], data[9]]) as usize, 10),
        2 | 3 if data.len() >= 12 => (u32::from_le_bytes([data[8], data[9], data[10], data[11]]) as usize, 12),
        2 | 3 => return Err(err(path, "truncated .npy header")),
        v => return Err(err(path, format!("unsupported .npy format version {v}"))),
    };
    let end = start.checked_add(hlen).filter(|&e| e <= data.len()).ok_or_else(|| err(path, "truncated .npy header"))?;
    let header = std::str::from_utf8(&data[start..end]).map_err(|_| err(path, ".npy header is not text"))?;
    let descr = dict_value(header, "descr")
        .and_then(|v| {
            let q = v.chars().next().filter(|c| *c == '\'' || *c == '"')?;
            v[1..].split(q).next()
        })
        .ok_or_else(|| err(path, "the .npy header has no 'descr'"))?;
    let fortran =
        dict_value(header, "fortran_order").ok_or_else(|| err(path, "the .npy header has no 'fortran_order'"))?;
    let shape_text = dict_value(header, "shape")
        .and_then(|v| v.strip_prefix('(')?.split(')').next())
        .ok_or_else(|| err(path, "the .npy header has no 'shape' tuple"))?;
    let shape = shape_text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.trim_end_matches('L').parse::<usize>())
        .collect::<Result<Vec<_>, _>>()
        .map_err(|_| err(path, format!("cannot parse the .npy shape ({shape_text})")))?;
    let size = match descr {
        "<f8" => 8,
        "<f4" => 4,
        other => return Err(err(path, format!("dtype '{other}' is not supported (need '<f8' or '<f4')"))),
    };
    if !fortran.starts_with("False") {
        return Err(err(path, "fortran_order arrays are not supported (need C order)"));
    }
    if shape.len() != 2 || shape[1] != COLS {
        return Err(err(
            path,
            format!(
                "shape ({shape_text}) is not (N, 17): each row must hold a 3x5 pose [R | t | (h, w, f)] and near, far"
            ),
        ));
    }
    let n = shape[0];
    if n == 0 {
        return Err(err(path, "holds no poses"));
    }
    let body = &data[end..];
    let need = n.checked_mul(COLS * size);
    if need != Some(body.len()) {
        return Err(err(
            path,
            format!(
                "holds {} data bytes but shape ({n}, {COLS}) of {descr} needs {}",
                body.len(),
                n as u128 * (COLS * size) as u128
            ),
        ));
    }
    let values: Vec<f64> = if size == 8 {
        body.chunks_exact(8).map(|b| f64::from_le_bytes(b.try_into().unwrap_or([0; 8]))).collect()
    } else {
        body.chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap_or([0; 4])) as f64).collect()
    };
    Ok(values.chunks_exact(COLS).map(|r| std::array::from_fn(|c| r[c])).collect())
}

/// The text after `'key':` in a Python dict literal (the `.npy` header), leading spaces removed.
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    [format!("'{key}'"), format!("\"{key}\"")].iter().find_map(|quoted| {
        let at = header.find(quoted.as_str())? + quoted.len();
        header[at..].trim_start().strip_prefix(':').map(str::trim_start)
    })
}
