//! Image preprocessing equal to transformers' PIL-backed `LlavaOnevisionImageProcessor`:
//! PIL's 8-bit two-pass resampling (bicubic a = -0.5 or bilinear, 22-bit fixed point, horizontal
//! pass first), anyres best-resolution selection, centred zero padding, 384x384 patches, the base
//! view first; multi-image prompts pad each image to a square with the mean colour and keep only
//! the base view. Rescale and normalise follow (pixels / 255 - mean) / std.

use super::config::{LlavaConfig, ProcessorConfig};

/// An 8-bit RGB image, row-major HWC.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    pub width: usize,
    pub height: usize,
    pub data: Vec<u8>,
}

impl RgbImage {
    pub fn new(width: usize, height: usize, data: Vec<u8>) -> Self {
        assert_eq!(data.len(), width * height * 3, "RgbImage: data length");
        Self { width, height, data }
    }

    /// From 8-bit pixels of `c` channels (gray, gray+alpha, RGB or RGBA, as a PNG decodes them),
    /// converted like PIL's `convert("RGB")` (alpha dropped).
    pub fn from_channels(w: usize, h: usize, c: usize, bytes: &[u8]) -> Self {
        assert!((1..=4).contains(&c) && bytes.len() == w * h * c, "RgbImage: {c} channels of {w}x{h}");
        let mut data = Vec::with_capacity(w * h * 3);
        for px in bytes.chunks_exact(c) {
            match c {
                1 | 2 => data.extend_from_slice(&[px[0], px[0], px[0]]),
                _ => data.extend_from_slice(&px[..3]),
            }
        }
        Self::new(w, h, data)
    }

    /// From linear `[0, 1]` floats (HWC), rounded to 8 bits.
    pub fn from_f32(width: usize, height: usize, rgb: &[f32]) -> Self {
        Self::new(width, height, rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect())
    }

    /// A copy of the rows `y0..y0+h` and columns `x0..x0+w`.
    pub fn crop(&self, x0: usize, y0: usize, w: usize, h: usize) -> Self {
        let mut data = Vec::with_capacity(w * h * 3);
        for y in y0..y0 + h {
            let row = (y * self.width + x0) * 3;
            data.extend_from_slice(&self.data[row..row + w * 3]);
        }
        Self::new(w, h, data)
    }

    /// Pastes `self` centred on a `width` x `height` canvas of `fill` (numpy-style split: the extra pixel goes after).
    fn pad_centered(&self, width: usize, height: usize, fill: [u8; 3]) -> Self {
        let x0 = (width - self.width) / 2;
        let y0 = (height - self.height) / 2;
        let mut data: Vec<u8> = std::iter::repeat_n(fill, width * height).flatten().collect();
        for y in 0..self.height {
            let src = y * self.width * 3;
            let dst = ((y + y0) * width + x0) * 3;
            data[dst..dst + self.width * 3].copy_from_slice(&self.data[src..src + self.width * 3]);
        }
        Self::new(width, height, data)
    }
}

const PRECISION_BITS: u32 = 32 - 8 - 2;

fn bicubic(x: f64) -> f64 {
    const A: f64 = -0.5;
    let x = x.abs();
    if x < 1.0 {
        ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0
    } else if x < 2.0 {
        (((x - 5.0) * x + 8.0) * x - 4.0) * A
    } else {
        0.0
    }
}

fn bilinear(x: f64) -> f64 {
    let x = x.abs();
    if x < 1.0 { 1.0 - x } else { 0.0 }
}

/// Per output pixel: first input index and fixed-point weights (PIL's `precompute_coeffs` + `normalize_coeffs_8bpc`).
fn coefficients(in_size: usize, out_size: usize, filter: fn(f64) -> f64, support: f64) -> Vec<(usize, Vec<i32>)> {
    let scale = in_size as f64 / out_size as f64;
    let filterscale = scale.max(1.0);
    let support = support * filterscale;
    let ss = 1.0 / filterscale;
    (0..out_size)
        .map(|xx| {
            let center = (xx as f64 + 0.5) * scale;
            let xmin = ((center - support + 0.5) as i64).max(0) as usize;
            let xmax = ((center + support + 0.5) as i64).min(in_size as i64) as usize;
            let w: Vec<f64> = (xmin..xmax).map(|x| filter((x as f64 - center + 0.5) * ss)).collect();
            let total: f64 = w.iter().sum();
            let fixed = w
                .iter()
                .map(|&k| {
                    let k = if total != 0.0 { k / total } else { k };
                    let s = k * (1u32 << PRECISION_BITS) as f64;
                    (if k < 0.0 { -0.5 + s } else { 0.5 + s }) as i32
                })
                .collect();
            (xmin, fixed)
        })
        .collect()
}

fn clip8(acc: i64) -> u8 {
    (acc >> PRECISION_BITS).clamp(0, 255) as u8
}

/// PIL `Image.resize((width, height), resample)` for an RGB image: bit-exact with Pillow's 8-bit path.
pub fn resize(img: &RgbImage, width: usize, height: usize, resample: u32) -> RgbImage {
    if img.width == width && img.height == height {
        return img.clone();
    }
    let (filter, support): (fn(f64) -> f64, f64) = if resample == 2 { (bilinear, 1.0) } else { (bicubic, 2.0) };
    let vert = coefficients(img.height, height, filter, support);
    let half = 1i64 << (PRECISION_BITS - 1);
    // Horizontal pass over the rows the vertical pass needs.
    let (y_first, y_last) =
        if img.height != height { (vert[0].0, vert[height - 1].0 + vert[height - 1].1.len()) } else { (0, img.height) };
    let tmp = if img.width != width {
        let horiz = coefficients(img.width, width, filter, support);
        let mut data = vec![0u8; width * (y_last - y_first) * 3];
        for (ty, y) in (y_first..y_last).enumerate() {
            let row = &img.data[y * img.width * 3..(y + 1) * img.width * 3];
            for (xx, (xmin, k)) in horiz.iter().enumerate() {
                for c in 0..3 {
                    let mut acc = half;
                    for (i, w) in k.iter().enumerate() {
                        acc += row[(xmin + i) * 3 + c] as i64 * *w as i64;
                    }
                    data[(ty * width + xx) * 3 + c] = clip8(acc);
                }
            }
        }
        RgbImage::new(width, y_last - y_first, data)
    } else {
        img.crop(0, y_first, img.width, y_last - y_first)
    };
    if img.height == height {
        return tmp;
    }
    let mut data = vec![0u8; width * height * 3];
    for (yy, (ymin, k)) in vert.iter().enumerate() {
        let y0 = ymin - y_first;
        for x in 0..width {
            for c in 0..3 {
                let mut acc = half;
                for (i, w) in k.iter().enumerate() {
                    acc += tmp.data[((y0 + i) * width + x) * 3 + c] as i64 * *w as i64;
                }
                data[(yy * width + x) * 3 + c] = clip8(acc);
            }
        }
    }
    RgbImage::new(width, height, data)
}

/// transformers' `select_best_resolution`: most effective pixels, then least waste. Sizes are (height, width).
pub fn select_best_resolution(orig: (usize, usize), pinpoints: &[(usize, usize)]) -> (usize, usize) {
    let (oh, ow) = (orig.0 as f64, orig.1 as f64);
    let mut best = pinpoints[0];
    let mut max_eff = 0i64;
    let mut min_waste = i64::MAX;
    for &(h, w) in pinpoints {
        let scale = (w as f64 / ow).min(h as f64 / oh);
        let (dw, dh) = ((ow * scale) as i64, (oh * scale) as i64);
        let eff = (dw * dh).min((orig.0 * orig.1) as i64);
        let waste = (w * h) as i64 - eff;
        if eff > max_eff || (eff == max_eff && waste < min_waste) {
            max_eff = eff;
            min_waste = waste;
            best = (h, w);
        }
    }
    best
}

/// transformers' `get_patch_output_size`: the aspect-preserving size inside `target` (height, width).
fn patch_output_size(orig: (usize, usize), target: (usize, usize)) -> (usize, usize) {
    let (oh, ow) = orig;
    let (th, tw) = target;
    let sw = tw as f64 / ow as f64;
    let sh = th as f64 / oh as f64;
    if sw < sh {
        ((oh as f64 * sw).ceil().min(th as f64) as usize, tw)
    } else {
        (th, (ow as f64 * sh).ceil().min(tw as f64) as usize)
    }
}

/// The 8-bit views fed to the vision tower for one image, base view first.
#[derive(Clone, Debug, PartialEq)]
pub struct ImagePatches {
    /// Each `size x size` RGB (base view, then the anyres grid row by row).
    pub views: Vec<RgbImage>,
    /// The source image size (height, width).
    pub orig_hw: (usize, usize),
    /// false for images of a multi-image prompt (base view only, padded to a square first).
    pub anyres: bool,
}

impl ImagePatches {
    /// Normalised pixels `[views, 3, size, size]` (CHW per view), as `pixel_values`.
    pub fn pixel_values(&self, cfg: &ProcessorConfig) -> Vec<f32> {
        let mut out = Vec::with_capacity(self.views.len() * 3 * cfg.size.0 * cfg.size.1);
        for v in &self.views {
            for c in 0..3 {
                let (m, s) = (cfg.mean[c], cfg.std[c]);
                out.extend(v.data.chunks_exact(3).map(|p| ((p[c] as f64 * cfg.rescale_factor) as f32 - m) / s));
            }
        }
        out
    }
}

/// Splits one image the way the processor does for a single-image prompt (anyres).
pub fn anyres_views(img: &RgbImage, cfg: &ProcessorConfig) -> ImagePatches {
    let (sh, sw) = cfg.size;
    let orig = (img.height, img.width);
    let best = select_best_resolution(orig, &cfg.pinpoints);
    let (nh, nw) = patch_output_size(orig, best);
    let resized = resize(img, nw, nh, cfg.resample);
    let padded = resized.pad_centered(best.1, best.0, [0, 0, 0]);
    let mut views = vec![resize(img, sw, sh, cfg.resample)];
    for y in (0..best.0).step_by(sh) {
        for x in (0..best.1).step_by(sw) {
            views.push(padded.crop(x, y, sw, sh));
        }
    }
    ImagePatches { views, orig_hw: orig, anyres: true }
}

/// One image of a multi-image prompt: padded to a square with the mean colour, resized, base view only.
pub fn base_view(img: &RgbImage, cfg: &ProcessorConfig) -> ImagePatches {
    let side = img.width.max(img.height);
    let fill = cfg.mean.map(|m| (m * 255.0) as u8);
    let square = if img.width == img.height { img.clone() } else { img.pad_centered(side, side, fill) };
    ImagePatches {
        views: vec![resize(&square, cfg.size.1, cfg.size.0, cfg.resample)],
        orig_hw: (img.height, img.width),
        anyres: false,
    }
}

/// Where the anyres features of one image land: the patch grid, the unpadded crop of the feature
/// grid and, when `anyres_max_N` applies, the size it is bilinearly shrunk to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AnyresGrid {
    /// Patches (rows, cols) of the best resolution.
    pub patches: (usize, usize),
    /// Unpadded crop of the (rows*grid, cols*grid) feature map: (row0, col0, height, width).
    pub crop: (usize, usize, usize, usize),
    /// Target (height, width) of the bilinear shrink, if any.
    pub shrink: Option<(usize, usize)>,
}

impl AnyresGrid {
    pub fn new(cfg: &LlavaConfig, orig_hw: (usize, usize)) -> Self {
        let g = cfg.vision.grid();
        let best = select_best_resolution(orig_hw, &cfg.pinpoints);
        let patches = (best.0 / cfg.vision.image_size, best.1 / cfg.vision.image_size);
        let (ch, cw) = (g * patches.0, g * patches.1);
        let (oh, ow) = (orig_hw.0 as f64, orig_hw.1 as f64);
        let crop = if ow / oh > cw as f64 / ch as f64 {
            let new_h = round7(oh * (cw as f64 / ow));
            let pad = (ch - new_h.min(ch)) / 2;
            (pad, 0, ch - 2 * pad, cw)
        } else {
            let new_w = round7(ow * (ch as f64 / oh));
            let pad = (cw - new_w.min(cw)) / 2;
            (0, pad, ch, cw - 2 * pad)
        };
        let (h, w) = (crop.2, crop.3);
        let ratio = ((h * w) as f64 / (cfg.max_num_patches * g * g) as f64).sqrt();
        let shrink =
            (ratio > 1.1).then(|| (((h as f64) / ratio).floor() as usize, ((w as f64) / ratio).floor() as usize));
        Self { patches, crop, shrink }
    }

    /// Feature rows and columns after the crop and the shrink.
    pub fn out_hw(&self) -> (usize, usize) {
        self.shrink.unwrap_or((self.crop.2, self.crop.3))
    }
}

/// `int(round(x, 7))` as Python computes it.
fn round7(x: f64) -> usize {
    ((x * 1e7).round() / 1e7) as usize
}

/// Number of placeholder tokens one image takes in the prompt.
pub fn num_image_tokens(cfg: &LlavaConfig, patches: &ImagePatches) -> usize {
    let base = cfg.vision.tokens();
    if !patches.anyres || patches.views.len() == 1 {
        return base + 1;
    }
    let (h, w) = AnyresGrid::new(cfg, patches.orig_hw).out_hw();
    base + h * w + h
}
