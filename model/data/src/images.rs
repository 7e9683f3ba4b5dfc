//! PNG output and colour maps.

use crate::error::{Error, IoContext, Result};
use std::io::BufWriter;
use std::path::Path;

/// Writes an 8-bit RGB PNG from `[H, W, 3]` floats in [0, 1] (clamped), atomically.
pub fn write_rgb(path: &Path, width: u32, height: u32, rgb: &[f32]) -> Result<()> {
    assert_eq!(rgb.len(), (width * height * 3) as usize);
    let bytes: Vec<u8> = rgb.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8).collect();
    write_bytes(path, width, height, &bytes)
}

/// Writes an 8-bit grayscale PNG (e.g. instance-id masks), atomically.
pub fn write_gray8(path: &Path, width: u32, height: u32, values: &[u8]) -> Result<()> {
    assert_eq!(values.len(), (width * height) as usize);
    write_png(path, width, height, values, png::ColorType::Grayscale, png::BitDepth::Eight)
}

/// Writes a 16-bit grayscale PNG (e.g. depth in millimetres), atomically.
pub fn write_gray16(path: &Path, width: u32, height: u32, values: &[u16]) -> Result<()> {
    assert_eq!(values.len(), (width * height) as usize);
    let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
    write_png(path, width, height, &bytes, png::ColorType::Grayscale, png::BitDepth::Sixteen)
}

/// Writes instance ids as a grayscale PNG: 8-bit when every id fits a byte, else 16-bit.
pub fn write_ids(path: &Path, width: u32, height: u32, ids: &[u16]) -> Result<()> {
    if ids.iter().all(|&i| i <= 255) {
        let bytes: Vec<u8> = ids.iter().map(|&i| i as u8).collect();
        write_gray8(path, width, height, &bytes)
    } else {
        write_gray16(path, width, height, ids)
    }
}

/// Writes an 8-bit RGB PNG from `[H, W, 3]` bytes, atomically.
pub fn write_rgb8(path: &Path, width: u32, height: u32, bytes: &[u8]) -> Result<()> {
    assert_eq!(bytes.len(), (width * height * 3) as usize);
    write_bytes(path, width, height, bytes)
}

fn write_bytes(path: &Path, width: u32, height: u32, bytes: &[u8]) -> Result<()> {
    write_png(path, width, height, bytes, png::ColorType::Rgb, png::BitDepth::Eight)
}

/// Reads an 8-bit PNG (gray, gray+alpha, RGB or RGBA) as (width, height, channels, bytes).
pub fn read_png8(path: &Path) -> Result<(u32, u32, usize, Vec<u8>)> {
    let err = |e: png::DecodingError| Error::invalid(path, format!("cannot read PNG: {e}"));
    let file = std::fs::File::open(path).at(path, "cannot read PNG")?;
    let mut dec = png::Decoder::new(std::io::BufReader::new(file));
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = dec.read_info().map_err(err)?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(err)?;
    buf.truncate(info.buffer_size());
    Ok((info.width, info.height, info.color_type.samples(), buf))
}

/// Reads an 8-bit PNG as the port's RGB image (gray and alpha converted like PIL's
/// `convert("RGB")`, alpha dropped).
pub fn read_rgb_image(path: &Path) -> Result<llava_onevision::RgbImage> {
    let (w, h, c, bytes) = read_png8(path)?;
    if !(1..=4).contains(&c) {
        return Err(Error::invalid(path, format!("{c} channels per pixel: expected gray, RGB or RGBA")));
    }
    Ok(llava_onevision::RgbImage::from_channels(w as usize, h as usize, c, &bytes))
}

/// Reads a 16-bit grayscale PNG (e.g. depth in millimetres) as (width, height, values).
pub fn read_gray16(path: &Path) -> Result<(u32, u32, Vec<u16>)> {
    let err = |e: png::DecodingError| Error::invalid(path, format!("cannot read PNG: {e}"));
    let file = std::fs::File::open(path).at(path, "cannot read PNG")?;
    let mut reader = png::Decoder::new(std::io::BufReader::new(file)).read_info().map_err(err)?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(err)?;
    if info.bit_depth != png::BitDepth::Sixteen || info.color_type != png::ColorType::Grayscale {
        return Err(Error::invalid(path, "expected a 16-bit grayscale PNG"));
    }
    let values = buf[..info.buffer_size()].chunks(2).map(|b| u16::from_be_bytes([b[0], b[1]])).collect();
    Ok((info.width, info.height, values))
}

/// An 8-bit RGB PNG of `[H, W, 3]` bytes, in memory (e.g. a frame served over HTTP).
pub fn encode_rgb8(width: u32, height: u32, bytes: &[u8]) -> Result<Vec<u8>> {
    assert_eq!(bytes.len(), (width * height * 3) as usize);
    let mut out = Vec::new();
    encode_png(&mut out, width, height, bytes, png::ColorType::Rgb, png::BitDepth::Eight)
        .map_err(|e| Error::input(format!("cannot encode PNG: {e}")))?;
    Ok(out)
}

fn encode_png(
    to: impl std::io::Write,
    width: u32,
    height: u32,
    bytes: &[u8],
    color: png::ColorType,
    depth: png::BitDepth,
) -> std::result::Result<(), png::EncodingError> {
    let mut enc = png::Encoder::new(to, width, height);
    enc.set_color(color);
    enc.set_depth(depth);
    let mut w = enc.write_header()?;
    w.write_image_data(bytes)?;
    w.finish()
}

fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    bytes: &[u8],
    color: png::ColorType,
    depth: png::BitDepth,
) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        crate::io::create_dir(dir)?;
    }
    crate::io::write_atomic_with(path, |tmp| {
        let file = std::fs::File::create(tmp).at(tmp, "cannot write PNG")?;
        encode_png(BufWriter::new(file), width, height, bytes, color, depth)
            .map_err(|e| Error::invalid(tmp, format!("cannot write PNG: {e}")))
    })
}

/// A perceptual blue-to-yellow ramp for t in [0, 1] (piecewise linear "viridis"-like).
pub fn ramp(t: f32) -> [f32; 3] {
    const STOPS: [[f32; 3]; 5] = [
        [0.267, 0.005, 0.329],
        [0.230, 0.322, 0.546],
        [0.128, 0.567, 0.551],
        [0.369, 0.789, 0.383],
        [0.993, 0.906, 0.144],
    ];
    let t = t.clamp(0.0, 1.0) * 4.0;
    let i = (t.floor() as usize).min(3);
    let f = t - i as f32;
    std::array::from_fn(|k| STOPS[i][k] * (1.0 - f) + STOPS[i + 1][k] * f)
}

/// Depth map (near = yellow, far = blue; empty pixels black) from expected depth and alpha.
pub fn depth_to_rgb(depth: &[f32], alpha: &[f32]) -> Vec<f32> {
    let valid: Vec<f32> = depth.iter().zip(alpha).filter(|(_, a)| **a > 0.5).map(|(d, _)| *d).collect();
    let lo = valid.iter().cloned().fold(f32::INFINITY, f32::min);
    let hi = valid.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
    depth
        .iter()
        .zip(alpha)
        .flat_map(|(&d, &a)| if a <= 0.5 || !(hi > lo) { [0.0; 3] } else { ramp(1.0 - (d - lo) / (hi - lo)) })
        .collect()
}

/// A stable pseudo-random colour per id (-1 = black).
pub fn id_color(id: i32) -> [f32; 3] {
    if id < 0 {
        return [0.0; 3];
    }
    let mut h = (id as u32).wrapping_mul(0x9E37_79B9) ^ 0x85EB_CA6B;
    h ^= h >> 15;
    h = h.wrapping_mul(0xC2B2_AE35);
    h ^= h >> 13;
    [
        0.25 + 0.75 * ((h & 0xFF) as f32 / 255.0),
        0.25 + 0.75 * (((h >> 8) & 0xFF) as f32 / 255.0),
        0.25 + 0.75 * (((h >> 16) & 0xFF) as f32 / 255.0),
    ]
}
