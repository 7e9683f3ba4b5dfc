//! Numerical stability on hard inputs (the design card: "test numerical stability on hard cases").
//! Finite inputs must give finite outputs and gradients; NaN/Inf inputs are rejected with an error.

#![allow(deprecated)] // burn-ndarray and TensorData::to_vec are deprecated in burn 0.22; the card names ndarray.

use chatsplat_tests::*;
use splat_kernels::cpu::{self, ForwardOut, GradOut};
use splat_kernels::{Camera, RasterConfig, SplatError, reference};

fn run(scene: &HostScene, cam: &Camera) -> (ForwardOut, GradOut) {
    scene.inputs().validate().expect("finite inputs are valid");
    let cfg = RasterConfig::default();
    let f = cpu::forward(&scene.inputs(), cam, &cfg);
    let hw = (cam.width * cam.height) as usize;
    let mut r = Rng::new(4);
    let gi: Vec<f32> = (0..hw * scene.channels()).map(|_| r.range(-1.0, 1.0)).collect();
    let ga: Vec<f32> = (0..hw).map(|_| r.range(-1.0, 1.0)).collect();
    let gd: Vec<f32> = (0..hw).map(|_| r.range(-1.0, 1.0)).collect();
    let g = cpu::backward(&scene.inputs(), cam, &cfg, &f.final_t, &f.n_visited, &gi, &ga, &gd);
    (f, g)
}

fn assert_finite(name: &str, f: &ForwardOut, g: &GradOut) {
    for (what, v) in [
        ("image", &f.image),
        ("alpha", &f.alpha),
        ("depth", &f.depth),
        ("grad means", &g.means),
        ("grad log_scales", &g.log_scales),
        ("grad quats", &g.quats),
        ("grad opacity", &g.opacity_logits),
        ("grad features", &g.features),
        ("grad background", &g.background),
        ("grad screen", &g.screen_offsets),
    ] {
        if let Some(k) = v.iter().position(|x| !x.is_finite()) {
            panic!("{name}: {what}[{k}] = {} is not finite", v[k]);
        }
    }
    assert!(f.alpha.iter().all(|&a| (0.0..=1.0).contains(&a)), "{name}: alpha outside [0, 1]");
}

fn one(mean: [f32; 3], ls: [f32; 3], q: [f32; 4], logit: f32, c: usize) -> HostScene {
    let mut s = HostScene::empty(c);
    s.push(mean, ls, q, logit, &vec![0.7; c]);
    s
}

#[test]
fn degenerate_quaternions_use_the_identity_policy() {
    let cam = front_camera(33, 29, 30.0);
    let identity = cpu::forward(
        &one([0.1, 0.0, 3.0], [-1.0, -2.0, -1.5], [1.0, 0.0, 0.0, 0.0], 1.0, 3).inputs(),
        &cam,
        &RasterConfig::default(),
    );
    for q in [[0.0f32; 4], [1e-40, 0.0, -1e-41, 0.0], [1e-13, 1e-13, 0.0, 0.0]] {
        let s = one([0.1, 0.0, 3.0], [-1.0, -2.0, -1.5], q, 1.0, 3);
        let (f, g) = run(&s, &cam);
        assert_finite("degenerate quaternion", &f, &g);
        assert_eq!(f.image, identity.image, "quaternion {q:?} must render as the identity rotation");
        assert!(g.quats.iter().all(|&v| v == 0.0), "identity policy has a zero quaternion gradient");
    }
    // Huge but finite quaternions normalise like any other.
    let s = one([0.1, 0.0, 3.0], [-1.0, -2.0, -1.5], [3e30, 0.0, 0.0, 0.0], 1.0, 3);
    let (f, g) = run(&s, &cam);
    assert_finite("huge quaternion", &f, &g);
    assert_eq!(f.image, identity.image);
}

#[test]
fn extreme_scales_and_anisotropy_stay_finite_and_match_the_reference() {
    let cam = front_camera(64, 48, 50.0);
    let q45 = [0.9238795, 0.0, 0.0, 0.3826834]; // 45 degrees about z
    let cases: [(&str, [f32; 3], [f32; 4]); 6] = [
        ("scale 1e-8", [(1e-8f32).ln(); 3], [1.0, 0.0, 0.0, 0.0]),
        ("scale 1e4", [(1e4f32).ln(); 3], [1.0, 0.0, 0.0, 0.0]),
        ("anisotropy 1e4:1", [0.0, (1e-4f32).ln(), (1e-4f32).ln()], q45),
        ("anisotropy 1e4:1 needle", [(1e-4f32).ln(), (1e-4f32).ln(), 0.0], [0.8, 0.3, 0.5, 0.1]),
        ("log scale 1000", [1000.0, -1000.0, 3.0], q45),
        ("flat disc", [-0.5, -0.5, (1e-8f32).ln()], [0.7, 0.7, 0.1, 0.0]),
    ];
    for (name, ls, q) in cases {
        let mut s = random_scene(20, 3, &cam, 8);
        s.push([0.05, -0.02, 2.5], ls, q, 2.0, &[0.2, 0.9, 0.5]);
        let (f, g) = run(&s, &cam);
        assert_finite(name, &f, &g);
        let r = reference::render(&s.inputs(), &cam, &RasterConfig::default()).to_forward_out();
        let e = max_abs_diff(&f.image, &r.image);
        assert!(e <= 2e-4, "{name}: image differs from the f64 reference by {e}");
    }
}

#[test]
fn near_plane_behind_camera_and_extreme_opacity() {
    let cam = front_camera(40, 30, 35.0);
    let mut s = HostScene::empty(4);
    let near = cam.near;
    s.push([0.0, 0.0, -1.0], [0.0; 3], [1.0, 0.0, 0.0, 0.0], 5.0, &[1.0; 4]); // behind
    s.push([0.0, 0.0, near * 0.5], [0.0; 3], [1.0, 0.0, 0.0, 0.0], 5.0, &[1.0; 4]); // centre before near
    s.push([0.01, 0.0, near * 1.01], [-1.0; 3], [1.0, 0.0, 0.0, 0.0], 0.0, &[0.5; 4]); // straddles near
    s.push([0.0, 0.0, near], [-6.0; 3], [1.0, 0.0, 0.0, 0.0], 0.0, &[0.5; 4]); // exactly at near
    s.push([0.2, 0.1, 2.0], [-2.0; 3], [1.0, 0.0, 0.0, 0.0], 50.0, &[0.1; 4]); // opacity logit +50
    s.push([-0.2, 0.1, 2.0], [-2.0; 3], [1.0, 0.0, 0.0, 0.0], -50.0, &[0.9; 4]); // opacity logit -50
    s.push([0.0, -0.2, 2.0], [-2.0; 3], [1.0, 0.0, 0.0, 0.0], 1e4, &[0.3; 4]);
    let (f, g) = run(&s, &cam);
    assert_finite("near plane / opacity", &f, &g);
    let r = reference::render(&s.inputs(), &cam, &RasterConfig::default()).to_forward_out();
    assert!(max_abs_diff(&f.image, &r.image) <= 1e-4);
    // The +50 logit Gaussian is clamped at alpha 0.99 somewhere.
    assert!(f.alpha.iter().any(|&a| a >= 0.98));
}

#[test]
fn ten_thousand_gaussians_stacked_on_one_pixel() {
    let cam = front_camera(32, 32, 40.0);
    let mut s = HostScene::empty(16);
    let mut r = Rng::new(77);
    for i in 0..10_000 {
        let feat: Vec<f32> = (0..16).map(|_| r.range(-1e3, 1e3)).collect();
        let z = 3.0 + (i % 7) as f32 * 1e-7;
        s.push([0.0, 0.0, z], [-9.0; 3], [1.0, 0.0, 0.0, 0.0], r.range(-3.0, 3.0), &feat);
    }
    let (f, g) = run(&s, &cam);
    assert_finite("stack", &f, &g);
    // Compositing stopped early: far fewer than 10,000 entries were visited at the centre.
    let centre = (16 * 32 + 16) as usize;
    assert!(f.n_visited[centre] > 0 && f.n_visited[centre] < 10_000, "visited {}", f.n_visited[centre]);
    assert!(f.final_t[centre] >= 1e-4 * 0.99);
    let rf = reference::render(&s.inputs(), &cam, &RasterConfig::default()).to_forward_out();
    // Features of magnitude 1e3: compare relative to that scale.
    let e = max_abs_diff(&f.image, &rf.image) / 1e3;
    assert!(e <= 1e-5, "relative error {e}");
}

#[test]
fn empty_and_fully_culled_scenes_and_a_one_pixel_image() {
    let cam = front_camera(19, 13, 20.0);
    let empty = HostScene::empty(5);
    let (f, g) = run(&empty, &cam);
    assert_finite("N = 0", &f, &g);
    assert!(f.image.chunks(5).all(|px| px == empty.background.as_slice()));
    assert!(f.top_id.iter().all(|&t| t == -1));
    let mut culled = HostScene::empty(5);
    for k in 0..50 {
        culled.push([0.0, 0.0, -(k as f32) - 1.0], [0.0; 3], [1.0, 0.0, 0.0, 0.0], 2.0, &[1.0; 5]);
    }
    let (f2, g2) = run(&culled, &cam);
    assert_finite("all culled", &f2, &g2);
    assert_eq!(f2.image, f.image);
    assert!(g2.means.iter().all(|&v| v == 0.0));
    assert!(g2.background.iter().any(|&v| v != 0.0), "background still receives gradient");
    let px = front_camera(1, 1, 1.0);
    let s = random_scene(30, 3, &px, 5);
    let (f3, g3) = run(&s, &px);
    assert_finite("1x1", &f3, &g3);
    assert_eq!(f3.image.len(), 3);
}

#[test]
fn non_finite_inputs_are_rejected_with_the_tensor_and_row() {
    let cam = front_camera(8, 8, 8.0);
    let mut s = random_scene(5, 2, &cam, 1);
    s.means[3 * 3 + 1] = f32::NAN;
    match s.inputs().validate() {
        Err(SplatError::NonFinite { tensor, row, .. }) => {
            assert_eq!(tensor, "means");
            assert_eq!(row, 3);
        }
        other => panic!("expected a NonFinite error, got {other:?}"),
    }
    let mut s = random_scene(5, 2, &cam, 1);
    s.features[2 * 4] = f32::INFINITY;
    let err = s.inputs().validate().unwrap_err();
    assert!(err.to_string().contains("features row 4"), "{err}");
    let mut s = random_scene(5, 2, &cam, 1);
    s.quats.pop();
    assert!(matches!(s.inputs().validate(), Err(SplatError::Shape(_))));
}
