//! The tensor-level op through burn: NdArray and Flex (plain and autodiff) against the CPU kernels, and
//! wgpu (lavapipe on CPU in CI) against NdArray. wgpu runs in one test to pay kernel compilation
//! once; set CHATSPLAT_REQUIRE_WGPU=1 to fail instead of skipping when no adapter exists.

#![allow(deprecated)] // burn-ndarray and TensorData::to_vec are deprecated in burn 0.22; the card names ndarray.

use burn::tensor::{Device, Tensor, TensorData};
use chatsplat_tests::*;
use splat_kernels::api::{SplatOptions, splat};
use splat_kernels::{Camera, FloatAdd, GradReduce, RasterConfig, SplatError, TileSort, cpu, reference};

struct Grads {
    means: Vec<f32>,
    log_scales: Vec<f32>,
    quats: Vec<f32>,
    opacity_logits: Vec<f32>,
    features: Vec<f32>,
    background: Vec<f32>,
    screen_offsets: Vec<f32>,
}

/// Renders on an autodiff `device` and back-propagates `<w, features> + <wa, alpha> + <wd, depth>`.
fn render_and_grad(
    scene: &HostScene,
    cam: &Camera,
    cfg: RasterConfig,
    device: &Device,
    seed: u64,
) -> (Vec<f32>, Grads) {
    render_and_grad_with(scene, cam, cfg, device, seed, None)
}

fn render_and_grad_with(
    scene: &HostScene,
    cam: &Camera,
    cfg: RasterConfig,
    device: &Device,
    seed: u64,
    max_pass_bytes: Option<usize>,
) -> (Vec<f32>, Grads) {
    let (g, bg) = scene.gaussians(device);
    let g = splat_kernels::Gaussians {
        means: g.means.require_grad(),
        log_scales: g.log_scales.require_grad(),
        quats: g.quats.require_grad(),
        opacity_logits: g.opacity_logits.require_grad(),
        features: g.features.require_grad(),
    };
    let bg = bg.require_grad();
    let n = scene.len();
    let offsets = Tensor::<2>::zeros([n, 2], device).require_grad();
    let opts = SplatOptions { config: cfg, validate: true, screen_offsets: Some(offsets.clone()), max_pass_bytes };
    let out = splat(&g, cam, bg.clone(), &opts).expect("valid inputs");
    let (h, w, c) = (cam.height as usize, cam.width as usize, scene.channels());
    let mut r = Rng::new(seed);
    let wf: Vec<f32> = (0..h * w * c).map(|_| r.range(-1.0, 1.0)).collect();
    let wa: Vec<f32> = (0..h * w).map(|_| r.range(-1.0, 1.0)).collect();
    let wd: Vec<f32> = (0..h * w).map(|_| r.range(-0.2, 0.2)).collect();
    let loss = (out.features.clone() * Tensor::<3>::from_data(TensorData::new(wf, [h, w, c]), device)).sum()
        + (out.alpha.clone() * Tensor::<2>::from_data(TensorData::new(wa, [h, w]), device)).sum()
        + (out.depth.clone() * Tensor::<2>::from_data(TensorData::new(wd, [h, w]), device)).sum();
    let grads = loss.backward();
    let get2 = |t: &Tensor<2>| host(t.grad(&grads).expect("gradient exists"));
    let gr = Grads {
        means: get2(&g.means),
        log_scales: get2(&g.log_scales),
        quats: get2(&g.quats),
        opacity_logits: host(g.opacity_logits.grad(&grads).expect("gradient exists")),
        features: get2(&g.features),
        background: host(bg.grad(&grads).expect("gradient exists")),
        screen_offsets: get2(&offsets),
    };
    (host(out.features), gr)
}

fn grad_list(g: &Grads) -> [(&'static str, &Vec<f32>); 7] {
    [
        ("means", &g.means),
        ("log_scales", &g.log_scales),
        ("quats", &g.quats),
        ("opacity_logits", &g.opacity_logits),
        ("features", &g.features),
        ("background", &g.background),
        ("screen_offsets", &g.screen_offsets),
    ]
}

/// The CPU backends, which share the host rasterizer: burn-ndarray and its successor burn-flex.
fn cpu_devices() -> [Device; 2] {
    [Device::ndarray(), Device::flex()]
}

#[test]
fn cpu_backends_forward_equals_the_cpu_kernel_bitwise() {
    let cam = front_camera(97, 61, 70.0);
    let scene = random_scene(200, 5, &cam, 3);
    let direct = cpu::forward(&scene.inputs(), &cam, &RasterConfig::default());
    for device in cpu_devices() {
        let (g, bg) = scene.gaussians(&device);
        let out = splat(&g, &cam, bg, &SplatOptions::default()).unwrap();
        assert_eq!(host(out.features), direct.image, "{device:?}");
        assert_eq!(host(out.alpha), direct.alpha, "{device:?}");
        assert_eq!(host(out.depth), direct.depth, "{device:?}");
        let ids: Vec<i32> = out.top_id.into_data().convert::<i32>().to_vec::<i32>().unwrap();
        assert_eq!(ids, direct.top_id, "{device:?}");
    }
}

#[test]
fn cpu_backends_autodiff_gradients_equal_the_hand_written_backward() {
    let cam = front_camera(64, 40, 50.0);
    let scene = random_scene(60, 4, &cam, 9);
    let cfg = RasterConfig::default();
    for device in cpu_devices() {
        let (_, g) = render_and_grad(&scene, &cam, cfg, &device.autodiff(), 17);
        assert_gradients_equal_the_direct_backward(&scene, &cam, cfg, &g);
    }
}

fn assert_gradients_equal_the_direct_backward(scene: &HostScene, cam: &Camera, cfg: RasterConfig, g: &Grads) {
    // The same upstream gradient, straight into the CPU backward.
    let (h, w, c) = (cam.height as usize, cam.width as usize, 4);
    let mut r = Rng::new(17);
    let wf: Vec<f32> = (0..h * w * c).map(|_| r.range(-1.0, 1.0)).collect();
    let wa: Vec<f32> = (0..h * w).map(|_| r.range(-1.0, 1.0)).collect();
    let wd: Vec<f32> = (0..h * w).map(|_| r.range(-0.2, 0.2)).collect();
    let f = cpu::forward(&scene.inputs(), cam, &cfg);
    let d = cpu::backward(&scene.inputs(), cam, &cfg, &f.final_t, &f.n_visited, &wf, &wa, &wd);
    let want = Grads {
        means: d.means,
        log_scales: d.log_scales,
        quats: d.quats,
        opacity_logits: d.opacity_logits,
        features: d.features,
        background: d.background,
        screen_offsets: d.screen_offsets,
    };
    for ((name, a), (_, b)) in grad_list(g).into_iter().zip(grad_list(&want)) {
        assert_eq!(a, b, "{name}: autodiff result differs from the direct backward");
        assert!(a.iter().any(|&v| v != 0.0), "{name}: gradient is all zero");
    }
}

/// Rendering wide features in channel groups (as wgpu does past its binding limit) changes no
/// output and no gradient.
fn assert_channel_groups_are_transparent(device: &Device) {
    let cam = front_camera(40, 24, 40.0);
    let scene = random_scene(50, 7, &cam, 31);
    let cfg = RasterConfig::default();
    let (f1, g1) = render_and_grad_with(&scene, &cam, cfg, device, 2, None);
    // 40 x 24 pixels x (2 + 2) floats x 4 bytes: two channels per pass, four passes.
    let (f2, g2) = render_and_grad_with(&scene, &cam, cfg, device, 2, Some(40 * 24 * 4 * 4));
    assert_eq!(f1, f2);
    for ((name, a), (_, b)) in grad_list(&g1).into_iter().zip(grad_list(&g2)) {
        assert_close(&format!("channel groups: {name}"), a, b, 1e-5);
    }
}

#[test]
fn ndarray_channel_groups_change_nothing() {
    assert_channel_groups_are_transparent(&Device::ndarray().autodiff());
}

#[test]
fn screen_gradient_accumulator_collects_per_view_norms() {
    let cam = front_camera(40, 30, 40.0);
    let scene = random_scene(25, 3, &cam, 4);
    let device = Device::ndarray().autodiff();
    let mut acc = splat_kernels::api::ScreenGradAccumulator::default();
    let mut expected = vec![0.0f32; scene.len()];
    for k in 0..2 {
        let (g, bg) = scene.gaussians(&device);
        let offsets = Tensor::<2>::zeros([scene.len(), 2], &device).require_grad();
        let opts = SplatOptions { screen_offsets: Some(offsets.clone()), ..Default::default() };
        let out = splat(&g, &cam, bg, &opts).unwrap();
        let loss = out.features.sum() * (k as f32 + 1.0);
        let grad = offsets.grad(&loss.backward()).unwrap();
        let host_grad = host(grad.clone());
        for i in 0..scene.len() {
            expected[i] += (host_grad[2 * i].powi(2) + host_grad[2 * i + 1].powi(2)).sqrt();
        }
        acc.add(grad);
    }
    assert_eq!(acc.norm_sum.len(), scene.len());
    for i in 0..scene.len() {
        assert!((acc.norm_sum[i] - expected[i]).abs() <= 1e-6 * expected[i].max(1.0));
    }
    assert!(acc.count.contains(&2), "visible Gaussians are counted in both views");
    assert!(acc.mean().iter().zip(&acc.norm_sum).all(|(m, s)| *m <= *s + 1e-9));
}

#[test]
fn ndarray_api_rejects_bad_input_with_clear_errors() {
    let cam = front_camera(16, 16, 16.0);
    let device = Device::ndarray();
    let mut scene = random_scene(4, 3, &cam, 2);
    scene.log_scales[5] = f32::NAN;
    let (g, bg) = scene.gaussians(&device);
    let err = splat(&g, &cam, bg, &SplatOptions::default()).unwrap_err();
    assert!(matches!(err, SplatError::NonFinite { tensor: "log_scales", row: 1, value } if value.is_nan()), "{err:?}");
    assert_eq!(err.to_string(), "splat: log_scales row 1 holds a non-finite value (NaN)");
    let scene = random_scene(4, 3, &cam, 2);
    let (g, _) = scene.gaussians(&device);
    let err = splat(&g, &cam, Tensor::zeros([2], &device), &SplatOptions::default()).unwrap_err();
    assert!(err.to_string().contains("background has shape [2], expected [3]"), "{err}");
    let (g, bg) = scene.gaussians(&device);
    let mut bad = cam;
    bad.near = -1.0;
    assert!(matches!(splat(&g, &bad, bg, &SplatOptions::default()), Err(SplatError::InvalidCamera(_))));
}

fn assert_close(name: &str, got: &[f32], want: &[f32], rel: f32) {
    let scale = want.iter().fold(1e-6f32, |a, b| a.max(b.abs()));
    let err = max_abs_diff(got, want);
    assert!(err <= rel * scale, "{name}: max error {err} > {rel} x {scale}");
}

#[test]
fn wgpu_matches_ndarray_forward_backward_and_hard_cases() {
    let Some(wgpu) = wgpu_device() else { return };
    let nd = Device::ndarray();
    let cfg = RasterConfig::default();
    // Forward, several channel counts, an image size that is not a multiple of 16.
    let cam = front_camera(97, 61, 70.0);
    // (every register bucket of the raster kernels, 4 to 64 channels, and 80 in global memory)
    for (k, c) in [1usize, 3, 6, 16, 32, 64, 80].into_iter().enumerate() {
        let scene = random_scene(150, c, &cam, 40 + k as u64);
        let (g, bg) = scene.gaussians(&wgpu);
        let out = splat(&g, &cam, bg, &SplatOptions::default()).unwrap();
        let feats = host(out.features);
        let alpha = host(out.alpha);
        let depth = host(out.depth);
        let ids: Vec<i32> = out.top_id.into_data().convert::<i32>().to_vec::<i32>().unwrap();
        let (gn, bgn) = scene.gaussians(&nd);
        let want = splat(&gn, &cam, bgn, &SplatOptions::default()).unwrap();
        let fast = cpu::ForwardOut { image: feats, alpha, depth, top_id: ids, ..Default::default() };
        // Pixels where f32 rounding may flip a threshold are taken from the wgpu result.
        let r = reference::render(&scene.inputs(), &cam, &cfg);
        let masked = masked_reference(&r, &fast, c);
        let _ = masked;
        let mut want_img = host(want.features);
        let mut want_alpha = host(want.alpha);
        let mut want_depth = host(want.depth);
        for (o, &amb) in r.ambiguous.iter().enumerate() {
            if amb {
                want_img[o * c..(o + 1) * c].copy_from_slice(&fast.image[o * c..(o + 1) * c]);
                want_alpha[o] = fast.alpha[o];
                want_depth[o] = fast.depth[o];
            }
        }
        assert_close(&format!("C={c} features"), &fast.image, &want_img, 1e-4);
        assert_close(&format!("C={c} alpha"), &fast.alpha, &want_alpha, 1e-4);
        assert_close(&format!("C={c} depth"), &fast.depth, &want_depth, 1e-4);
        let want_ids: Vec<i32> = want.top_id.into_data().convert::<i32>().to_vec::<i32>().unwrap();
        let same = fast.top_id.iter().zip(&want_ids).filter(|(a, b)| a == b).count();
        assert!(same * 1000 >= 999 * want_ids.len(), "C={c}: top ids differ on {} pixels", want_ids.len() - same);
    }
    // Gradients on a smooth configuration (no thresholds, so no rounding-induced branch flips).
    // (every register bucket, 4 to 64 channels, and 80 in global memory)
    let cam = front_camera(45, 37, 50.0);
    for (k, c) in [3usize, 6, 16, 32, 64, 80].into_iter().enumerate() {
        let scene = random_scene(40, c, &cam, 60 + k as u64);
        let (fw, gw) = render_and_grad(&scene, &cam, RasterConfig::smooth(), &wgpu.clone().autodiff(), 5);
        let (fnd, gnd) = render_and_grad(&scene, &cam, RasterConfig::smooth(), &nd.clone().autodiff(), 5);
        assert_close("smooth forward", &fw, &fnd, 1e-4);
        for ((name, a), (_, b)) in grad_list(&gw).into_iter().zip(grad_list(&gnd)) {
            assert_close(&format!("C={c} grad {name}"), a, b, 1e-3);
        }
    }
    // Every other way of adding a tile's gradients matches too: the plane-summed backward (what
    // GPUs run by default, forced here on lavapipe) and each atomic float add the adapter has
    // (the compare-and-swap loop always; the native add where the adapter reports it).
    let native = splat_kernels::cube::native_float_add_on(&wgpu) == Some(true);
    if !native {
        eprintln!("skipping the native float add: this adapter has none (the compare-and-swap loop is tested)");
    }
    let mut ways = vec![
        ("cas", RasterConfig { float_add: FloatAdd::Cas, ..RasterConfig::smooth() }),
        ("bitonic", RasterConfig { tile_sort: TileSort::Bitonic, ..RasterConfig::smooth() }),
    ];
    // (lavapipe through Vulkan has subgroups; an adapter without them refuses the plane path by name)
    if splat_kernels::cube::adapter::subgroups() == Some(true) {
        ways.push(("plane", RasterConfig { grad_reduce: GradReduce::Plane, ..RasterConfig::smooth() }));
    } else {
        eprintln!("skipping the plane-summed backward: this adapter has no subgroup operations");
        let forced = RasterConfig { grad_reduce: GradReduce::Plane, ..RasterConfig::smooth() };
        let scene = random_scene(40, 3, &cam, 60);
        let refused = std::panic::catch_unwind(|| render_and_grad(&scene, &cam, forced, &wgpu.clone().autodiff(), 5));
        let payload = refused.map(|_| ()).expect_err("a forced plane path without subgroups runs");
        let message = payload.downcast_ref::<String>().cloned().unwrap_or_default();
        assert!(message.contains("subgroup"), "a forced plane path is refused by name: {message}");
    }
    if native {
        ways.push(("native", RasterConfig { float_add: FloatAdd::Native, ..RasterConfig::smooth() }));
    }
    for (way, config) in ways {
        for (k, c) in [3usize, 32].into_iter().enumerate() {
            let scene = random_scene(40, c, &cam, 60 + k as u64);
            let (fw, gw) = render_and_grad(&scene, &cam, config, &wgpu.clone().autodiff(), 5);
            let (fnd, gnd) = render_and_grad(&scene, &cam, RasterConfig::smooth(), &nd.clone().autodiff(), 5);
            assert_close(&format!("smooth forward ({way})"), &fw, &fnd, 1e-4);
            for ((name, a), (_, b)) in grad_list(&gw).into_iter().zip(grad_list(&gnd)) {
                assert_close(&format!("C={c} {way} grad {name}"), a, b, 1e-3);
            }
        }
    }
    // Hard cases stay finite on wgpu too.
    let cam = front_camera(33, 21, 30.0);
    let mut hard = HostScene::empty(3);
    hard.push([0.0, 0.0, 2.0], [0.0; 3], [0.0; 4], 50.0, &[1e3, -1e3, 0.5]);
    hard.push([0.1, 0.0, 2.0], [(1e-8f32).ln(); 3], [1e-40, 0.0, 0.0, 0.0], -50.0, &[1.0; 3]);
    hard.push([0.0, 0.1, 2.0], [0.0, (1e-4f32).ln(), (1e-4f32).ln()], [0.92, 0.0, 0.0, 0.38], 1.0, &[0.2; 3]);
    hard.push([0.0, 0.0, -1.0], [0.0; 3], [1.0, 0.0, 0.0, 0.0], 2.0, &[1.0; 3]);
    hard.push([0.0, 0.0, 0.0101], [-1.0; 3], [1.0, 0.0, 0.0, 0.0], 0.0, &[0.5; 3]);
    hard.push([0.0, 0.0, 3.0], [(1e4f32).ln(); 3], [1.0, 0.0, 0.0, 0.0], 0.0, &[0.5; 3]);
    for _ in 0..2000 {
        hard.push([0.0, 0.0, 4.0], [-9.0; 3], [1.0, 0.0, 0.0, 0.0], 0.5, &[100.0, 0.0, -100.0]);
    }
    let (f, g) = render_and_grad(&hard, &cam, cfg, &wgpu.clone().autodiff(), 8);
    assert!(f.iter().all(|v| v.is_finite()), "wgpu forward not finite on hard cases");
    for (name, v) in grad_list(&g) {
        assert!(v.iter().all(|x| x.is_finite()), "wgpu grad {name} not finite on hard cases");
    }
    let (fc, _) = render_and_grad(&hard, &cam, cfg, &nd.clone().autodiff(), 8);
    assert_close("hard forward", &f, &fc, 1e-4);
    // Permutation invariance and culling on wgpu: identical images.
    let cam = front_camera(50, 40, 50.0);
    let scene = random_scene(120, 4, &cam, 11);
    let order: Vec<usize> = (0..scene.len()).rev().collect();
    let rev = scene.permuted(&order);
    let mut culled = scene.clone();
    culled.push([0.0, 0.0, -2.0], [0.0; 3], [1.0, 0.0, 0.0, 0.0], 3.0, &[1.0; 4]);
    culled.push([50.0, 0.0, 2.0], [-2.0; 3], [1.0, 0.0, 0.0, 0.0], 3.0, &[1.0; 4]);
    let render = |s: &HostScene| {
        let (g, bg) = s.gaussians(&wgpu);
        host(splat(&g, &cam, bg, &SplatOptions::default()).unwrap().features)
    };
    let base = render(&scene);
    assert_eq!(render(&rev), base, "wgpu image changed under a permutation of the Gaussians");
    assert_eq!(render(&culled), base, "off-screen Gaussians changed the wgpu image");
    assert_channel_groups_are_transparent(&wgpu.clone().autodiff());
    // The fuzz scenes of the CPU suite (extreme but finite values everywhere) stay finite on wgpu.
    let cam = front_camera(23, 17, 20.0);
    let mut drawn = 0;
    for seed in 0..40u64 {
        let s = fuzz_scene(seed);
        let (f, g) = render_and_grad(&s, &cam, cfg, &wgpu.clone().autodiff(), seed);
        assert!(f.iter().all(|v| v.is_finite()), "fuzz seed {seed}: wgpu forward not finite");
        for (name, v) in grad_list(&g) {
            assert!(v.iter().all(|x| x.is_finite()), "fuzz seed {seed}: wgpu grad {name} not finite");
        }
        drawn += (f != s.background.repeat(23 * 17)) as usize;
    }
    assert!(drawn >= 10, "only {drawn} fuzz scenes drew anything on wgpu");
    // N = 0 and a 1x1 image.
    let empty = HostScene::empty(2);
    let (g0, bg0) = empty.gaussians(&wgpu);
    let out = splat(&g0, &front_camera(1, 1, 1.0), bg0, &SplatOptions::default()).unwrap();
    assert_eq!(host(out.features), empty.background);
    let small = front_camera(9, 7, 8.0);
    let (f0, g0) = render_and_grad(&empty, &small, cfg, &wgpu.clone().autodiff(), 3);
    let (_, g0n) = render_and_grad(&empty, &small, cfg, &nd.clone().autodiff(), 3);
    assert!(f0.chunks(2).all(|px| px == empty.background.as_slice()));
    assert!(g0.means.is_empty() && g0.features.is_empty());
    assert_close("N = 0 background gradient", &g0.background, &g0n.background, 1e-5);
    assert_radix_and_bitonic_lists_agree(&wgpu, &nd);
    // Last: on lavapipe it ends in a caught panic.
    assert_right_or_refused_past_the_loop_limit(&wgpu, &nd);
}

/// The two ways of ordering the tiles' lists ([`TileSort`]) give the same lists: the same image
/// and top contributors bit for bit, and ndarray's top contributors where depths tie (the
/// (depth, id) order). The scene spans several radix blocks of Gaussians and of tile entries and
/// two tile-id digits, with 400 overlapping Gaussians at one depth, in front of the others, and
/// some behind the camera.
fn assert_radix_and_bitonic_lists_agree(wgpu: &Device, nd: &Device) {
    let cam = front_camera(200, 150, 120.0); // 13 x 10 tiles
    let mut scene = random_scene(5000, 3, &cam, 17);
    let mut r = Rng::new(18);
    for k in 0..400 {
        let (x, y) = (r.range(-0.7, 0.7), r.range(-0.5, 0.5));
        scene.push([x, y, 2.0], [-2.5, -2.8, -3.0], [1.0, 0.0, 0.0, 0.0], r.range(0.0, 3.0), &[k as f32 / 400.0; 3]);
    }
    for _ in 0..50 {
        scene.push([r.range(-1.0, 1.0), 0.0, -2.0], [-2.0; 3], [1.0, 0.0, 0.0, 0.0], 2.0, &[1.0; 3]);
    }
    let render = |device: &Device, tile_sort: TileSort| {
        let (g, bg) = scene.gaussians(device);
        let opts = SplatOptions { config: RasterConfig { tile_sort, ..RasterConfig::default() }, ..Default::default() };
        let out = splat(&g, &cam, bg, &opts).unwrap();
        (host(out.features), out.top_id.into_data().convert::<i32>().to_vec::<i32>().unwrap())
    };
    let (radix, radix_ids) = render(wgpu, TileSort::Radix);
    let (bitonic, bitonic_ids) = render(wgpu, TileSort::Bitonic);
    assert_eq!(radix, bitonic, "radix and bitonic lists composite differently");
    assert_eq!(radix_ids, bitonic_ids, "radix and bitonic lists differ in top contributors");
    let (cpu, cpu_ids) = render(nd, TileSort::Auto);
    assert_close("radix against ndarray", &radix, &cpu, 1e-4);
    let same = radix_ids.iter().zip(&cpu_ids).filter(|(a, b)| a == b).count();
    assert!(same * 1000 >= 999 * cpu_ids.len(), "top ids differ from ndarray on {} pixels", cpu_ids.len() - same);
    let tied: std::collections::BTreeSet<i32> = radix_ids.iter().copied().filter(|&i| i >= 5000).collect();
    assert!(tied.len() > 50, "the tied Gaussians lead many pixels ({} do)", tied.len());
}

/// One 16x16 tile under 3,000 faint Gaussians with 80 channels (above the kernels' register limit,
/// so their channel loops run in global memory): about 240,000 loop iterations per pixel, past the
/// 65,535 at which Mesa lavapipe silently ends a shader's loops. The wgpu op must then refuse
/// (panic naming the limit) instead of returning an image and gradients that lost Gaussians; on a
/// GPU, without the limit, it must match ndarray. (Up to 64 channels the channel loops are
/// unrolled and such a tile stays below the limit.) The Gaussians are anisotropic, so that every
/// gradient, the rotations' too, is well above rounding.
fn assert_right_or_refused_past_the_loop_limit(wgpu: &Device, nd: &Device) {
    let cam = front_camera(16, 16, 16.0);
    let mut r = Rng::new(91);
    let c = 80;
    assert!(c > splat_kernels::cube::MAX_REG_CHANNELS);
    let mut heavy = HostScene::empty(c);
    for _ in 0..3000 {
        let feat: Vec<f32> = (0..c).map(|_| r.f()).collect();
        heavy.push(
            [r.range(-0.5, 0.5), r.range(-0.5, 0.5), r.range(1.9, 2.1)],
            [0.3, -0.4, 0.0],
            [0.9, 0.1, 0.3, 0.2],
            -5.2,
            &feat,
        );
    }
    let cfg = RasterConfig::default();
    let got = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        render_and_grad(&heavy, &cam, cfg, &wgpu.clone().autodiff(), 4)
    }));
    match got {
        Err(payload) => {
            let msg = payload
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            assert!(msg.contains("65,535") && msg.contains("ndarray"), "unexpected panic past the loop limit: {msg}");
        }
        Ok((f, g)) => {
            let (fc, gc) = render_and_grad(&heavy, &cam, cfg, &nd.clone().autodiff(), 4);
            assert_close("heavy tile forward", &f, &fc, 1e-4);
            for ((name, a), (_, b)) in grad_list(&g).into_iter().zip(grad_list(&gc)) {
                assert_close(&format!("heavy tile grad {name}"), a, b, 1e-3);
            }
        }
    }
}

/// The benchmarks' launch counter (`eval::launches`) sees the kernels wgpu work issues: three
/// element-wise ops are three launches at least without burn's fusion (other tests' launches in
/// this process may add to the count, never take from it).
#[test]
fn the_launch_counter_sees_wgpu_kernels() {
    let Some(wgpu) = wgpu_device() else { return };
    let x = Tensor::<1>::from_floats([1.0, 2.0, 3.0], &wgpu);
    let (v, n) = eval::launches::count_launches(|| host((x.clone() + 1.0).exp() * 2.0));
    let want: Vec<f32> = [2.0f32, 3.0, 4.0].iter().map(|a| a.exp() * 2.0).collect();
    assert_close("the work itself", &v, &want, 1e-6);
    assert!(n >= 3, "{n} launches counted for three element-wise ops on wgpu");
}
