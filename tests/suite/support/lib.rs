//! Shared helpers of the integration tests: seeded random scenes and comparisons.
#![allow(deprecated)]

use burn::tensor::{Device, Tensor, TensorData};
use splat_kernels::cpu::SplatInputsRef;
use splat_kernels::{Camera, Gaussians};

pub use model::rng::Rng;

pub mod fake_hub;
pub mod fixture;
pub mod unlabelled;

// The browser driver, the HTTP client and scratch paths live with the benches that share them.
pub use eval::scratch::{Scratch, temp_dir};
pub use eval::{browser, http};

/// Host copy of a scene's inputs (the op's own host layout).
pub type HostScene = splat_kernels::ext::HostInputs;

/// Test conveniences on [`HostScene`].
pub trait SceneExt {
    fn inputs(&self) -> SplatInputsRef<'_>;
    fn empty(channels: usize) -> Self;
    fn push(&mut self, mean: [f32; 3], log_scale: [f32; 3], quat: [f32; 4], logit: f32, feat: &[f32]);
    /// Burn tensors on `device`.
    fn gaussians(&self, device: &Device) -> (Gaussians, Tensor<1>);
    /// The same Gaussians and background, Gaussian `order[k]` becoming Gaussian `k`.
    fn permuted(&self, order: &[usize]) -> Self;
}

impl SceneExt for HostScene {
    fn inputs(&self) -> SplatInputsRef<'_> {
        self.as_slices()
    }
    fn empty(channels: usize) -> Self {
        Self { background: vec![0.25; channels], ..Default::default() }
    }
    fn push(&mut self, mean: [f32; 3], log_scale: [f32; 3], quat: [f32; 4], logit: f32, feat: &[f32]) {
        assert_eq!(feat.len(), self.channels());
        self.means.extend_from_slice(&mean);
        self.log_scales.extend_from_slice(&log_scale);
        self.quats.extend_from_slice(&quat);
        self.opacity_logits.push(logit);
        self.features.extend_from_slice(feat);
        self.screen_offsets.extend_from_slice(&[0.0, 0.0]);
    }
    fn permuted(&self, order: &[usize]) -> Self {
        let c = self.channels();
        let mut p = Self::empty(c);
        p.background = self.background.clone();
        for &i in order {
            p.push(
                self.means[3 * i..3 * i + 3].try_into().unwrap(),
                self.log_scales[3 * i..3 * i + 3].try_into().unwrap(),
                self.quats[4 * i..4 * i + 4].try_into().unwrap(),
                self.opacity_logits[i],
                &self.features[c * i..c * (i + 1)],
            );
        }
        p
    }
    fn gaussians(&self, device: &Device) -> (Gaussians, Tensor<1>) {
        let n = self.len();
        let c = self.channels();
        let t2 = |v: &Vec<f32>, w: usize| Tensor::<2>::from_data(TensorData::new(v.clone(), [n, w]), device);
        (
            Gaussians {
                means: t2(&self.means, 3),
                log_scales: t2(&self.log_scales, 3),
                quats: t2(&self.quats, 4),
                opacity_logits: Tensor::<1>::from_data(TensorData::new(self.opacity_logits.clone(), [n]), device),
                features: t2(&self.features, c),
            },
            Tensor::<1>::from_data(TensorData::new(self.background.clone(), [c]), device),
        )
    }
}

/// A camera at the origin looking down +z (OpenCV), `w x h` pixels.
pub fn front_camera(w: u32, h: u32, focal: f32) -> Camera {
    Camera::new(glam::Mat4::IDENTITY, focal, focal, w, h)
}

/// `n` random Gaussians in front of `cam` with `c`-channel features in [0, 1].
pub fn random_scene(n: usize, c: usize, cam: &Camera, seed: u64) -> HostScene {
    let mut r = Rng::new(seed);
    let mut s = HostScene::empty(c);
    s.background = (0..c).map(|_| r.f()).collect();
    for _ in 0..n {
        let z = r.range(2.0, 6.0);
        // Keep centres inside the image (the Jacobian clamp is not exercised here).
        let u = r.range(-0.45, 0.45) * cam.width as f32 / cam.fx;
        let v = r.range(-0.45, 0.45) * cam.height as f32 / cam.fy;
        let feat: Vec<f32> = (0..c).map(|_| r.f()).collect();
        s.push(
            [u * z, v * z, z],
            [r.range(-3.5, -1.3), r.range(-3.5, -1.3), r.range(-3.5, -1.3)],
            [r.normal(), r.normal(), r.normal(), r.normal()],
            r.range(-2.0, 2.0),
            &feat,
        );
    }
    s
}

/// Largest absolute difference.
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "length mismatch");
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// Reads a float tensor to the host (`to_vec` right after `into_data`, as wgpu readback is lazy).
pub fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().to_vec::<f32>().expect("f32 tensor")
}

/// The reference's outputs with threshold-ambiguous pixels replaced by `fast`'s values, after
/// checking that such pixels are rare (at most 1%).
pub fn masked_reference(
    r: &splat_kernels::reference::RefOut,
    fast: &splat_kernels::cpu::ForwardOut,
    c: usize,
) -> splat_kernels::cpu::ForwardOut {
    let n_amb = r.ambiguous.iter().filter(|&&a| a).count();
    assert!(
        n_amb * 100 <= r.ambiguous.len(),
        "{n_amb} of {} pixels are threshold-ambiguous: the scene is badly conditioned",
        r.ambiguous.len()
    );
    let mut out = r.to_forward_out();
    for (o, &amb) in r.ambiguous.iter().enumerate() {
        if amb {
            out.image[o * c..(o + 1) * c].copy_from_slice(&fast.image[o * c..(o + 1) * c]);
            out.alpha[o] = fast.alpha[o];
            out.depth[o] = fast.depth[o];
            out.top_id[o] = fast.top_id[o];
        }
    }
    out
}

fn pick(r: &mut Rng, options: &[f32]) -> f32 {
    options[(r.next_u64() % options.len() as u64) as usize]
}

/// A scene mixing extreme but finite values in every tensor (zero, denormal and huge values,
/// Gaussians at and behind the near plane, opacity logits of +-1e4), deterministic from `seed`.
pub fn fuzz_scene(seed: u64) -> HostScene {
    let pos = [0.0, 1e-38, -1e-42, 0.3, -0.4, 1e6, -1e6, 3.0e38];
    let depth = [0.0, 0.0101, 0.5, 2.0, 1e3, 1e9, -1.0, 1e-30];
    let ls = [-1000.0, -40.0, -18.4, -3.0, 0.0, 9.2, 25.0, 1000.0];
    let quat = [0.0, 1e-45, -1e-40, 1e-13, 0.7, -1.0, 1e30, -3e38];
    let logit = [-1e4, -50.0, -3.0, 0.0, 2.0, 50.0, 1e4, 1e-40];
    let feat = [0.0, 1e-42, -1e3, 1e3, 0.5, -7.0];
    let mut r = Rng::new(seed);
    let c = 1 + (seed % 4) as usize;
    let mut s = HostScene::empty(c);
    s.background = (0..c).map(|_| pick(&mut r, &feat)).collect();
    for _ in 0..(1 + seed % 25) {
        let z = pick(&mut r, &depth);
        let f: Vec<f32> = (0..c).map(|_| pick(&mut r, &feat)).collect();
        let mut m = [pick(&mut r, &pos) * 1e-3, pick(&mut r, &pos) * 1e-3, z];
        if seed.is_multiple_of(3) {
            // Keep some centres on screen so the extreme shapes are actually rasterised.
            m = [r.range(-0.5, 0.5) * z.abs(), r.range(-0.5, 0.5) * z.abs(), z];
        }
        s.push(
            m,
            [pick(&mut r, &ls), pick(&mut r, &ls), pick(&mut r, &ls)],
            [pick(&mut r, &quat), pick(&mut r, &quat), pick(&mut r, &quat), pick(&mut r, &quat)],
            pick(&mut r, &logit),
            &f,
        );
    }
    s
}

/// The `N` of "N prompt tokens" in the report an answer prints on standard error (`ask`, `chat`).
pub fn prompt_tokens(stderr: &str) -> usize {
    stderr
        .lines()
        .find_map(|l| l.split_once(" prompt tokens").and_then(|(n, _)| n.split_whitespace().last()?.parse().ok()))
        .unwrap_or_else(|| panic!("no prompt token count in {stderr}"))
}

/// The wgpu device where the splatting op can run on the adapter (lavapipe on CPU machines, any
/// GPU); `None` (and a SKIPPED line saying why: no adapter, or one the op refuses, such as
/// llvmpipe through OpenGL) otherwise, unless CHATSPLAT_REQUIRE_WGPU=1, which makes that a failure.
pub fn wgpu_device() -> Option<Device> {
    match splat_kernels::cube::adapter::device() {
        Ok(device) => Some(device),
        Err(why) => {
            if std::env::var("CHATSPLAT_REQUIRE_WGPU").is_ok_and(|v| v == "1") {
                panic!("CHATSPLAT_REQUIRE_WGPU=1 but {why}");
            }
            eprintln!("SKIPPED: {why}");
            None
        }
    }
}

/// 8-bit ids (as a test writes them to a PNG) as the loaders return them.
pub fn wide(ids: &[u8]) -> Vec<u16> {
    ids.iter().map(|&i| i as u16).collect()
}
