//! A Gaussian cloud held on the host.

use burn::tensor::{Device, Tensor, TensorData};
use splat_kernels::Gaussians;
use std::collections::BTreeMap;

/// Zeroth-order spherical-harmonic constant: colour = 0.5 + SH_C0 * f_dc.
pub const SH_C0: f32 = 0.282_094_8;

/// N Gaussians with colour (SH degree 0 plus optional higher bands) and named extra channels.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianCloud {
    pub means: Vec<[f32; 3]>,
    pub log_scales: Vec<[f32; 3]>,
    /// (w, x, y, z), as Inria's rot_0..rot_3.
    pub quats: Vec<[f32; 4]>,
    pub opacity_logits: Vec<f32>,
    /// SH DC coefficients per Gaussian (RGB).
    pub sh_dc: Vec<[f32; 3]>,
    /// Higher SH bands, `rest_per_gaussian` values per Gaussian (Inria's f_rest_* order).
    pub sh_rest: Vec<f32>,
    pub rest_per_gaussian: usize,
    /// Extra per-Gaussian channels by name (identity or language features), each `len * width`.
    pub extra: BTreeMap<String, (usize, Vec<f32>)>,
}

impl GaussianCloud {
    pub fn len(&self) -> usize {
        self.means.len()
    }
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// Keeps the Gaussians whose `keep` entry is true (`keep` has one entry per Gaussian), every
    /// attribute and extra channel alike, in their order.
    ///
    /// # Panics
    /// When `keep` is not one entry per Gaussian.
    pub fn retain(&mut self, keep: &[bool]) {
        assert_eq!(keep.len(), self.len(), "one keep flag per Gaussian");
        fn rows<T: Clone>(v: &[T], width: usize, keep: &[bool]) -> Vec<T> {
            v.chunks(width.max(1)).zip(keep).filter(|(_, k)| **k).flat_map(|(r, _)| r.to_vec()).collect()
        }
        self.means = rows(&self.means, 1, keep);
        self.log_scales = rows(&self.log_scales, 1, keep);
        self.quats = rows(&self.quats, 1, keep);
        self.opacity_logits = rows(&self.opacity_logits, 1, keep);
        self.sh_dc = rows(&self.sh_dc, 1, keep);
        if self.rest_per_gaussian > 0 {
            self.sh_rest = rows(&self.sh_rest, self.rest_per_gaussian, keep);
        }
        for (width, values) in self.extra.values_mut() {
            if *width > 0 {
                *values = rows(values, *width, keep);
            }
        }
    }

    /// Base colour of each Gaussian (SH degree 0), not clamped.
    pub fn colors(&self) -> Vec<[f32; 3]> {
        self.sh_dc.iter().map(|d| d.map(|v| 0.5 + SH_C0 * v)).collect()
    }

    /// Axis-aligned bounds of the centres.
    pub fn bounds(&self) -> Option<(glam::Vec3, glam::Vec3)> {
        let first = glam::Vec3::from(*self.means.first()?);
        Some(self.means.iter().fold((first, first), |(lo, hi), m| {
            let v = glam::Vec3::from(*m);
            (lo.min(v), hi.max(v))
        }))
    }

    /// Tensors on `device` with RGB (SH degree 0) as the splatted features.
    pub fn to_gaussians(&self, device: &Device) -> Gaussians {
        let flat = |v: Vec<f32>, w: usize| Tensor::<2>::from_data(TensorData::new(v, [self.len(), w]), device);
        Gaussians {
            means: flat(self.means.concat(), 3),
            log_scales: flat(self.log_scales.concat(), 3),
            quats: flat(self.quats.concat(), 4),
            opacity_logits: Tensor::<1>::from_data(TensorData::new(self.opacity_logits.clone(), [self.len()]), device),
            features: flat(self.colors().concat(), 3),
        }
    }
}
