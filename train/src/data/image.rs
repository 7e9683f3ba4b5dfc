//! Image decoding and resampling shared by every loader.
//!
//! * Colour images are 8-bit PNG (gray, gray+alpha, RGB, RGBA; 16-bit PNGs are reduced to 8 bits)
//!   or baseline/progressive 8-bit JPEG (`.jpg` / `.jpeg`, gray or RGB). Alpha is composited
//!   over the [`Background`], then the image is box-filtered by the integer downscale factor `k`
//!   (output `floor(W/k) x floor(H/k)`; a partial last block is dropped).
//! * Masks and depth maps are downscaled by taking the top-left sample of each `k x k` block,
//!   so ids stay exact and depth is never blended across edges.

use super::Background;
use std::io::{BufReader, Read};
use std::path::Path;

/// `"<path>: <msg>"`.
pub(crate) fn err(path: &Path, msg: impl std::fmt::Display) -> String {
    format!("{}: {msg}", path.display())
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
pub(crate) fn decode(path: &Path) -> Result<Image8, String> {
    let img = if is_jpeg(path) {
        decode_jpeg(path)?
    } else {
        let (width, height, channels, bytes) = model::images::read_png8(path)?;
        Image8 { width, height, channels, bytes }
    };
    let need = img.width as usize * img.height as usize * img.channels;
    if !(1..=4).contains(&img.channels) || img.bytes.len() != need || need == 0 {
        return Err(err(
            path,
            format!("decoded {} bytes for a {}x{} image with {} channels", img.bytes.len(), img.width, img.height, img.channels),
        ));
    }
    Ok(img)
}

fn decode_jpeg(path: &Path) -> Result<Image8, String> {
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
    Ok(Image8 {
        width: info.width as u32,
        height: info.height as u32,
        channels,
        bytes,
    })
}

/// `(floor(w/k), floor(h/k))`, or an error if that is empty.
pub(crate) fn downscaled_size(path: &Path, w: u32, h: u32, k: u32) -> Result<(u32, u32), String> {
    let (dw, dh) = (w / k.max(1), h / k.max(1));
    if dw == 0 || dh == 0 {
        return Err(err(path, format!("{w}x{h} is smaller than the downscale factor {k}")));
    }
    Ok((dw, dh))
}

impl Image8 {
    /// `[H/k, W/k, 3]` floats in [0, 1]: alpha composited over `background` at full resolution,
    /// then averaged over `k x k` blocks. Returns `(width, height, rgb)`.
    pub(crate) fn to_rgb(&self, path: &Path, k: u32, background: Background) -> Result<(u32, u32, Vec<f32>), String> {
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
                    let (c, a) = match ch {
                        1 => ([px[0]; 3], 255),
                        2 => ([px[0]; 3], px[1]),
                        3 => ([px[0], px[1], px[2]], 255),
                        _ => ([px[0], px[1], px[2]], px[3]),
                    };
                    let a = a as f32 / 255.0;
                    for q in 0..3 {
                        acc[q] += c[q] as f32 / 255.0 * a + bg * (1.0 - a);
                    }
                }
            }
            for q in 0..3 {
                out[q] = acc[q] * norm;
            }
        }
        Ok((dw, dh, rgb))
    }
}

/// Nearest-sample downscale of a `[h, w]` map (row stride `w`) to `[dh, dw]` by factor `k`
/// (the top-left sample of each block). The caller guarantees `full` covers `dh*k` rows.
pub(crate) fn subsample<T: Copy>(full: &[T], w: u32, dw: u32, dh: u32, k: u32) -> Vec<T> {
    (0..dh)
        .flat_map(|y| (0..dw).map(move |x| full[((y * k) * w + x * k) as usize]))
        .collect()
}

/// `"<path>: is AxB but its image is CxD"` unless the sizes agree.
pub(crate) fn check_size(path: &Path, got: (u32, u32), image: (u32, u32)) -> Result<(), String> {
    if got == image {
        Ok(())
    } else {
        Err(err(path, format!("is {}x{} but its image is {}x{}", got.0, got.1, image.0, image.1)))
    }
}

/// An 8-bit id mask (first channel of any 8-bit PNG) the size `(w, h)` of its image, downscaled
/// by nearest sample to `[h/k, w/k]`.
pub(crate) fn read_ids8(path: &Path, w: u32, h: u32, k: u32) -> Result<Vec<u8>, String> {
    let (mw, mh, mc, bytes) = model::images::read_png8(path)?;
    check_size(path, (mw, mh), (w, h))?;
    if mc == 0 || bytes.len() != mw as usize * mh as usize * mc {
        return Err(err(path, "mask has an unexpected pixel layout"));
    }
    let ids: Vec<u8> = bytes.chunks_exact(mc).map(|c| c[0]).collect();
    Ok(subsample(&ids, w, w / k, h / k, k))
}

/// A 16-bit grayscale PNG the size `(w, h)` of its image, times `scale`, downscaled by nearest
/// sample to `[h/k, w/k]`.
pub(crate) fn read_depth16(path: &Path, w: u32, h: u32, k: u32, scale: f32) -> Result<Vec<f32>, String> {
    let (dw, dh, raw) = model::images::read_gray16(path)?;
    check_size(path, (dw, dh), (w, h))?;
    if raw.len() != w as usize * h as usize {
        return Err(err(path, "depth map has an unexpected pixel layout"));
    }
    let full: Vec<f32> = raw.into_iter().map(|d| d as f32 * scale).collect();
    Ok(subsample(&full, w, w / k, h / k, k))
}

/// A label image: the first channel of an 8- or 16-bit PNG (lower bit depths are expanded to 8).
/// Returns `(width, height, values, sixteen_bit)`.
pub(crate) fn read_labels(path: &Path) -> Result<(u32, u32, Vec<u16>, bool), String> {
    let fail = |e: &dyn std::fmt::Display| err(path, format!("cannot read PNG: {e}"));
    let mut data = Vec::new();
    std::fs::File::open(path)
        .and_then(|mut f| f.read_to_end(&mut data))
        .map_err(|e| fail(&e))?;
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
    let values = buf
        .chunks_exact(step)
        .map(|c| if sixteen { u16::from_be_bytes([c[0], c[1]]) } else { c[0] as u16 })
        .collect();
    Ok((info.width, info.height, values, sixteen))
}

/// The `png`/`jpg`/`jpeg` files directly in `dir`, sorted by file name.
pub(crate) fn list_images(dir: &Path) -> Result<Vec<std::path::PathBuf>, String> {
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
