//! Fuzzing with mixed extreme but finite inputs (zero, denormal and huge values in every tensor):
//! outputs and gradients must stay finite, alpha within [0, 1].

#![allow(deprecated)]

use chatsplat_tests::*;
use splat_kernels::{RasterConfig, cpu};

#[test]
fn mixed_extreme_finite_inputs_give_finite_outputs_and_gradients() {
    let cam = front_camera(23, 17, 20.0);
    let hw = (cam.width * cam.height) as usize;
    let mut drawn = 0;
    let mut grads_seen = 0;
    for seed in 0..300u64 {
        let s = fuzz_scene(seed);
        let c = s.channels();
        let mut r = Rng::new(seed + 1000);
        if s.means.iter().any(|v| !v.is_finite()) {
            continue;
        }
        s.inputs().validate().expect("finite inputs are accepted");
        let cfg = RasterConfig::default();
        let f = cpu::forward(&s.inputs(), &cam, &cfg);
        let gi: Vec<f32> = (0..hw * c).map(|_| r.range(-1.0, 1.0)).collect();
        let ga: Vec<f32> = (0..hw).map(|_| r.range(-1.0, 1.0)).collect();
        let gd: Vec<f32> = (0..hw).map(|_| r.range(-1e-3, 1e-3)).collect();
        let g = cpu::backward(&s.inputs(), &cam, &cfg, &f.final_t, &f.n_visited, &gi, &ga, &gd);
        let all = [
            ("image", &f.image),
            ("alpha", &f.alpha),
            ("depth", &f.depth),
            ("d means", &g.means),
            ("d log_scales", &g.log_scales),
            ("d quats", &g.quats),
            ("d opacity", &g.opacity_logits),
            ("d features", &g.features),
            ("d background", &g.background),
            ("d screen", &g.screen_offsets),
        ];
        for (name, v) in all {
            if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                panic!("seed {seed}: {name}[{k}] = {} is not finite", v[k]);
            }
        }
        assert!(f.alpha.iter().all(|a| (0.0..=1.0).contains(a)), "seed {seed}: alpha out of range");
        drawn += f.top_id.iter().any(|&t| t >= 0) as usize;
        grads_seen += g.means.iter().any(|&v| v != 0.0) as usize;
    }
    // The fuzz must exercise the rasterizer, not only the culling.
    eprintln!("{drawn} of 300 scenes drew pixels, {grads_seen} produced mean gradients");
    assert!(drawn >= 60 && grads_seen >= 30, "only {drawn} scenes drew and {grads_seen} had gradients");
}
