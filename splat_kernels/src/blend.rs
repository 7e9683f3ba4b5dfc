//! Rendering with the geometry frozen: the blend weights of one camera, kept and replayed.
//!
//! With the Gaussians' geometry fixed (the language stage trains only their features), a view's
//! feature map is linear in the features: pixel `p` gets `sum_i w_pi f_i`, where `w_pi = alpha_i
//! T_i` is Gaussian `i`'s blend weight there, plus `T_p` times the background. [`BlendWeights::of`]
//! walks the tiles exactly as [`crate::cpu::forward`] composites them and records those weights
//! (pixel-major, front to back); [`BlendWeights::render`] is then the same map as the rasterizer's
//! (the same products summed in the same order), and [`BlendWeights::features_grad`] the
//! rasterizer's feature gradient, without projecting, sorting or evaluating a Gaussian again.
//! [`crate::blend_ext`] makes it a differentiable burn op.

use crate::camera::Camera;
use crate::constants::RasterConfig;
use crate::cpu::{SplatInputsRef, bin, tile_pixels, walk_tile};
use rayon::prelude::*;

/// Every Gaussian's blend weight at every pixel of one camera, pixel-major (row-major pixels,
/// each pixel's Gaussians front to back).
#[derive(Clone, Default, PartialEq)]
pub struct BlendWeights {
    pub width: usize,
    pub height: usize,
    /// The number of Gaussians (rows of the features the weights blend).
    pub gaussians: usize,
    /// `[H * W + 1]`: pixel `p`'s entries are `offsets[p]..offsets[p + 1]`.
    pub offsets: Vec<usize>,
    /// `[E]` Gaussian of each entry.
    pub gids: Vec<u32>,
    /// `[E]` blend weight `alpha * T` of each entry.
    pub weights: Vec<f32>,
    /// `[H * W]` final transmittance (the background's weight).
    pub final_t: Vec<f32>,
}

impl std::fmt::Debug for BlendWeights {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "BlendWeights({}x{}, {} Gaussians, {} entries)", self.width, self.height, self.gaussians, self.len())
    }
}

impl BlendWeights {
    /// The weights of `inp`'s Gaussians seen from `cam` (their features and background are not
    /// read). `inp` must have passed [`SplatInputsRef::validate`].
    pub fn of(inp: &SplatInputsRef, cam: &Camera, cfg: &RasterConfig) -> Self {
        let b = bin(inp, cam, cfg);
        let num_tiles = b.tile_offsets.len() - 1;
        // per tile: (local pixel, Gaussian, weight) in walk order, then stably by pixel
        let tiles: Vec<(Vec<(u32, u32, f32)>, Vec<f32>)> = (0..num_tiles)
            .into_par_iter()
            .map(|t| {
                let mut e = Vec::new();
                let ft = walk_tile(&b, cam, cfg, t, |q, _, gid, _, w| e.push((q as u32, gid, w)));
                e.sort_by_key(|x| x.0);
                (e, ft)
            })
            .collect();
        let (wd, hd) = (cam.width as usize, cam.height as usize);
        let global = |t: usize, q: usize| {
            let (x0, y0, x1, _) = tile_pixels(cam, t);
            let w = (x1 - x0) as usize;
            (y0 as usize + q / w) * wd + x0 as usize + q % w
        };
        let mut offsets = vec![0usize; wd * hd + 1];
        let mut final_t = vec![1.0f32; wd * hd];
        for (t, (e, ft)) in tiles.iter().enumerate() {
            for &(q, _, _) in e {
                offsets[global(t, q as usize) + 1] += 1;
            }
            for (q, &v) in ft.iter().enumerate() {
                final_t[global(t, q)] = v;
            }
        }
        for p in 0..wd * hd {
            offsets[p + 1] += offsets[p];
        }
        let total = offsets[wd * hd];
        let (mut gids, mut weights) = (vec![0u32; total], vec![0f32; total]);
        let mut cursor = offsets.clone();
        for (t, (e, _)) in tiles.iter().enumerate() {
            for &(q, gid, w) in e {
                let p = global(t, q as usize);
                gids[cursor[p]] = gid;
                weights[cursor[p]] = w;
                cursor[p] += 1;
            }
        }
        Self { width: wd, height: hd, gaussians: inp.len(), offsets, gids, weights, final_t }
    }

    /// The number of (pixel, Gaussian) entries.
    pub fn len(&self) -> usize {
        self.gids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.gids.is_empty()
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.offsets.len() * size_of::<usize>() + self.len() * 8 + self.final_t.len() * 4
    }

    /// `[H * W, C]` map of `features` (`[N, C]`) over a zero background: the rasterizer's map.
    pub fn render(&self, features: &[f32], c: usize) -> Vec<f32> {
        assert_eq!(features.len(), self.gaussians * c, "features must be [{}, {c}]", self.gaussians);
        let mut out = vec![0f32; self.width * self.height * c];
        out.par_chunks_mut(c).enumerate().with_min_len(64).for_each(|(p, px)| {
            for k in self.offsets[p]..self.offsets[p + 1] {
                let (g, w) = (self.gids[k] as usize, self.weights[k]);
                let f = &features[g * c..(g + 1) * c];
                for ch in 0..c {
                    px[ch] += w * f[ch];
                }
            }
        });
        out
    }

    /// `[N, C]` gradient of the features from the map's gradient `g_image` (`[H * W, C]`).
    pub fn features_grad(&self, g_image: &[f32], c: usize) -> Vec<f32> {
        assert_eq!(g_image.len(), self.width * self.height * c, "the map gradient must be [H * W, {c}]");
        let mut out = vec![0f32; self.gaussians * c];
        for p in 0..self.width * self.height {
            let g = &g_image[p * c..(p + 1) * c];
            for k in self.offsets[p]..self.offsets[p + 1] {
                let (i, w) = (self.gids[k] as usize, self.weights[k]);
                let row = &mut out[i * c..(i + 1) * c];
                for ch in 0..c {
                    row[ch] += w * g[ch];
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cpu;

    /// A small scene with overlapping, partly opaque Gaussians across several tiles.
    fn scene(n: usize, c: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
        let mut s = 0x2545_F491_4F6C_DD1Du64;
        let mut r = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32
        };
        let mut means = Vec::new();
        let (mut scales, mut quats, mut opac, mut feats) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for _ in 0..n {
            means.extend([r() * 2.0 - 1.0, r() * 2.0 - 1.0, 2.0 + r() * 2.0]);
            scales.extend([-3.0 + r() * 1.5, -3.0 + r() * 1.5, -3.0 + r()]);
            quats.extend([1.0, r() - 0.5, r() - 0.5, r() - 0.5]);
            opac.push(r() * 6.0 - 2.0);
            feats.extend((0..c).map(|_| r() * 2.0 - 1.0));
        }
        (means, scales, quats, opac, feats)
    }

    #[test]
    fn replayed_weights_give_the_rasterizers_map_and_feature_gradient() {
        let (n, c) = (300, 5);
        let (means, scales, quats, opac, feats) = scene(n, c);
        let (bg, offs) = (vec![0f32; c], vec![0f32; n * 2]);
        let inp = SplatInputsRef {
            means: &means,
            log_scales: &scales,
            quats: &quats,
            opacity_logits: &opac,
            features: &feats,
            background: &bg,
            screen_offsets: &offs,
        };
        let cam = Camera::look_at(glam::Vec3::ZERO, glam::Vec3::Z, glam::Vec3::Y, 60.0, 40, 37);
        let cfg = RasterConfig::default();
        let fwd = cpu::forward(&inp, &cam, &cfg);
        let w = BlendWeights::of(&inp, &cam, &cfg);
        assert!(w.len() > 40 * 37, "the scene should overlap: {} entries", w.len());
        assert_eq!(w.render(&feats, c), fwd.image, "same products in the same order: the same map");
        assert_eq!(w.final_t, fwd.final_t);
        let g_image: Vec<f32> = (0..40 * 37 * c).map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.5).collect();
        let zeros = vec![0f32; 40 * 37];
        let g = cpu::backward(&inp, &cam, &cfg, &fwd.final_t, &fwd.n_visited, &g_image, &zeros, &zeros);
        let mine = w.features_grad(&g_image, c);
        let worst = mine.iter().zip(&g.features).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        let scale = g.features.iter().map(|x| x.abs()).fold(0f32, f32::max);
        assert!(scale > 0.1 && worst <= 1e-5 * scale, "feature gradient off by {worst} (scale {scale})");
    }
}
