//! nerfstudio / Blender loaders: the synthetic dataset round-trips, real lego (PNG) and fox (JPEG)
//! load, malformed inputs give errors naming the file and the problem.

#![allow(deprecated)]

use chatsplat_tests::temp_dir;
use std::path::{Path, PathBuf};
use train::data::nerfstudio::{LoadOptions, load};
use train::data::synth::{self, SynthOptions};

fn synth_dir(tag: &str) -> (PathBuf, SynthOptions) {
    let o = SynthOptions {
        seed: 5,
        views: 6,
        width: 48,
        height: 40,
        ..Default::default()
    };
    let d = temp_dir(tag);
    synth::write_dataset(&d, &o, |_, _| {}).unwrap();
    (d, o)
}

#[test]
fn synthetic_dataset_round_trips_through_the_loader() {
    let (dir, o) = synth_dir("rt");
    let ds = load(&dir, &LoadOptions { holdout_every: 3, ..Default::default() }).unwrap();
    assert_eq!((ds.train.len(), ds.test.len()), (4, 2));
    let objects = model::synthetic::tabletop_objects(o.seed);
    // Views 2 and 5 are held out.
    for (view, i) in ds.train.iter().zip([0usize, 1, 3, 4]).chain(ds.test.iter().zip([2, 5])) {
        let want = synth::view_camera(i, &o);
        let d = (view.camera.world_to_cam - want.world_to_cam).abs().to_cols_array().into_iter().fold(0.0f32, f32::max);
        assert!(d < 1e-4, "view {i}: pose differs by {d}");
        assert!((view.camera.fx - want.fx).abs() < 1e-3 && (view.camera.cx - want.cx).abs() < 1e-4);
        let r = synth::render_view(&want, &objects);
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
    let e = load(dir, &LoadOptions::default()).unwrap_err();
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
    std::fs::write(&tf, good.replacen("\"fl_x\"", "\"k1\": 0.05, \"fl_x\"", 1)).unwrap();
    expect_err(&dir, "lens distortion (k1 = 0.05) is not supported");
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
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/datasets/lego");
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
    let fox = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/datasets/fox");
    let names = ["0001.jpg", "0002.jpg"];
    if !names.iter().all(|n| fox.join("images").join(n).is_file()) {
        eprintln!("SKIPPED: ../shared absent (../shared/datasets/fox/images)");
        return;
    }
    // fox's own transforms.json has lens distortion, which the loader refuses; point a
    // distortion-free transforms.json at two of its JPEGs (absolute paths).
    let dir = temp_dir("fox-jpeg");
    std::fs::create_dir_all(&dir).unwrap();
    let frames: Vec<serde_json::Value> = names
        .iter()
        .map(|n| {
            serde_json::json!({
                "file_path": fox.join("images").join(n).to_str().unwrap(),
                "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]],
            })
        })
        .collect();
    let tf = serde_json::json!({ "fl_x": 1375.52, "fl_y": 1374.49, "cx": 554.558, "cy": 965.268, "w": 1080, "h": 1920, "frames": frames });
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
