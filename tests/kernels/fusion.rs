//! The splatting op on burn's fusion backend (the `fusion` feature of splat_kernels, where the
//! dispatch backend's CubeCL variant is `Fusion<CubeBackend>` and the op runs outside fusion):
//! `cargo test --workspace --features splat_kernels/fusion --test fusion` (lavapipe; by hand, .ci/run lints it).
//!
//! The op sits between element-wise work that fusion defers and joins (activations before it, a
//! loss after it), as in training; forward and gradients must equal burn-ndarray's, step after
//! step, and the binning the forward hands to the backward must arrive intact.

#![allow(deprecated)] // burn-ndarray, the oracle here as in the other tests, is deprecated in burn 0.22

use burn::backend::fusion::Fusion;
use burn::backend::wgpu::CubeBackend;
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Tensor, TensorData};
use splat_kernels::api::SplatOptions;
use splat_kernels::{Camera, Gaussians, RasterConfig, splat};

/// With the feature on, the CubeCL variant of burn's dispatch backend is the fusion backend (a
/// compile-time check: this only builds when the two types are one).
const _: fn(burn::backend::Cube) -> Fusion<CubeBackend> = |b| b;

/// The wgpu device where the op can run on the adapter; `None` (with a SKIPPED line saying why)
/// otherwise, unless CHATSPLAT_REQUIRE_WGPU=1, which makes that a failure.
fn wgpu_device() -> Option<Device> {
    match splat_kernels::cube::adapter::device() {
        Ok(device) => Some(device),
        Err(why) if std::env::var("CHATSPLAT_REQUIRE_WGPU").is_ok_and(|v| v == "1") => {
            panic!("CHATSPLAT_REQUIRE_WGPU=1 but {why}")
        }
        Err(why) => {
            eprintln!("SKIPPED: {why}");
            None
        }
    }
}

/// A small deterministic generator (xorshift), values in [lo, hi).
struct Rng(u64);

impl Rng {
    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        lo + (hi - lo) * ((self.0 >> 40) as f32 / (1u64 << 24) as f32)
    }

    fn fill(&mut self, n: usize, lo: f32, hi: f32) -> Vec<f32> {
        (0..n).map(|_| self.range(lo, hi)).collect()
    }
}

/// Raw parameters of `n` Gaussians in front of an identity camera, and the loss weights.
struct Scene {
    n: usize,
    c: usize,
    means: Vec<f32>,
    log_scales: Vec<f32>,
    quats: Vec<f32>,
    logits: Vec<f32>,
    raw_features: Vec<f32>,
    target: Vec<f32>,
    w_alpha: Vec<f32>,
}

fn scene(n: usize, c: usize, cam: &Camera, seed: u64) -> Scene {
    let mut r = Rng(seed | 1);
    let mut means = Vec::with_capacity(n * 3);
    for _ in 0..n {
        let z = r.range(2.0, 6.0);
        means.extend([
            r.range(-0.45, 0.45) * cam.width as f32 / cam.fx * z,
            r.range(-0.45, 0.45) * cam.height as f32 / cam.fy * z,
            z,
        ]);
    }
    let (h, w) = (cam.height as usize, cam.width as usize);
    Scene {
        n,
        c,
        means,
        log_scales: r.fill(n * 3, -3.0, -1.5),
        quats: r.fill(n * 4, -1.0, 1.0),
        logits: r.fill(n, -1.0, 3.0),
        raw_features: r.fill(n * c, -2.0, 2.0),
        target: r.fill(h * w * c, 0.0, 1.0),
        w_alpha: r.fill(h * w, -1.0, 1.0),
    }
}

/// The parameters as leaves on `device` (autodiff).
struct Params {
    means: Tensor<2>,
    log_scales: Tensor<2>,
    quats: Tensor<2>,
    logits: Tensor<1>,
    raw_features: Tensor<2>,
}

impl Params {
    fn new(s: &Scene, device: &Device) -> Self {
        let t2 = |v: &Vec<f32>, k: usize| {
            Tensor::<2>::from_data(TensorData::new(v.clone(), [s.n, k]), device).require_grad()
        };
        Self {
            means: t2(&s.means, 3),
            log_scales: t2(&s.log_scales, 3),
            quats: t2(&s.quats, 4),
            logits: Tensor::<1>::from_data(TensorData::new(s.logits.clone(), [s.n]), device).require_grad(),
            raw_features: t2(&s.raw_features, s.c),
        }
    }
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().to_vec::<f32>().expect("f32 data")
}

/// One step: element-wise activations (deferred and fused on the fusion backend), the op, an L1
/// loss and an alpha term, backward, and a plain gradient step on every parameter. Returns the
/// rendered features, the loss, each parameter's gradient and the parameters after the step.
fn step(s: &Scene, p: &Params, cam: &Camera, config: RasterConfig) -> (Vec<f32>, f32, Vec<Vec<f32>>, Params) {
    let device = p.means.device();
    let (h, w) = (cam.height as usize, cam.width as usize);
    let g = Gaussians {
        means: p.means.clone(),
        log_scales: p.log_scales.clone() * 0.9 - 0.1,
        quats: p.quats.clone(),
        opacity_logits: p.logits.clone(),
        features: sigmoid(p.raw_features.clone() * 1.5),
    };
    let background = Tensor::<1>::from_data(TensorData::new(vec![0.25; s.c], [s.c]), &device);
    let opts = SplatOptions { config, ..SplatOptions::default() };
    let out = splat(&g, cam, background, &opts).expect("valid inputs");
    let target = Tensor::<3>::from_data(TensorData::new(s.target.clone(), [h, w, s.c]), &device);
    let w_alpha = Tensor::<2>::from_data(TensorData::new(s.w_alpha.clone(), [h, w]), &device);
    let loss = (out.features.clone() - target).abs().mean() + (out.alpha * w_alpha).mean() * 0.1;
    let value = host(loss.clone())[0];
    let grads = loss.backward();
    let grad = |name: &str, t: &Tensor<2>| t.grad(&grads).unwrap_or_else(|| panic!("{name} has a gradient"));
    let descend = |t: &Tensor<2>, g: &Tensor<2>| (t.clone().detach() - g.clone() * 0.05).detach().require_grad();
    let g_logits = p.logits.grad(&grads).expect("opacity_logits has a gradient");
    let g = [
        grad("means", &p.means),
        grad("log_scales", &p.log_scales),
        grad("quats", &p.quats),
        g_logits.clone().unsqueeze_dim(1),
        grad("features", &p.raw_features),
    ];
    let stepped = Params {
        means: descend(&p.means, &g[0]),
        log_scales: descend(&p.log_scales, &g[1]),
        quats: descend(&p.quats, &g[2]),
        logits: (p.logits.clone().detach() - g_logits * 0.05).detach().require_grad(),
        raw_features: descend(&p.raw_features, &g[4]),
    };
    let gl = g.into_iter().map(host).collect();
    (host(out.features), value, gl, stepped)
}

fn assert_close(what: &str, got: &[f32], want: &[f32], rel: f32) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    let scale = want.iter().fold(1e-6f32, |a, b| a.max(b.abs()));
    let err = got.iter().zip(want).fold(0.0f32, |a, (x, y)| a.max((x - y).abs()));
    assert!(err.is_finite() && err <= rel * scale, "{what}: max error {err} > {rel} x {scale}");
}

#[test]
fn the_op_on_the_fusion_backend_trains_as_on_ndarray() {
    let Some(wgpu) = wgpu_device() else { return };
    let cam = Camera::new(glam::Mat4::IDENTITY, 50.0, 50.0, 45, 37);
    // 16 channels: a register bucket; a smooth configuration, so that no threshold flips on f32
    // rounding and the two backends' gradients can be compared element by element.
    let s = scene(60, 16, &cam, 11);
    let config = RasterConfig::smooth();
    let names = ["means", "log_scales", "quats", "opacity_logits", "features"];
    let (mut pf, mut pn) = (Params::new(&s, &wgpu.clone().autodiff()), Params::new(&s, &Device::ndarray().autodiff()));
    for k in 0..3 {
        let (img_f, loss_f, grads_f, next_f) = step(&s, &pf, &cam, config);
        let (img_n, loss_n, grads_n, next_n) = step(&s, &pn, &cam, config);
        assert!(img_n.iter().any(|v| (v - 0.25).abs() > 0.05), "step {k}: the scene covers the image");
        assert_close(&format!("step {k}: features"), &img_f, &img_n, 1e-4);
        assert!((loss_f - loss_n).abs() <= 1e-4 * loss_n.abs().max(1e-3), "step {k}: loss {loss_f} vs {loss_n}");
        for ((name, a), b) in names.iter().zip(&grads_f).zip(&grads_n) {
            assert!(b.iter().any(|v| *v != 0.0), "step {k}: ndarray's {name} gradient is zero");
            assert_close(&format!("step {k}: grad {name}"), a, b, 1e-3);
        }
        (pf, pn) = (next_f, next_n);
    }
    // The default configuration (thresholds, tile early exits) renders the stepped scene too.
    let g = |p: &Params| Gaussians {
        means: p.means.clone().inner(),
        log_scales: p.log_scales.clone().inner(),
        quats: p.quats.clone().inner(),
        opacity_logits: p.logits.clone().inner(),
        features: sigmoid(p.raw_features.clone().inner()),
    };
    let bg = |d: &Device| Tensor::<1>::from_data(TensorData::new(vec![0.0; s.c], [s.c]), d);
    let of = splat(&g(&pf), &cam, bg(&wgpu), &SplatOptions::default()).expect("valid inputs");
    let on = splat(&g(&pn), &cam, bg(&Device::ndarray()), &SplatOptions::default()).expect("valid inputs");
    let (ids_f, ids_n) = (host(of.top_id.float()), host(on.top_id.float()));
    let same = ids_f.iter().zip(&ids_n).filter(|(a, b)| a == b).count();
    assert!(same * 100 >= 99 * ids_n.len(), "top ids differ on {} pixels", ids_n.len() - same);
    assert_close("default configuration: alpha", &host(of.alpha), &host(on.alpha), 1e-3);
}

/// Kept blend weights (the language stage's renders with the geometry frozen) replay on the
/// fusion backend too, with the features' gradient.
#[test]
fn kept_blend_weights_replay_on_the_fusion_backend() {
    let Some(wgpu) = wgpu_device() else { return };
    let cam = Camera::new(glam::Mat4::IDENTITY, 40.0, 40.0, 33, 29);
    let s = scene(50, 8, &cam, 5);
    let zeros = vec![0.0; s.n * 2];
    let background = vec![0.0; s.c];
    let inputs = splat_kernels::cpu::SplatInputsRef {
        means: &s.means,
        log_scales: &s.log_scales,
        quats: &s.quats,
        opacity_logits: &s.logits,
        features: &s.raw_features,
        background: &background,
        screen_offsets: &zeros,
    };
    let weights = std::sync::Arc::new(splat_kernels::blend::BlendWeights::of(&inputs, &cam, &RasterConfig::default()));
    let run = |device: &Device| {
        let raw = Tensor::<2>::from_data(TensorData::new(s.raw_features.clone(), [s.n, s.c]), device).require_grad();
        let map = splat_kernels::blend_ext::blend(sigmoid(raw.clone()) * 2.0 - 1.0, &weights).expect("matching sizes");
        let (h, w) = (cam.height as usize, cam.width as usize);
        let target = Tensor::<3>::from_data(TensorData::new(s.target[..h * w * s.c].to_vec(), [h, w, s.c]), device);
        let grads = (map.clone() - target).abs().sum().backward();
        (host(map), host(raw.grad(&grads).expect("the features have a gradient")))
    };
    let (map_f, grad_f) = run(&wgpu.autodiff());
    let (map_n, grad_n) = run(&Device::ndarray().autodiff());
    assert!(map_n.iter().any(|v| v.abs() > 0.05), "the Gaussians cover the image");
    assert_close("blend map", &map_f, &map_n, 1e-5);
    assert_close("blend features' gradient", &grad_f, &grad_n, 1e-5);
}
