//! The burn-ops baseline computes the same math as the kernels (it is what `splat-bench` compares
//! against, so it must be right).

#![allow(deprecated)] // burn-ndarray and TensorData::to_vec are deprecated in burn 0.22; the card names ndarray.

use burn::tensor::{Device, Tensor, TensorData};
use chatsplat_tests::*;
use splat_kernels::{RasterConfig, cpu, dense, reference};

#[test]
fn dense_burn_ops_forward_and_gradients_match_the_kernels() {
    let cam = front_camera(40, 29, 40.0);
    let scene = random_scene(30, 3, &cam, 77);
    let cfg = RasterConfig::default();
    let device = Device::ndarray();
    let (g, bg) = scene.gaussians(&device);
    let proj = dense::project(&g, &cam, &cfg);
    let hw = (cam.width * cam.height) as usize;
    let (f, a, d) = dense::composite(&proj, &cam, &cfg, bg, 0, hw);
    let fast = cpu::forward(&scene.inputs(), &cam, &cfg);
    let got = cpu::ForwardOut {
        image: host(f),
        alpha: host(a),
        depth: host(d),
        top_id: fast.top_id.clone(),
        ..Default::default()
    };
    let r = reference::render(&scene.inputs(), &cam, &cfg);
    let want = masked_reference(&r, &got, 3);
    assert!(max_abs_diff(&got.image, &want.image) <= 1e-4);
    assert!(max_abs_diff(&got.alpha, &want.alpha) <= 1e-4);
    assert!(max_abs_diff(&got.depth, &want.depth) <= 1e-3);

    // Gradients through burn autodiff (smooth configuration) against the hand-written backward.
    let cfg = RasterConfig::smooth();
    let ad = Device::ndarray().autodiff();
    let (g, bg) = scene.gaussians(&ad);
    let g = splat_kernels::Gaussians {
        means: g.means.require_grad(),
        features: g.features.require_grad(),
        opacity_logits: g.opacity_logits.require_grad(),
        ..g
    };
    let proj = dense::project(&g, &cam, &cfg);
    let (f, _, _) = dense::composite(&proj, &cam, &cfg, bg, 0, hw);
    let mut rng = Rng::new(1);
    let wf: Vec<f32> = (0..hw * 3).map(|_| rng.range(-1.0, 1.0)).collect();
    let loss = (f * Tensor::<2>::from_data(TensorData::new(wf.clone(), [hw, 3]), &ad)).sum();
    let grads = loss.backward();
    let fw = cpu::forward(&scene.inputs(), &cam, &cfg);
    let want =
        cpu::backward(&scene.inputs(), &cam, &cfg, &fw.final_t, &fw.n_visited, &wf, &vec![0.0; hw], &vec![0.0; hw]);
    for (name, got, want) in [
        ("features", host(g.features.grad(&grads).unwrap()), want.features),
        ("opacity", host(g.opacity_logits.grad(&grads).unwrap()), want.opacity_logits),
        ("means", host(g.means.grad(&grads).unwrap()), want.means),
    ] {
        let scale = want.iter().fold(1e-6f32, |a, b| a.max(b.abs()));
        let err = max_abs_diff(&got, &want);
        assert!(err <= 2e-3 * scale, "{name}: dense autodiff vs kernel backward error {err} (scale {scale})");
    }
}
