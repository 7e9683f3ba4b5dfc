//! Tensor-level entry point: [`splat`] renders a set of Gaussians on any backend (NdArray, wgpu,
//! and either under autodiff) and returns feature, alpha, depth and top-id maps.

use crate::camera::Camera;
use crate::constants::RasterConfig;
use crate::error::SplatError;
use crate::ext::{SplatBackend, SplatPrims};
use burn::backend::Dispatch;
use burn::tensor::{Int, Tensor};

/// A set of N Gaussians with C-channel features, all on one device.
#[derive(Clone, Debug)]
pub struct Gaussians {
    /// `[N, 3]` world-space centres.
    pub means: Tensor<2>,
    /// `[N, 3]` natural-log standard deviations along the local axes.
    pub log_scales: Tensor<2>,
    /// `[N, 4]` rotations as (w, x, y, z); normalised inside the op.
    pub quats: Tensor<2>,
    /// `[N]` opacity logits (opacity = sigmoid(logit)).
    pub opacity_logits: Tensor<1>,
    /// `[N, C]` features to splat (RGB, identity, language...).
    pub features: Tensor<2>,
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacity_logits.dims()[0]
    }
    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Feature channels C.
    pub fn channels(&self) -> usize {
        self.features.dims()[1]
    }
}

/// Options of [`splat`].
#[derive(Clone, Debug)]
pub struct SplatOptions {
    /// Compositing thresholds (3DGS defaults).
    pub config: RasterConfig,
    /// Check every input for NaN/Inf before rendering (one device sync). On by default.
    pub validate: bool,
    /// `[N, 2]` screen-space offsets added to the projected centres. Pass zeros that require grad to
    /// read the screen-space mean gradient (the densification signal) from `.grad()`.
    pub screen_offsets: Option<Tensor<2>>,
    /// Largest buffer (bytes) one pass may bind; wider feature sets are rendered in channel
    /// groups. `None`: 128 MiB on wgpu/CubeCL devices (the usual storage-binding limit, e.g. a
    /// 1280x720x64 map is 243 MB), unlimited on the CPU.
    pub max_pass_bytes: Option<usize>,
}

impl Default for SplatOptions {
    fn default() -> Self {
        Self { config: RasterConfig::default(), validate: true, screen_offsets: None, max_pass_bytes: None }
    }
}

/// Rendered maps.
#[derive(Clone, Debug)]
pub struct SplatRender {
    /// `[H, W, C]` composited features, background included.
    pub features: Tensor<3>,
    /// `[H, W]` accumulated opacity.
    pub alpha: Tensor<2>,
    /// `[H, W]` blend-weighted depth `sum_i w_i z_i`.
    pub depth: Tensor<2>,
    /// `[H, W]` id of the Gaussian with the largest blend weight, -1 where nothing was drawn.
    pub top_id: Tensor<2, Int>,
}

impl SplatRender {
    /// `[H, W]` expected depth `sum_i w_i z_i / sum_i w_i` (0 where alpha is ~0).
    pub fn expected_depth(&self) -> Tensor<2> {
        self.depth.clone() / self.alpha.clone().clamp_min(1e-6)
    }
}

fn check_dims(name: &str, got: &[usize], want: &[usize]) -> Result<(), SplatError> {
    if got != want {
        return Err(SplatError::Shape(format!("{name} has shape {got:?}, expected {want:?}")));
    }
    Ok(())
}

fn check_finite<const D: usize>(name: &'static str, t: &Tensor<D>) -> Result<(), SplatError> {
    let bad = t.clone().is_nan().any().bool_or(t.clone().is_inf().any());
    if bad.into_scalar::<bool>() {
        let dims = t.dims();
        let width: usize = dims[1..].iter().product::<usize>().max(1);
        let data = t.clone().into_data().to_vec::<f32>().unwrap_or_default();
        let k = data.iter().position(|v| !v.is_finite()).unwrap_or(0);
        return Err(SplatError::NonFinite {
            tensor: name,
            row: k / width,
            value: data.get(k).copied().unwrap_or(f32::NAN),
        });
    }
    Ok(())
}

/// Whether `device` runs CubeCL kernels (wgpu) rather than on the host.
pub fn on_cube(device: &burn::tensor::Device) -> bool {
    matches!(device.clone().inner().as_dispatch(), burn::backend::DispatchDevice::Cube(_))
}

/// Renders `gaussians` from `camera` over `background` (`[C]`).
///
/// Differentiable (hand-written backward) with respect to every Gaussian tensor, the background and
/// the screen offsets when they live on an autodiff device. Errors on shape mismatches, invalid
/// cameras, and (with `validate`) NaN/Inf inputs.
pub fn splat(
    gaussians: &Gaussians,
    camera: &Camera,
    background: Tensor<1>,
    options: &SplatOptions,
) -> Result<SplatRender, SplatError> {
    camera.validate()?;
    let n = gaussians.opacity_logits.dims()[0];
    let c = gaussians.features.dims()[1];
    if c == 0 {
        return Err(SplatError::Shape("features must have at least one channel".into()));
    }
    check_dims("means", &gaussians.means.dims(), &[n, 3])?;
    check_dims("log_scales", &gaussians.log_scales.dims(), &[n, 3])?;
    check_dims("quats", &gaussians.quats.dims(), &[n, 4])?;
    check_dims("features", &gaussians.features.dims(), &[n, c])?;
    check_dims("background", &background.dims(), &[c])?;
    let device = gaussians.means.device();
    let offsets = match &options.screen_offsets {
        Some(t) => {
            check_dims("screen_offsets", &t.dims(), &[n, 2])?;
            t.clone()
        }
        None => Tensor::zeros([n, 2], &device),
    };
    if options.validate && n > 0 {
        check_finite("means", &gaussians.means)?;
        check_finite("log_scales", &gaussians.log_scales)?;
        check_finite("quats", &gaussians.quats)?;
        check_finite("opacity_logits", &gaussians.opacity_logits)?;
        check_finite("features", &gaussians.features)?;
        check_finite("screen_offsets", &offsets)?;
    }
    if options.validate {
        check_finite("background", &background)?;
    }
    let is_cube = on_cube(&device);
    let budget = options.max_pass_bytes.unwrap_or(if is_cube { 128 << 20 } else { usize::MAX });
    let floats = budget / 4;
    let hw = (camera.width * camera.height) as usize;
    let per_pass = c.min((floats / hw).saturating_sub(2)).min(floats / n.max(1)).max(1);
    let mut feature_maps = Vec::with_capacity(c.div_ceil(per_pass));
    let mut first = None;
    for start in (0..c).step_by(per_pass) {
        let len = per_pass.min(c - start);
        let (feats, bg) = if len == c {
            (gaussians.features.clone(), background.clone())
        } else {
            (gaussians.features.clone().narrow(1, start, len), background.clone().narrow(0, start, len))
        };
        let prims = SplatPrims {
            means: gaussians.means.clone().into_dispatch(),
            log_scales: gaussians.log_scales.clone().into_dispatch(),
            quats: gaussians.quats.clone().into_dispatch(),
            opacity_logits: gaussians.opacity_logits.clone().into_dispatch(),
            features: feats.into_dispatch(),
            background: bg.into_dispatch(),
            screen_offsets: offsets.clone().into_dispatch(),
        };
        let out = <Dispatch as SplatBackend>::splat_forward(prims, *camera, options.config);
        let packed = Tensor::<3>::from_dispatch(out.packed);
        feature_maps.push(packed.clone().narrow(2, 0, len));
        if first.is_none() {
            first = Some((packed, Tensor::<2, Int>::from_dispatch(out.top_id), len));
        }
    }
    let (packed, top_id, len0) = first.expect("at least one channel group");
    let features =
        if feature_maps.len() == 1 { feature_maps.pop().expect("one map") } else { Tensor::cat(feature_maps, 2) };
    let alpha = packed.clone().narrow(2, len0, 1).squeeze_dim::<2>(2);
    let depth = packed.narrow(2, len0 + 1, 1).squeeze_dim::<2>(2);
    Ok(SplatRender { features, alpha, depth, top_id })
}

/// Accumulates the per-Gaussian norm of the screen-space mean gradient over iterations, as 3DGS
/// densification needs (`sum of |dL/dmean2d|` and the number of views where it was non-zero).
#[derive(Clone, Debug, Default)]
pub struct ScreenGradAccumulator {
    pub norm_sum: Vec<f32>,
    pub count: Vec<u32>,
}

impl ScreenGradAccumulator {
    /// Adds one view's `[N, 2]` gradient of the screen offsets (pixel units).
    pub fn add(&mut self, grad: Tensor<2>) {
        self.add_scaled(grad, 1.0, 1.0);
    }

    /// As [`add`](Self::add), measuring the gradient in NDC units as 3DGS's densification
    /// threshold does: d/d(ndc) = d/d(pixel) x (size / 2) per axis.
    pub fn add_ndc(&mut self, grad: Tensor<2>, width: u32, height: u32) {
        self.add_scaled(grad, 0.5 * width as f32, 0.5 * height as f32);
    }

    /// Clears the statistics for `n` Gaussians (after densification changed the count).
    pub fn reset(&mut self, n: usize) {
        self.norm_sum = vec![0.0; n];
        self.count = vec![0; n];
    }

    fn add_scaled(&mut self, grad: Tensor<2>, sx: f32, sy: f32) {
        let n = grad.dims()[0];
        if self.norm_sum.len() != n {
            self.reset(n);
        }
        let g = grad.into_data().to_vec::<f32>().expect("f32 gradient");
        for i in 0..n {
            let (gx, gy) = (g[2 * i] * sx, g[2 * i + 1] * sy);
            let norm = (gx * gx + gy * gy).sqrt();
            if norm > 0.0 {
                self.norm_sum[i] += norm;
                self.count[i] += 1;
            }
        }
    }

    /// Mean norm per Gaussian over the views that saw it.
    pub fn mean(&self) -> Vec<f32> {
        self.norm_sum.iter().zip(&self.count).map(|(&s, &c)| if c > 0 { s / c as f32 } else { 0.0 }).collect()
    }
}
