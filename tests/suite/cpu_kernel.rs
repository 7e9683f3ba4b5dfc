//! The CPU rasterizer against the dense f64 reference: forward, finite-difference gradients,
//! invariances and determinism.

#![allow(deprecated)] // burn-ndarray and TensorData::to_vec are deprecated in burn 0.22; the card names ndarray.

use chatsplat_tests::*;
use splat_kernels::RasterConfig;
use splat_kernels::cpu;
use splat_kernels::reference;

fn assert_forward_matches(scene: &HostScene, cam: &splat_kernels::Camera, cfg: &RasterConfig, tol: f32) {
    let fast = cpu::forward(&scene.inputs(), cam, cfg);
    let r = reference::render(&scene.inputs(), cam, cfg);
    let slow = masked_reference(&r, &fast, scene.channels());
    let e_img = max_abs_diff(&fast.image, &slow.image);
    let e_alpha = max_abs_diff(&fast.alpha, &slow.alpha);
    let max_depth = slow.depth.iter().fold(1.0f32, |a, &b| a.max(b.abs()));
    let e_depth = max_abs_diff(&fast.depth, &slow.depth) / max_depth;
    assert!(e_img <= tol, "C={} image error {e_img} > {tol}", scene.channels());
    assert!(e_alpha <= tol, "alpha error {e_alpha} > {tol}");
    assert!(e_depth <= tol, "relative depth error {e_depth} > {tol}");
    let same = fast.top_id.iter().zip(&slow.top_id).filter(|(a, b)| a == b).count();
    assert!(
        same as f32 >= 0.999 * fast.top_id.len() as f32,
        "top id differs on {} of {} pixels",
        fast.top_id.len() - same,
        fast.top_id.len()
    );
    assert!(fast.top_id.iter().any(|&t| t >= 0), "scene drew nothing: the test would be vacuous");
}

#[test]
fn forward_matches_reference_for_many_channel_counts() {
    let cam = front_camera(97, 61, 70.0);
    for (k, c) in [1usize, 3, 16, 32, 64, 80].into_iter().enumerate() {
        let scene = random_scene(80, c, &cam, 100 + k as u64);
        assert_forward_matches(&scene, &cam, &RasterConfig::default(), 1e-5);
    }
}

#[test]
fn forward_matches_reference_on_odd_sizes_and_off_centre_principal_point() {
    for (w, h) in [(1u32, 1u32), (17, 5), (33, 47), (130, 18)] {
        let mut cam = front_camera(w, h, 40.0);
        cam.cx = 0.3 * w as f32;
        cam.cy = 0.6 * h as f32;
        let mut scene = random_scene(50, 3, &cam, w as u64 * 7 + h as u64);
        // A big blob over the whole view so that even 1x1 draws something.
        scene.push([0.0, 0.0, 3.0], [0.5, 0.5, 0.5], [1.0, 0.0, 0.0, 0.0], 1.0, &[0.9, 0.1, 0.4]);
        assert_forward_matches(&scene, &cam, &RasterConfig::default(), 1e-5);
    }
}

/// Random upstream gradient; the scalar loss is `<g, outputs>`.
struct Upstream {
    image: Vec<f32>,
    alpha: Vec<f32>,
    depth: Vec<f32>,
}

fn loss(r: &reference::RefOut, g: &Upstream) -> f64 {
    let mut l = 0.0f64;
    for (a, b) in r.image.iter().zip(&g.image) {
        l += a * *b as f64;
    }
    for (a, b) in r.alpha.iter().zip(&g.alpha) {
        l += a * *b as f64;
    }
    for (a, b) in r.depth.iter().zip(&g.depth) {
        l += a * *b as f64;
    }
    l
}

fn check_gradients(scene: &HostScene, cam: &splat_kernels::Camera, seed: u64) {
    let cfg = RasterConfig::smooth();
    let hw = (cam.width * cam.height) as usize;
    let c = scene.channels();
    let mut rng = Rng::new(seed);
    let g = Upstream {
        image: (0..hw * c).map(|_| rng.range(-1.0, 1.0)).collect(),
        alpha: (0..hw).map(|_| rng.range(-1.0, 1.0)).collect(),
        depth: (0..hw).map(|_| rng.range(-0.2, 0.2)).collect(),
    };
    let fwd = cpu::forward(&scene.inputs(), cam, &cfg);
    let an = cpu::backward(&scene.inputs(), cam, &cfg, &fwd.final_t, &fwd.n_visited, &g.image, &g.alpha, &g.depth);
    type Field = fn(&mut HostScene) -> &mut Vec<f32>;
    let fields: [(&str, Field, &Vec<f32>, f32); 7] = [
        ("means", |s| &mut s.means, &an.means, 1e-3),
        ("log_scales", |s| &mut s.log_scales, &an.log_scales, 1e-3),
        ("quats", |s| &mut s.quats, &an.quats, 1e-3),
        ("opacity_logits", |s| &mut s.opacity_logits, &an.opacity_logits, 1e-3),
        ("features", |s| &mut s.features, &an.features, 1e-2),
        ("background", |s| &mut s.background, &an.background, 1e-2),
        ("screen_offsets", |s| &mut s.screen_offsets, &an.screen_offsets, 1e-2),
    ];
    for (name, field, analytic, eps) in fields {
        let len = field(&mut scene.clone()).len();
        let mut fd = vec![0.0f64; len];
        for k in 0..len {
            let mut plus = scene.clone();
            field(&mut plus)[k] += eps;
            let mut minus = scene.clone();
            field(&mut minus)[k] -= eps;
            let lp = loss(&reference::render(&plus.inputs(), cam, &cfg), &g);
            let lm = loss(&reference::render(&minus.inputs(), cam, &cfg), &g);
            // The perturbation actually applied in f32.
            let h = (field(&mut plus)[k] as f64) - (field(&mut minus)[k] as f64);
            fd[k] = (lp - lm) / h;
        }
        let scale = fd.iter().fold(0.0f64, |a, b| a.max(b.abs()));
        assert!(scale > 1e-6, "{name}: all finite differences vanish, the check would be vacuous");
        for k in 0..len {
            let a = analytic[k] as f64;
            let tol = 1e-2 * fd[k].abs() + 1e-3 * scale + 1e-6;
            assert!(
                (a - fd[k]).abs() <= tol,
                "C={c} {name}[{k}]: analytic {a:.6e} vs finite difference {:.6e} (tol {tol:.2e})",
                fd[k]
            );
        }
    }
}

#[test]
fn gradients_match_finite_differences_of_the_reference() {
    let cam = front_camera(45, 37, 50.0);
    for (k, c) in [1usize, 3, 16].into_iter().enumerate() {
        let scene = random_scene(6, c, &cam, 7 + k as u64);
        check_gradients(&scene, &cam, 99 + k as u64);
    }
}

#[test]
fn gradients_match_finite_differences_with_a_rotated_camera_and_clamped_jacobian() {
    let mut cam = splat_kernels::Camera::look_at(
        glam::Vec3::new(1.5, -0.7, -3.0),
        glam::Vec3::new(0.0, 0.0, 1.0),
        glam::Vec3::new(0.0, -1.0, 0.0),
        60.0,
        40,
        32,
    );
    cam.cx = 18.0;
    let mut scene = HostScene::empty(2);
    let mut r = Rng::new(5);
    for _ in 0..5 {
        let m = [r.range(-0.7, 0.7), r.range(-0.7, 0.7), r.range(0.5, 1.5)];
        scene.push(
            m,
            [r.range(-2.0, -1.2); 3],
            [r.normal(), r.normal(), r.normal(), r.normal()],
            r.range(-1.0, 1.0),
            &[r.f(), r.f()],
        );
    }
    // One Gaussian far off-axis (beyond the 1.3 x tan(fov/2) clamp) but wide enough to reach the image.
    let c2w = cam.world_to_cam.inverse();
    let far_left = c2w.transform_point3(glam::Vec3::new(-2.4, 0.1, 2.0));
    scene.push(far_left.into(), [-0.2, -0.4, -0.3], [0.9, 0.1, 0.3, -0.2], 0.5, &[0.3, 0.8]);
    check_gradients(&scene, &cam, 3);
}

#[test]
fn gaussians_entirely_off_screen_do_not_change_the_image() {
    let cam = front_camera(64, 48, 60.0);
    let scene = random_scene(40, 3, &cam, 1);
    let base = cpu::forward(&scene.inputs(), &cam, &RasterConfig::default());
    let mut more = scene.clone();
    let mut r = Rng::new(2);
    for _ in 0..30 {
        let z = r.range(2.0, 5.0);
        // Far to the side, behind the camera, or beyond the far plane.
        more.push([z * 5.0, 0.0, z], [-2.0; 3], [1.0, 0.0, 0.0, 0.0], 3.0, &[1.0, 1.0, 1.0]);
        more.push([0.0, 0.0, -z], [-1.0; 3], [1.0, 0.0, 0.0, 0.0], 3.0, &[1.0, 1.0, 1.0]);
        more.push([0.0, 0.0, 2e10], [-1.0; 3], [1.0, 0.0, 0.0, 0.0], 3.0, &[1.0, 1.0, 1.0]);
    }
    let with = cpu::forward(&more.inputs(), &cam, &RasterConfig::default());
    assert_eq!(base.image, with.image);
    assert_eq!(base.alpha, with.alpha);
    assert_eq!(base.top_id, with.top_id);
}

#[test]
fn permuting_gaussians_does_not_change_the_image() {
    let cam = front_camera(50, 40, 50.0);
    let scene = random_scene(120, 4, &cam, 11);
    let n = scene.len();
    let mut perm: Vec<usize> = (0..n).collect();
    Rng::new(12).shuffle(&mut perm);
    let p = scene.permuted(&perm);
    let cfg = RasterConfig::default();
    let a = cpu::forward(&scene.inputs(), &cam, &cfg);
    let b = cpu::forward(&p.inputs(), &cam, &cfg);
    assert_eq!(a.image, b.image, "image must be bitwise identical under permutation");
    assert_eq!(a.depth, b.depth);
    for (ta, tb) in a.top_id.iter().zip(&b.top_id) {
        let mapped = if *tb >= 0 { perm[*tb as usize] as i32 } else { -1 };
        assert_eq!(*ta, mapped);
    }
}

#[test]
fn cpu_path_is_bitwise_deterministic_across_runs_and_thread_counts() {
    let cam = front_camera(97, 61, 70.0);
    let scene = random_scene(3000, 8, &cam, 21);
    let cfg = RasterConfig::default();
    let hw = (cam.width * cam.height) as usize;
    let mut r = Rng::new(3);
    let gi: Vec<f32> = (0..hw * 8).map(|_| r.range(-1.0, 1.0)).collect();
    let ga: Vec<f32> = (0..hw).map(|_| r.range(-1.0, 1.0)).collect();
    let gd: Vec<f32> = (0..hw).map(|_| r.range(-1.0, 1.0)).collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let f = cpu::forward(&scene.inputs(), &cam, &cfg);
            let g = cpu::backward(&scene.inputs(), &cam, &cfg, &f.final_t, &f.n_visited, &gi, &ga, &gd);
            (f, g)
        })
    };
    let (f1, g1) = run(1);
    let (f2, g2) = run(4);
    let (f3, g3) = run(4);
    assert_eq!(f1, f2);
    assert_eq!(f2, f3);
    assert_eq!(g1, g2);
    assert_eq!(g2, g3);
    assert!(g1.means.iter().any(|&v| v != 0.0));
}
