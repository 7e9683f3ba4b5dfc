//! COLMAP, LLFF and Replica loaders and `load_any`: every test writes its own tiny fixture (8x6
//! images, hand-encoded .bin / .npy files) and checks geometry against independently computed
//! projections, plus the error messages for malformed inputs.

#![allow(deprecated)]

use chatsplat_tests::{Scratch, temp_dir};
use glam::Vec3;
use model::data::{LoadOptions, colmap, llff, load_any, replica};
use model::images::{write_gray8, write_gray16, write_rgb};
use splat_kernels::Camera;
use std::path::Path;

const W: u32 = 8;
const H: u32 = 6;

fn opts(downscale: u32, holdout_every: usize) -> LoadOptions {
    LoadOptions { downscale, holdout_every, ..Default::default() }
}

/// Pixel position of world point `p` through the loaded camera (`u = fx * x / z + cx`).
fn project(c: &Camera, p: [f64; 3]) -> (f32, f32) {
    let q = c.world_to_cam.transform_point3(Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32));
    assert!(q.z > 0.0, "point behind the camera");
    (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy)
}

/// World-space camera axes (right, down, forward) and centre.
fn axes(c: &Camera) -> [Vec3; 4] {
    let c2w = c.world_to_cam.inverse();
    [
        c2w.transform_vector3(Vec3::X),
        c2w.transform_vector3(Vec3::Y),
        c2w.transform_vector3(Vec3::Z),
        c2w.transform_point3(Vec3::ZERO),
    ]
}

fn close3(a: Vec3, b: [f32; 3], tol: f32) -> bool {
    (a - Vec3::from_array(b)).abs().max_element() < tol
}

fn names(views: &[model::data::View]) -> Vec<String> {
    views.iter().map(|v| v.image_path.file_name().unwrap().to_string_lossy().into_owned()).collect()
}

fn expect_err<T: std::fmt::Debug>(r: model::Result<T>, needles: &[&str]) -> String {
    let e = r.expect_err("expected an error").to_string();
    for n in needles {
        assert!(e.contains(n), "expected `{n}` in: {e}");
    }
    e
}

/// An 8x6 image whose pixel (x, y) is `(x / 7, y / 5, tag)`.
fn gradient(tag: f32, w: u32, h: u32) -> Vec<f32> {
    (0..h).flat_map(|y| (0..w).flat_map(move |x| [x as f32 / 7.0, y as f32 / 5.0, tag])).collect()
}

fn q8(v: f32) -> f32 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5).floor() / 255.0
}

// ---------------------------------------------------------------------------------------------
// COLMAP fixture

#[derive(Clone)]
struct Cam {
    id: i32,
    model: i32,
    name: &'static str,
    w: u64,
    h: u64,
    params: Vec<f64>,
}

#[derive(Clone)]
struct Img {
    id: i32,
    q: [f64; 4],
    t: [f64; 3],
    cam: i32,
    name: String,
    pts: Vec<(f64, f64, i64)>,
}

#[derive(Clone)]
struct Pt {
    id: u64,
    xyz: [f64; 3],
    rgb: [u8; 3],
    track: Vec<(i32, i32)>,
}

#[derive(Clone)]
pub(crate) struct Colmap {
    cams: Vec<Cam>,
    imgs: Vec<Img>,
    pts: Vec<Pt>,
}

/// Hand-written rotation matrix of a unit quaternion (w, x, y, z), row-major.
fn quat_rows(q: [f64; 4]) -> [[f64; 3]; 3] {
    let [w, x, y, z] = q;
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
        [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
        [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

fn to_cam(im: &Img, p: [f64; 3]) -> [f64; 3] {
    let r = quat_rows(im.q);
    std::array::from_fn(|i| r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2] + im.t[i])
}

/// (fx, fy, cx, cy) of a fixture camera.
fn pinhole(c: &Cam) -> [f64; 4] {
    match c.model {
        0 | 2 | 3 => [c.params[0], c.params[0], c.params[1], c.params[2]],
        _ => [c.params[0], c.params[1], c.params[2], c.params[3]],
    }
}

const NAMES: [&str; 5] = ["img_d.png", "img_b.png", "img_e.png", "img_a.png", "img_c.png"];

/// Three cameras (PINHOLE, SIMPLE_RADIAL with k = 0, OPENCV with zero distortion), five images
/// listed out of name order, four points; each image's points2D are the exact projections of
/// the points (plus one unmatched observation), except image 3 whose points2D line is empty.
fn colmap_fixture() -> Colmap {
    let cams = vec![
        Cam { id: 1, model: 1, name: "PINHOLE", w: 8, h: 6, params: vec![10.0, 11.0, 4.2, 2.9] },
        Cam { id: 2, model: 2, name: "SIMPLE_RADIAL", w: 8, h: 6, params: vec![9.0, 4.0, 3.0, 0.0] },
        Cam { id: 3, model: 4, name: "OPENCV", w: 8, h: 6, params: vec![9.5, 9.25, 3.75, 3.1, 0.0, 0.0, 0.0, 0.0] },
    ];
    let pts_xyz = [[0.0, 0.0, 0.0], [0.5, -0.3, 0.2], [-0.4, 0.25, -0.3], [0.3, 0.4, 0.5]];
    let ids = [4, 2, 5, 1, 3];
    let cam_of = [1, 2, 3, 1, 2];
    let axis = {
        let a = [0.3f64, 1.0, 0.2];
        let n = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        a.map(|v| v / n)
    };
    let mut imgs = vec![];
    for j in 0..5 {
        let ang = 0.1 * j as f64 - 0.2;
        let (s, c) = (0.5 * ang).sin_cos();
        let mut im = Img {
            id: ids[j],
            q: [c, s * axis[0], s * axis[1], s * axis[2]],
            t: [0.1 * j as f64 - 0.2, 0.05 * j as f64, 4.0 + 0.1 * j as f64],
            cam: cam_of[j],
            name: NAMES[j].to_string(),
            pts: vec![],
        };
        if im.id != 3 {
            let [fx, fy, cx, cy] = pinhole(&cams[(im.cam - 1) as usize]);
            for (k, p) in pts_xyz.iter().enumerate() {
                let pc = to_cam(&im, *p);
                im.pts.push((fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy, 10 + k as i64));
            }
            im.pts.push((1.0, 1.0, -1));
        }
        imgs.push(im);
    }
    let pts = pts_xyz
        .iter()
        .enumerate()
        .map(|(k, &xyz)| Pt {
            id: 10 + k as u64,
            xyz,
            rgb: [40 * k as u8, 255 - 30 * k as u8, 7],
            track: imgs.iter().filter(|im| im.id != 3).map(|im| (im.id, k as i32)).collect(),
        })
        .collect();
    Colmap { cams, imgs, pts }
}

#[derive(Default)]
struct Le(Vec<u8>);

impl Le {
    fn i32(&mut self, v: i32) -> &mut Self {
        self.0.extend(v.to_le_bytes());
        self
    }
    fn u64(&mut self, v: u64) -> &mut Self {
        self.0.extend(v.to_le_bytes());
        self
    }
    fn i64(&mut self, v: i64) -> &mut Self {
        self.0.extend(v.to_le_bytes());
        self
    }
    fn f64(&mut self, v: f64) -> &mut Self {
        self.0.extend(v.to_le_bytes());
        self
    }
    fn u8(&mut self, v: u8) -> &mut Self {
        self.0.push(v);
        self
    }
    fn cstr(&mut self, s: &str) -> &mut Self {
        self.0.extend(s.as_bytes());
        self.0.push(0);
        self
    }
}

impl Colmap {
    fn cameras_bin(&self) -> Vec<u8> {
        let mut b = Le::default();
        b.u64(self.cams.len() as u64);
        for c in &self.cams {
            b.i32(c.id).i32(c.model).u64(c.w).u64(c.h);
            for &p in &c.params {
                b.f64(p);
            }
        }
        b.0
    }
    fn images_bin(&self) -> Vec<u8> {
        let mut b = Le::default();
        b.u64(self.imgs.len() as u64);
        for im in &self.imgs {
            b.i32(im.id);
            for v in im.q.iter().chain(&im.t) {
                b.f64(*v);
            }
            b.i32(im.cam).cstr(&im.name).u64(im.pts.len() as u64);
            for &(x, y, id) in &im.pts {
                b.f64(x).f64(y).i64(id);
            }
        }
        b.0
    }
    fn points_bin(&self) -> Vec<u8> {
        let mut b = Le::default();
        b.u64(self.pts.len() as u64);
        for p in &self.pts {
            b.u64(p.id).f64(p.xyz[0]).f64(p.xyz[1]).f64(p.xyz[2]);
            b.u8(p.rgb[0]).u8(p.rgb[1]).u8(p.rgb[2]).f64(0.25).u64(p.track.len() as u64);
            for &(i, k) in &p.track {
                b.i32(i).i32(k);
            }
        }
        b.0
    }
    fn cameras_txt(&self) -> String {
        let mut s = String::from(
            "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
        );
        s += &format!("# Number of cameras: {}\n", self.cams.len());
        for c in &self.cams {
            let p: Vec<String> = c.params.iter().map(|v| v.to_string()).collect();
            s += &format!("{} {} {} {} {}\n", c.id, c.name, c.w, c.h, p.join(" "));
        }
        s
    }
    fn images_txt(&self) -> String {
        let mut s = String::from(
            "# Image list with two lines of data per image:\n\
                #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
                #   POINTS2D[] as (X, Y, POINT3D_ID)\n",
        );
        s += &format!("# Number of images: {}, mean observations per image: 4\n", self.imgs.len());
        for im in &self.imgs {
            let [qw, qx, qy, qz] = im.q;
            let [tx, ty, tz] = im.t;
            s += &format!("{} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {} {}\n", im.id, im.cam, im.name);
            let p: Vec<String> = im.pts.iter().map(|(x, y, id)| format!("{x} {y} {id}")).collect();
            s += &format!("{}\n", p.join(" "));
        }
        s
    }
    fn points_txt(&self) -> String {
        let mut s = String::from(
            "# 3D point list with one line of data per point:\n\
                #   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
        );
        s += &format!("# Number of points: {}, mean track length: 4\n", self.pts.len());
        for p in &self.pts {
            let t: Vec<String> = p.track.iter().map(|(i, k)| format!("{i} {k}")).collect();
            let [x, y, z] = p.xyz;
            let [r, g, b] = p.rgb;
            s += &format!("{} {x} {y} {z} {r} {g} {b} 0.25 {}\n", p.id, t.join(" "));
        }
        s
    }
    /// Writes the model (binary or text) into `sparse`.
    fn write(&self, sparse: &Path, bin: bool) {
        std::fs::create_dir_all(sparse).unwrap();
        if bin {
            std::fs::write(sparse.join("cameras.bin"), self.cameras_bin()).unwrap();
            std::fs::write(sparse.join("images.bin"), self.images_bin()).unwrap();
            std::fs::write(sparse.join("points3D.bin"), self.points_bin()).unwrap();
        } else {
            std::fs::write(sparse.join("cameras.txt"), self.cameras_txt()).unwrap();
            std::fs::write(sparse.join("images.txt"), self.images_txt()).unwrap();
            std::fs::write(sparse.join("points3D.txt"), self.points_txt()).unwrap();
        }
    }
}

/// Writes the images (pixel blue channel = index of the name in sorted order / 10) and a mask for
/// each (the ids of `img_a.png` returned, the others shifted by their index); returns the ids of
/// `img_a.png`.
fn colmap_images(dir: &Path) -> Vec<u8> {
    let mut sorted = NAMES;
    sorted.sort();
    let ids = |k: u32| -> Vec<u8> { (0..W * H).map(|i| ((i % W + i / W + k) % 4) as u8).collect() };
    for (i, n) in sorted.iter().enumerate() {
        write_rgb(&dir.join("images").join(n), W, H, &gradient(i as f32 / 10.0, W, H)).unwrap();
        write_gray8(&dir.join("masks").join(n), W, H, &ids(i as u32)).unwrap();
    }
    ids(0)
}

pub(crate) fn colmap_dir(tag: &str, bin: bool) -> (Scratch, Colmap) {
    let dir = temp_dir(tag);
    let fx = colmap_fixture();
    fx.write(&dir.join("sparse/0"), bin);
    colmap_images(&dir);
    (dir, fx)
}

#[test]
fn colmap_cameras_reproduce_the_points2d_and_bin_equals_txt() {
    let (dir_b, fx) = colmap_dir("colmap-bin", true);
    let (dir_t, _) = colmap_dir("colmap-txt", false);
    let (ds_b, pts_b) = colmap::load(&dir_b, &opts(1, 0)).unwrap();
    let (ds_t, pts_t) = colmap::load(&dir_t, &opts(1, 0)).unwrap();
    // Sorted by name; the image content follows the name.
    assert_eq!(names(&ds_b.train), ["img_a.png", "img_b.png", "img_c.png", "img_d.png", "img_e.png"]);
    for (i, v) in ds_b.train.iter().enumerate() {
        assert!((v.rgb[2] - q8(i as f32 / 10.0)).abs() < 1e-6, "{}: wrong pixels", v.image_path.display());
        assert_eq!((v.camera.width, v.camera.height), (W, H));
    }
    // Binary and text encodings give identical cameras and points.
    for (a, b) in ds_b.train.iter().zip(&ds_t.train) {
        assert_eq!(a.camera, b.camera, "{}", a.image_path.display());
        assert_eq!(a.rgb, b.rgb);
    }
    assert_eq!(pts_b, pts_t);
    assert_eq!(pts_b.xyz.len(), 4);
    for (k, p) in fx.pts.iter().enumerate() {
        assert_eq!(pts_b.xyz[k], p.xyz.map(|v| v as f32));
        assert_eq!(pts_b.rgb[k], p.rgb);
    }
    // Every point projects to the pixel COLMAP's points2D records.
    let mut checked = 0;
    for im in &fx.imgs {
        let v = ds_b.train.iter().find(|v| v.image_path.ends_with(&im.name)).unwrap();
        let [fxx, fyy, cx, cy] = pinhole(&fx.cams[(im.cam - 1) as usize]);
        assert_eq!([v.camera.fx, v.camera.fy, v.camera.cx, v.camera.cy], [fxx, fyy, cx, cy].map(|x| x as f32));
        for &(x, y, id) in im.pts.iter().filter(|p| p.2 >= 0) {
            let p = fx.pts.iter().find(|p| p.id as i64 == id).unwrap();
            let (u, w) = project(&v.camera, p.xyz);
            assert!(
                (u as f64 - x).abs() < 1e-3 && (w as f64 - y).abs() < 1e-3,
                "{}: ({u}, {w}) vs ({x}, {y})",
                im.name
            );
            checked += 1;
        }
        // A point on the optical axis lands on the principal point; the camera centre is -R^T t.
        let [_, _, fwd, centre] = axes(&v.camera);
        let r = quat_rows(im.q);
        let c: [f64; 3] = std::array::from_fn(|i| -(0..3).map(|j| r[j][i] * im.t[j]).sum::<f64>());
        assert!(close3(centre, c.map(|v| v as f32), 1e-5), "{}: centre {centre} vs {c:?}", im.name);
        let on_axis = centre + 3.0 * fwd;
        let (u, w) = project(&v.camera, on_axis.to_array().map(|v| v as f64));
        assert!((u - v.camera.cx).abs() < 1e-4 && (w - v.camera.cy).abs() < 1e-4);
    }
    assert_eq!(checked, 16);
    std::fs::remove_dir_all(&dir_b).ok();
    std::fs::remove_dir_all(&dir_t).ok();
}

#[test]
fn colmap_split_downscale_masks_and_layouts() {
    let (dir, fx) = colmap_dir("colmap-opts", true);
    let (full, _) = colmap::load(&dir, &opts(1, 0)).unwrap();
    // Every second view (in name order) is held out.
    let (ds, _) = colmap::load(&dir, &opts(1, 2)).unwrap();
    assert_eq!((ds.train.len(), ds.test.len()), (3, 2));
    assert_eq!(names(&ds.test), ["img_b.png", "img_d.png"]);
    assert_eq!(names(&ds.train), ["img_a.png", "img_c.png", "img_e.png"]);
    // Masks: one per image, none missing.
    let ids = colmap_images(&dir);
    assert_eq!(full.train[0].instance_ids.as_deref(), Some(&ids[..]));
    assert!(full.train.iter().all(|v| v.instance_ids.is_some() && v.depth.is_none()));
    // Downscale by 2: 4x3, intrinsics halved, the same points project to half the pixel
    // coordinates, colours are 2x2 box averages and masks the top-left samples.
    let (half, _) = colmap::load(&dir, &opts(2, 0)).unwrap();
    for (h, f) in half.train.iter().zip(&full.train) {
        let c = h.camera;
        assert_eq!((c.width, c.height), (4, 3));
        assert_eq!(
            [c.fx, c.fy, c.cx, c.cy],
            [f.camera.fx / 2.0, f.camera.fy / 2.0, f.camera.cx / 2.0, f.camera.cy / 2.0]
        );
        for p in &fx.pts {
            let (a, b) = (project(&c, p.xyz), project(&f.camera, p.xyz));
            assert!((a.0 - b.0 / 2.0).abs() < 1e-4 && (a.1 - b.1 / 2.0).abs() < 1e-4);
        }
        for y in 0..3 {
            for x in 0..4 {
                let want: f32 =
                    (0..4).map(|s| f.rgb[(((2 * y + s / 2) * 8 + 2 * x + s % 2) * 3) as usize]).sum::<f32>() / 4.0;
                assert!((h.rgb[((y * 4 + x) * 3) as usize] - want).abs() < 1e-6);
            }
        }
    }
    let m = half.train[0].instance_ids.as_ref().unwrap();
    assert_eq!(m.len(), 12);
    assert!((0..12).all(|i| m[i] == ids[(i / 4) * 2 * 8 + (i % 4) * 2]));
    // Flat `sparse/` layout, and .bin preferred over a broken .txt next to it.
    let flat = temp_dir("colmap-flat");
    fx.write(&flat.join("sparse"), true);
    std::fs::write(flat.join("sparse/cameras.txt"), "garbage").unwrap();
    colmap_images(&flat);
    let (f2, _) = colmap::load(&flat, &opts(1, 0)).unwrap();
    assert_eq!(f2.train.len(), 5);
    assert_eq!(f2.train[0].camera, full.train[0].camera);
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&flat).ok();
}

#[test]
fn colmap_truncated_and_miscounted_binaries_are_reported() {
    let (dir, fx) = colmap_dir("colmap-trunc", true);
    let sparse = dir.join("sparse/0");
    for (file, bytes) in
        [("cameras.bin", fx.cameras_bin()), ("images.bin", fx.images_bin()), ("points3D.bin", fx.points_bin())]
    {
        let name_at = bytes.windows(4).position(|w| w == b"img_").unwrap_or(9);
        for cut in [0, 5, 8, 9, 13, 30, name_at + 2, bytes.len() / 2, bytes.len() - 1] {
            std::fs::write(sparse.join(file), &bytes[..cut]).unwrap();
            let e = expect_err(colmap::load(&dir, &opts(1, 0)), &[&format!("{file}: truncated at byte ")]);
            let at: usize = e.split("truncated at byte ").nth(1).unwrap().split(':').next().unwrap().parse().unwrap();
            assert!(at <= cut, "{file} cut at {cut} but reported at {at}: {e}");
        }
        // Extra bytes: the count announces fewer records than the file holds.
        let mut long = bytes.clone();
        long.extend([0u8; 5]);
        std::fs::write(sparse.join(file), &long).unwrap();
        expect_err(colmap::load(&dir, &opts(1, 0)), &[file, "5 bytes left after the", "count does not match"]);
        std::fs::write(sparse.join(file), &bytes).unwrap();
    }
    // A count larger than the records present reads as truncation.
    let mut b = fx.points_bin();
    b[0] = 9;
    std::fs::write(sparse.join("points3D.bin"), &b).unwrap();
    expect_err(colmap::load(&dir, &opts(1, 0)), &["points3D.bin: truncated at byte"]);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn colmap_bad_models_give_errors_naming_the_file() {
    let (dir, fx) = colmap_dir("colmap-bad", true);
    let sparse = dir.join("sparse/0");
    let load = || colmap::load(&dir, &opts(1, 0));
    // Non-zero distortion, in both encodings.
    let mut d = fx.clone();
    d.cams[2].params[4] = 0.01;
    d.write(&sparse, true);
    expect_err(load(), &["cameras.bin: camera 3 (OPENCV)", "non-zero distortion", "colmap image_undistorter"]);
    std::fs::remove_file(sparse.join("cameras.bin")).unwrap();
    std::fs::write(sparse.join("cameras.txt"), d.cameras_txt()).unwrap();
    expect_err(load(), &["cameras.txt: camera 3 (OPENCV)", "non-zero distortion", "colmap image_undistorter"]);
    std::fs::remove_file(sparse.join("cameras.txt")).unwrap();
    // Fisheye models are refused even without distortion.
    let mut d = fx.clone();
    d.cams[2].model = 5;
    d.write(&sparse, true);
    expect_err(load(), &["cameras.bin: camera 3 (OPENCV_FISHEYE)", "fisheye", "colmap image_undistorter"]);
    // Unknown model id / name.
    d.cams[2].model = 99;
    d.write(&sparse, true);
    expect_err(load(), &["cameras.bin: camera 3: unknown camera model id 99"]);
    std::fs::remove_file(sparse.join("cameras.bin")).unwrap();
    std::fs::write(sparse.join("cameras.txt"), fx.cameras_txt().replace("OPENCV", "FISHY")).unwrap();
    expect_err(load(), &["cameras.txt: line 6: camera 3: unknown camera model `FISHY`"]);
    // Header count that does not match the entries.
    std::fs::write(sparse.join("cameras.txt"), fx.cameras_txt().replace("cameras: 3", "cameras: 4")).unwrap();
    expect_err(load(), &["cameras.txt: the header announces 4 cameras but 3 are listed"]);
    std::fs::remove_file(sparse.join("cameras.txt")).unwrap();
    // An image referring to a camera that does not exist.
    let mut d = fx.clone();
    d.imgs[3].cam = 7;
    d.write(&sparse, true);
    expect_err(load(), &["images.bin: image 1 (img_a.png) refers to camera 7, which cameras.bin does not define"]);
    // Text images: points2D not in triples.
    std::fs::remove_file(sparse.join("images.bin")).unwrap();
    std::fs::write(sparse.join("images.txt"), fx.images_txt().replacen(" -1\n", "\n", 1)).unwrap();
    expect_err(load(), &["images.txt: line 6: image 4: POINTS2D holds 14 numbers"]);
    fx.write(&sparse, true);
    std::fs::remove_file(sparse.join("images.txt")).unwrap();
    // Missing model file, image directory, image file; wrong image size.
    std::fs::remove_file(sparse.join("points3D.bin")).unwrap();
    expect_err(load(), &["points3D.bin: missing (and so is points3D.txt)"]);
    fx.write(&sparse, true);
    std::fs::remove_file(dir.join("images/img_c.png")).unwrap();
    expect_err(load(), &["img_c.png: image is missing (listed in images.bin)"]);
    write_rgb(&dir.join("images/img_c.png"), W, H + 1, &gradient(0.0, W, H + 1)).unwrap();
    expect_err(load(), &["img_c.png: image is 8x7 but camera 2 in cameras.bin is 8x6"]);
    std::fs::remove_dir_all(dir.join("images")).unwrap();
    expect_err(load(), &["images: image directory is missing"]);
    colmap_images(&dir);
    write_gray8(&dir.join("masks/img_b.png"), 4, 3, &[0; 12]).unwrap();
    expect_err(load(), &["img_b.png: is 4x3 but its image is 8x6"]);
    std::fs::remove_dir_all(dir.join("sparse")).unwrap();
    std::fs::create_dir_all(dir.join("sparse")).unwrap();
    expect_err(load(), &["sparse: no COLMAP model"]);
    expect_err(colmap::load(&dir, &opts(0, 0)), &["downscale must be at least 1"]);
    std::fs::remove_dir_all(&dir).ok();
}

// ---------------------------------------------------------------------------------------------
// LLFF fixture

/// A `.npy` file of `rows` with the given dtype (`<f8` / `<f4`), shape text and format version.
fn npy(rows: &[Vec<f64>], descr: &str, shape: &str, version: u8) -> Vec<u8> {
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    let pre = if version == 1 { 10 } else { 12 };
    while (pre + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut b = b"\x93NUMPY".to_vec();
    b.extend([version, 0]);
    if version == 1 {
        b.extend((header.len() as u16).to_le_bytes());
    } else {
        b.extend((header.len() as u32).to_le_bytes());
    }
    b.extend(header.as_bytes());
    for v in rows.iter().flatten() {
        if descr == "<f4" {
            b.extend((*v as f32).to_le_bytes());
        } else {
            b.extend(v.to_le_bytes());
        }
    }
    b
}

/// An LLFF row: 3x5 `[R | t | (h, w, f)]` with `R` given by its columns (down, right, back).
fn llff_row(cols: [[f64; 3]; 3], t: [f64; 3], hwf: [f64; 3], near: f64, far: f64) -> Vec<f64> {
    let mut r = vec![];
    for i in 0..3 {
        r.extend([cols[0][i], cols[1][i], cols[2][i], t[i], hwf[i]]);
    }
    r.extend([near, far]);
    r
}

/// Three views: an identity LLFF rotation at the origin, the same rotation at (1, 2, 3), and a
/// camera turned 90 degrees about world x. `(h, w, f) = (12, 16, 20)` while the images are 8x6,
/// so the loaded focal length is 20 * 8 / 16 = 10.
fn llff_rows() -> Vec<Vec<f64>> {
    let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    // down = x, right = -z, back = y
    let turned = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]];
    let hwf = [12.0, 16.0, 20.0];
    vec![
        llff_row(id, [0.0; 3], hwf, 1.0, 10.0),
        llff_row(id, [1.0, 2.0, 3.0], hwf, 1.0, 10.0),
        llff_row(turned, [0.0; 3], hwf, 0.5, 5.0),
    ]
}

pub(crate) fn llff_dir(tag: &str) -> Scratch {
    let dir = temp_dir(tag);
    for (i, n) in ["a.png", "b.jpg.png", "c.png"].iter().enumerate() {
        write_rgb(&dir.join("images").join(n), W, H, &gradient(i as f32 / 4.0, W, H)).unwrap();
    }
    std::fs::write(dir.join("images/notes.txt"), "not an image").unwrap();
    std::fs::write(dir.join("poses_bounds.npy"), npy(&llff_rows(), "<f8", "(3, 17)", 1)).unwrap();
    dir
}

#[test]
fn llff_axes_intrinsics_and_split() {
    let dir = llff_dir("llff-axes");
    let ds = llff::load(&dir, &opts(1, 0)).unwrap();
    assert_eq!(names(&ds.train), ["a.png", "b.jpg.png", "c.png"]);
    let c0 = ds.train[0].camera;
    assert_eq!([c0.fx, c0.fy, c0.cx, c0.cy], [10.0, 10.0, 4.0, 3.0]);
    // Identity LLFF pose: columns [down, right, back] = world x, y, z, so the camera looks
    // down world -z with image-right = +y and image-down = +x.
    let [right, down, fwd, centre] = axes(&c0);
    assert!(close3(fwd, [0.0, 0.0, -1.0], 1e-6), "forward {fwd}");
    assert!(close3(right, [0.0, 1.0, 0.0], 1e-6), "right {right}");
    assert!(close3(down, [1.0, 0.0, 0.0], 1e-6), "down {down}");
    assert!(close3(centre, [0.0; 3], 1e-6));
    // A point straight ahead projects to the principal point; one displaced along +x (down)
    // lands below it: v = f * 0.5 / 5 + cy = 4.
    assert_eq!(project(&c0, [0.0, 0.0, -5.0]), (4.0, 3.0));
    let (u, v) = project(&c0, [0.5, 0.0, -5.0]);
    assert!((u - 4.0).abs() < 1e-5 && (v - 4.0).abs() < 1e-5, "({u}, {v})");
    let (u, v) = project(&c0, [0.0, 0.5, -5.0]);
    assert!((u - 5.0).abs() < 1e-5 && (v - 3.0).abs() < 1e-5, "({u}, {v})");
    // The translation column is the camera centre.
    let [_, _, fwd1, centre1] = axes(&ds.train[1].camera);
    assert!(close3(centre1, [1.0, 2.0, 3.0], 1e-5) && close3(fwd1, [0.0, 0.0, -1.0], 1e-6));
    // back = +y, so forward = -y; right = -z.
    let [right2, _, fwd2, _] = axes(&ds.train[2].camera);
    assert!(close3(fwd2, [0.0, -1.0, 0.0], 1e-6) && close3(right2, [0.0, 0.0, -1.0], 1e-6));
    // Colours.
    for (i, v) in ds.train.iter().enumerate() {
        assert!((v.rgb[2] - q8(i as f32 / 4.0)).abs() < 1e-6 && v.instance_ids.is_none());
    }
    // Holdout: every 3rd view.
    let s = llff::load(&dir, &opts(1, 3)).unwrap();
    assert_eq!((s.train.len(), s.test.len()), (2, 1));
    assert_eq!(names(&s.test), ["c.png"]);
    // '<f4' data and format version 2 load the same cameras.
    std::fs::write(dir.join("poses_bounds.npy"), npy(&llff_rows(), "<f4", "(3, 17)", 2)).unwrap();
    let f4 = llff::load(&dir, &opts(1, 0)).unwrap();
    for (a, b) in f4.train.iter().zip(&ds.train) {
        assert_eq!(a.camera, b.camera);
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn llff_downscale_prefers_images_k_and_reads_masks() {
    let dir = llff_dir("llff-down");
    // No images_2: box-filter images/.
    let full = llff::load(&dir, &opts(1, 0)).unwrap();
    let half = llff::load(&dir, &opts(2, 0)).unwrap();
    let (f, h) = (&full.train[0], &half.train[0]);
    assert_eq!((h.camera.width, h.camera.height, h.camera.fx, h.camera.cx, h.camera.cy), (4, 3, 5.0, 2.0, 1.5));
    let want = (f.rgb[0] + f.rgb[3] + f.rgb[24] + f.rgb[27]) / 4.0;
    assert!((h.rgb[0] - want).abs() < 1e-6);
    // images_2 with the right count is used as is: its own colours, f scaled by 4 / 16.
    for (i, n) in ["a.png", "b.png", "c.png"].iter().enumerate() {
        write_rgb(&dir.join("images_2").join(n), 4, 3, &[0.2 * i as f32 + 0.1; 36]).unwrap();
    }
    let pre = llff::load(&dir, &opts(2, 0)).unwrap();
    let c = pre.train[1].camera;
    assert_eq!((c.width, c.height, c.fx, c.cx, c.cy), (4, 3, 5.0, 2.0, 1.5));
    assert!(pre.train[1].image_path.starts_with(dir.join("images_2")));
    assert!((pre.train[1].rgb[0] - q8(0.3)).abs() < 1e-6);
    // With masks (defined on images/), images/ is box-filtered and the masks subsampled.
    let ids: Vec<u8> = (0..48).map(|i| (i % 5) as u8).collect();
    write_gray8(&dir.join("masks/b.jpg.png"), W, H, &ids).unwrap();
    // a mask folder that covers some images only is refused, naming the first missing mask
    expect_err(llff::load(&dir, &opts(2, 0)), &["a.png", "is missing", "has masks for 1 of the 3 images"]);
    for n in ["a.png", "c.png"] {
        write_gray8(&dir.join("masks").join(n), W, H, &[0; 48]).unwrap();
    }
    let m = llff::load(&dir, &opts(2, 0)).unwrap();
    assert!(m.train[1].image_path.starts_with(dir.join("images")));
    let got = m.train[1].instance_ids.as_ref().unwrap();
    assert_eq!(got, &(0..12).map(|i| ids[(i / 4) * 16 + (i % 4) * 2]).collect::<Vec<_>>());
    assert_eq!(m.train[0].instance_ids.as_deref(), Some(&[0u8; 12][..]));
    // images_2 with the wrong count is ignored.
    std::fs::remove_dir_all(dir.join("masks")).unwrap();
    std::fs::remove_file(dir.join("images_2/c.png")).unwrap();
    let ignored = llff::load(&dir, &opts(2, 0)).unwrap();
    assert!(ignored.train[0].image_path.starts_with(dir.join("images")));
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn llff_malformed_inputs_give_errors_naming_the_file() {
    let dir = llff_dir("llff-bad");
    let file = dir.join("poses_bounds.npy");
    let load = || llff::load(&dir, &opts(1, 0));
    let rows = llff_rows();
    let good = npy(&rows, "<f8", "(3, 17)", 1);
    let mut bad = good.clone();
    bad[1] = b'X';
    std::fs::write(&file, &bad).unwrap();
    expect_err(load(), &["poses_bounds.npy: not a NumPy .npy file (bad magic)"]);
    std::fs::write(&file, &good[..7]).unwrap();
    expect_err(load(), &["poses_bounds.npy: not a NumPy .npy file"]);
    std::fs::write(&file, &good[..40]).unwrap();
    expect_err(load(), &["poses_bounds.npy: truncated .npy header"]);
    std::fs::write(&file, &good[..good.len() - 8]).unwrap();
    expect_err(load(), &["poses_bounds.npy: holds 400 data bytes but shape (3, 17) of <f8 needs 408"]);
    let short: Vec<Vec<f64>> = rows.iter().map(|r| r[..15].to_vec()).collect();
    std::fs::write(&file, npy(&short, "<f8", "(3, 15)", 1)).unwrap();
    expect_err(load(), &["poses_bounds.npy: shape (3, 15) is not (N, 17)"]);
    std::fs::write(&file, npy(&rows, ">f8", "(3, 17)", 1)).unwrap();
    expect_err(load(), &["poses_bounds.npy: dtype '>f8' is not supported"]);
    let mut nf = rows.clone();
    nf[1][15] = 20.0;
    std::fs::write(&file, npy(&nf, "<f8", "(3, 17)", 1)).unwrap();
    expect_err(load(), &["poses_bounds.npy: row 1: near = 20 and far = 10 must satisfy 0 < near < far"]);
    // Two rows, three images.
    std::fs::write(&file, npy(&rows[..2], "<f8", "(2, 17)", 1)).unwrap();
    expect_err(load(), &["images: holds 3 images but", "poses_bounds.npy has 2 poses"]);
    // An image that is not a rescaled (h, w).
    std::fs::write(&file, &good).unwrap();
    write_rgb(&dir.join("images/c.png"), W, W, &gradient(0.0, W, W)).unwrap();
    expect_err(load(), &["c.png: image is 8x8, which is not a rescaled 16x12"]);
    // Corrupt JPEG.
    std::fs::remove_file(dir.join("images/c.png")).unwrap();
    std::fs::write(dir.join("images/c.jpg"), b"\xff\xd8\xff\xe0 not really").unwrap();
    expect_err(load(), &["c.jpg: cannot decode JPEG"]);
    std::fs::remove_file(&file).unwrap();
    expect_err(load(), &["poses_bounds.npy: cannot read"]);
    std::fs::remove_dir_all(&dir).ok();
}

// ---------------------------------------------------------------------------------------------
// Replica fixture

/// Camera-to-world of frame `i`: a rotation by `0.3 i` about world y, centre `(i, -0.5, 2)`.
fn replica_c2w(i: usize) -> [[f64; 4]; 4] {
    let (s, c) = (0.3 * i as f64).sin_cos();
    [[c, 0.0, s, i as f64], [0.0, 1.0, 0.0, -0.5], [-s, 0.0, c, 2.0], [0.0, 0.0, 0.0, 1.0]]
}

/// 16-bit instance labels of frame `i`: 0 in the top row, then ids that first appear in the order
/// 1000, 42, 7 over the sequence.
fn replica_labels(i: usize) -> Vec<u16> {
    let pal: [&[u16]; 4] = [&[1000, 42], &[42, 1000], &[7, 1000], &[42]];
    (0..W * H).map(|p| if p < W { 0 } else { pal[i][(p as usize) % pal[i].len()] }).collect()
}

pub(crate) fn replica_dir(tag: &str, frames: usize) -> Scratch {
    let dir = temp_dir(tag);
    let mut traj = String::new();
    for i in 0..frames {
        let m = replica_c2w(i);
        let vals: Vec<String> = m.iter().flatten().map(|v| format!("{v:.17e}")).collect();
        traj += &vals.join(" ");
        traj += "\n";
        write_rgb(&dir.join(format!("rgb/rgb_{i}.png")), W, H, &gradient(i as f32 / 8.0, W, H)).unwrap();
        let mm: Vec<u16> = (0..W * H).map(|p| 1000 + 250 * i as u16 + p as u16).collect();
        write_gray16(&dir.join(format!("depth/depth_{i}.png")), W, H, &mm).unwrap();
        write_gray16(&dir.join(format!("semantic_instance/semantic_instance_{i}.png")), W, H, &replica_labels(i))
            .unwrap();
    }
    std::fs::write(dir.join("traj_w_c.txt"), traj).unwrap();
    dir
}

#[test]
fn replica_intrinsics_poses_depth_and_labels() {
    let dir = replica_dir("replica", 4);
    let ds = replica::load(&dir, &opts(1, 0)).unwrap();
    assert_eq!(ds.train.len(), 4);
    for (i, v) in ds.train.iter().enumerate() {
        let c = v.camera;
        // 90 degree hfov: fx = fy = (W/2) / tan(45 deg) = 4; the centre (W/2, H/2) in this
        // project's pixel convention is Semantic-NeRF's ((W-1)/2, (H-1)/2).
        assert!((c.fx - 4.0).abs() < 1e-5 && (c.fy - 4.0).abs() < 1e-5, "f = {} {}", c.fx, c.fy);
        assert_eq!((c.cx, c.cy, c.width, c.height), (4.0, 3.0, W, H));
        // traj_w_c is camera-to-world, OpenCV: its columns are the camera axes and centre.
        let m = replica_c2w(i);
        let [right, down, fwd, centre] = axes(&c);
        let col = |k: usize| [m[0][k] as f32, m[1][k] as f32, m[2][k] as f32];
        for (got, k) in [(right, 0), (down, 1), (fwd, 2), (centre, 3)] {
            assert!(close3(got, col(k), 1e-5), "frame {i} column {k}: {got} vs {:?}", col(k));
        }
        // A camera-space point (0.5, -0.25, 2) projects to (4 + 4 * 0.25, 3 - 4 * 0.125).
        let pc = [0.5, -0.25, 2.0, 1.0];
        let pw: [f64; 3] = std::array::from_fn(|r| (0..4).map(|k| m[r][k] * pc[k]).sum());
        let (u, w) = project(&c, pw);
        assert!((u - 5.0).abs() < 1e-4 && (w - 2.5).abs() < 1e-4, "({u}, {w})");
        // Depth in metres.
        let d = v.depth.as_ref().unwrap();
        assert_eq!(d.len(), 48);
        for p in [0usize, 17, 47] {
            let want = (1000 + 250 * i + p) as f32 / 1000.0;
            assert!((d[p] - want).abs() < 1e-6, "frame {i} pixel {p}: {} vs {want}", d[p]);
        }
        assert!((v.rgb[2] - q8(i as f32 / 8.0)).abs() < 1e-6);
    }
    // 16-bit ids compacted over the sequence in order of first appearance: 1000 -> 1, 42 -> 2,
    // 7 -> 3; 0 stays 0.
    for (i, v) in ds.train.iter().enumerate() {
        let want: Vec<u8> = replica_labels(i)
            .iter()
            .map(|&l| match l {
                0 => 0,
                1000 => 1,
                42 => 2,
                7 => 3,
                _ => unreachable!(),
            })
            .collect();
        assert_eq!(v.instance_ids.as_ref().unwrap(), &want, "frame {i}");
    }
    // Holdout and downscale: intrinsics halved, depth and ids subsampled (top-left of 2x2).
    let s = replica::load(&dir, &opts(2, 2)).unwrap();
    assert_eq!((s.train.len(), s.test.len()), (2, 2));
    assert_eq!(names(&s.test), ["rgb_1.png", "rgb_3.png"]);
    let c = s.train[0].camera;
    assert!((c.fx - 2.0).abs() < 1e-5);
    assert_eq!((c.cx, c.cy, c.width, c.height), (2.0, 1.5, 4, 3));
    let d = s.train[0].depth.as_ref().unwrap();
    assert_eq!(d.len(), 12);
    assert!((d[5] - (1000 + 2 * 8 + 2) as f32 / 1000.0).abs() < 1e-6);
    assert_eq!(s.train[0].instance_ids.as_ref().unwrap()[5], ds.train[0].instance_ids.as_ref().unwrap()[18]);
    // intrinsics.json overrides the default.
    std::fs::write(dir.join("intrinsics.json"), r#"{"fx": 5.5, "fy": 6.0, "cx": 3.25, "cy": 2.75}"#).unwrap();
    let c = replica::load(&dir, &opts(1, 0)).unwrap().train[2].camera;
    assert_eq!([c.fx, c.fy, c.cx, c.cy], [5.5, 6.0, 3.25, 2.75]);
    std::fs::write(dir.join("intrinsics.json"), r#"{"fx": 5.5, "fy": 6.0, "cx": 3.25}"#).unwrap();
    expect_err(replica::load(&dir, &opts(1, 0)), &["intrinsics.json: `cy` is missing"]);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn replica_8bit_labels_and_errors() {
    let dir = replica_dir("replica-bad", 3);
    let load = || replica::load(&dir, &opts(1, 0));
    // 8-bit labels are used verbatim.
    let ids8: Vec<u8> = (0..48).map(|p| (p * 5) as u8).collect();
    for i in 0..3 {
        write_gray8(&dir.join(format!("semantic_instance/semantic_instance_{i}.png")), W, H, &ids8).unwrap();
    }
    assert_eq!(load().unwrap().train[1].instance_ids.as_ref().unwrap(), &ids8);
    // Mixed bit depths.
    write_gray16(&dir.join("semantic_instance/semantic_instance_2.png"), W, H, &replica_labels(0)).unwrap();
    expect_err(load(), &["semantic_instance_2.png: 16-bit labels in a sequence whose earlier labels are 8-bit"]);
    // 16-bit labels: distinct ids accumulate over the sequence.
    let many: Vec<u16> = (0..48).map(|p| 1 + p as u16).collect();
    let more: Vec<u16> = (0..48).map(|p| 100 + 5 * p as u16).collect();
    let lots: Vec<u16> = (0..48).map(|p| 400 + 7 * p as u16).collect();
    for (i, l) in [many, more, lots].iter().enumerate() {
        write_gray16(&dir.join(format!("semantic_instance/semantic_instance_{i}.png")), W, H, l).unwrap();
    }
    // 144 distinct ids over the sequence fit in 8 bits.
    assert!(load().is_ok());
    let big: Vec<u16> = (0..W * 40).map(|p| 1000 + p as u16).collect();
    write_gray16(&dir.join("semantic_instance/semantic_instance_1.png"), W, 40, &big).unwrap();
    expect_err(load(), &["semantic_instance_1.png: is 8x40 but its image is 8x6"]);
    // More than 255 distinct non-zero 16-bit ids do not fit.
    let d = temp_dir("replica-many");
    std::fs::create_dir_all(d.join("rgb")).unwrap();
    std::fs::write(d.join("traj_w_c.txt"), "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n").unwrap();
    write_rgb(&d.join("rgb/rgb_0.png"), 16, 17, &gradient(0.0, 16, 17)).unwrap();
    let ids: Vec<u16> = (0..16 * 17).map(|p| 1 + p as u16).collect();
    write_gray16(&d.join("semantic_instance/semantic_instance_0.png"), 16, 17, &ids).unwrap();
    expect_err(
        replica::load(&d, &opts(1, 0)),
        &["semantic_instance_0.png: more than 255 distinct non-zero instance ids"],
    );
    std::fs::remove_dir_all(&d).ok();
    // Missing files and a bad trajectory.
    std::fs::remove_dir_all(dir.join("semantic_instance")).unwrap();
    std::fs::remove_file(dir.join("depth/depth_2.png")).unwrap();
    expect_err(load(), &["depth_2.png: depth of frame 2 is missing"]);
    std::fs::remove_dir_all(dir.join("depth")).unwrap();
    assert!(load().unwrap().train[0].depth.is_none());
    std::fs::remove_file(dir.join("rgb/rgb_1.png")).unwrap();
    expect_err(load(), &["rgb_1.png: image of frame 1 is missing", "lists 3 frames"]);
    let traj = dir.join("traj_w_c.txt");
    std::fs::write(&traj, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n1 0 0 0 0 1 0 0 0 0 1 0 0 0 0\n").unwrap();
    expect_err(load(), &["traj_w_c.txt: line 2: 15 numbers, expected 16"]);
    std::fs::write(&traj, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 x 1\n").unwrap();
    expect_err(load(), &["traj_w_c.txt: line 1: cannot parse `x` as a number"]);
    std::fs::write(&traj, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 2\n").unwrap();
    expect_err(load(), &["traj_w_c.txt: line 1: not an invertible camera-to-world matrix"]);
    std::fs::remove_file(&traj).unwrap();
    expect_err(load(), &["traj_w_c.txt: cannot read"]);
    std::fs::remove_dir_all(&dir).ok();
}

// ---------------------------------------------------------------------------------------------
// load_any

#[test]
fn load_any_detects_each_format() {
    let o = opts(1, 0);
    let (c, _) = colmap_dir("any-colmap", true);
    assert_eq!(load_any(&c, &o).unwrap().train.len(), 5);
    let l = llff_dir("any-llff");
    // LLFF scenes usually also carry a (distorted) COLMAP model: poses_bounds.npy wins.
    let mut distorted = colmap_fixture();
    distorted.cams[2].params[4] = 0.1;
    distorted.write(&l.join("sparse/0"), true);
    let ds = load_any(&l, &o).unwrap();
    assert_eq!(ds.train.len(), 3);
    assert_eq!(ds.train[0].camera.fx, 10.0);
    let r = replica_dir("any-replica", 2);
    assert_eq!(load_any(&r, &o).unwrap().train[1].depth.as_ref().unwrap().len(), 48);
    let n = temp_dir("any-nerfstudio");
    let so = model::data::synth::SynthOptions { views: 3, width: 16, height: 12, ..Default::default() };
    model::data::synth::write_dataset(&n, &so, |_, _| {}).unwrap();
    assert_eq!(load_any(&n, &o).unwrap().train.len(), 3);
    let empty = temp_dir("any-empty");
    std::fs::create_dir_all(&empty).unwrap();
    expect_err(
        load_any(&empty, &o),
        &[
            "no known scene format",
            "transforms.json",
            "transforms_train.json",
            "poses_bounds.npy",
            "sparse/",
            "traj_w_c.txt",
        ],
    );
    expect_err(load_any(&empty.join("nope"), &o), &["nope: not a directory"]);
}

/// The teacher stage reads every format through the same detection as `train` (not only
/// nerfstudio): tokens of every training view of a COLMAP and an LLFF capture, and the teacher
/// directory reloads its dataset.
#[test]
fn teacher_tokens_are_extracted_from_colmap_and_llff_captures() {
    let dev = burn::tensor::Device::ndarray();
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tiny-llava-ov");
    let vlm = model::vlm::LlavaOnevision::load(&fixture, &dev).unwrap();
    for (tag, dir) in [("colmap", colmap_dir("teacher-colmap", true).0), ("llff", llff_dir("teacher-llff"))] {
        let out = temp_dir(&format!("teacher-{tag}-out"));
        let teacher = model::run::TeacherDir::new(&out);
        let sum = train::teacher::extract(&vlm, &dir, &teacher, &Default::default(), |_| {}, |_, _| {}).unwrap();
        let set = train::teacher::TeacherSet::open(&out).unwrap();
        let ds = set.dataset().unwrap();
        assert!(!ds.train.is_empty(), "{tag}");
        assert_eq!(sum.written, ds.train.len(), "{tag}: one token file per training view");
        assert_eq!(set.views.len(), ds.train.len(), "{tag}");
        let (g, d) = (set.index.grid, set.index.dim);
        for v in 0..ds.train.len() {
            let t = set.tokens(v, None).unwrap();
            assert_eq!(t.len(), g * g * d, "{tag} view {v}");
            assert!(t.iter().any(|x| *x != 0.0), "{tag} view {v}: tokens of a real image");
        }
        assert_eq!(set.index.fingerprint, ds.fingerprint(), "{tag}: the index records the dataset");
        std::fs::remove_dir_all(&out).ok();
    }
}

/// Gaussian Grouping's layout: instance-id PNGs in `object_mask/` beside `images/` (what SAM +
/// DEVA write) are the capture's masks when there is no `masks/`, for COLMAP and LLFF alike.
#[test]
fn gaussian_grouping_object_masks_are_read() {
    let (dir, _) = colmap_dir("colmap-grouping", true);
    let (with_masks, _) = colmap::load(&dir, &opts(1, 0)).unwrap();
    std::fs::rename(dir.join("masks"), dir.join("object_mask")).unwrap();
    let (grouping, _) = colmap::load(&dir, &opts(1, 0)).unwrap();
    assert!(grouping.train[0].instance_ids.is_some(), "object_mask/img_a.png is read");
    for (a, b) in with_masks.train.iter().zip(&grouping.train) {
        assert_eq!(a.instance_ids, b.instance_ids);
    }
    let dir = llff_dir("llff-grouping");
    let ids = |k: u32| -> Vec<u8> { (0..W * H).map(|i| ((i + k) % 3) as u8).collect() };
    for (k, n) in ["a.png", "b.jpg.png", "c.png"].iter().enumerate() {
        write_gray8(&dir.join("object_mask").join(n), W, H, &ids(k as u32)).unwrap();
    }
    let ds = llff::load(&dir, &opts(1, 0)).unwrap();
    let b = ds.train.iter().find(|v| v.image_path.ends_with("b.jpg.png")).unwrap();
    assert_eq!(b.instance_ids.as_deref(), Some(&ids(1)[..]));
    assert!(ds.train.iter().all(|v| v.instance_ids.is_some()));
    // an empty object_mask/ (SAM + DEVA not run yet) loads without masks, with a warning
    std::fs::remove_dir_all(dir.join("object_mask")).unwrap();
    std::fs::create_dir_all(dir.join("object_mask")).unwrap();
    let before = model::error::warnings();
    let ds = llff::load(&dir, &opts(1, 0)).unwrap();
    assert!(ds.train.iter().all(|v| v.instance_ids.is_none()));
    assert!(model::error::warnings() > before, "an empty mask folder is warned about");
}

#[test]
fn masks_from_another_tool_replace_any_formats_own() {
    // Replica (own 16-bit labels) and LLFF (no masks): `--masks DIR` gives both the same ids.
    for (tag, dir, images) in [
        ("masks-replica", replica_dir("masks-replica-data", 2), vec!["rgb_0", "rgb_1"]),
        ("masks-llff", llff_dir("masks-llff-data"), vec!["a", "b.jpg", "c"]),
    ] {
        let masks = temp_dir(tag);
        let ids = |i: usize| -> Vec<u8> { (0..W * H).map(|p| ((p as usize + i) % 7) as u8).collect() };
        for (i, stem) in images.iter().enumerate() {
            write_gray8(&masks.join(format!("{stem}.png")), W, H, &ids(i)).unwrap();
        }
        let with = |k: u32| LoadOptions { masks: Some(masks.to_path_buf()), ..opts(k, 0) };
        let ds = load_any(&dir, &with(1)).unwrap();
        assert_eq!(ds.train.len(), images.len(), "{tag}");
        for (i, v) in ds.train.iter().enumerate() {
            assert_eq!(v.instance_ids.as_ref().unwrap(), &ids(i), "{tag} view {i}");
        }
        // downscaled by nearest sample, like the format's own masks
        let half = load_any(&dir, &with(2)).unwrap();
        let got = half.train[1].instance_ids.as_ref().unwrap();
        assert_eq!(got, &(0..12).map(|j| ids(1)[(j / 4) * 16 + (j % 4) * 2]).collect::<Vec<_>>(), "{tag}");
        // a mask of the wrong size, a missing mask, a folder that is not there: errors naming the file
        write_gray8(&masks.join(format!("{}.png", images[1])), W - 2, H, &vec![0; ((W - 2) * H) as usize]).unwrap();
        expect_err(load_any(&dir, &with(1)), &[&format!("{}.png", images[1]), "is 6x6 but its image"]);
        std::fs::remove_file(masks.join(format!("{}.png", images[0]))).unwrap();
        expect_err(load_any(&dir, &with(1)), &[&format!("{}.png", images[0]), "is missing: every image needs a mask"]);
        let gone = LoadOptions { masks: Some(masks.join("nope")), ..opts(1, 0) };
        expect_err(load_any(&dir, &gone), &["nope", "is not a directory"]);
        std::fs::remove_dir_all(&dir).ok();
        std::fs::remove_dir_all(&masks).ok();
    }
}

/// Writes a PNG of raw samples (`bits` per sample, big-endian 16-bit) with an optional palette.
fn raw_png(path: &Path, w: u32, h: u32, color: png::ColorType, bits: png::BitDepth, data: &[u8]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let mut enc = png::Encoder::new(std::fs::File::create(path).unwrap(), w, h);
    enc.set_color(color);
    enc.set_depth(bits);
    if color == png::ColorType::Indexed {
        enc.set_palette((0..=255u8).flat_map(|i| [i, 255 - i, i / 2]).collect::<Vec<u8>>());
    }
    enc.write_header().unwrap().write_image_data(data).unwrap();
}

/// Instance masks are read by value whatever the PNG layout tools write (8- or 16-bit gray, a
/// palette's indices, a gray mask saved as RGB), and what cannot be read right is refused, naming
/// the file and a pixel: ids above 255 (no silent cut to a byte) and colour-coded masks (no
/// silent read of the red channel).
#[test]
fn instance_masks_of_every_png_layout_are_read_by_value_or_refused() {
    use png::{BitDepth, ColorType};
    let (dir, _) = colmap_dir("mask-layouts", true);
    let mask = dir.join("masks/img_a.png");
    let ids: Vec<u8> = (0..W * H).map(|i| (i * 37 % 256) as u8).collect();
    let load_a = || colmap::load(&dir, &opts(1, 0)).map(|(ds, _)| ds.train[0].instance_ids.clone().unwrap());
    // 16-bit gray with ids below 256: the same ids (the high byte alone would make them all 0)
    let wide: Vec<u8> = ids.iter().flat_map(|&v| (v as u16).to_be_bytes()).collect();
    raw_png(&mask, W, H, ColorType::Grayscale, BitDepth::Sixteen, &wide);
    assert_eq!(load_a().unwrap(), ids);
    // a palette PNG (DEVA): the index is the id, whatever colour the palette gives it
    raw_png(&mask, W, H, ColorType::Indexed, BitDepth::Eight, &ids);
    assert_eq!(load_a().unwrap(), ids);
    // 4-bit palette, packed two pixels a byte
    let small: Vec<u8> = ids.iter().map(|v| v % 16).collect();
    let packed: Vec<u8> = small.chunks(2).map(|p| (p[0] << 4) | p[1]).collect();
    raw_png(&mask, W, H, ColorType::Indexed, BitDepth::Four, &packed);
    assert_eq!(load_a().unwrap(), small);
    // a gray mask saved as RGB: read; a colour-coded one: refused
    let rgb: Vec<u8> = ids.iter().flat_map(|&v| [v, v, v]).collect();
    raw_png(&mask, W, H, ColorType::Rgb, BitDepth::Eight, &rgb);
    assert_eq!(load_a().unwrap(), ids);
    let mut coloured = rgb.clone();
    coloured[3 * 9 + 1] ^= 0x40;
    raw_png(&mask, W, H, ColorType::Rgb, BitDepth::Eight, &coloured);
    expect_err(load_a(), &["img_a.png", "colour-coded mask", "pixel (1, 1)"]);
    // 16-bit ids above 255 are refused, naming the pixel
    let mut big = wide.clone();
    big[2 * 10..2 * 10 + 2].copy_from_slice(&300u16.to_be_bytes());
    raw_png(&mask, W, H, ColorType::Grayscale, BitDepth::Sixteen, &big);
    expect_err(load_a(), &["img_a.png", "instance id 300 at pixel (2, 1)", "above 255"]);
    // some masks missing: refused, naming the first missing mask
    raw_png(&mask, W, H, ColorType::Grayscale, BitDepth::Eight, &ids);
    std::fs::remove_file(dir.join("masks/img_c.png")).unwrap();
    expect_err(load_a(), &["img_c.png", "is missing", "has masks for 4 of the 5 images"]);
}

/// A synthetic capture (4 views of 16x12) whose transforms.json is edited by `edit` (given the
/// capture's folder too), loaded with every second view held out.
fn edited_capture(tag: &str, edit: impl Fn(&mut serde_json::Value)) -> model::Result<model::data::Dataset> {
    edited_capture_in(tag, 2, |_, tf| edit(tf))
}

fn edited_capture_in(
    tag: &str,
    holdout_every: usize,
    edit: impl Fn(&Path, &mut serde_json::Value),
) -> model::Result<model::data::Dataset> {
    let dir = temp_dir(tag);
    let o = model::data::synth::SynthOptions { seed: 4, views: 4, width: 16, height: 12, ..Default::default() };
    model::data::synth::write_dataset(&dir, &o, |_, _| {}).unwrap();
    let path = dir.join("transforms.json");
    let mut tf: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    edit(&dir, &mut tf);
    std::fs::write(&path, tf.to_string()).unwrap();
    load_any(&dir, &LoadOptions { holdout_every, ..Default::default() })
}

/// An edit giving every frame frame 0's `key`.
fn like_frame0(key: &'static str) -> Box<dyn Fn(&mut serde_json::Value)> {
    Box::new(move |tf| {
        let v = tf["frames"][0][key].clone();
        for f in tf["frames"].as_array_mut().unwrap() {
            f[key] = v.clone();
        }
    })
}

/// Captures no reconstruction can come from are refused with the image and the problem; the
/// unedited capture loads.
#[test]
fn degenerate_captures_are_refused() {
    assert_eq!(edited_capture("capture-ok", |_| {}).unwrap().train.len(), 2);
    let frame0 = |tf: &serde_json::Value| tf["frames"][0].clone();
    let cases: Vec<(&str, Box<dyn Fn(&mut serde_json::Value)>, &[&str])> = vec![
        ("focal-mm", Box::new(|tf| tf["fl_x"] = 0.035.into()), &["focal length fx = 0.035", "field of view"]),
        ("focal-huge", Box::new(|tf| tf["fl_y"] = 1e9.into()), &["focal length fy", "field of view"]),
        ("principal-far", Box::new(|tf| tf["cx"] = 400.into()), &["principal point (400", "far outside"]),
        ("same-pose", like_frame0("transform_matrix"), &["all 4 views have the same camera pose"]),
        ("same-file", like_frame0("file_path"), &["is both a training view and a held-out view"]),
        (
            "listed-twice",
            Box::new(move |tf| {
                let f = frame0(tf);
                tf["frames"].as_array_mut().unwrap().insert(1, f);
            }),
            &["is both a training view and a held-out view"],
        ),
        ("depth-scale", Box::new(|tf| tf["depth_unit_scale_factor"] = (-0.001).into()), &["depth_unit_scale_factor"]),
    ];
    for (tag, edit, want) in cases {
        let e = expect_err(edited_capture(tag, edit), want);
        assert!(e.contains(".png") || e.contains("transforms.json"), "{tag}: names no file: {e}");
    }
}

/// nerfstudio's own `mask_path` is a 0/255 validity mask: read as instance ids (one object) only
/// with a warning that says so.
#[test]
fn binary_nerfstudio_masks_are_warned_about() {
    let before = model::error::warnings();
    let ds = edited_capture_in("binary-masks", 0, |dir, tf| {
        for f in tf["frames"].as_array_mut().unwrap() {
            let m = f.as_object_mut().unwrap().remove("instance_mask_path").unwrap();
            let valid: Vec<u8> = (0..16 * 12).map(|i| if i % 16 < 8 { 255 } else { 0 }).collect();
            write_gray8(&dir.join(m.as_str().unwrap()), 16, 12, &valid).unwrap();
            f["mask_path"] = m;
        }
    })
    .unwrap();
    assert!(ds.train.iter().all(|v| v.instance_ids.as_ref().unwrap().contains(&255)));
    assert!(model::error::warnings() > before, "a 0/255 mask_path is warned about");
}
