//! The CPU rasterizer: plain Rust on slices, rayon over tiles. Backend-agnostic: the burn glue
//! ([`crate::ext`]) reads tensors into slices and wraps the results, so any CPU backend can use it.
//!
//! Determinism: tiles are independent and per-Gaussian gradients are summed over intersections in
//! tile order, so the result does not depend on the number of threads or on scheduling.

use crate::camera::Camera;
use crate::constants::{EMPTY_ID, RasterConfig, TILE_SIZE};
use crate::project::{self, GaussianGrad, Projected, ProjectedGrad};
use rayon::prelude::*;

/// The seven inputs of the op, one `T` each, flat and row-major (`N` Gaussians, `C` channels):
/// borrowed slices ([`SplatInputsRef`]), owned host copies and gradients (`Vec<f32>`:
/// [`GradOut`], `ext::HostInputs`). The backend primitives are `ext::SplatPrims`, which burn's
/// extension derive needs spelled out.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SplatInputs<T> {
    /// `[N, 3]`
    pub means: T,
    /// `[N, 3]`
    pub log_scales: T,
    /// `[N, 4]` as (w, x, y, z), not necessarily normalised.
    pub quats: T,
    /// `[N]`
    pub opacity_logits: T,
    /// `[N, C]`
    pub features: T,
    /// `[C]`
    pub background: T,
    /// `[N, 2]` offsets added to the projected centres (zeros in normal use; its gradient is the
    /// screen-space mean gradient that densification accumulates).
    pub screen_offsets: T,
}

/// Borrowed inputs: what the rasterizers read.
pub type SplatInputsRef<'a> = SplatInputs<&'a [f32]>;

/// Gradients with respect to every input, in the inputs' shapes (`screen_offsets`: the
/// screen-space centres' gradient, the densification signal).
pub type GradOut = SplatInputs<Vec<f32>>;

impl<T> SplatInputs<T> {
    /// Each of the seven through `f`, in declaration order.
    pub fn map<U>(self, mut f: impl FnMut(T) -> U) -> SplatInputs<U> {
        SplatInputs {
            means: f(self.means),
            log_scales: f(self.log_scales),
            quats: f(self.quats),
            opacity_logits: f(self.opacity_logits),
            features: f(self.features),
            background: f(self.background),
            screen_offsets: f(self.screen_offsets),
        }
    }
}

impl<T: AsRef<[f32]>> SplatInputs<T> {
    /// Borrowed slices of owned (or already borrowed) values.
    pub fn as_slices(&self) -> SplatInputsRef<'_> {
        SplatInputs {
            means: self.means.as_ref(),
            log_scales: self.log_scales.as_ref(),
            quats: self.quats.as_ref(),
            opacity_logits: self.opacity_logits.as_ref(),
            features: self.features.as_ref(),
            background: self.background.as_ref(),
            screen_offsets: self.screen_offsets.as_ref(),
        }
    }
    /// `N`
    pub fn len(&self) -> usize {
        self.opacity_logits.as_ref().len()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// `C`: the background's length.
    pub fn channels(&self) -> usize {
        self.background.as_ref().len()
    }
}

impl SplatInputsRef<'_> {
    fn mean(&self, i: usize) -> [f32; 3] {
        [self.means[3 * i], self.means[3 * i + 1], self.means[3 * i + 2]]
    }
    fn log_scale(&self, i: usize) -> [f32; 3] {
        [self.log_scales[3 * i], self.log_scales[3 * i + 1], self.log_scales[3 * i + 2]]
    }
    fn quat(&self, i: usize) -> [f32; 4] {
        let q = &self.quats[4 * i..4 * i + 4];
        [q[0], q[1], q[2], q[3]]
    }

    /// Checks lengths against `N` and `C` and that every value is finite.
    pub fn validate(&self) -> Result<(), crate::error::SplatError> {
        let n = self.len();
        let c = self.channels();
        if c == 0 {
            return Err(crate::error::SplatError::Shape("features must have at least one channel".into()));
        }
        let checks: [(&str, &[f32], usize, usize); 7] = [
            ("means", self.means, n * 3, 3),
            ("log_scales", self.log_scales, n * 3, 3),
            ("quats", self.quats, n * 4, 4),
            ("opacity_logits", self.opacity_logits, n, 1),
            ("features", self.features, n * c, c),
            ("background", self.background, c, c),
            ("screen_offsets", self.screen_offsets, n * 2, 2),
        ];
        for (name, data, want, width) in checks {
            if data.len() != want {
                return Err(crate::error::SplatError::Shape(format!(
                    "{name} has {} values, expected {want} ({} rows of {width})",
                    data.len(),
                    want / width.max(1)
                )));
            }
            if let Some(k) = data.iter().position(|v| !v.is_finite()) {
                return Err(crate::error::SplatError::NonFinite {
                    tensor: name,
                    row: k / width.max(1),
                    value: data[k],
                });
            }
        }
        Ok(())
    }
}

/// Outputs of the forward pass, all row-major.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ForwardOut {
    /// `[H, W, C]` composited features including the background.
    pub image: Vec<f32>,
    /// `[H, W]` accumulated opacity `1 - T_final`.
    pub alpha: Vec<f32>,
    /// `[H, W]` blend-weighted depth `sum_i w_i z_i` (divide by alpha for the expectation).
    pub depth: Vec<f32>,
    /// `[H, W]` index of the Gaussian with the largest blend weight, or -1.
    pub top_id: Vec<i32>,
    /// `[H, W]` final transmittance (saved for the backward pass).
    pub final_t: Vec<f32>,
    /// `[H, W]` number of tile-list entries visited (saved for the backward pass).
    pub n_visited: Vec<i32>,
}

/// Projected Gaussians binned into tiles and depth-sorted per tile.
pub struct Binned {
    pub projected: Vec<Option<Projected>>,
    /// `tiles + 1` offsets into `gids`.
    pub tile_offsets: Vec<usize>,
    /// Gaussian ids, grouped by tile, sorted by (depth, id) within a tile.
    pub gids: Vec<u32>,
}

/// Projects and bins all Gaussians.
pub fn bin(inp: &SplatInputsRef, cam: &Camera, cfg: &RasterConfig) -> Binned {
    let n = inp.len();
    let projected: Vec<Option<Projected>> = (0..n)
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            let mut p = project::project(cam, cfg, inp.mean(i), inp.log_scale(i), inp.quat(i), inp.opacity_logits[i])?;
            let off = [inp.screen_offsets[2 * i], inp.screen_offsets[2 * i + 1]];
            if off != [0.0, 0.0] {
                p.mean2d[0] += off[0];
                p.mean2d[1] += off[1];
                p.rect = project::tile_rect(p.mean2d, p.radius, cam.tiles());
                if p.rect[0] >= p.rect[2] || p.rect[1] >= p.rect[3] {
                    return None;
                }
            }
            Some(p)
        })
        .collect();
    let [tx, ty] = cam.tiles();
    let num_tiles = (tx * ty) as usize;
    let mut counts = vec![0usize; num_tiles + 1];
    for p in projected.iter().flatten() {
        for y in p.rect[1]..p.rect[3] {
            for x in p.rect[0]..p.rect[2] {
                counts[(y * tx + x) as usize + 1] += 1;
            }
        }
    }
    for t in 0..num_tiles {
        counts[t + 1] += counts[t];
    }
    let tile_offsets = counts;
    let mut cursor = tile_offsets.clone();
    let mut gids = vec![0u32; tile_offsets[num_tiles]];
    for (i, p) in projected.iter().enumerate() {
        if let Some(p) = p {
            for y in p.rect[1]..p.rect[3] {
                for x in p.rect[0]..p.rect[2] {
                    let t = (y * tx + x) as usize;
                    gids[cursor[t]] = i as u32;
                    cursor[t] += 1;
                }
            }
        }
    }
    // Sort each tile's list by (depth, id): a total order, hence deterministic.
    let mut slices = Vec::with_capacity(num_tiles);
    let mut rest: &mut [u32] = &mut gids;
    for t in 0..num_tiles {
        let (head, tail) = rest.split_at_mut(tile_offsets[t + 1] - tile_offsets[t]);
        slices.push(head);
        rest = tail;
    }
    slices.into_par_iter().for_each(|s| {
        s.sort_unstable_by(|&a, &b| {
            let da = projected[a as usize].as_ref().map(|p| p.depth).unwrap_or(0.0);
            let db = projected[b as usize].as_ref().map(|p| p.depth).unwrap_or(0.0);
            da.total_cmp(&db).then(a.cmp(&b))
        })
    });
    Binned { projected, tile_offsets, gids }
}

/// Pixel coordinates covered by tile `t`, clipped to the image.
pub(crate) fn tile_pixels(cam: &Camera, t: usize) -> (u32, u32, u32, u32) {
    let tx = cam.tiles()[0] as usize;
    let x0 = (t % tx) as u32 * TILE_SIZE;
    let y0 = (t / tx) as u32 * TILE_SIZE;
    let x1 = (x0 + TILE_SIZE).min(cam.width);
    let y1 = (y0 + TILE_SIZE).min(cam.height);
    (x0, y0, x1, y1)
}

/// `power` of a Gaussian at pixel centre `(px, py)` and the deltas.
#[inline]
fn eval_power(p: &Projected, px: f32, py: f32) -> (f32, f32, f32) {
    let dx = px - p.mean2d[0];
    let dy = py - p.mean2d[1];
    let power = -0.5 * (p.conic[0] * dx * dx + p.conic[2] * dy * dy) - p.conic[1] * dx * dy;
    (power, dx, dy)
}

/// Pixel window `[x0, x1) x [y0, y1)` (local to the tile whose first pixel is `(ox, oy)`) outside
/// which the Gaussian's alpha is
/// provably below `alpha_min`: the ellipse `o exp(power) >= alpha_min` and its bounding box,
/// widened by one pixel against rounding. Skipping pixels outside it changes no result (they
/// would be skipped by the alpha test anyway); it only saves work for small Gaussians.
#[inline]
fn pixel_window(
    p: &Projected,
    cfg: &RasterConfig,
    ox: u32,
    oy: u32,
    w: usize,
    h: usize,
) -> (usize, usize, usize, usize) {
    let full = (0, w, 0, h);
    if !(cfg.alpha_min > 0.0) {
        return full;
    }
    if p.opacity < cfg.alpha_min {
        return (0, 0, 0, 0);
    }
    let [a, b, c] = p.conic;
    let det = a * c - b * b;
    if !(det > 0.0) {
        return full;
    }
    let k = 2.0 * (p.opacity / cfg.alpha_min).ln();
    let hx = (k * c / det).sqrt() + 1.0;
    let hy = (k * a / det).sqrt() + 1.0;
    if !(hx.is_finite() && hy.is_finite()) {
        return full;
    }
    // Pixel centres are at integer + 0.5.
    let lo = |m: f32, half: f32, o: u32, n: usize| ((m - half - 0.5 - o as f32).floor().max(0.0) as usize).min(n);
    let hi =
        |m: f32, half: f32, o: u32, n: usize| ((m + half - 0.5 - o as f32).ceil() + 1.0).clamp(0.0, n as f32) as usize;
    (lo(p.mean2d[0], hx, ox, w), hi(p.mean2d[0], hx, ox, w), lo(p.mean2d[1], hy, oy, h), hi(p.mean2d[1], hy, oy, h))
}

/// A power below which `opacity * exp(power) < alpha_min` for certain, with a margin (1e-3 in
/// the exponent) far beyond the rounding of `exp` and `ln`: pixels below it are skipped without
/// computing `exp`, and every pixel the alpha test keeps is still kept (bitwise the same result).
/// `-inf` (no cut) when `alpha_min` is not positive.
#[inline]
fn power_cut(p: &Projected, cfg: &RasterConfig) -> f32 {
    if cfg.alpha_min > 0.0 && p.opacity > 0.0 { (cfg.alpha_min / p.opacity).ln() - 1e-3 } else { f32::NEG_INFINITY }
}

/// Walks tile `t`'s depth-sorted list front to back exactly as the forward composites it, calling
/// `visit(q, k, gid, projected, weight)` for every Gaussian that contributes to the tile's pixel
/// `q` (row-major within the tile), `k` being its position in the tile's list and `weight` its
/// blend weight `alpha * T`. Returns the tile's final transmittance per pixel.
#[inline]
pub(crate) fn walk_tile(
    b: &Binned,
    cam: &Camera,
    cfg: &RasterConfig,
    t: usize,
    mut visit: impl FnMut(usize, usize, u32, &Projected, f32),
) -> Vec<f32> {
    let (x0, y0, x1, y1) = tile_pixels(cam, t);
    let (w, h) = ((x1 - x0) as usize, (y1 - y0) as usize);
    let np = w * h;
    let mut final_t = vec![1.0f32; np];
    let mut done = vec![false; np];
    let mut active = np;
    let list = &b.gids[b.tile_offsets[t]..b.tile_offsets[t + 1]];
    for (k, &gid) in list.iter().enumerate() {
        if active == 0 {
            break;
        }
        let p = b.projected[gid as usize].as_ref().expect("binned Gaussian is projected");
        let (wx0, wx1, wy0, wy1) = pixel_window(p, cfg, x0, y0, w, h);
        let cut = power_cut(p, cfg);
        for py in wy0..wy1 {
            for px in wx0..wx1 {
                let q = py * w + px;
                if done[q] {
                    continue;
                }
                let (power, _, _) = eval_power(p, (x0 as usize + px) as f32 + 0.5, (y0 as usize + py) as f32 + 0.5);
                if power > 0.0 || power < cut {
                    continue;
                }
                let alpha = (p.opacity * power.exp()).min(cfg.alpha_max);
                if alpha < cfg.alpha_min {
                    continue;
                }
                let t_pix = final_t[q];
                let next_t = t_pix * (1.0 - alpha);
                if next_t < cfg.t_min {
                    done[q] = true;
                    active -= 1;
                    continue;
                }
                visit(q, k, gid, p, alpha * t_pix);
                final_t[q] = next_t;
            }
        }
    }
    final_t
}

struct TileFwd {
    image: Vec<f32>,
    alpha: Vec<f32>,
    depth: Vec<f32>,
    top_id: Vec<i32>,
    final_t: Vec<f32>,
    n_visited: Vec<i32>,
}

/// Forward pass. `inp` must have passed [`SplatInputsRef::validate`].
pub fn forward(inp: &SplatInputsRef, cam: &Camera, cfg: &RasterConfig) -> ForwardOut {
    let binned = bin(inp, cam, cfg);
    forward_binned(inp, cam, cfg, &binned)
}

/// Forward pass on already binned Gaussians.
pub fn forward_binned(inp: &SplatInputsRef, cam: &Camera, cfg: &RasterConfig, b: &Binned) -> ForwardOut {
    let c = inp.channels();
    let num_tiles = b.tile_offsets.len() - 1;
    let tiles: Vec<TileFwd> = (0..num_tiles)
        .into_par_iter()
        .map(|t| {
            let (x0, y0, x1, y1) = tile_pixels(cam, t);
            let (w, h) = ((x1 - x0) as usize, (y1 - y0) as usize);
            let np = w * h;
            let mut out = TileFwd {
                image: vec![0.0; np * c],
                alpha: vec![0.0; np],
                depth: vec![0.0; np],
                top_id: vec![EMPTY_ID; np],
                final_t: Vec::new(),
                n_visited: vec![0; np],
            };
            let mut best_w = vec![0.0f32; np];
            let f_all = inp.features;
            out.final_t = walk_tile(b, cam, cfg, t, |q, k, gid, p, wgt| {
                let f = &f_all[gid as usize * c..(gid as usize + 1) * c];
                let img = &mut out.image[q * c..(q + 1) * c];
                for ch in 0..c {
                    img[ch] += wgt * f[ch];
                }
                out.depth[q] += wgt * p.depth;
                if wgt > best_w[q] {
                    best_w[q] = wgt;
                    out.top_id[q] = gid as i32;
                }
                out.n_visited[q] = k as i32 + 1;
            });
            for q in 0..np {
                let tf = out.final_t[q];
                out.alpha[q] = 1.0 - tf;
                for ch in 0..c {
                    out.image[q * c + ch] += tf * inp.background[ch];
                }
            }
            out
        })
        .collect();
    let (wd, hd) = (cam.width as usize, cam.height as usize);
    let mut res = ForwardOut {
        image: vec![0.0; wd * hd * c],
        alpha: vec![0.0; wd * hd],
        depth: vec![0.0; wd * hd],
        top_id: vec![EMPTY_ID; wd * hd],
        final_t: vec![1.0; wd * hd],
        n_visited: vec![0; wd * hd],
    };
    for (t, tile) in tiles.into_iter().enumerate() {
        let (x0, y0, x1, y1) = tile_pixels(cam, t);
        let w = (x1 - x0) as usize;
        for py in y0 as usize..y1 as usize {
            for px in x0 as usize..x1 as usize {
                let q = (py - y0 as usize) * w + (px - x0 as usize);
                let o = py * wd + px;
                res.image[o * c..(o + 1) * c].copy_from_slice(&tile.image[q * c..(q + 1) * c]);
                res.alpha[o] = tile.alpha[q];
                res.depth[o] = tile.depth[q];
                res.top_id[o] = tile.top_id[q];
                res.final_t[o] = tile.final_t[q];
                res.n_visited[o] = tile.n_visited[q];
            }
        }
    }
    res
}

/// Number of per-intersection gradient slots besides the features: mean2d (2), conic (3),
/// opacity (1), depth (1).
const ISECT_FIXED: usize = 7;

/// Backward pass.
///
/// * `final_t`, `n_visited`: saved by [`forward`].
/// * `g_image [H, W, C]`, `g_alpha [H, W]`, `g_depth [H, W]`: upstream gradients.
#[allow(clippy::too_many_arguments)]
pub fn backward(
    inp: &SplatInputsRef,
    cam: &Camera,
    cfg: &RasterConfig,
    final_t: &[f32],
    n_visited: &[i32],
    g_image: &[f32],
    g_alpha: &[f32],
    g_depth: &[f32],
) -> GradOut {
    let n = inp.len();
    let c = inp.channels();
    let stride = ISECT_FIXED + c;
    let b = bin(inp, cam, cfg);
    let num_tiles = b.tile_offsets.len() - 1;
    let wd = cam.width as usize;
    let mut isect = vec![0.0f32; b.gids.len() * stride];
    {
        let mut chunks = Vec::with_capacity(num_tiles);
        let mut rest: &mut [f32] = &mut isect;
        for t in 0..num_tiles {
            let (head, tail) = rest.split_at_mut((b.tile_offsets[t + 1] - b.tile_offsets[t]) * stride);
            chunks.push((t, head));
            rest = tail;
        }
        chunks.into_par_iter().for_each(|(t, buf)| {
            let (x0, y0, x1, y1) = tile_pixels(cam, t);
            let (w, h) = ((x1 - x0) as usize, (y1 - y0) as usize);
            let np = w * h;
            let list = &b.gids[b.tile_offsets[t]..b.tile_offsets[t + 1]];
            // Per-pixel state, walking back to front.
            let mut tt = vec![0.0f32; np];
            let mut last = vec![0usize; np];
            let mut rec_f = vec![0.0f32; np * c];
            let mut rec_z = vec![0.0f32; np];
            let mut max_last = 0usize;
            for py in 0..h {
                for px in 0..w {
                    let q = py * w + px;
                    let o = (y0 as usize + py) * wd + x0 as usize + px;
                    tt[q] = final_t[o];
                    last[q] = n_visited[o].max(0) as usize;
                    max_last = max_last.max(last[q]);
                    rec_f[q * c..(q + 1) * c].copy_from_slice(inp.background);
                }
            }
            for k in (0..max_last).rev() {
                let gid = list[k] as usize;
                let p = b.projected[gid].as_ref().expect("binned Gaussian is projected");
                let f = &inp.features[gid * c..(gid + 1) * c];
                let slot = &mut buf[k * stride..(k + 1) * stride];
                let (wx0, wx1, wy0, wy1) = pixel_window(p, cfg, x0, y0, w, h);
                let cut = power_cut(p, cfg);
                for py in wy0..wy1 {
                    for px in wx0..wx1 {
                        let q = py * w + px;
                        if k >= last[q] {
                            continue;
                        }
                        let (power, dx, dy) =
                            eval_power(p, (x0 as usize + px) as f32 + 0.5, (y0 as usize + py) as f32 + 0.5);
                        if power > 0.0 || power < cut {
                            continue;
                        }
                        let g = power.exp();
                        let raw = p.opacity * g;
                        let alpha = raw.min(cfg.alpha_max);
                        if alpha < cfg.alpha_min {
                            continue;
                        }
                        let o = (y0 as usize + py) * wd + x0 as usize + px;
                        // Transmittance in front of this Gaussian.
                        let t_k = tt[q] / (1.0 - alpha);
                        let wgt = alpha * t_k;
                        let gf = &g_image[o * c..(o + 1) * c];
                        let rf = &mut rec_f[q * c..(q + 1) * c];
                        let mut d_alpha = 0.0f32;
                        for ch in 0..c {
                            d_alpha += gf[ch] * (f[ch] - rf[ch]);
                            slot[ISECT_FIXED + ch] += wgt * gf[ch];
                            rf[ch] = alpha * f[ch] + (1.0 - alpha) * rf[ch];
                        }
                        d_alpha += g_depth[o] * (p.depth - rec_z[q]);
                        d_alpha *= t_k;
                        d_alpha += g_alpha[o] * final_t[o] / (1.0 - alpha);
                        slot[6] += wgt * g_depth[o];
                        rec_z[q] = alpha * p.depth + (1.0 - alpha) * rec_z[q];
                        tt[q] = t_k;
                        if raw < cfg.alpha_max {
                            slot[5] += d_alpha * g;
                            let d_power = d_alpha * p.opacity * g;
                            slot[0] += d_power * (p.conic[0] * dx + p.conic[1] * dy);
                            slot[1] += d_power * (p.conic[2] * dy + p.conic[1] * dx);
                            slot[2] += d_power * (-0.5 * dx * dx);
                            slot[3] += d_power * (-dx * dy);
                            slot[4] += d_power * (-0.5 * dy * dy);
                        }
                    }
                }
            }
        });
    }
    // Group intersections by Gaussian (tile order kept) and reduce.
    let mut counts = vec![0usize; n + 1];
    for &g in &b.gids {
        counts[g as usize + 1] += 1;
    }
    for i in 0..n {
        counts[i + 1] += counts[i];
    }
    let mut cursor = counts.clone();
    let mut by_gid = vec![0usize; b.gids.len()];
    for (k, &g) in b.gids.iter().enumerate() {
        by_gid[cursor[g as usize]] = k;
        cursor[g as usize] += 1;
    }
    let mut out = GradOut {
        means: vec![0.0; n * 3],
        log_scales: vec![0.0; n * 3],
        quats: vec![0.0; n * 4],
        opacity_logits: vec![0.0; n],
        features: vec![0.0; n * c],
        background: vec![0.0; c],
        screen_offsets: vec![0.0; n * 2],
    };
    let per: Vec<(GaussianGrad, [f32; 2])> = (0..n)
        .into_par_iter()
        .with_min_len(256)
        .map(|i| {
            let mut pg = ProjectedGrad::default();
            for &k in &by_gid[counts[i]..counts[i + 1]] {
                let s = &isect[k * stride..k * stride + ISECT_FIXED];
                pg.mean2d[0] += s[0];
                pg.mean2d[1] += s[1];
                pg.conic[0] += s[2];
                pg.conic[1] += s[3];
                pg.conic[2] += s[4];
                pg.opacity += s[5];
                pg.depth += s[6];
            }
            if counts[i] == counts[i + 1] {
                return (GaussianGrad::default(), [0.0; 2]);
            }
            let gg =
                project::project_backward(cam, inp.mean(i), inp.log_scale(i), inp.quat(i), inp.opacity_logits[i], &pg);
            (gg, pg.mean2d)
        })
        .collect();
    out.features.par_chunks_mut(c).enumerate().with_min_len(256).for_each(|(i, fg)| {
        for &k in &by_gid[counts[i]..counts[i + 1]] {
            let s = &isect[k * stride + ISECT_FIXED..(k + 1) * stride];
            for ch in 0..c {
                fg[ch] += s[ch];
            }
        }
    });
    for (i, (gg, m2)) in per.into_iter().enumerate() {
        out.means[3 * i..3 * i + 3].copy_from_slice(&gg.mean);
        out.log_scales[3 * i..3 * i + 3].copy_from_slice(&gg.log_scale);
        out.quats[4 * i..4 * i + 4].copy_from_slice(&gg.quat);
        out.opacity_logits[i] = gg.opacity_logit;
        out.screen_offsets[2 * i..2 * i + 2].copy_from_slice(&m2);
    }
    for (o, &tf) in final_t.iter().enumerate() {
        for ch in 0..c {
            out.background[ch] += g_image[o * c + ch] * tf;
        }
    }
    out
}
