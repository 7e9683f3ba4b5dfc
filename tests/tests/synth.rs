//! The built-in synthetic dataset (`chatsplat synth`): deterministic, every object visible, depth
//! consistent with the geometry, poses consistent with transforms.json, and the same scene as the
//! Gaussian tabletop.

#![allow(deprecated)]

use burn::tensor::{Device, Tensor};
use chatsplat_tests::temp_dir;
use glam::{Mat4, Vec3, Vec4};
use model::data::synth::{self, SynthOptions};
use model::images::{read_gray16, read_png8};
use splat_kernels::api::{SplatOptions, splat};

fn opts() -> SynthOptions {
    SynthOptions { seed: 11, views: 6, width: 64, height: 56, ..Default::default() }
}

#[test]
fn dataset_is_deterministic_complete_and_geometrically_consistent() {
    let (a, b) = (temp_dir("a"), temp_dir("b"));
    let mut calls = 0;
    synth::write_dataset(&a, &opts(), |_, _| calls += 1).unwrap();
    synth::write_dataset(&b, &opts(), |_, _| {}).unwrap();
    assert_eq!(calls, 6, "progress reported once per view");
    for rel in
        ["transforms.json", "scene.json", "images/frame_0003.png", "masks/frame_0003.png", "depth/frame_0003.png"]
    {
        assert_eq!(
            std::fs::read(a.join(rel)).unwrap(),
            std::fs::read(b.join(rel)).unwrap(),
            "{rel} differs between runs"
        );
    }
    let tf: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("transforms.json")).unwrap()).unwrap();
    let scene: serde_json::Value = serde_json::from_slice(&std::fs::read(a.join("scene.json")).unwrap()).unwrap();
    let objects = scene["objects"].as_array().unwrap();
    assert_eq!(objects.len(), 5);
    let (fx, fy, cx, cy) = (
        tf["fl_x"].as_f64().unwrap() as f32,
        tf["fl_y"].as_f64().unwrap() as f32,
        tf["cx"].as_f64().unwrap() as f32,
        tf["cy"].as_f64().unwrap() as f32,
    );
    let (w, h) = (64usize, 56usize);
    let mut seen = [0usize; 7];
    let mut checked = 0;
    for f in tf["frames"].as_array().unwrap() {
        let m: Vec<Vec<f32>> = f["transform_matrix"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r.as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect())
            .collect();
        // OpenGL camera-to-world -> OpenCV world-to-camera.
        let c2w_gl = Mat4::from_cols_array_2d(&std::array::from_fn(|c| std::array::from_fn(|r| m[r][c])));
        let c2w = c2w_gl * Mat4::from_diagonal(Vec4::new(1.0, -1.0, -1.0, 1.0));
        let w2c = c2w.inverse();
        // The cameras look at LOOK_AT: it projects to the principal point.
        let p = w2c.transform_point3(synth::LOOK_AT);
        assert!(p.z > 0.0 && (fx * p.x / p.z).abs() < 0.5 && (fy * p.y / p.z).abs() < 0.5);
        let (_, _, ch, ids) = read_png8(&a.join(f["instance_mask_path"].as_str().unwrap())).unwrap();
        assert_eq!(ch, 1);
        let (_, _, depth) = read_gray16(&a.join(f["depth_file_path"].as_str().unwrap())).unwrap();
        let eye = c2w.transform_point3(Vec3::ZERO);
        for o in 0..w * h {
            seen[ids[o] as usize] += 1;
            assert_eq!(ids[o] == 0, depth[o] == 0, "depth present exactly where a surface is");
            let id = ids[o] as usize;
            if id >= 2 && objects[id - 2]["shape"] == "sphere" {
                // Back-project and check the point lies on the sphere.
                let (x, y) = ((o % w) as f32 + 0.5, (o / w) as f32 + 0.5);
                let z = depth[o] as f32 * synth::DEPTH_SCALE;
                let pc = Vec3::new((x - cx) / fx * z, (y - cy) / fy * z, z);
                let pw = c2w.transform_point3(pc);
                let pos: Vec<f32> = objects[id - 2]["position"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_f64().unwrap() as f32)
                    .collect();
                let r = objects[id - 2]["size"].as_f64().unwrap() as f32;
                let dist = (pw - Vec3::from_slice(&pos)).length();
                // 1 mm depth quantisation along a ray at up to ~60 degrees incidence.
                assert!((dist - r).abs() < 4e-3 * (pw - eye).length().max(1.0), "point off the sphere by {}", dist - r);
                checked += 1;
            }
        }
    }
    assert!(checked > 50, "too few sphere pixels checked ({checked})");
    assert!(seen[0] > 0 && seen[1] > 0, "background and table visible");
    for (id, &n) in seen.iter().enumerate().skip(2) {
        assert!(n >= 10, "object {id} covers only {n} pixels over all views");
    }
    std::fs::remove_dir_all(&a).ok();
    std::fs::remove_dir_all(&b).ok();
}

#[test]
fn gaussian_tabletop_covers_the_same_pixels_as_the_analytic_scene() {
    let o = SynthOptions { seed: 7, views: 4, width: 80, height: 80, ..Default::default() };
    let objects = model::data::synth::scene::tabletop_objects(o.seed);
    let (cloud, _) = model::data::synth::gaussians::tabletop(o.seed, 60);
    let device = Device::ndarray();
    let g = cloud.to_gaussians(&device);
    let mut agree = 0usize;
    let mut total = 0usize;
    for i in 0..o.views {
        let cam = synth::view_camera(i, &o);
        let v = synth::raycast::render_view(&cam, &objects);
        let out = splat(&g, &cam, Tensor::zeros([3], &device), &SplatOptions::default()).unwrap();
        let alpha = out.alpha.into_data().to_vec::<f32>().unwrap();
        for (a, id) in alpha.iter().zip(&v.ids) {
            agree += ((*a > 0.5) == (*id != 0)) as usize;
            total += 1;
        }
    }
    let frac = agree as f32 / total as f32;
    assert!(frac > 0.93, "coverage agrees on only {:.1}% of pixels", 100.0 * frac);
}
