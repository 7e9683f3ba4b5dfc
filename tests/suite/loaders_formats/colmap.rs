//! COLMAP: a hand-encoded model (text and binary) whose cameras reproduce its points2D.

use super::*;
use model::data::colmap;

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
fn colmap_images(dir: &Path) -> Vec<u16> {
    let mut sorted = NAMES;
    sorted.sort();
    let ids = |k: u32| -> Vec<u8> { (0..W * H).map(|i| ((i % W + i / W + k) % 4) as u8).collect() };
    for (i, n) in sorted.iter().enumerate() {
        write_rgb(&dir.join("images").join(n), W, H, &gradient(i as f32 / 10.0, W, H)).unwrap();
        write_gray8(&dir.join("masks").join(n), W, H, &ids(i as u32)).unwrap();
    }
    chatsplat_tests::wide(&ids(0))
}

/// The fixture's binary model in `sparse` with camera 3 (OPENCV) given a radial distortion, as
/// the (distorted) COLMAP model LLFF scenes often carry beside `poses_bounds.npy`.
pub(super) fn write_distorted_colmap(sparse: &Path) {
    let mut distorted = colmap_fixture();
    distorted.cams[2].params[4] = 0.1;
    distorted.write(sparse, true);
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
