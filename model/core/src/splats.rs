//! The trainable scene: Gaussians as a burn `Module` — means, log-scales, quaternions, opacity
//! logits, spherical-harmonic colour (degree 0-3), a 16-channel identity feature and the
//! identity classifier (linear 16 -> number of objects), as in Gaussian Grouping. Every
//! per-Gaussian parameter is a rank-2 tensor `[N, width]`, so densification and optimizer-state
//! bookkeeping treat them uniformly; [`SplatParams`] holds one value per parameter by name.

use crate::ObjectId;
use crate::cloud::{GaussianCloud, SH_C0};
use crate::error::Result;
use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};
use splat_kernels::api::{SplatOptions, splat};
use splat_kernels::{Camera, Gaussians};

/// Identity feature width (Gaussian Grouping).
pub const IDENTITY_DIM: usize = 16;
/// Higher-order SH coefficients per colour channel at degree 3.
pub const SH_REST: usize = 15;

const C1: f32 = 0.488_602_5;
const C2: [f32; 5] = [1.092_548_4, -1.092_548_4, 0.315_391_57, -1.092_548_4, 0.546_274_2];
const C3: [f32; 7] = [-0.590_043_6, 2.890_611_4, -0.457_045_8, 0.373_176_33, -0.457_045_8, 1.445_305_7, -0.590_043_6];

/// One value per parameter of a [`SplatModel`], by name: its tensors, their learning rates, their
/// optimizer states. The seven per-Gaussian parameters (rows of `[N, width]`) come first.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SplatParams<T> {
    pub means: T,
    pub log_scales: T,
    pub quats: T,
    pub opacity_logits: T,
    pub sh_dc: T,
    pub sh_rest: T,
    pub identity: T,
    pub classifier_w: T,
    pub classifier_b: T,
}

impl<T> SplatParams<T> {
    /// Parameter names, as stored in checkpoints.
    pub const NAMES: [&'static str; 9] = [
        "means",
        "log_scales",
        "quats",
        "opacity_logits",
        "sh_dc",
        "sh_rest",
        "identity",
        "classifier_w",
        "classifier_b",
    ];

    /// Builds every field from its name.
    pub fn from_fn(mut f: impl FnMut(&'static str) -> T) -> Self {
        Self {
            means: f("means"),
            log_scales: f("log_scales"),
            quats: f("quats"),
            opacity_logits: f("opacity_logits"),
            sh_dc: f("sh_dc"),
            sh_rest: f("sh_rest"),
            identity: f("identity"),
            classifier_w: f("classifier_w"),
            classifier_b: f("classifier_b"),
        }
    }

    /// Every field with its name, in [`NAMES`](Self::NAMES) order.
    pub fn into_named(self) -> [(&'static str, T); 9] {
        [
            ("means", self.means),
            ("log_scales", self.log_scales),
            ("quats", self.quats),
            ("opacity_logits", self.opacity_logits),
            ("sh_dc", self.sh_dc),
            ("sh_rest", self.sh_rest),
            ("identity", self.identity),
            ("classifier_w", self.classifier_w),
            ("classifier_b", self.classifier_b),
        ]
    }

    /// Applies `f(name, value)` to every field.
    pub fn map<U>(self, mut f: impl FnMut(&'static str, T) -> U) -> SplatParams<U> {
        let mut named = self.into_named().into_iter();
        SplatParams::from_fn(|_| {
            let (n, v) = named.next().expect("nine fields");
            f(n, v)
        })
    }

    pub fn as_ref(&self) -> SplatParams<&T> {
        SplatParams {
            means: &self.means,
            log_scales: &self.log_scales,
            quats: &self.quats,
            opacity_logits: &self.opacity_logits,
            sh_dc: &self.sh_dc,
            sh_rest: &self.sh_rest,
            identity: &self.identity,
            classifier_w: &self.classifier_w,
            classifier_b: &self.classifier_b,
        }
    }

    pub fn as_mut(&mut self) -> SplatParams<&mut T> {
        SplatParams {
            means: &mut self.means,
            log_scales: &mut self.log_scales,
            quats: &mut self.quats,
            opacity_logits: &mut self.opacity_logits,
            sh_dc: &mut self.sh_dc,
            sh_rest: &mut self.sh_rest,
            identity: &mut self.identity,
            classifier_w: &mut self.classifier_w,
            classifier_b: &mut self.classifier_b,
        }
    }

    /// Pairs the fields of `self` and `other`.
    pub fn zip<U>(self, other: SplatParams<U>) -> SplatParams<(T, U)> {
        let mut o = other.into_named().into_iter();
        self.map(|_, v| (v, o.next().expect("nine fields").1))
    }

    /// Whether parameter `name` has one row per Gaussian (all but the classifier).
    pub fn is_row(name: &str) -> bool {
        !name.starts_with("classifier")
    }

    /// Row width of per-Gaussian parameter `name` (0 for the classifier).
    pub fn row_width(name: &str) -> usize {
        match name {
            "means" | "log_scales" | "sh_dc" => 3,
            "quats" => 4,
            "opacity_logits" => 1,
            "sh_rest" => 3 * SH_REST,
            "identity" => IDENTITY_DIM,
            _ => 0,
        }
    }
}

/// A rendered view: RGB `[H, W, 3]`, the identity class of each pixel, alpha `[H, W]`.
pub struct ViewRender {
    pub rgb: Vec<f32>,
    pub ids: Vec<ObjectId>,
    pub alpha: Vec<f32>,
}

/// The splat background `[3 + 16]` of an RGB background: the colour, zero identity.
pub fn background(rgb: [f32; 3], device: &Device) -> Tensor<1> {
    let mut bg = rgb.to_vec();
    bg.extend([0.0; IDENTITY_DIM]);
    Tensor::from_data(TensorData::new(bg, [3 + IDENTITY_DIM]), device)
}

/// The scene being optimised.
#[derive(Module, Debug)]
pub struct SplatModel {
    /// `[N, 3]`
    pub means: Param<Tensor<2>>,
    /// `[N, 3]` natural-log standard deviations.
    pub log_scales: Param<Tensor<2>>,
    /// `[N, 4]` (w, x, y, z).
    pub quats: Param<Tensor<2>>,
    /// `[N, 1]`
    pub opacity_logits: Param<Tensor<2>>,
    /// `[N, 3]` SH band 0 (colour = 0.5 + C0 * dc + ...).
    pub sh_dc: Param<Tensor<2>>,
    /// `[N, 45]`: SH coefficient k = 1..15 of channel c at column (k-1)*3 + c.
    pub sh_rest: Param<Tensor<2>>,
    /// `[N, 16]` identity features.
    pub identity: Param<Tensor<2>>,
    /// `[16, K]` identity classifier weight.
    pub classifier_w: Param<Tensor<2>>,
    /// `[1, K]` identity classifier bias.
    pub classifier_b: Param<Tensor<2>>,
}

impl SplatModel {
    /// Builds the model from its tensors.
    pub fn from_tensors(t: SplatParams<Tensor<2>>) -> Self {
        Self {
            means: Param::from_tensor(t.means),
            log_scales: Param::from_tensor(t.log_scales),
            quats: Param::from_tensor(t.quats),
            opacity_logits: Param::from_tensor(t.opacity_logits),
            sh_dc: Param::from_tensor(t.sh_dc),
            sh_rest: Param::from_tensor(t.sh_rest),
            identity: Param::from_tensor(t.identity),
            classifier_w: Param::from_tensor(t.classifier_w),
            classifier_b: Param::from_tensor(t.classifier_b),
        }
    }

    /// All tensors, by name.
    pub fn tensors(&self) -> SplatParams<Tensor<2>> {
        SplatParams {
            means: self.means.val(),
            log_scales: self.log_scales.val(),
            quats: self.quats.val(),
            opacity_logits: self.opacity_logits.val(),
            sh_dc: self.sh_dc.val(),
            sh_rest: self.sh_rest.val(),
            identity: self.identity.val(),
            classifier_w: self.classifier_w.val(),
            classifier_b: self.classifier_b.val(),
        }
    }

    /// The model restricted to Gaussians `keep` (row indices, in that order); the classifier kept.
    pub fn rows(&self, keep: &[usize]) -> SplatModel {
        let dev = self.means.val().device();
        let idx: Vec<i64> = keep.iter().map(|&i| i as i64).collect();
        let idx = Tensor::<1, burn::tensor::Int>::from_data(TensorData::new(idx, [keep.len()]), &dev);
        SplatModel::from_tensors(
            self.tensors().map(|name, t| if SplatParams::<()>::is_row(name) { t.select(0, idx.clone()) } else { t }),
        )
    }

    pub fn len(&self) -> usize {
        self.means.val().dims()[0]
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn num_classes(&self) -> usize {
        self.classifier_w.val().dims()[1]
    }

    /// Bytes of the per-Gaussian parameters in f32.
    pub fn row_bytes(&self) -> usize {
        let width: usize = SplatParams::<()>::NAMES.iter().map(|n| SplatParams::<()>::row_width(n)).sum();
        self.len() * width * 4
    }

    /// A model from a host cloud; identity comes from the cloud's `identity` extra (zeros if
    /// absent), the classifier from `classifier` (`[16 * K + K]`, or a zero classifier with `classes`).
    pub fn from_cloud(cloud: &GaussianCloud, classifier: Option<&[f32]>, classes: usize, device: &Device) -> Self {
        let n = cloud.len();
        let t = |v: Vec<f32>, w: usize| Tensor::<2>::from_data(TensorData::new(v, [n, w]), device);
        let mut rest = vec![0f32; n * 3 * SH_REST];
        // Inria order: f_rest_{c * per + k}, per = rest_per_gaussian / 3.
        let per = cloud.rest_per_gaussian / 3;
        for i in 0..n {
            for c in 0..3 {
                for k in 0..per.min(SH_REST) {
                    rest[i * 45 + k * 3 + c] = cloud.sh_rest[i * cloud.rest_per_gaussian + c * per + k];
                }
            }
        }
        let identity = match cloud.extra.get("identity") {
            Some((w, v)) if *w == IDENTITY_DIM => v.clone(),
            _ => vec![0.0; n * IDENTITY_DIM],
        };
        let (w, b) = match classifier {
            Some(c) if c.len() == (IDENTITY_DIM + 1) * classes => {
                (c[..IDENTITY_DIM * classes].to_vec(), c[IDENTITY_DIM * classes..].to_vec())
            }
            _ => (vec![0.0; IDENTITY_DIM * classes], vec![0.0; classes]),
        };
        Self::from_tensors(SplatParams {
            means: t(cloud.means.concat(), 3),
            log_scales: t(cloud.log_scales.concat(), 3),
            quats: t(cloud.quats.concat(), 4),
            opacity_logits: t(cloud.opacity_logits.clone(), 1),
            sh_dc: t(cloud.sh_dc.concat(), 3),
            sh_rest: t(rest, 3 * SH_REST),
            identity: t(identity, IDENTITY_DIM),
            classifier_w: Tensor::from_data(TensorData::new(w, [IDENTITY_DIM, classes]), device),
            classifier_b: Tensor::from_data(TensorData::new(b, [1, classes]), device),
        })
    }

    /// The host cloud (Inria layout, SH up to degree 3, identity as the `identity` extra) and the
    /// classifier as `[16 * K weights, K biases]`.
    pub fn to_cloud(&self) -> (GaussianCloud, Vec<f32>) {
        let SplatParams {
            means,
            log_scales,
            quats,
            opacity_logits: opacity,
            sh_dc: dc,
            sh_rest: rest,
            identity,
            classifier_w: w,
            classifier_b: b,
        } = self.tensors().map(|_, t| host(t));
        let n = means.len() / 3;
        let rows =
            |v: &[f32], k: usize| -> Vec<[f32; 3]> { (0..k).map(|i| [v[3 * i], v[3 * i + 1], v[3 * i + 2]]).collect() };
        let mut sh_rest = vec![0f32; n * 45];
        for i in 0..n {
            for c in 0..3 {
                for k in 0..SH_REST {
                    sh_rest[i * 45 + c * SH_REST + k] = rest[i * 45 + k * 3 + c];
                }
            }
        }
        let mut cloud = GaussianCloud {
            means: rows(&means, n),
            log_scales: rows(&log_scales, n),
            quats: (0..n).map(|i| [quats[4 * i], quats[4 * i + 1], quats[4 * i + 2], quats[4 * i + 3]]).collect(),
            opacity_logits: opacity,
            sh_dc: rows(&dc, n),
            sh_rest,
            rest_per_gaussian: 45,
            extra: Default::default(),
        };
        cloud.extra.insert("identity".into(), (IDENTITY_DIM, identity));
        let mut cls = w;
        cls.extend(b);
        (cloud, cls)
    }

    /// View-dependent colours `[N, 3]` at SH degree `degree` (0..=3) seen from `camera`.
    pub fn colors(&self, camera: &Camera, degree: usize) -> Tensor<2> {
        sh_colors(self.means.val(), self.sh_dc.val(), self.sh_rest.val(), camera, degree)
    }

    /// The splat inputs with features = [RGB (3) | identity (16)].
    pub fn gaussians(&self, camera: &Camera, degree: usize) -> Gaussians {
        self.gaussians_with(Tensor::cat(vec![self.colors(camera, degree), self.identity.val()], 1))
    }

    /// The splat inputs of this geometry carrying `features` `[N, C]`.
    fn gaussians_with(&self, features: Tensor<2>) -> Gaussians {
        Gaussians {
            means: self.means.val(),
            log_scales: self.log_scales.val(),
            quats: self.quats.val(),
            opacity_logits: self.opacity_logits.val().reshape([self.len()]),
            features,
        }
    }

    /// Identity logits `[H*W, K]` of a rendered `[H, W, 3 + 16]` feature map.
    pub fn identity_logits(&self, features: Tensor<3>) -> Tensor<2> {
        let [h, w, _] = features.dims();
        let feat = features.narrow(2, 3, IDENTITY_DIM).reshape([h * w, IDENTITY_DIM]);
        feat.matmul(self.classifier_w.val()) + self.classifier_b.val()
    }

    /// The identity class of each pixel seen from `cam` (`[H * W]`, 0 = background): what
    /// [`render`](Self::render) gives as `ids`, from the identity channels alone (no SH colours, 16
    /// channels instead of 19; object masks need nothing else).
    pub fn render_ids(&self, cam: &Camera) -> Result<Vec<ObjectId>> {
        Ok(self.render_identity(cam, self.identity.val())?.0)
    }

    /// [`render_ids`](Self::render_ids) and, in the same pass (one projection and binning instead
    /// of two), per-Gaussian `extra` features `[N, C]` over a zero background: `(ids, [H, W, C])`,
    /// the same map as a render of `extra` alone (compositing is per channel).
    pub fn render_ids_with(&self, cam: &Camera, extra: Tensor<2>) -> Result<(Vec<ObjectId>, Tensor<3>)> {
        let c = extra.dims()[1];
        let (ids, out) = self.render_identity(cam, Tensor::cat(vec![self.identity.val(), extra], 1))?;
        Ok((ids, out.narrow(2, IDENTITY_DIM, c)))
    }

    /// Renders `features` `[N, 16 + C]` (the identity first) over a zero background: the identity
    /// class of each pixel and the whole `[H, W, 16 + C]` map.
    fn render_identity(&self, cam: &Camera, features: Tensor<2>) -> Result<(Vec<ObjectId>, Tensor<3>)> {
        let dev = self.means.val().device();
        let width = features.dims()[1];
        let opts = SplatOptions { validate: false, ..Default::default() };
        let out = splat(&self.gaussians_with(features), cam, Tensor::zeros([width], &dev), &opts)?;
        let [h, w, _] = out.features.dims();
        let identity = out.features.clone().narrow(2, 0, IDENTITY_DIM).reshape([h * w, IDENTITY_DIM]);
        let logits = identity.matmul(self.classifier_w.val()) + self.classifier_b.val();
        Ok((class_ids(logits), out.features))
    }

    /// RGB alone `[H * W * 3]` (clamped to 0..=1) from `cam` at SH degree `degree` over the RGB
    /// `background`: what a frame shows, 3 channels splatted instead of [`render`](Self::render)'s
    /// 19, and no identity classifier.
    pub fn render_rgb(&self, cam: &Camera, degree: usize, background_rgb: [f32; 3]) -> Result<Vec<f32>> {
        let g = self.gaussians_with(self.colors(cam, degree));
        let bg = Tensor::<1>::from_data(TensorData::new(background_rgb.to_vec(), [3]), &self.means.val().device());
        let opts = SplatOptions { validate: false, ..Default::default() };
        Ok(host(splat(&g, cam, bg, &opts)?.features.clamp(0.0, 1.0)))
    }

    /// Every Gaussian's blend weight at every pixel seen from `cam` (`splat_kernels::blend`): what
    /// a pixel is made of, Gaussian by Gaussian, without rendering any feature.
    pub fn blend_weights(&self, cam: &Camera) -> Result<splat_kernels::blend::BlendWeights> {
        cam.validate()?;
        let n = self.len();
        let (means, log_scales) = (host(self.means.val()), host(self.log_scales.val()));
        let (quats, opacity_logits) = (host(self.quats.val()), host(self.opacity_logits.val()));
        let screen_offsets = vec![0f32; 2 * n];
        let inp = splat_kernels::cpu::SplatInputsRef {
            means: &means,
            log_scales: &log_scales,
            quats: &quats,
            opacity_logits: &opacity_logits,
            features: &[],
            background: &[],
            screen_offsets: &screen_offsets,
        };
        Ok(splat_kernels::blend::BlendWeights::of(&inp, cam, &SplatOptions::default().config))
    }

    /// The identity class of each Gaussian (`[N]`, 0 = background): the classifier applied to the
    /// Gaussian's own identity feature, as it is applied to the rendered features of a pixel.
    pub fn gaussian_classes(&self) -> Vec<ObjectId> {
        class_ids(self.identity.val().matmul(self.classifier_w.val()) + self.classifier_b.val())
    }

    /// Renders RGB, the identity class of each pixel and alpha from `cam` at SH degree `degree`
    /// over the RGB `background`.
    pub fn render(&self, cam: &Camera, degree: usize, background_rgb: [f32; 3]) -> Result<ViewRender> {
        let bg = background(background_rgb, &self.means.val().device());
        let opts = SplatOptions { validate: false, ..Default::default() };
        let out = splat(&self.gaussians(cam, degree), cam, bg, &opts)?;
        let logits = self.identity_logits(out.features.clone());
        Ok(ViewRender { rgb: host(out.features.narrow(2, 0, 3)), ids: class_ids(logits), alpha: host(out.alpha) })
    }
}

/// The most likely class of each row of `[P, K]` logits.
fn class_ids(logits: Tensor<2>) -> Vec<ObjectId> {
    let ids = logits.argmax(1).into_data().convert::<i64>().to_vec::<i64>().expect("i64 ids");
    ids.into_iter().map(|i| i.clamp(0, ObjectId::MAX as i64) as ObjectId).collect()
}

/// Reads a tensor to the host as f32.
pub fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().convert::<f32>().try_to_vec::<f32>().expect("f32 tensor")
}

/// Evaluates real SH (3DGS convention, `0.5 + ...`, clamped at 0) for each Gaussian's viewing direction.
/// `sh_dc` `[N,3]`, `sh_rest` `[N,45]` (k-major), result `[N,3]`: the basis of each Gaussian's
/// direction as one `[N, K]` tensor, then one broadcast product with `sh_rest` as `[N, K, 3]`
/// summed over `K` (a few large ops instead of one slice, product and sum per coefficient).
pub fn sh_colors(means: Tensor<2>, sh_dc: Tensor<2>, sh_rest: Tensor<2>, camera: &Camera, degree: usize) -> Tensor<2> {
    let c = sh_dc * SH_C0;
    if degree == 0 {
        return (c + 0.5).clamp_min(0.0);
    }
    let n = means.dims()[0];
    let center = camera.world_to_cam.inverse().w_axis.truncate();
    let eye = Tensor::<2>::from_data(TensorData::new(center.to_array().to_vec(), [1, 3]), &means.device());
    let d = means - eye;
    let d = d.clone() / (d.powf_scalar(2.0).sum_dim(1).sqrt() + 1e-12);
    let basis = sh_basis(d, degree.min(3));
    let k = basis.dims()[1];
    let rest = if k == SH_REST { sh_rest } else { sh_rest.narrow(1, 0, 3 * k) };
    let c = c + (rest.reshape([n, k, 3]) * basis.reshape([n, k, 1])).sum_dim(1).reshape([n, 3]);
    (c + 0.5).clamp_min(0.0)
}

/// The real SH basis without the constant term, `[N, 3 | 8 | 15]` for degree 1 | 2 | 3, of unit
/// directions `d` `[N, 3]` (3DGS's signs and constants).
fn sh_basis(d: Tensor<2>, degree: usize) -> Tensor<2> {
    let x = d.clone().narrow(1, 0, 1);
    let y = d.clone().narrow(1, 1, 1);
    let z = d.narrow(1, 2, 1);
    let mut b = vec![y.clone() * (-C1), z.clone() * C1, x.clone() * (-C1)];
    if degree > 1 {
        let (xx, yy, zz) = (x.clone() * x.clone(), y.clone() * y.clone(), z.clone() * z.clone());
        let xy = x.clone() * y.clone();
        b.extend([
            xy.clone() * C2[0],
            y.clone() * z.clone() * C2[1],
            (zz.clone() * 2.0 - xx.clone() - yy.clone()) * C2[2],
            x.clone() * z.clone() * C2[3],
            (xx.clone() - yy.clone()) * C2[4],
        ]);
        if degree > 2 {
            let zz4 = zz.clone() * 4.0 - xx.clone() - yy.clone();
            b.extend([
                y.clone() * (xx.clone() * 3.0 - yy.clone()) * C3[0],
                xy * z.clone() * C3[1],
                y * zz4.clone() * C3[2],
                z.clone() * (zz * 2.0 - xx.clone() * 3.0 - yy.clone() * 3.0) * C3[3],
                x.clone() * zz4 * C3[4],
                z * (xx.clone() - yy.clone()) * C3[5],
                x * (xx - yy * 3.0) * C3[6],
            ]);
        }
    }
    Tensor::cat(b, 1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// The plain twin of [`sh_colors`]: one Gaussian at a time in f64, the 3DGS polynomials
    /// written out term by term.
    fn sh_oracle(m: [f32; 3], eye: Vec3, dc: &[f32], rest: &[f32], degree: usize) -> [f32; 3] {
        let v = [m[0] as f64 - eye.x as f64, m[1] as f64 - eye.y as f64, m[2] as f64 - eye.z as f64];
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let (x, y, z) = (v[0] / len, v[1] / len, v[2] / len);
        let (c1, c2, c3) = (C1 as f64, C2.map(|c| c as f64), C3.map(|c| c as f64));
        let basis = [
            -c1 * y,
            c1 * z,
            -c1 * x,
            c2[0] * x * y,
            c2[1] * y * z,
            c2[2] * (2.0 * z * z - x * x - y * y),
            c2[3] * x * z,
            c2[4] * (x * x - y * y),
            c3[0] * y * (3.0 * x * x - y * y),
            c3[1] * x * y * z,
            c3[2] * y * (4.0 * z * z - x * x - y * y),
            c3[3] * z * (2.0 * z * z - 3.0 * x * x - 3.0 * y * y),
            c3[4] * x * (4.0 * z * z - x * x - y * y),
            c3[5] * z * (x * x - y * y),
            c3[6] * x * (x * x - 3.0 * y * y),
        ];
        let used = [0, 3, 8, 15][degree];
        std::array::from_fn(|ch| {
            let mut c = SH_C0 as f64 * dc[ch] as f64;
            for k in 0..used {
                c += basis[k] * rest[k * 3 + ch] as f64;
            }
            (c + 0.5).max(0.0) as f32
        })
    }

    #[test]
    fn render_rgb_is_the_rgb_of_the_full_render_clamped() {
        let dev = Device::ndarray();
        let mut r = crate::rng::Rng::new(5);
        let n = 200;
        let mut vals =
            |k: usize, lo: f32, hi: f32| -> Vec<f32> { (0..n * k).map(|_| lo + r.f() * (hi - lo)).collect() };
        let t = |v: Vec<f32>, w: usize| Tensor::<2>::from_data(TensorData::new(v, [n, w]), &dev);
        let model = SplatModel::from_tensors(SplatParams {
            means: t(vals(3, -1.0, 1.0), 3),
            log_scales: t(vals(3, -3.5, -2.0), 3),
            quats: t(vals(4, -1.0, 1.0), 4),
            opacity_logits: t(vals(1, -1.0, 4.0), 1),
            // colours past 0..=1 both ways: the clamp is part of what is compared
            sh_dc: t(vals(3, -3.0, 3.0), 3),
            sh_rest: t(vals(45, -0.5, 0.5), 45),
            identity: t(vals(IDENTITY_DIM, -1.0, 1.0), IDENTITY_DIM),
            classifier_w: Tensor::from_data(
                TensorData::new(vals(1, -1.0, 1.0)[..IDENTITY_DIM * 4].to_vec(), [IDENTITY_DIM, 4]),
                &dev,
            ),
            classifier_b: Tensor::zeros([1, 4], &dev),
        });
        let cam = Camera::look_at(Vec3::new(0.4, -3.0, 1.2), Vec3::ZERO, Vec3::Z, 50.0, 40, 30);
        let bg = [0.2, 0.5, 0.9];
        for degree in [0, 3] {
            let full = model.render(&cam, degree, bg).unwrap();
            let rgb = model.render_rgb(&cam, degree, bg).unwrap();
            assert_eq!(rgb.len(), 40 * 30 * 3);
            let (mut clamped, mut covered) = (0, 0);
            for (i, (&a, &b)) in rgb.iter().zip(&full.rgb).enumerate() {
                assert!((a - b.clamp(0.0, 1.0)).abs() < 1e-5, "degree {degree}, value {i}: {a} vs {b}");
                clamped += usize::from(!(0.0..=1.0).contains(&b));
                covered += usize::from(full.alpha[i / 3] > 0.5);
            }
            assert!(clamped > 0 && covered > 100, "degree {degree}: {clamped} clamped, {covered} covered");
        }
    }

    #[test]
    fn sh_colors_match_the_per_gaussian_formula_at_every_degree() {
        let dev = Device::ndarray();
        let mut r = crate::rng::Rng::new(11);
        let n = 64;
        let mut vals = |k: usize, s: f32| -> Vec<f32> { (0..n * k).map(|_| (r.f() - 0.5) * s).collect() };
        let (means, dc, rest) = (vals(3, 4.0), vals(3, 2.0), vals(45, 1.0));
        let eye = Vec3::new(0.3, -2.5, 1.7);
        let cam = Camera::look_at(eye, Vec3::ZERO, Vec3::Z, 50.0, 32, 24);
        let t = |v: &Vec<f32>, k: usize| Tensor::<2>::from_data(TensorData::new(v.clone(), [n, k]), &dev);
        for degree in 0..=3 {
            let got = host(sh_colors(t(&means, 3), t(&dc, 3), t(&rest, 45), &cam, degree));
            let mut clamped = 0;
            for i in 0..n {
                let m = [means[3 * i], means[3 * i + 1], means[3 * i + 2]];
                let want = sh_oracle(m, eye, &dc[3 * i..3 * i + 3], &rest[45 * i..45 * i + 45], degree);
                for ch in 0..3 {
                    let g = got[3 * i + ch];
                    assert!(
                        (g - want[ch]).abs() < 1e-5,
                        "degree {degree}, Gaussian {i}, channel {ch}: {g} vs {}",
                        want[ch]
                    );
                    clamped += usize::from(want[ch] == 0.0);
                }
            }
            assert!(clamped < n * 3 / 2, "degree {degree}: most colours clamped, the test would say little");
        }
    }
}
