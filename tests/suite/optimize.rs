//! The op inside a burn training loop: a `Module` of Gaussian parameters fitted with burn's Adam
//! to renders of a hidden scene, through the hand-written backward, on NdArray and wgpu.

#![allow(deprecated)] // burn-ndarray and TensorData::to_vec are deprecated in burn 0.22; the card names ndarray.

use burn::module::{Module, Param};
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor};
use chatsplat_tests::*;
use splat_kernels::api::{SplatOptions, splat};
use splat_kernels::{Camera, Gaussians};

#[derive(Module, Debug)]
struct Splats {
    means: Param<Tensor<2>>,
    log_scales: Param<Tensor<2>>,
    quats: Param<Tensor<2>>,
    opacity_logits: Param<Tensor<1>>,
    features: Param<Tensor<2>>,
}

impl Splats {
    fn from_scene(s: &HostScene, device: &Device) -> Self {
        let (g, _) = s.gaussians(device);
        Self {
            means: Param::from_tensor(g.means),
            log_scales: Param::from_tensor(g.log_scales),
            quats: Param::from_tensor(g.quats),
            opacity_logits: Param::from_tensor(g.opacity_logits),
            features: Param::from_tensor(g.features),
        }
    }
    fn gaussians(&self) -> Gaussians {
        Gaussians {
            means: self.means.val(),
            log_scales: self.log_scales.val(),
            quats: self.quats.val(),
            opacity_logits: self.opacity_logits.val(),
            features: self.features.val(),
        }
    }
}

fn cameras() -> Vec<Camera> {
    [-0.6f32, 0.0, 0.6]
        .iter()
        .map(|&x| {
            Camera::look_at(
                glam::Vec3::new(x, -0.3, -0.5),
                glam::Vec3::new(0.0, 0.0, 4.0),
                glam::Vec3::new(0.0, -1.0, 0.0),
                45.0,
                48,
                40,
            )
        })
        .collect()
}

fn fit(device: &Device) -> (f32, f32) {
    let cam0 = front_camera(48, 40, 50.0);
    let truth = random_scene(40, 3, &cam0, 5);
    // Start from a perturbed copy: moved centres, wrong colours and opacities.
    let mut start = truth.clone();
    let mut r = Rng::new(6);
    for v in start.means.iter_mut() {
        *v += r.range(-0.08, 0.08);
    }
    for v in start.features.iter_mut() {
        *v = r.f();
    }
    for v in start.opacity_logits.iter_mut() {
        *v = 0.0;
    }
    let cams = cameras();
    let opts = SplatOptions::default();
    let (gt, bg) = truth.gaussians(device);
    let targets: Vec<Tensor<3>> = cams.iter().map(|c| splat(&gt, c, bg.clone(), &opts).unwrap().features).collect();
    let ad = device.clone().autodiff();
    let bg_ad = Tensor::<1>::from_data(bg.into_data(), &ad);
    let targets: Vec<Tensor<3>> = targets.into_iter().map(|t| Tensor::from_data(t.into_data(), &ad)).collect();
    let mut model = Splats::from_scene(&start, &ad);
    let mut optim = AdamConfig::new().init();
    let mut first = None;
    let mut last = 0.0;
    for it in 0..60 {
        let mut total = 0.0;
        for (cam, target) in cams.iter().zip(&targets) {
            let out = splat(&model.gaussians(), cam, bg_ad.clone(), &opts).unwrap();
            let loss = (out.features - target.clone()).abs().mean();
            total += loss.clone().into_data().to_vec::<f32>().unwrap()[0];
            let grads = GradientsParams::from_grads(loss.backward(), &model);
            model = optim.step(0.02, model, grads);
        }
        if it == 0 {
            first = Some(total);
        }
        last = total;
    }
    eprintln!("L1 {:.5} -> {last:.5}", first.unwrap());
    (first.unwrap(), last)
}

#[test]
fn adam_on_ndarray_fits_gaussians_to_renders() {
    let (first, last) = fit(&Device::ndarray());
    assert!(last < 0.1 * first, "L1 went from {first} to {last}: less than a 90% drop");
}

#[test]
fn adam_on_wgpu_fits_gaussians_to_renders() {
    let Some(device) = chatsplat_tests::wgpu_device() else { return };
    let (first, last) = fit(&device);
    assert!(last < 0.1 * first, "L1 went from {first} to {last}: less than a 90% drop");
}
