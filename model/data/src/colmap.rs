//! COLMAP sparse reconstructions of undistorted images.
//!
//! Layout: `dir/sparse/0/{cameras,images,points3D}.{bin,txt}` (or the same files directly in
//! `dir/sparse/`), images in `dir/images/<name>` and optional instance masks in
//! `dir/masks/<name with extension .png>` (8-bit ids, 0 = background; Gaussian Grouping's
//! `dir/object_mask/` is read the same way when there is no `masks/`). For each of the three
//! model files the binary version is used when both exist.
//!
//! Both encodings follow COLMAP's `model.cc` (binary: little endian):
//!
//! * `cameras`: `u64 count`, then per camera `i32 id, i32 model, u64 width, u64 height,
//!   f64 params[n(model)]`; text: `ID MODEL_NAME WIDTH HEIGHT PARAMS...`.
//! * `images`: `u64 count`, then per image `i32 id, f64 qw qx qy qz, f64 tx ty tz, i32 camera_id,
//!   name (NUL-terminated), u64 n, n x (f64 x, f64 y, i64 point3D_id)`; text: two lines per
//!   image, `ID QW QX QY QZ TX TY TZ CAMERA_ID NAME` and the (possibly empty) `X Y POINT3D_ID ...`.
//! * `points3D`: `u64 count`, then per point `u64 id, f64 x y z, u8 r g b, f64 error, u64 n,
//!   n x (i32 image_id, i32 point2D_idx)`; text: `ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)...`.
//!
//! Text lines starting with `#` are comments; COLMAP's `# Number of ...: N` header lines are
//! checked against the entries listed.
//!
//! Poses `(q, t)` are world-to-camera in the OpenCV convention (`p_cam = R(q) p + t`), which is
//! [`Camera`]'s, so they are used as they are. COLMAP's pixel convention (the top-left pixel's
//! centre is `(0.5, 0.5)`) is also [`Camera`]'s, so `cx, cy` are taken verbatim.
//!
//! Camera models: `PINHOLE` and `SIMPLE_PINHOLE`; `SIMPLE_RADIAL`, `RADIAL`, `OPENCV`,
//! `FULL_OPENCV` and `FOV` only when all their distortion parameters are exactly 0 (then they
//! are pinhole cameras). Fisheye models and non-zero distortion are refused: run
//! `colmap image_undistorter` and load its output.
//!
//! Views are sorted by image name, then every `holdout_every`-th is held out for testing.

use super::image::{decode, err, read_ids};
use super::{Dataset, LoadOptions, View, check_options, split};
use crate::error::Result;
use glam::{DMat3, DMat4, DQuat, DVec3};
use splat_kernels::Camera;
use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

/// The sparse points of the reconstruction (`points3D`), in file order, for initialising
/// Gaussians: positions in world units and 8-bit colours.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SparsePoints {
    pub xyz: Vec<[f32; 3]>,
    pub rgb: Vec<[u8; 3]>,
}

/// A COLMAP camera model: id, name, parameter count, whether the focal length is shared
/// (`f, cx, cy, ...` rather than `fx, fy, cx, cy, ...`), whether it is a fisheye projection.
struct Model {
    id: i32,
    name: &'static str,
    params: usize,
    single_focal: bool,
    fisheye: bool,
}

const fn model(id: i32, name: &'static str, params: usize, single_focal: bool, fisheye: bool) -> Model {
    Model { id, name, params, single_focal, fisheye }
}

/// COLMAP's camera models (`src/colmap/sensor/models.h`).
const MODELS: [Model; 12] = [
    model(0, "SIMPLE_PINHOLE", 3, true, false),
    model(1, "PINHOLE", 4, false, false),
    model(2, "SIMPLE_RADIAL", 4, true, false),
    model(3, "RADIAL", 5, true, false),
    model(4, "OPENCV", 8, false, false),
    model(5, "OPENCV_FISHEYE", 8, false, true),
    model(6, "FULL_OPENCV", 12, false, false),
    model(7, "FOV", 5, false, false),
    model(8, "SIMPLE_RADIAL_FISHEYE", 4, true, true),
    model(9, "RADIAL_FISHEYE", 5, true, true),
    model(10, "THIN_PRISM_FISHEYE", 12, false, true),
    model(11, "RAD_TAN_THIN_PRISM_FISHEYE", 16, false, true),
];

/// Pinhole intrinsics of one COLMAP camera, in pixels of the full-resolution image.
#[derive(Clone, Copy, Debug)]
struct Intrinsics {
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

/// One registered image: world-to-camera rotation `(qw, qx, qy, qz)` and translation.
struct ImageRec {
    id: i32,
    q: [f64; 4],
    t: [f64; 3],
    camera_id: i32,
    name: String,
}

/// Loads a COLMAP project (see the module docs): the views, split into train and test, and the
/// sparse points.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<(Dataset, SparsePoints)> {
    check_options(opts)?;
    let sparse = find_sparse(dir)?;
    let cam_file = pick(&sparse, "cameras")?;
    let img_file = pick(&sparse, "images")?;
    let pts_file = pick(&sparse, "points3D")?;
    let cameras = if is_bin(&cam_file) { cameras_bin(&cam_file)? } else { cameras_txt(&cam_file)? };
    let mut images = if is_bin(&img_file) { images_bin(&img_file)? } else { images_txt(&img_file)? };
    let points = if is_bin(&pts_file) { points_bin(&pts_file)? } else { points_txt(&pts_file)? };
    if images.is_empty() {
        return Err(err(&img_file, "no registered images"));
    }
    let mut names = HashSet::new();
    for im in &images {
        if !names.insert(im.name.as_str()) {
            return Err(err(&img_file, format!("image name `{}` appears twice", im.name)));
        }
    }
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let cam_name = file_name(&cam_file);
    let images_dir = dir.join("images");
    if !images_dir.is_dir() {
        return Err(err(&images_dir, "image directory is missing"));
    }
    let k = opts.downscale;
    let mut missing_masks = vec![];
    let mut views = Vec::with_capacity(images.len());
    for im in &images {
        let intr = cameras.get(&im.camera_id).ok_or_else(|| {
            err(
                &img_file,
                format!(
                    "image {} ({}) refers to camera {}, which {cam_name} does not define",
                    im.id, im.name, im.camera_id
                ),
            )
        })?;
        let path = images_dir.join(&im.name);
        if !path.is_file() {
            return Err(err(&path, format!("image is missing (listed in {})", file_name(&img_file))));
        }
        let img = decode(&path)?;
        let (w, h) = (img.width, img.height);
        if (w, h) != (intr.width, intr.height) {
            return Err(err(
                &path,
                format!("image is {w}x{h} but camera {} in {cam_name} is {}x{}", im.camera_id, intr.width, intr.height),
            ));
        }
        let world_to_cam = pose(&im.q, &im.t).ok_or_else(|| {
            err(&img_file, format!("image {} ({}): the pose is not a finite rotation and translation", im.id, im.name))
        })?;
        let (dw, dh, rgb) = img.to_rgb(&path, k, opts.background)?;
        let s = k as f64;
        let mut camera = Camera::new(world_to_cam, (intr.fx / s) as f32, (intr.fy / s) as f32, dw, dh);
        camera.cx = (intr.cx / s) as f32;
        camera.cy = (intr.cy / s) as f32;
        let mask = super::mask_dir(dir).join(Path::new(&im.name).with_extension("png"));
        let instance_ids = super::own_mask(opts, mask, &mut missing_masks, |m| read_ids(m, w, h, k))?;
        views.push(View { image_path: path, camera, rgb, instance_ids, depth: None });
    }
    super::check_own_masks(&super::mask_dir(dir), &missing_masks, views.len())?;
    super::apply_masks(&mut views, opts)?;
    Ok((split(views, opts.holdout_every)?, points))
}

/// `dir/sparse/0` when it exists, else `dir/sparse` when it holds a cameras file.
fn find_sparse(dir: &Path) -> Result<PathBuf> {
    let zero = dir.join("sparse").join("0");
    if zero.is_dir() {
        return Ok(zero);
    }
    let flat = dir.join("sparse");
    if flat.join("cameras.bin").is_file() || flat.join("cameras.txt").is_file() {
        return Ok(flat);
    }
    Err(err(&flat, "no COLMAP model: looked for sparse/0/ and sparse/cameras.{bin,txt}"))
}

/// `<stem>.bin` if present, else `<stem>.txt`.
fn pick(sparse: &Path, stem: &str) -> Result<PathBuf> {
    let bin = sparse.join(format!("{stem}.bin"));
    let txt = sparse.join(format!("{stem}.txt"));
    if bin.is_file() {
        Ok(bin)
    } else if txt.is_file() {
        Ok(txt)
    } else {
        Err(err(&bin, format!("missing (and so is {stem}.txt)")))
    }
}

fn is_bin(path: &Path) -> bool {
    path.extension().is_some_and(|e| e == "bin")
}

fn file_name(path: &Path) -> String {
    path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()
}

/// World-to-camera from a (not necessarily unit) quaternion `(w, x, y, z)` and a translation.
fn pose(q: &[f64; 4], t: &[f64; 3]) -> Option<glam::Mat4> {
    let q = DQuat::from_xyzw(q[1], q[2], q[3], q[0]);
    let t = DVec3::from_array(*t);
    let n = q.length();
    if !(n.is_finite() && n > 1e-9 && t.is_finite()) {
        return None;
    }
    let r = DMat3::from_quat(q / n);
    let m = DMat4::from_cols(r.x_axis.extend(0.0), r.y_axis.extend(0.0), r.z_axis.extend(0.0), t.extend(1.0));
    Some(m.as_mat4())
}

/// Checks a camera's model and parameters and returns its pinhole intrinsics.
fn intrinsics(file: &Path, id: i32, m: &Model, width: u64, height: u64, p: &[f64]) -> Result<Intrinsics> {
    let at = |msg: String| err(file, format!("camera {id} ({}): {msg}", m.name));
    if m.fisheye {
        return Err(at(
            "fisheye models are not supported; undistort the images with `colmap image_undistorter` and load its output"
                .into(),
        ));
    }
    let basic = if m.single_focal { 3 } else { 4 };
    if p.len() != m.params {
        return Err(at(format!("needs {} parameters, found {}", m.params, p.len())));
    }
    let dist = &p[basic..];
    if dist.iter().any(|&d| d != 0.0) {
        return Err(at(format!(
            "non-zero distortion parameters {dist:?} are not supported; undistort the images with \
             `colmap image_undistorter` and load its output"
        )));
    }
    let (fx, fy, cx, cy) = if m.single_focal { (p[0], p[0], p[1], p[2]) } else { (p[0], p[1], p[2], p[3]) };
    if !(fx.is_finite() && fx > 0.0 && fy.is_finite() && fy > 0.0 && cx.is_finite() && cy.is_finite()) {
        return Err(at(format!(
            "focal lengths ({fx}, {fy}) must be positive and the principal point ({cx}, {cy}) finite"
        )));
    }
    let size = |v: u64| u32::try_from(v).ok().filter(|&v| v > 0);
    let (Some(width), Some(height)) = (size(width), size(height)) else {
        return Err(at(format!("image size {width}x{height} is invalid")));
    };
    Ok(Intrinsics { width, height, fx, fy, cx, cy })
}

fn insert_camera(file: &Path, map: &mut HashMap<i32, Intrinsics>, id: i32, c: Intrinsics) -> Result<()> {
    if map.insert(id, c).is_some() {
        return Err(err(file, format!("camera {id} is defined twice")));
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Binary files

/// A bounds-checked little-endian reader over a whole file.
struct Bin<'a> {
    path: &'a Path,
    data: &'a [u8],
    pos: usize,
}

impl<'a> Bin<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8]> {
        let left = self.data.len() - self.pos;
        if n > left {
            return Err(err(self.path, format!("truncated at byte {}: {what} needs {n} bytes, {left} left", self.pos)));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N]> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N, what)?);
        Ok(a)
    }
    fn u8(&mut self, what: &str) -> Result<u8> {
        Ok(self.array::<1>(what)?[0])
    }
    fn i32(&mut self, what: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.array(what)?))
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.array(what)?))
    }
    /// Skips `count` records of `size` bytes.
    fn skip(&mut self, count: u64, size: usize, what: &str) -> Result<()> {
        let n = count.checked_mul(size as u64).and_then(|n| usize::try_from(n).ok()).unwrap_or(usize::MAX);
        self.take(n, what).map(|_| ())
    }
    /// A NUL-terminated UTF-8 string.
    fn cstr(&mut self, what: &str) -> Result<String> {
        let start = self.pos;
        let Some(len) = self.data[start..].iter().position(|&b| b == 0) else {
            return Err(err(
                self.path,
                format!("truncated at byte {}: {what} has no terminating NUL", self.data.len()),
            ));
        };
        let bytes = self.take(len + 1, what)?;
        String::from_utf8(bytes[..len].to_vec())
            .map_err(|_| err(self.path, format!("{what} at byte {start} is not UTF-8")))
    }
    /// The leading record count, and a capacity that the remaining bytes can justify.
    fn count(&mut self, min_record: usize) -> Result<(u64, usize)> {
        let n = self.u64("the record count")?;
        let room = (self.data.len() - self.pos) / min_record.max(1);
        Ok((n, usize::try_from(n).unwrap_or(usize::MAX).min(room)))
    }
    /// Fails if bytes are left after the announced records.
    fn finish(&self, n: u64, what: &str) -> Result<()> {
        let left = self.data.len() - self.pos;
        if left > 0 {
            return Err(err(
                self.path,
                format!("{left} bytes left after the {n} {what} the header announces (count does not match the data)"),
            ));
        }
        Ok(())
    }
}

fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| err(path, format!("cannot read: {e}")))
}

fn cameras_bin(path: &Path) -> Result<HashMap<i32, Intrinsics>> {
    let data = read_bytes(path)?;
    let mut r = Bin { path, data: &data, pos: 0 };
    let (n, cap) = r.count(24)?;
    let mut map = HashMap::with_capacity(cap);
    for i in 0..n {
        let what = format!("camera {i}");
        let id = r.i32(&what)?;
        let model_id = r.i32(&what)?;
        let width = r.u64(&what)?;
        let height = r.u64(&what)?;
        let m = MODELS
            .iter()
            .find(|m| m.id == model_id)
            .ok_or_else(|| err(path, format!("camera {id}: unknown camera model id {model_id}")))?;
        let params = (0..m.params).map(|_| r.f64(&what)).collect::<Result<Vec<_>, _>>()?;
        insert_camera(path, &mut map, id, intrinsics(path, id, m, width, height, &params)?)?;
    }
    r.finish(n, "cameras")?;
    Ok(map)
}

fn images_bin(path: &Path) -> Result<Vec<ImageRec>> {
    let data = read_bytes(path)?;
    let mut r = Bin { path, data: &data, pos: 0 };
    let (n, cap) = r.count(73)?;
    let mut out = Vec::with_capacity(cap);
    for i in 0..n {
        let what = format!("image {i}");
        let id = r.i32(&what)?;
        let mut q = [0.0; 4];
        for v in &mut q {
            *v = r.f64(&what)?;
        }
        let mut t = [0.0; 3];
        for v in &mut t {
            *v = r.f64(&what)?;
        }
        let camera_id = r.i32(&what)?;
        let name = r.cstr(&format!("the name of image {id}"))?;
        if name.is_empty() {
            return Err(err(path, format!("image {id} has an empty name")));
        }
        let n2d = r.u64(&what)?;
        r.skip(n2d, 24, &format!("the {n2d} points2D of image {id}"))?;
        out.push(ImageRec { id, q, t, camera_id, name });
    }
    r.finish(n, "images")?;
    Ok(out)
}

fn points_bin(path: &Path) -> Result<SparsePoints> {
    let data = read_bytes(path)?;
    let mut r = Bin { path, data: &data, pos: 0 };
    let (n, cap) = r.count(51)?;
    let mut pts = SparsePoints { xyz: Vec::with_capacity(cap), rgb: Vec::with_capacity(cap) };
    for i in 0..n {
        let what = format!("point {i}");
        let id = r.u64(&what)?;
        let xyz = [r.f64(&what)?, r.f64(&what)?, r.f64(&what)?];
        let rgb = [r.u8(&what)?, r.u8(&what)?, r.u8(&what)?];
        r.f64(&what)?; // reprojection error
        let track = r.u64(&what)?;
        r.skip(track, 8, &format!("the track of point {id}"))?;
        pts.xyz.push(point_xyz(path, id, xyz)?);
        pts.rgb.push(rgb);
    }
    r.finish(n, "points")?;
    Ok(pts)
}

fn point_xyz(path: &Path, id: u64, xyz: [f64; 3]) -> Result<[f32; 3]> {
    let p = xyz.map(|v| v as f32);
    if p.iter().all(|v| v.is_finite()) {
        Ok(p)
    } else {
        Err(err(path, format!("point {id} has a non-finite position {xyz:?}")))
    }
}

// ---------------------------------------------------------------------------------------------
// Text files

fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| err(path, format!("cannot read: {e}")))
}

/// Parses one whitespace-separated field.
fn field<T: std::str::FromStr>(path: &Path, line: usize, tok: Option<&str>, what: &str) -> Result<T> {
    let tok = tok.ok_or_else(|| err(path, format!("line {line}: {what} is missing")))?;
    tok.parse().map_err(|_| err(path, format!("line {line}: cannot parse {what} from `{tok}`")))
}

/// The count in a COLMAP header comment `# Number of <noun>: N[, ...]`, if present.
fn header_count(text: &str, noun: &str) -> Option<usize> {
    let prefix = format!("# Number of {noun}:");
    text.lines().take_while(|l| l.starts_with('#')).find_map(|l| {
        let rest = l.strip_prefix(&prefix)?.trim_start();
        let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
        digits.parse().ok()
    })
}

fn check_header(path: &Path, text: &str, noun: &str, found: usize) -> Result<()> {
    match header_count(text, noun) {
        Some(n) if n != found => Err(err(path, format!("the header announces {n} {noun} but {found} are listed"))),
        _ => Ok(()),
    }
}

/// Non-empty, non-comment lines with their 1-based numbers.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn cameras_txt(path: &Path) -> Result<HashMap<i32, Intrinsics>> {
    let text = read_text(path)?;
    let mut map = HashMap::new();
    for (ln, line) in data_lines(&text) {
        let mut tok = line.split_whitespace();
        let id: i32 = field(path, ln, tok.next(), "CAMERA_ID")?;
        let name = tok.next().ok_or_else(|| err(path, format!("line {ln}: MODEL is missing")))?;
        let m = MODELS
            .iter()
            .find(|m| m.name == name)
            .ok_or_else(|| err(path, format!("line {ln}: camera {id}: unknown camera model `{name}`")))?;
        let width: u64 = field(path, ln, tok.next(), "WIDTH")?;
        let height: u64 = field(path, ln, tok.next(), "HEIGHT")?;
        let params = tok.map(|t| field(path, ln, Some(t), "a camera parameter")).collect::<Result<Vec<f64>, _>>()?;
        insert_camera(path, &mut map, id, intrinsics(path, id, m, width, height, &params)?)?;
    }
    check_header(path, &text, "cameras", map.len())?;
    Ok(map)
}

fn images_txt(path: &Path) -> Result<Vec<ImageRec>> {
    let text = read_text(path)?;
    let lines: Vec<&str> = text.lines().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let (ln, line) = (i + 1, lines[i].trim());
        if line.is_empty() || line.starts_with('#') {
            i += 1;
            continue;
        }
        // The first nine fields, then the name (the rest of the line: names may hold spaces).
        let mut rest = line;
        let mut tok = Vec::with_capacity(9);
        for _ in 0..9 {
            rest = rest.trim_start();
            let end = rest.find(char::is_whitespace).unwrap_or(rest.len());
            tok.push(&rest[..end]);
            rest = &rest[end..];
        }
        let name = rest.trim().to_string();
        let names = ["IMAGE_ID", "QW", "QX", "QY", "QZ", "TX", "TY", "TZ"];
        let get = |k: usize| Some(tok[k]).filter(|s| !s.is_empty());
        let id: i32 = field(path, ln, get(0), names[0])?;
        let mut q = [0.0; 4];
        for (k, v) in q.iter_mut().enumerate() {
            *v = field(path, ln, get(1 + k), names[1 + k])?;
        }
        let mut t = [0.0; 3];
        for (k, v) in t.iter_mut().enumerate() {
            *v = field(path, ln, get(5 + k), names[5 + k])?;
        }
        let camera_id: i32 = field(path, ln, get(8), "CAMERA_ID")?;
        if name.is_empty() {
            return Err(err(path, format!("line {ln}: image {id}: NAME is missing")));
        }
        // The POINTS2D line (possibly empty, possibly absent at the end of the file).
        if let Some(points) = lines.get(i + 1).filter(|l| !l.trim_start().starts_with('#')) {
            let vals: Vec<&str> = points.split_whitespace().collect();
            if !vals.len().is_multiple_of(3) {
                return Err(err(
                    path,
                    format!(
                        "line {}: image {id}: POINTS2D holds {} numbers, not (X, Y, POINT3D_ID) triples",
                        ln + 1,
                        vals.len()
                    ),
                ));
            }
            for v in vals {
                field::<f64>(path, ln + 1, Some(v), "a POINTS2D value")?;
            }
            i += 2;
        } else {
            i += 1;
        }
        out.push(ImageRec { id, q, t, camera_id, name });
    }
    check_header(path, &text, "images", out.len())?;
    Ok(out)
}

fn points_txt(path: &Path) -> Result<SparsePoints> {
    let text = read_text(path)?;
    let mut pts = SparsePoints::default();
    for (ln, line) in data_lines(&text) {
        let mut tok = line.split_whitespace();
        let id: u64 = field(path, ln, tok.next(), "POINT3D_ID")?;
        let mut xyz = [0.0f64; 3];
        for (v, what) in xyz.iter_mut().zip(["X", "Y", "Z"]) {
            *v = field(path, ln, tok.next(), what)?;
        }
        let mut rgb = [0u8; 3];
        for (v, what) in rgb.iter_mut().zip(["R", "G", "B"]) {
            *v = field(path, ln, tok.next(), what)?;
        }
        field::<f64>(path, ln, tok.next(), "ERROR")?;
        let track: Vec<&str> = tok.collect();
        if !track.len().is_multiple_of(2) {
            return Err(err(
                path,
                format!(
                    "line {ln}: point {id}: TRACK holds {} numbers, not (IMAGE_ID, POINT2D_IDX) pairs",
                    track.len()
                ),
            ));
        }
        for v in track {
            field::<i64>(path, ln, Some(v), "a TRACK value")?;
        }
        pts.xyz.push(point_xyz(path, id, xyz)?);
        pts.rgb.push(rgb);
    }
    check_header(path, &text, "points", pts.xyz.len())?;
    Ok(pts)
}
