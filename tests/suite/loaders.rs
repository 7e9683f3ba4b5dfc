//! nerfstudio / Blender loaders: the synthetic dataset round-trips, real lego (PNG) and fox (JPEG)
//! load, OpenCV lens distortion is undistorted (colours bilinear, masks and depth nearest), fisheye
//! and malformed inputs give errors naming the file and the problem.

#![allow(deprecated)]

use chatsplat_tests::{Scratch, temp_dir};
use model::data::nerfstudio::{LoadOptions, load};
use model::data::synth::{self, SynthOptions};
use std::path::Path;

fn synth_dir(tag: &str) -> (Scratch, SynthOptions) {
    let o = SynthOptions { seed: 5, views: 6, width: 48, height: 40, ..Default::default() };
    let d = temp_dir(tag);
    synth::write_dataset(&d, &o, |_, _| {}).unwrap();
    (d, o)
}

#[test]
fn synthetic_dataset_round_trips_through_the_loader() {
    let (dir, o) = synth_dir("rt");
    let ds = load(&dir, &LoadOptions { holdout_every: 3, ..Default::default() }).unwrap();
    assert_eq!((ds.train.len(), ds.test.len()), (4, 2));
    let scene = model::data::synth::scene::SynthScene::from_seed(o.seed);
    // Views 2 and 5 are held out.
    for (view, i) in ds.train.iter().zip([0usize, 1, 3, 4]).chain(ds.test.iter().zip([2, 5])) {
        let want = synth::view_camera(i, &o);
        let d = (view.camera.world_to_cam - want.world_to_cam).abs().to_cols_array().into_iter().fold(0.0f32, f32::max);
        assert!(d < 1e-4, "view {i}: pose differs by {d}");
        assert!((view.camera.fx - want.fx).abs() < 1e-3 && (view.camera.cx - want.cx).abs() < 1e-4);
        let r = synth::raycast::render_view(&want, &scene);
        let e = view.rgb.iter().zip(&r.rgb).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(e <= 0.5 / 255.0 + 1e-6, "view {i}: image differs by {e}");
        assert_eq!(view.instance_ids.as_ref().unwrap(), &r.ids);
        let dd = view.depth.as_ref().unwrap().iter().zip(&r.depth).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(dd <= 0.6e-3, "view {i}: depth differs by {dd}");
    }
    let half = load(&dir, &LoadOptions { downscale: 2, holdout_every: 0, ..Default::default() }).unwrap();
    assert_eq!(half.train.len(), 6);
    let v = &half.train[0];
    assert_eq!((v.camera.width, v.camera.height), (24, 20));
    assert_eq!(v.rgb.len(), 24 * 20 * 3);
    assert!((v.camera.fx - synth::view_camera(0, &o).fx / 2.0).abs() < 1e-3);
    std::fs::remove_dir_all(&dir).ok();
}

fn expect_err(dir: &Path, needle: &str) {
    let e = load(dir, &LoadOptions::default()).unwrap_err().to_string();
    assert!(e.contains(needle), "expected `{needle}` in: {e}");
}

#[test]
fn malformed_datasets_give_errors_naming_the_file() {
    let (dir, _) = synth_dir("bad");
    let tf = dir.join("transforms.json");
    let good = std::fs::read_to_string(&tf).unwrap();
    expect_err(&temp_dir("missing"), "no transforms.json or transforms_train.json");
    std::fs::write(&tf, "{ not json").unwrap();
    expect_err(&dir, "transforms.json: invalid JSON");
    std::fs::write(&tf, good.replacen("\"frames\"", "\"frames_\"", 1)).unwrap();
    expect_err(&dir, "no `frames` array");
    std::fs::write(&tf, good.replacen("\"fl_x\"", "\"k4\": 0.05, \"fl_x\"", 1)).unwrap();
    expect_err(&dir, "fisheye lens distortion (k4 = 0.05) is not supported");
    std::fs::write(&tf, good.replacen("\"w\": 48", "\"w\": 50", 1)).unwrap();
    expect_err(&dir, "frame_0000.png: image is 48x40 but the transforms say 50x40");
    std::fs::write(&tf, &good).unwrap();
    std::fs::remove_file(dir.join("images/frame_0004.png")).unwrap();
    expect_err(&dir, "frame 4: image");
    std::fs::write(&tf, good.replacen("images/frame_0000.png", "images/frame_0000.jpg", 1)).unwrap();
    std::fs::write(dir.join("images/frame_0000.jpg"), b"\xff\xd8").unwrap();
    expect_err(&dir, "frame_0000.jpg: cannot decode JPEG");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn lego_from_shared_datasets_loads_at_quarter_resolution() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/datasets/lego");
    if !dir.join("transforms_train.json").is_file() {
        eprintln!("SKIPPED: ../shared/datasets/lego is not present");
        return;
    }
    let ds = load(&dir, &LoadOptions { downscale: 4, ..Default::default() }).unwrap();
    assert_eq!((ds.train.len(), ds.test.len()), (88, 12));
    for v in ds.train.iter().chain(&ds.test) {
        let c = v.camera;
        assert_eq!((c.width, c.height), (200, 200));
        assert!((c.fx - 1111.111 / 4.0).abs() < 0.05, "fx {}", c.fx);
        let eye = c.world_to_cam.inverse().transform_point3(glam::Vec3::ZERO);
        assert!((eye.length() - 4.03).abs() < 0.05, "camera radius {}", eye.length());
        let o = c.world_to_cam.transform_point3(glam::Vec3::ZERO);
        assert!(o.z > 0.0, "the origin is in front of every camera");
        let (u, v2) = (c.fx * o.x / o.z + c.cx, c.fy * o.y / o.z + c.cy);
        assert!((u - 100.0).abs() < 30.0 && (v2 - 100.0).abs() < 30.0, "origin projects to ({u}, {v2})");
    }
    // White background composited over the RGBA alpha: the image corners are white.
    let rgb = &ds.train[0].rgb;
    assert!(rgb[..3].iter().all(|&x| x > 0.99));
}

#[test]
fn fox_jpegs_from_shared_datasets_decode() {
    let fox = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/datasets/fox");
    let names = ["0001.jpg", "0002.jpg"];
    if !names.iter().all(|n| fox.join("images").join(n).is_file()) {
        eprintln!("SKIPPED: ../shared absent (../shared/datasets/fox/images)");
        return;
    }
    // fox's own transforms.json has lens distortion (undistorted by the loader, see
    // `fox_from_shared_datasets_loads_undistorted`); point a distortion-free transforms.json at
    // two of its JPEGs (absolute paths) to check the plain decode.
    let dir = temp_dir("fox-jpeg");
    std::fs::create_dir_all(&dir).unwrap();
    let frames: Vec<serde_json::Value> = names
        .iter()
        .enumerate()
        .map(|(i, n)| {
            serde_json::json!({
                "file_path": fox.join("images").join(n).to_str().unwrap(),
                "transform_matrix": [[1, 0, 0, i], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]],
            })
        })
        .collect();
    let tf = serde_json::json!({
        "fl_x": 1375.52, "fl_y": 1374.49, "cx": 554.558, "cy": 965.268, "w": 1080, "h": 1920, "frames": frames
    });
    std::fs::write(dir.join("transforms.json"), tf.to_string()).unwrap();
    let mean = |rgb: &[f32]| -> [f32; 3] {
        let n = (rgb.len() / 3) as f32;
        std::array::from_fn(|q| rgb.iter().skip(q).step_by(3).sum::<f32>() / n)
    };
    let mut means = vec![];
    for k in [4, 8] {
        let ds = load(&dir, &LoadOptions { downscale: k, holdout_every: 0, ..Default::default() }).unwrap();
        assert_eq!(ds.train.len(), 2);
        let v = &ds.train[0];
        assert_eq!((v.camera.width, v.camera.height), (1080 / k, 1920 / k));
        assert!((v.camera.fx - 1375.52 / k as f32).abs() < 1e-3);
        assert!(v.rgb.iter().all(|x| (0.0..=1.0).contains(x)));
        // A colour photo: not gray, not flat.
        assert!(v.rgb.chunks(3).any(|p| (p[0] - p[2]).abs() > 0.1), "decoded as gray");
        let m = mean(&v.rgb);
        let var = v.rgb.iter().skip(1).step_by(3).map(|g| (g - m[1]).powi(2)).sum::<f32>() / (v.rgb.len() / 3) as f32;
        assert!(var > 1e-3, "flat image (green variance {var})");
        means.push(m);
    }
    // The box filter keeps the mean colour (both factors divide 1080x1920 exactly).
    for q in 0..3 {
        assert!((means[0][q] - means[1][q]).abs() < 1e-4, "mean colour changes with downscale: {means:?}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

// ---- OpenCV radial-tangential distortion ----------------------------------------------------

const DW: u32 = 64;
const DH: u32 = 48;
/// fl_x, fl_y, cx, cy of the distorted fixture (pixel centres at i + 0.5).
const INTR: [f64; 4] = [52.0, 50.0, 31.3, 24.6];
/// k1, k2, p1, p2.
const DIST: [f64; 4] = [0.1, -0.05, 0.002, -0.001];

/// The OpenCV "OPENCV" model on normalised coordinates (no k3).
fn distort(x: f64, y: f64) -> (f64, f64) {
    let [k1, k2, p1, p2] = DIST;
    let r2 = x * x + y * y;
    let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
    (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
}

/// Inverse of [`distort`] by fixed-point iteration (as OpenCV's undistortPoints).
fn undistort(xd: f64, yd: f64) -> (f64, f64) {
    let [k1, k2, p1, p2] = DIST;
    let (mut x, mut y) = (xd, yd);
    for _ in 0..200 {
        let r2 = x * x + y * y;
        let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
        let (tx, ty) = (2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y);
        (x, y) = ((xd - tx) / radial, (yd - ty) / radial);
    }
    let (cx, cy) = distort(x, y);
    assert!(
        (cx - xd).abs() < 1e-9 && (cy - yd).abs() < 1e-9,
        "fixed-point undistortion did not converge at ({xd}, {yd})"
    );
    (x, y)
}

/// The ideal pinhole image: a smooth colour pattern of the normalised coordinates.
fn pattern(x: f64, y: f64) -> [f32; 3] {
    std::array::from_fn(|c| {
        let c = c as f64;
        (0.5 + 0.3 * (11.0 * x + c).sin() * (9.0 * y - 0.5 * c).cos() + 0.1 * x) as f32
    })
}

/// Normalised pinhole coordinates of pixel `(i, j)`'s centre.
fn normalised(i: u32, j: u32) -> (f64, f64) {
    let [fx, fy, cx, cy] = INTR;
    ((i as f64 + 0.5 - cx) / fx, (j as f64 + 0.5 - cy) / fy)
}

/// [`pattern`] on the undistorted pinhole grid: `[DH, DW, 3]`.
fn pinhole_image() -> Vec<f32> {
    (0..DH)
        .flat_map(|j| {
            (0..DW).flat_map(move |i| {
                let (x, y) = normalised(i, j);
                pattern(x, y)
            })
        })
        .collect()
}

/// A one-frame dataset whose image is [`pattern`] seen through the distortion [`DIST`]: each
/// distorted pixel shows the pattern at its undistorted position. Also writes a mask (a block of
/// id 7) and a depth map (1000 mm everywhere). `extra` is merged into the top level.
fn distorted_dir(tag: &str, extra: serde_json::Value) -> Scratch {
    let dir = temp_dir(tag);
    std::fs::create_dir_all(&dir).unwrap();
    let rgb: Vec<f32> = (0..DH)
        .flat_map(|j| {
            (0..DW).flat_map(move |i| {
                let (xd, yd) = normalised(i, j);
                let (x, y) = undistort(xd, yd);
                pattern(x, y)
            })
        })
        .collect();
    model::images::write_rgb(&dir.join("rgb.png"), DW, DH, &rgb).unwrap();
    let mask: Vec<u8> = (0..DH)
        .flat_map(|j| (0..DW).map(move |i| if (24..40).contains(&i) && (16..32).contains(&j) { 7 } else { 0 }))
        .collect();
    model::images::write_gray8(&dir.join("mask.png"), DW, DH, &mask).unwrap();
    model::images::write_gray16(&dir.join("depth.png"), DW, DH, &vec![1000u16; (DW * DH) as usize]).unwrap();
    let [fx, fy, cx, cy] = INTR;
    let [k1, k2, p1, p2] = DIST;
    let mut tf = serde_json::json!({
        "camera_model": "OPENCV",
        "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": DW, "h": DH,
        "k1": k1, "k2": k2, "p1": p1, "p2": p2,
        "depth_unit_scale_factor": 0.001,
        "frames": [{
            "file_path": "rgb.png",
            "mask_path": "mask.png",
            "depth_file_path": "depth.png",
            "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]],
        }],
    });
    for (k, v) in extra.as_object().unwrap() {
        tf[k] = v.clone();
    }
    std::fs::write(dir.join("transforms.json"), tf.to_string()).unwrap();
    dir
}

fn load_one(dir: &Path, downscale: u32) -> model::data::View {
    let mut ds = load(dir, &LoadOptions { downscale, holdout_every: 0, ..Default::default() }).unwrap();
    assert_eq!((ds.train.len(), ds.test.len()), (1, 0));
    ds.train.remove(0)
}

fn mean_abs(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).map(|(a, b)| (a - b).abs()).sum::<f32>() / a.len() as f32
}

#[test]
fn opencv_distortion_is_undistorted_to_the_pinhole_image() {
    let dir = distorted_dir("undistort", serde_json::json!({}));
    let v = load_one(&dir, 1);
    let c = v.camera;
    // Same intrinsics and size: the undistorted image is the ideal pinhole camera.
    assert_eq!((c.width, c.height), (DW, DH));
    assert!((c.fx - 52.0).abs() < 1e-4 && (c.fy - 50.0).abs() < 1e-4);
    assert!((c.cx - 31.3).abs() < 1e-4 && (c.cy - 24.6).abs() < 1e-4);
    let want = pinhole_image();
    let undistorted = mean_abs(&v.rgb, &want);
    // The raw (still distorted) image, read with the coefficients set to zero.
    let raw_dir = distorted_dir("undistort-raw", serde_json::json!({ "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0 }));
    let raw = load_one(&raw_dir, 1);
    let distorted = mean_abs(&raw.rgb, &want);
    eprintln!("mean abs error against the pinhole pattern: undistorted {undistorted:.5}, raw {distorted:.5}");
    assert!(undistorted < 0.03, "undistorted image is off by {undistorted}");
    assert!(undistorted * 2.0 < distorted, "undistortion does not help: {undistorted} vs raw {distorted}");
    assert!(v.rgb.iter().all(|x| (0.0..=1.0).contains(x)));
    // Undistortion happens at full resolution, before the box filter.
    let half = load_one(&dir, 2);
    assert_eq!((half.camera.width, half.camera.height), (DW / 2, DH / 2));
    assert!((half.camera.fx - 26.0).abs() < 1e-4 && (half.camera.cx - 15.65).abs() < 1e-4);
    let w = DW as usize;
    for (o, px) in half.rgb.chunks(3).enumerate() {
        let (x, y) = (o % (w / 2), o / (w / 2));
        for q in 0..3 {
            let at = |dx: usize, dy: usize| v.rgb[((2 * y + dy) * w + 2 * x + dx) * 3 + q];
            let avg = (at(0, 0) + at(1, 0) + at(0, 1) + at(1, 1)) / 4.0;
            assert!((px[q] - avg).abs() < 1e-5, "downscaled pixel {o} channel {q}: {} vs {avg}", px[q]);
        }
    }
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&raw_dir).ok();
}

#[test]
fn zero_distortion_coefficients_leave_images_bit_identical() {
    let zero = serde_json::json!({ "k1": 0.0, "k2": 0.0, "k3": 0.0, "k4": 0.0, "p1": 0.0, "p2": -0.0 });
    let with_zeros = distorted_dir("zero-coef", zero);
    let a = load_one(&with_zeros, 1);
    let a2 = load_one(&with_zeros, 2);
    // The same files without any coefficient: the undistortion-free path.
    let tf = with_zeros.join("transforms.json");
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&tf).unwrap()).unwrap();
    for key in ["k1", "k2", "k3", "k4", "p1", "p2"] {
        json.as_object_mut().unwrap().remove(key);
    }
    std::fs::write(&tf, json.to_string()).unwrap();
    let b = load_one(&with_zeros, 1);
    let b2 = load_one(&with_zeros, 2);
    for (a, b) in [(&a, &b), (&a2, &b2)] {
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.rgb), bits(&b.rgb));
        assert_eq!(a.instance_ids, b.instance_ids);
        assert_eq!(bits(a.depth.as_ref().unwrap()), bits(b.depth.as_ref().unwrap()));
        assert_eq!(a.camera, b.camera);
    }
    // And the image is the file's pixels, untouched.
    let (_, _, _, bytes) = model::images::read_png8(&with_zeros.join("rgb.png")).unwrap();
    assert!(a.rgb.iter().zip(&bytes).all(|(x, &b)| *x == b as f32 / 255.0));
    std::fs::remove_dir_all(&with_zeros).ok();
}

#[test]
fn masks_and_depth_are_undistorted_by_nearest_sample() {
    let dir = distorted_dir("undistort-mask", serde_json::json!({}));
    let v = load_one(&dir, 1);
    let ids = v.instance_ids.as_ref().unwrap();
    assert_eq!(ids.len(), (DW * DH) as usize);
    assert!(ids.iter().all(|&i| i == 0 || i == 7), "ids other than 0 and 7 after undistortion");
    let w = DW as usize;
    assert_eq!(ids[24 * w + 32], 7, "the block centre keeps its id");
    let sevens = ids.iter().filter(|&&i| i == 7).count();
    assert!((200..=320).contains(&sevens), "{sevens} pixels of id 7 (the block has 256)");
    // Depth: exact values, 0 where the source position falls outside the image (the corners,
    // pushed outwards by the barrel distortion), the full value in the middle.
    let depth = v.depth.as_ref().unwrap();
    assert!(depth.iter().all(|&d| d == 0.0 || (d - 1.0).abs() < 1e-6), "blended depth");
    assert_eq!(depth[0], 0.0, "the top-left corner maps outside the source");
    assert!((depth[24 * w + 32] - 1.0).abs() < 1e-6);
    // Downscaled: nearest sample of the undistorted full-resolution maps.
    let half = load_one(&dir, 2);
    let hids = half.instance_ids.as_ref().unwrap();
    assert_eq!(hids.len(), w / 2 * (DH as usize / 2));
    for (o, &id) in hids.iter().enumerate() {
        let (x, y) = (o % (w / 2), o / (w / 2));
        assert_eq!(id, ids[2 * y * w + 2 * x]);
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn fisheye_distortion_is_refused() {
    for (tag, extra) in [
        ("fisheye-k4", serde_json::json!({ "k4": 0.01 })),
        (
            "fisheye-model",
            serde_json::json!({ "camera_model": "OPENCV_FISHEYE", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0 }),
        ),
    ] {
        let dir = distorted_dir(tag, extra);
        let e = load(&dir, &LoadOptions::default()).unwrap_err().to_string();
        assert!(e.contains("fisheye") && e.contains("not supported"), "{tag}: {e}");
        assert!(e.contains(&dir.join("transforms.json").display().to_string()), "{tag}: the file is not named: {e}");
        std::fs::remove_dir_all(&dir).ok();
    }
}

#[test]
fn fox_from_shared_datasets_loads_undistorted() {
    let fox = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/datasets/fox");
    if !fox.join("transforms.json").is_file() {
        eprintln!("SKIPPED: ../shared absent (../shared/datasets/fox)");
        return;
    }
    let t = std::time::Instant::now();
    let ds = load(&fox, &LoadOptions { downscale: 8, ..Default::default() }).unwrap();
    eprintln!(
        "fox: {} + {} views loaded (undistorted, downscale 8) in {:.2?}",
        ds.train.len(),
        ds.test.len(),
        t.elapsed()
    );
    assert_eq!(ds.train.len() + ds.test.len(), 67);
    for v in ds.train.iter().chain(&ds.test) {
        assert_eq!((v.camera.width, v.camera.height), (135, 240));
        assert_eq!(v.rgb.len(), 135 * 240 * 3);
        assert!(v.rgb.iter().all(|x| x.is_finite() && (0.0..=1.0).contains(x)));
        assert!((v.camera.fx - 1375.52 / 8.0).abs() < 1e-3 && (v.camera.cy - 965.268 / 8.0).abs() < 1e-3);
    }
    // The same JPEG without distortion coefficients: a plain decode. Undistortion moves pixels
    // (by up to a few full-resolution pixels), so the images differ, but only slightly.
    let first =
        ds.train.iter().find(|v| v.image_path.ends_with("images/0001.jpg")).expect("0001.jpg is a training view");
    let dir = temp_dir("fox-plain");
    std::fs::create_dir_all(&dir).unwrap();
    let tf = serde_json::json!({
        "fl_x": 1375.52, "fl_y": 1374.49, "cx": 554.558, "cy": 965.268, "w": 1080, "h": 1920,
        "frames": [{
            "file_path": fox.join("images/0001.jpg").to_str().unwrap(),
            "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]
        }],
    });
    std::fs::write(dir.join("transforms.json"), tf.to_string()).unwrap();
    let plain = load_one(&dir, 8);
    let max = first.rgb.iter().zip(&plain.rgb).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    let mean = mean_abs(&first.rgb, &plain.rgb);
    eprintln!("fox 0001.jpg: undistorted vs plain decode: max {max:.4}, mean {mean:.5}");
    assert!(max > 1e-3, "undistortion left the image unchanged");
    assert!(mean < 0.05, "undistortion changed the image too much (mean {mean})");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn masks_given_with_the_masks_option_are_undistorted_like_the_captures_own() {
    let dir = distorted_dir("masks-option-distorted", serde_json::json!({}));
    let own = load_one(&dir, 1).instance_ids.unwrap();
    assert!(own.contains(&7));
    // the same block with id 9 in another folder, named after the image
    let masks = temp_dir("masks-option-dir");
    let m: Vec<u8> = (0..DH)
        .flat_map(|j| (0..DW).map(move |i| if (24..40).contains(&i) && (16..32).contains(&j) { 9 } else { 0 }))
        .collect();
    model::images::write_gray8(&masks.join("rgb.png"), DW, DH, &m).unwrap();
    let opts = LoadOptions { masks: Some(masks.to_path_buf()), holdout_every: 0, ..Default::default() };
    for ds in [load(&dir, &opts).unwrap(), model::data::load_any(&dir, &opts).unwrap()] {
        let given = ds.train[0].instance_ids.clone().unwrap();
        let want: Vec<u16> = own.iter().map(|&i| if i == 7 { 9 } else { i }).collect();
        assert_eq!(given, want, "undistorted exactly as the capture's own mask");
    }
    std::fs::remove_file(masks.join("rgb.png")).unwrap();
    let e = load(&dir, &opts).unwrap_err().to_string();
    assert!(e.contains("rgb.png") && e.contains("is missing"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
    std::fs::remove_dir_all(&masks).ok();
}
