//! Image decoding and resampling shared by every loader.
//!
//! * Colour images are 8-bit PNG (gray, gray+alpha, RGB, RGBA; 16-bit PNGs are reduced to 8 bits)
//!   or baseline/progressive 8-bit JPEG (`.jpg` / `.jpeg`, gray or RGB). Alpha is composited
//!   over the [`Background`], then the image is box-filtered by the integer downscale factor `k`
//!   (output `floor(W/k) x floor(H/k)`; a partial last block is dropped).
//! * Masks and depth maps are downscaled by taking the top-left sample of each `k x k` block,
//!   so ids stay exact and depth is never blended across edges.
//! * A [`Remap`] (e.g. lens undistortion) resamples at full resolution, before the downscale:
//!   colours bilinearly (clamped to the edge), ids and depth by nearest sample (0 outside).

use super::Background;
use crate::error::{Error, Result};
use std::io::{BufReader, Read};
use std::path::Path;

/// `"<path>: <msg>"`.
pub(crate) fn err(path: &Path, msg: impl std::fmt::Display) -> Error {
    Error::invalid(path, msg.to_string())
}

/// Whether the extension says JPEG (`jpg` / `jpeg`, any case).
pub(crate) fn is_jpeg(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("jpg") || e.eq_ignore_ascii_case("jpeg"))
}

/// Whether the extension is one [`decode`] reads (`png`, `jpg`, `jpeg`, any case).
pub(crate) fn is_image(path: &Path) -> bool {
    is_jpeg(path) || path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("png"))
}

/// A decoded 8-bit image: `[height, width, channels]` bytes, with 1 (gray), 2 (gray + alpha),
/// 3 (RGB) or 4 (RGBA) channels.
pub(crate) struct Image8 {
    pub width: u32,
    pub height: u32,
    pub channels: usize,
    pub bytes: Vec<u8>,
}

/// Largest JPEG we agree to decode (bytes of output), so that a corrupt header cannot make us
/// allocate gigabytes.
const MAX_JPEG_BYTES: usize = 16384 * 16384 * 3;

/// Decodes a PNG or (by extension) JPEG colour image.
pub(crate) fn decode(path: &Path) -> Result<Image8> {
    let img = if is_jpeg(path) {
        decode_jpeg(path)?
    } else {
        let (width, height, channels, bytes) = crate::images::read_png8(path)?;
        Image8 { width, height, channels, bytes }
    };
    let need = img.width as usize * img.height as usize * img.channels;
    if !(1..=4).contains(&img.channels) || img.bytes.len() != need || need == 0 {
        return Err(err(
            path,
            format!(
                "decoded {} bytes for a {}x{} image with {} channels",
                img.bytes.len(),
                img.width,
                img.height,
                img.channels
            ),
        ));
    }
    Ok(img)
}

fn decode_jpeg(path: &Path) -> Result<Image8> {
    use jpeg_decoder::PixelFormat;
    let file = std::fs::File::open(path).map_err(|e| err(path, format!("cannot read JPEG: {e}")))?;
    let mut dec = jpeg_decoder::Decoder::new(BufReader::new(file));
    dec.set_max_decoding_buffer_size(MAX_JPEG_BYTES);
    dec.read_info().map_err(|e| err(path, format!("cannot decode JPEG: {e}")))?;
    let info = dec.info().ok_or_else(|| err(path, "cannot decode JPEG: no frame header"))?;
    let channels = match info.pixel_format {
        PixelFormat::L8 => 1,
        PixelFormat::RGB24 => 3,
        PixelFormat::CMYK32 => return Err(err(path, "CMYK JPEG images are not supported; convert to RGB")),
        PixelFormat::L16 => {
            return Err(err(path, "JPEG with more than 8 bits per sample is not supported; convert to 8-bit"));
        }
    };
    let bytes = dec.decode().map_err(|e| err(path, format!("cannot decode JPEG: {e}")))?;
    Ok(Image8 { width: info.width as u32, height: info.height as u32, channels, bytes })
}

/// `(floor(w/k), floor(h/k))`, or an error if that is empty.
pub(crate) fn downscaled_size(path: &Path, w: u32, h: u32, k: u32) -> Result<(u32, u32)> {
    let (dw, dh) = (w / k.max(1), h / k.max(1));
    if dw == 0 || dh == 0 {
        return Err(err(path, format!("{w}x{h} is smaller than the downscale factor {k}")));
    }
    Ok((dw, dh))
}

impl Image8 {
    /// `[H/k, W/k, 3]` floats in [0, 1]: alpha composited over `background` at full resolution,
    /// then averaged over `k x k` blocks. Returns `(width, height, rgb)`.
    pub(crate) fn to_rgb(&self, path: &Path, k: u32, background: Background) -> Result<(u32, u32, Vec<f32>)> {
        let (w, ch) = (self.width as usize, self.channels);
        let (dw, dh) = downscaled_size(path, self.width, self.height, k)?;
        let k = k as usize;
        let bg = background.value();
        let mut rgb = vec![0.0f32; dw as usize * dh as usize * 3];
        let norm = 1.0 / (k * k) as f32;
        for (o, out) in rgb.chunks_exact_mut(3).enumerate() {
            let (x, y) = (o % dw as usize, o / dw as usize);
            let mut acc = [0.0f32; 3];
            for sy in 0..k {
                let row = (y * k + sy) * w + x * k;
                for px in self.bytes[row * ch..(row + k) * ch].chunks_exact(ch) {
                    let c = composite(px, bg);
                    for q in 0..3 {
                        acc[q] += c[q];
                    }
                }
            }
            for q in 0..3 {
                out[q] = acc[q] * norm;
            }
        }
        Ok((dw, dh, rgb))
    }

    /// Like [`Image8::to_rgb`], but the full-resolution image is first resampled through `remap`
    /// (bilinearly, on the colours composited over `background`) and then box-filtered by `k`.
    pub(crate) fn to_rgb_remapped(
        &self,
        path: &Path,
        k: u32,
        background: Background,
        remap: &Remap,
    ) -> Result<(u32, u32, Vec<f32>)> {
        if (remap.width, remap.height) != (self.width, self.height) {
            return Err(err(
                path,
                format!(
                    "resampling map is {}x{} but the image is {}x{}",
                    remap.width, remap.height, self.width, self.height
                ),
            ));
        }
        let w = self.width as usize;
        let (dw, dh) = downscaled_size(path, self.width, self.height, k)?;
        let (k, dw, dh) = (k as usize, dw as usize, dh as usize);
        let bg = background.value();
        // Composite once per source pixel, then interpolate the colours.
        let full: Vec<[f32; 3]> = self.bytes.chunks_exact(self.channels).map(|px| composite(px, bg)).collect();
        let (sx, sy) = (remap.step_x, remap.step_y);
        let mut rgb = vec![0.0f32; dw * dh * 3];
        for y in 0..dh * k {
            let block_row = &mut rgb[(y / k) * dw * 3..(y / k + 1) * dw * 3];
            for (x, t) in remap.taps[y * w..y * w + dw * k].iter().enumerate() {
                let i = t.index as usize;
                let (a, b, c, d) = (full[i], full[i + sx], full[i + sy], full[i + sy + sx]);
                let out = &mut block_row[(x / k) * 3..(x / k) * 3 + 3];
                for q in 0..3 {
                    let top = a[q] + (b[q] - a[q]) * t.wx;
                    let bottom = c[q] + (d[q] - c[q]) * t.wx;
                    out[q] += top + (bottom - top) * t.wy;
                }
            }
        }
        let norm = 1.0 / (k * k) as f32;
        for v in &mut rgb {
            *v = (*v * norm).clamp(0.0, 1.0);
        }
        Ok((dw as u32, dh as u32, rgb))
    }
}

/// One pixel (1 to 4 channels) as RGB floats, alpha composited over the background `bg`.
#[inline]
fn composite(px: &[u8], bg: f32) -> [f32; 3] {
    let (c, a) = match px.len() {
        1 => ([px[0]; 3], 255),
        2 => ([px[0]; 3], px[1]),
        3 => ([px[0], px[1], px[2]], 255),
        _ => ([px[0], px[1], px[2]], px[3]),
    };
    let a = a as f32 / 255.0;
    [0, 1, 2].map(|q| c[q] as f32 / 255.0 * a + bg * (1.0 - a))
}

/// The bilinear footprint of one output pixel: the top-left source tap (row-major index) and the
/// weights of the right and lower neighbours.
#[derive(Clone, Copy)]
struct Tap {
    index: u32,
    wx: f32,
    wy: f32,
}

/// A precomputed resampling of a `width x height` image through a coordinate map (e.g. lens
/// undistortion), built once and applied to any number of images of that size.
///
/// Output pixel `(i, j)` takes its value from the source at the continuous position
/// `(u, v) = map(i + 0.5, j + 0.5)`, where source pixel `(x, y)` covers `[x, x+1) x [y, y+1)`:
///
/// * colours ([`Image8::to_rgb_remapped`]) are sampled bilinearly at array coordinates
///   `(u - 0.5, v - 0.5)`; positions outside the source take the nearest edge pixel (clamp);
/// * ids and depth ([`Remap::nearest`]) take the source pixel containing `(u, v)`, or 0
///   (`T::default()`) when `(u, v)` lies outside the source.
pub(crate) struct Remap {
    width: u32,
    height: u32,
    /// Per output pixel, row-major.
    taps: Vec<Tap>,
    /// Per output pixel: the nearest source pixel, or `u32::MAX` outside the source.
    nearest: Vec<u32>,
    /// Index offsets of the right and lower taps (0 for an image 1 pixel wide / high).
    step_x: usize,
    step_y: usize,
}

impl Remap {
    /// Evaluates `map` once per output pixel centre.
    pub(crate) fn new(width: u32, height: u32, mut map: impl FnMut(f64, f64) -> (f64, f64)) -> Self {
        let (w, h) = (width as usize, height as usize);
        assert!(w > 0 && h > 0 && (w * h) < u32::MAX as usize, "remap of a {w}x{h} image");
        // Clamps an array coordinate into [0, len - 1] (NaN -> 0) and splits it into the left
        // tap (at most len - 2, so that the right tap exists) and the right tap's weight.
        let axis = |s: f64, len: usize| -> (usize, f32) {
            let s = if s.is_nan() { 0.0 } else { s.clamp(0.0, (len - 1) as f64) };
            let i0 = (s.floor() as usize).min(len.saturating_sub(2));
            (i0, (s - i0 as f64) as f32)
        };
        let mut taps = Vec::with_capacity(w * h);
        let mut nearest = Vec::with_capacity(w * h);
        for j in 0..h {
            for i in 0..w {
                let (u, v) = map(i as f64 + 0.5, j as f64 + 0.5);
                let (x0, wx) = axis(u - 0.5, w);
                let (y0, wy) = axis(v - 0.5, h);
                taps.push(Tap { index: (y0 * w + x0) as u32, wx, wy });
                let inside = (0.0..w as f64).contains(&u) && (0.0..h as f64).contains(&v);
                nearest.push(if inside { (v as usize * w + u as usize) as u32 } else { u32::MAX });
            }
        }
        Self { width, height, taps, nearest, step_x: usize::from(w > 1), step_y: if h > 1 { w } else { 0 } }
    }

    /// A `[height, width]` id or depth map resampled by nearest sample; `T::default()` (0)
    /// where the source position lies outside the image.
    pub(crate) fn nearest<T: Copy + Default>(&self, src: &[T]) -> Vec<T> {
        assert_eq!(src.len(), self.nearest.len(), "remap of a map of another size");
        self.nearest.iter().map(|&s| if s == u32::MAX { T::default() } else { src[s as usize] }).collect()
    }
}

/// Nearest-sample downscale of a `[h, w]` map (row stride `w`) to `[dh, dw]` by factor `k`
/// (the top-left sample of each block). The caller guarantees `full` covers `dh*k` rows.
pub(crate) fn subsample<T: Copy>(full: &[T], w: u32, dw: u32, dh: u32, k: u32) -> Vec<T> {
    (0..dh).flat_map(|y| (0..dw).map(move |x| full[((y * k) * w + x * k) as usize])).collect()
}

/// `"<path>: is AxB but its image is CxD"` unless the sizes agree.
pub(crate) fn check_size(path: &Path, got: (u32, u32), image: (u32, u32)) -> Result<()> {
    if got == image {
        Ok(())
    } else {
        Err(err(path, format!("is {}x{} but its image is {}x{}", got.0, got.1, image.0, image.1)))
    }
}

/// An instance-id mask ([`read_ids_any`]) the size `(w, h)` of its image, downscaled
/// by nearest sample to `[h/k, w/k]`.
pub(crate) fn read_ids(path: &Path, w: u32, h: u32, k: u32) -> Result<Vec<u16>> {
    Ok(subsample(&read_ids_full(path, w, h)?, w, w / k, h / k, k))
}

/// [`read_ids`] at full resolution: `[h, w]` ids.
pub(crate) fn read_ids_full(path: &Path, w: u32, h: u32) -> Result<Vec<u16>> {
    let (mw, mh, ids) = read_ids_any(path)?;
    check_size(path, (mw, mh), (w, h))?;
    Ok(ids)
}

/// An instance-id PNG of any size as a dataset holds it: [`read_ids16_any`], an id above
/// [`MAX_INSTANCE_ID`] refused naming its pixel (the identity classifier has a class per id up
/// to the largest), so that no id is silently cut or wrapped.
pub(crate) fn read_ids_any(path: &Path) -> Result<(u32, u32, Vec<u16>)> {
    let (w, h, ids) = read_ids16_any(path)?;
    if let Some(p) = ids.iter().position(|&v| v > MAX_INSTANCE_ID) {
        return Err(err(
            path,
            format!(
                "holds instance id {} at pixel ({}, {}): ids above {MAX_INSTANCE_ID} are not supported (the identity \
                 classifier has a class per id up to the largest; renumber the objects 1..=N, as `chatsplat masks` \
                 writes them)",
                ids[p],
                p % w as usize,
                p / w as usize
            ),
        ));
    }
    Ok((w, h, ids))
}

/// The largest instance id a dataset's masks may hold (16-bit masks; ids need not be dense).
pub const MAX_INSTANCE_ID: u16 = 4095;

/// A PNG or (by its extension) JPEG colour image as the VLM port's 8-bit RGB image (gray and
/// alpha converted like PIL's `convert("RGB")`, alpha dropped).
pub fn read_rgb_any(path: &Path) -> Result<llava_onevision::RgbImage> {
    let img = decode(path)?;
    let (w, h) = (img.width as usize, img.height as usize);
    Ok(llava_onevision::RgbImage::from_channels(w, h, img.channels, &img.bytes))
}

/// An instance-id PNG of any size: its width, height and `[h, w]` 16-bit ids (0 = background).
///
/// The id is the pixel's value in a one-channel PNG: grayscale of any bit depth (8 or 16 bits
/// as tools write them) or a palette PNG's index (DEVA / Gaussian Grouping). An RGB(A) mask is
/// read only where its three channels agree (a gray mask saved as colour); a colour-coded mask
/// is refused naming a pixel, so that no id is read from one channel.
pub fn read_ids16_any(path: &Path) -> Result<(u32, u32, Vec<u16>)> {
    let fail = |e: &dyn std::fmt::Display| err(path, format!("cannot read PNG: {e}"));
    let file = std::fs::File::open(path).map_err(|e| fail(&e))?;
    let mut dec = png::Decoder::new(BufReader::new(file));
    dec.set_transformations(png::Transformations::IDENTITY);
    let mut reader = dec.read_info().map_err(|e| fail(&e))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| fail(&e))?;
    let (w, h) = (info.width as usize, info.height as usize);
    let (bits, samples, line) = (info.bit_depth as usize, info.color_type.samples(), info.line_size);
    if w == 0 || h == 0 || buf.len() < line * h || line * 8 < w * samples * bits {
        return Err(err(path, "mask has an unexpected pixel layout"));
    }
    let mut ids = Vec::with_capacity(w * h);
    for (y, row) in buf.chunks_exact(line).take(h).enumerate() {
        // sample `c` of pixel `x` of this row, unpacked from 1-16 bits
        let sample = |x: usize, c: usize| -> u16 {
            let i = x * samples + c;
            match bits {
                16 => u16::from_be_bytes([row[2 * i], row[2 * i + 1]]),
                8 => row[i] as u16,
                b => {
                    let per = 8 / b;
                    ((row[i / per] >> (8 - b * (i % per + 1))) & ((1u8 << b) - 1)) as u16
                }
            }
        };
        for x in 0..w {
            let v = sample(x, 0);
            if samples >= 3 && (sample(x, 1) != v || sample(x, 2) != v) {
                return Err(err(
                    path,
                    format!(
                        "is a colour-coded mask (pixel ({x}, {y}) is ({v}, {}, {})): instance ids must be one \
                         channel, a grayscale or palette PNG whose value is the id (0 = background)",
                        sample(x, 1),
                        sample(x, 2)
                    ),
                ));
            }
            ids.push(v);
        }
    }
    Ok((info.width, info.height, ids))
}

/// A 16-bit grayscale PNG the size `(w, h)` of its image, times `scale`, downscaled by nearest
/// sample to `[h/k, w/k]`.
pub(crate) fn read_depth16(path: &Path, w: u32, h: u32, k: u32, scale: f32) -> Result<Vec<f32>> {
    Ok(subsample(&read_depth16_full(path, w, h, scale)?, w, w / k, h / k, k))
}

/// [`read_depth16`] at full resolution: `[h, w]` depths.
pub(crate) fn read_depth16_full(path: &Path, w: u32, h: u32, scale: f32) -> Result<Vec<f32>> {
    let (dw, dh, raw) = crate::images::read_gray16(path)?;
    check_size(path, (dw, dh), (w, h))?;
    if raw.len() != w as usize * h as usize {
        return Err(err(path, "depth map has an unexpected pixel layout"));
    }
    Ok(raw.into_iter().map(|d| d as f32 * scale).collect())
}

/// A label image: the first channel of an 8- or 16-bit PNG (lower bit depths are expanded to 8).
/// Returns `(width, height, values, sixteen_bit)`.
pub(crate) fn read_labels(path: &Path) -> Result<(u32, u32, Vec<u16>, bool)> {
    let fail = |e: &dyn std::fmt::Display| err(path, format!("cannot read PNG: {e}"));
    let mut data = Vec::new();
    std::fs::File::open(path).and_then(|mut f| f.read_to_end(&mut data)).map_err(|e| fail(&e))?;
    let mut dec = png::Decoder::new(std::io::Cursor::new(data));
    dec.set_transformations(png::Transformations::EXPAND);
    let mut reader = dec.read_info().map_err(|e| fail(&e))?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| fail(&e))?;
    buf.truncate(info.buffer_size());
    let sixteen = info.bit_depth == png::BitDepth::Sixteen;
    let step = info.color_type.samples() * if sixteen { 2 } else { 1 };
    if step == 0 || buf.len() != info.width as usize * info.height as usize * step {
        return Err(err(path, "label image has an unexpected pixel layout"));
    }
    let values =
        buf.chunks_exact(step).map(|c| if sixteen { u16::from_be_bytes([c[0], c[1]]) } else { c[0] as u16 }).collect();
    Ok((info.width, info.height, values, sixteen))
}

/// The `png`/`jpg`/`jpeg` files directly in `dir`, sorted by file name.
pub(crate) fn list_images(dir: &Path) -> Result<Vec<std::path::PathBuf>> {
    let entries = std::fs::read_dir(dir).map_err(|e| err(dir, format!("cannot list images: {e}")))?;
    let mut files = Vec::new();
    for e in entries {
        let p = e.map_err(|e| err(dir, format!("cannot list images: {e}")))?.path();
        if p.is_file() && is_image(&p) {
            files.push(p);
        }
    }
    files.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    Ok(files)
}
