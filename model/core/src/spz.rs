//! Niantic's `.spz` files: compressed 3D Gaussians, as Spark, SuperSplat and Niantic's own `spz`
//! library read them: often a tenth of an Inria `.ply`'s size.
//!
//! The whole file is one gzip member. Its payload is a 16-byte little-endian header — magic
//! `0x5053474e` ("NGSP"), version (u32), the number of Gaussians N (u32), SH degree (u8, 0..=3),
//! fractional bits of the positions (u8), flags (u8, bit 0: antialiased) and a reserved byte —
//! then one block per attribute, each over all N Gaussians in order:
//!
//! | block | bytes per Gaussian | encoding |
//! |---|---|---|
//! | positions | 9 | x, y, z as 24-bit signed fixed point (`round(v * 2^bits)`), little-endian |
//! | alphas | 1 | `round(sigmoid(opacity logit) * 255)` |
//! | colours | 3 | SH DC `c` as `round((c * 0.15 + 0.5) * 255)` |
//! | scales | 3 | log scale `s` as `round((s + 10) * 16)` |
//! | rotations | 3 (v2), 4 (v3) | v2: x, y, z of the unit quaternion with w >= 0, `round(v * 127.5 + 127.5)` |
//! | SH rest | 9, 24 or 45 | `v * 128 + 128` to a bucket, per coefficient, channel (r, g, b) innermost |
//!
//! Every byte is clamped to 0..=255. The SH rest buckets are 8 (degree 1) and 16 (degrees 2 and 3),
//! i.e. 5 and 4 significant bits. A v2 rotation's w is rebuilt as `sqrt(1 - x² - y² - z²)`. A v3
//! rotation is "smallest three" in a little-endian 32-bit word: it holds, in its top 2 bits, the
//! index (in x, y, z, w order) of the component of largest magnitude, taken positive and rebuilt
//! from the others; below it the other three, each as a sign bit over a 9-bit magnitude `|v| /
//! sqrt(1/2) * 511`, the last of them (highest index) in the lowest 10 bits, as Niantic's reader
//! unpacks them.
//!
//! [`write`] writes version 2 with 12 fractional bits, which every spz reader loads;
//! [`encode_version`] also writes version 3. [`parse`] reads versions 2 and 3 with any fractional
//! bits up to 24. The cloud's coordinates are stored as they are (no axis flip: what Niantic's
//! `ply_to_spz` does by default), and its SH rest is reordered between the Inria `f_rest_*` order
//! (channel-major) and spz's (channel innermost). An `.spz` holds no extra per-Gaussian channels:
//! writing drops the cloud's [`extra`](GaussianCloud::extra) fields (identity, language features).
//!
//! Everything but the Gaussian count and the SH degree is lossy. Errors of a round trip through
//! [`encode`] and [`parse`] for values within the format's range: the bound (half a quantisation
//! step, or as derived in the tests) and the largest error measured (`spz::tests`: random degree-3
//! clouds, and 120 000 rotations, 20 000 of them near 180°):
//!
//! | attribute | range held | bound | measured max |
//! |---|---|---|---|
//! | position | \|v\| < 2048 | 2^-13 = 1.22e-4 | 1.22e-4 |
//! | opacity, after the sigmoid | all | 0.5/255 = 1.96e-3 | 1.96e-3 |
//! | SH DC | \|c\| <= 3.33 | 0.5/255/0.15 = 1.31e-2 | 1.31e-2 |
//! | log scale | -10 ..= 5.94 | 1/32 = 3.13e-2 | 3.12e-2 |
//! | rotation v2: 1 - \|q·q'\| of the unit quaternions | all | sqrt(3)/255 = 6.8e-3 (13°) | 5.6e-3 (12°) |
//! | rotation v3: 1 - \|q·q'\| | all | 6 (sqrt(1/2)/1022)² = 2.9e-6 (0.28°) | 1.7e-6 (0.21°) |
//! | SH rest, degree 1 | \|v\| <= 1 | 4/128 = 3.13e-2 | 3.12e-2 |
//! | SH rest, degrees 2 and 3 | \|v\| <= 1 | 8/128 = 6.25e-2 | 6.25e-2 |
//!
//! A v2 rotation keeps x, y and z to half a byte's step (1/255) but rebuilds w from them, so a
//! quaternion with w near 0 (a rotation near 180°) loses most, far more than one near w = 1. v3
//! holds every rotation within 0.3°. The SH rest is rounded once to its bucket (Niantic rounds to
//! 1/128 first, then to the bucket, which can be off by half a 1/128 step more); the bytes are of
//! the same form and decode alike in any reader.
//!
//! Opacity: a byte of 0 or 255 would be a logit of ∓∞, so it reads back as sigmoid⁻¹ of 0.25/255
//! (resp. 1 - 0.25/255), which stays within the same bound. Values outside the ranges above are
//! clamped, with one [warning](crate::error::warn) per write saying how many; a position outside
//! ±2048 is refused (it would not be a nearby point, but one on the other side of the scene).
//! Non-finite values are refused; a zero quaternion is written as the identity (the renderer's
//! policy).
//!
//! Reading refuses, with an error naming the file, anything but one complete gzip member whose
//! payload is exactly the header plus N Gaussians of the header's version and degree: version 1
//! (float16 positions) and versions above 3, extension blocks (flag bit 1), a degree above 3, and
//! a count the gzip stream cannot hold (deflate expands at most 1032-fold) are refused before
//! anything is allocated for them, and no more of the payload than the header promises (plus one
//! byte) is ever decompressed.

use crate::GaussianCloud;
use crate::error::{Error, IoContext, Result};
use flate2::Compression;
use flate2::bufread::GzDecoder;
use flate2::write::GzEncoder;
use std::io::{Read, Write};
use std::path::Path;

/// "NGSP", little-endian.
const MAGIC: u32 = 0x5053_474e;
/// Bytes of the payload's header.
const HEADER: usize = 16;
/// The first two bytes of every gzip stream.
const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];
/// Fractional bits of the positions written: 1/4096 steps, within ±2048.
const FRACTIONAL_BITS: u8 = 12;
/// The most fractional bits read (with 24, a 24-bit position holds only |v| < 1/2).
const MAX_FRACTIONAL_BITS: u8 = 24;
/// Niantic's scale of the SH DC colour (0.15, not SH_C0 = 0.28, so that DC values a little
/// outside the displayable range survive).
const COLOR_SCALE: f64 = 0.15;
/// An opacity byte of 0 or 255 reads back as this far inside (0, 1) (a finite logit).
const ALPHA_EDGE: f64 = 0.25 / 255.0;
/// The most Gaussians read or written: 2^27 (a GaussianCloud of them is ~30 GB).
const MAX_POINTS: u64 = 1 << 27;
/// Deflate's largest expansion: 258 bytes out of each 2 bits in, i.e. at most 1032 : 1.
const MAX_DEFLATE_RATIO: u64 = 1032;
const FLAG_ANTIALIASED: u8 = 0x1;
const FLAG_EXTENSIONS: u8 = 0x2;
/// SH coefficients per channel beyond DC, by degree.
const COEFFS: [usize; 4] = [0, 3, 8, 15];

/// Bytes per Gaussian of a payload of `version` (2 or 3) and SH `degree` (0..=3).
fn bytes_per_point(version: u32, degree: usize) -> usize {
    9 + 1 + 3 + 3 + if version >= 3 { 4 } else { 3 } + 3 * COEFFS[degree]
}

/// A byte from a real value, rounded and clamped; `clamped` counts values outside 0..=255.
fn to_byte(v: f64, clamped: &mut usize) -> u8 {
    let r = v.round();
    if !(0.0..=255.0).contains(&r) {
        *clamped += 1;
    }
    r.clamp(0.0, 255.0) as u8
}

/// SH rest bucket (in steps of 1/128) of coefficient `k` (0-based, beyond DC): 8 for degree 1
/// (k < 3), 16 for degrees 2 and 3 (Niantic's 5 and 4 significant bits).
fn sh_bucket(k: usize) -> f64 {
    if k < 3 { 8.0 } else { 16.0 }
}

/// `cloud` as the bytes of a version-2 `.spz` file (what [`write`] writes). The cloud's
/// [`extra`](GaussianCloud::extra) channels are dropped: the format cannot hold them.
///
/// # Errors
/// [`Error::Input`] when the cloud's SH rest is not of degree 0..=3 (`rest_per_gaussian` 0, 9,
/// 24 or 45), its attributes are not one per Gaussian, a value is not finite, a position lies
/// outside ±2048, or it holds more than 2^27 Gaussians.
pub fn encode(cloud: &GaussianCloud) -> Result<Vec<u8>> {
    encode_version(cloud, 2)
}

/// `cloud` as the bytes of a `.spz` file of `version` 2 or 3 (3: rotations to 9 bits + sign in
/// "smallest three" order, one byte more per Gaussian; readers older than version 3 load only
/// version 2). Errors as [`encode`].
pub fn encode_version(cloud: &GaussianCloud, version: u32) -> Result<Vec<u8>> {
    let fail = |m: String| Error::input(format!("cannot write as .spz: {m}"));
    if version != 2 && version != 3 {
        return Err(fail(format!("version {version}: only versions 2 and 3 are written")));
    }
    let n = cloud.len();
    let rest = cloud.rest_per_gaussian;
    let degree = match COEFFS.iter().position(|&k| 3 * k == rest) {
        Some(d) => d,
        None => {
            return Err(fail(format!(
                "{rest} SH rest values per Gaussian is no SH degree .spz holds (0, 9, 24 or 45: degree 0 to 3)"
            )));
        }
    };
    let lens = [
        ("log_scales", cloud.log_scales.len()),
        ("quats", cloud.quats.len()),
        ("opacity_logits", cloud.opacity_logits.len()),
        ("sh_dc", cloud.sh_dc.len()),
    ];
    for (name, len) in lens {
        if len != n {
            return Err(fail(format!("{name} holds {len} entries for {n} Gaussians")));
        }
    }
    if cloud.sh_rest.len() != n * rest {
        return Err(fail(format!("sh_rest holds {} values, not {n} x {rest}", cloud.sh_rest.len())));
    }
    if n as u64 > MAX_POINTS {
        return Err(fail(format!("{n} Gaussians: at most {MAX_POINTS} are written")));
    }
    for i in 0..n {
        let attributes: [(&str, &[f32]); 5] = [
            ("position", &cloud.means[i]),
            ("log scale", &cloud.log_scales[i]),
            ("rotation", &cloud.quats[i]),
            ("opacity", std::slice::from_ref(&cloud.opacity_logits[i])),
            ("SH DC", &cloud.sh_dc[i]),
        ];
        for (name, v) in attributes.into_iter().chain([("SH rest", &cloud.sh_rest[i * rest..(i + 1) * rest])]) {
            if let Some(x) = v.iter().find(|x| !x.is_finite()) {
                return Err(fail(format!("Gaussian {i}: its {name} holds {x}, not a finite number")));
            }
        }
    }

    let mut raw = Vec::with_capacity(HEADER + n * bytes_per_point(version, degree));
    raw.extend_from_slice(&MAGIC.to_le_bytes());
    raw.extend_from_slice(&version.to_le_bytes());
    raw.extend_from_slice(&(n as u32).to_le_bytes());
    raw.extend_from_slice(&[degree as u8, FRACTIONAL_BITS, 0, 0]);
    // positions
    let scale = f64::from(1u32 << FRACTIONAL_BITS);
    let limit = f64::from(1u32 << 23);
    for (i, m) in cloud.means.iter().enumerate() {
        for (axis, &v) in ["x", "y", "z"].iter().zip(m) {
            let q = (f64::from(v) * scale).round();
            if !(-limit..limit).contains(&q) {
                return Err(fail(format!(
                    "Gaussian {i} has {axis} = {v}, outside the ±{} that 24-bit positions with {FRACTIONAL_BITS} \
                     fractional bits hold",
                    limit / scale
                )));
            }
            raw.extend_from_slice(&(q as i32).to_le_bytes()[..3]);
        }
    }
    let mut ignored = 0;
    // alphas (the sigmoid is in 0..=1: nothing to clamp)
    for &l in &cloud.opacity_logits {
        raw.push(to_byte(sigmoid(f64::from(l)) * 255.0, &mut ignored));
    }
    // colours
    let mut clamped_dc = 0;
    for dc in &cloud.sh_dc {
        for &c in dc {
            raw.push(to_byte((f64::from(c) * COLOR_SCALE + 0.5) * 255.0, &mut clamped_dc));
        }
    }
    // scales
    let mut clamped_scale = 0;
    for s in &cloud.log_scales {
        for &v in s {
            raw.push(to_byte((f64::from(v) + 10.0) * 16.0, &mut clamped_scale));
        }
    }
    // rotations
    for &q in &cloud.quats {
        let [w, x, y, z] = unit_quat(q);
        if version >= 3 {
            raw.extend_from_slice(&smallest_three([x, y, z, w]).to_le_bytes());
        } else {
            let s = if w < 0.0 { -127.5 } else { 127.5 };
            for v in [x, y, z] {
                raw.push(to_byte(v * s + 127.5, &mut ignored));
            }
        }
    }
    // SH rest: Inria's channel-major f_rest (all of r's coefficients, then g's, then b's) to spz's
    // coefficient-major order (channel innermost), each rounded once, to its bucket (a multiple of
    // the bucket from 128, as Niantic's bytes are; any reader decodes them as (b - 128) / 128).
    let k_per = COEFFS[degree];
    let mut clamped_sh = 0;
    for i in 0..n {
        let g = &cloud.sh_rest[i * rest..(i + 1) * rest];
        for k in 0..k_per {
            let bucket = sh_bucket(k);
            for c in 0..3 {
                let v = f64::from(g[c * k_per + k]);
                clamped_sh += usize::from(v.abs() > 1.0);
                let steps = (v * 128.0 / bucket).clamp(-64.0, 64.0).round();
                raw.push(to_byte(steps * bucket + 128.0, &mut ignored));
            }
        }
    }
    debug_assert_eq!(raw.len(), HEADER + n * bytes_per_point(version, degree));
    let clamped: Vec<String> = [
        (clamped_dc, "SH DC values outside ±3.33"),
        (clamped_scale, "log scales outside -10..=5.94"),
        (clamped_sh, "SH rest values outside ±1"),
    ]
    .iter()
    .filter(|(k, _)| *k > 0)
    .map(|(k, what)| format!("{k} {what}"))
    .collect();
    if !clamped.is_empty() {
        crate::error::warn(format!(".spz: clamped to the format's range: {} (of {n} Gaussians)", clamped.join(", ")));
    }
    let mut gz = GzEncoder::new(Vec::with_capacity(raw.len() / 4), Compression::default());
    gz.write_all(&raw).and_then(|_| gz.finish()).map_err(|e| fail(format!("gzip failed: {e}")))
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// `q` (w, x, y, z) normalised; the identity when it cannot be (the renderer's policy for zero
/// quaternions).
fn unit_quat(q: [f32; 4]) -> [f64; 4] {
    match splat_kernels::project::normalize_quat(q) {
        Some(_) => {
            let q = q.map(f64::from);
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            q.map(|v| v / n)
        }
        None => [1.0, 0.0, 0.0, 0.0],
    }
}

/// A unit quaternion (x, y, z, w order) as a v3 "smallest three" word.
fn smallest_three(q: [f64; 4]) -> u32 {
    let largest = (1..4).fold(0, |b, i| if q[i].abs() > q[b].abs() { i } else { b });
    let negate = q[largest] < 0.0;
    let mut word = largest as u32;
    for (i, &v) in q.iter().enumerate() {
        if i != largest {
            let sign = u32::from((v < 0.0) != negate);
            let mag = (v.abs() / std::f64::consts::FRAC_1_SQRT_2 * 511.0).round().min(511.0) as u32;
            word = (word << 10) | (sign << 9) | mag;
        }
    }
    word
}

/// A v3 "smallest three" word as a quaternion (x, y, z, w order).
fn from_smallest_three(mut word: u32) -> [f64; 4] {
    let largest = (word >> 30) as usize;
    let mut q = [0.0; 4];
    let mut sum = 0.0;
    for i in (0..4).rev() {
        if i != largest {
            let v = f64::from(word & 511) / 511.0 * std::f64::consts::FRAC_1_SQRT_2;
            q[i] = if word & 512 != 0 { -v } else { v };
            sum += v * v;
            word >>= 10;
        }
    }
    q[largest] = (1.0 - sum).max(0.0).sqrt();
    q
}

/// Writes `cloud` as a version-2 `.spz` file, atomically (temp file + rename). Its
/// [`extra`](GaussianCloud::extra) channels are dropped (the format cannot hold them); errors as
/// [`encode`], naming `path`.
pub fn write(path: &Path, cloud: &GaussianCloud) -> Result<()> {
    let bytes = encode(cloud).map_err(|e| match e {
        Error::Input(m) => Error::invalid(path, m),
        e => e,
    })?;
    crate::io::write_atomic_with(path, |tmp| {
        let mut f = std::fs::File::create(tmp).at(tmp, "cannot write")?;
        f.write_all(&bytes).at(tmp, "cannot write")?;
        f.sync_all().at(tmp, "cannot write")
    })
}

/// Reads a `.spz` file.
pub fn read(path: &Path) -> Result<GaussianCloud> {
    let bytes = std::fs::read(path).at(path, "cannot read")?;
    parse(&bytes, path)
}

/// Reads a Gaussian file of either format: `.spz` when its name ends in `.spz` (any case) or it
/// starts with the gzip magic, an Inria-layout `.ply` ([`crate::ply`]) otherwise.
pub fn read_any(path: &Path) -> Result<GaussianCloud> {
    let bytes = std::fs::read(path).at(path, "cannot read")?;
    let named_spz = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("spz"));
    if named_spz || bytes.starts_with(&GZIP_MAGIC) { parse(&bytes, path) } else { crate::ply::parse(&bytes, path) }
}

/// Reads from `r` until `buf` is full or the stream ends; the bytes read.
fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(k) => got += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// Parses `.spz` bytes; `src` names the input in errors. The header's count is checked against
/// what the gzip stream can hold before anything is allocated for it, and no more than the header
/// promises is decompressed.
pub fn parse(bytes: &[u8], src: impl AsRef<Path>) -> Result<GaussianCloud> {
    let src = src.as_ref();
    let err = |m: String| Error::invalid(src, m);
    if !bytes.starts_with(&GZIP_MAGIC) {
        let hint = if bytes.starts_with(b"ply") { " (it is a .ply file)" } else { "" };
        return Err(err(format!("not a .spz file: not gzip-compressed (no gzip magic 1f 8b at its start){hint}")));
    }
    let gz_err = |e: std::io::Error| err(format!("corrupt or truncated gzip stream: {e}"));
    let mut gz = GzDecoder::new(bytes);
    let mut head = [0u8; HEADER];
    let got = read_up_to(&mut gz, &mut head).map_err(gz_err)?;
    if got < HEADER {
        return Err(err(format!("not a .spz file: its payload is {got} bytes, shorter than the 16-byte header")));
    }
    let u32_at = |o: usize| u32::from_le_bytes(head[o..o + 4].try_into().expect("4 bytes"));
    let magic = u32_at(0);
    if magic != MAGIC {
        return Err(err(format!(
            "not a .spz file: its payload starts with {magic:#010x}, not the magic {MAGIC:#010x} (\"NGSP\")"
        )));
    }
    let version = u32_at(4);
    match version {
        2 | 3 => {}
        1 => return Err(err("unsupported .spz version 1 (float16 positions): versions 2 and 3 are read".into())),
        v => return Err(err(format!("unsupported .spz version {v}: versions 2 and 3 are read"))),
    }
    let n = u64::from(u32_at(8));
    let [degree, bits, flags, _reserved] = [head[12], head[13], head[14], head[15]];
    if degree > 3 {
        return Err(err(format!("SH degree {degree}: .spz holds degrees 0 to 3")));
    }
    let degree = usize::from(degree);
    if bits > MAX_FRACTIONAL_BITS {
        return Err(err(format!("{bits} fractional bits for 24-bit positions: at most {MAX_FRACTIONAL_BITS}")));
    }
    if flags & FLAG_EXTENSIONS != 0 {
        return Err(err("the file holds extension blocks (flag bit 1), which are not supported".into()));
    }
    if n > MAX_POINTS {
        return Err(err(format!("the header declares {n} Gaussians: at most {MAX_POINTS} are read")));
    }
    let stride = bytes_per_point(version, degree);
    let expected = n * stride as u64;
    if expected > (bytes.len() as u64).saturating_mul(MAX_DEFLATE_RATIO) {
        return Err(err(format!(
            "truncated: the header declares {n} Gaussians of {stride} bytes ({expected} bytes) but a {}-byte gzip \
             stream cannot hold that many",
            bytes.len()
        )));
    }
    let mut body = Vec::new();
    (&mut gz).take(expected + 1).read_to_end(&mut body).map_err(gz_err)?;
    if (body.len() as u64) < expected {
        return Err(err(format!(
            "truncated: the header declares {n} Gaussians of {stride} bytes ({expected} bytes after the header) but \
             only {} bytes follow",
            body.len()
        )));
    }
    if body.len() as u64 > expected {
        return Err(err(format!(
            "the payload holds more than the header's {n} Gaussians of {stride} bytes ({expected} bytes after the \
             16-byte header): the count disagrees with the payload"
        )));
    }
    // The end of the stream (its CRC and length are checked there), and nothing after it.
    let mut probe = [0u8; 1];
    if read_up_to(&mut gz, &mut probe).map_err(gz_err)? != 0 {
        return Err(err("the payload holds more than the header declares".into()));
    }
    let after = gz.into_inner().len();
    if after > 0 {
        return Err(err(format!("{after} bytes follow the gzip stream: the file is not one .spz")));
    }
    if flags & FLAG_ANTIALIASED != 0 {
        crate::error::warn(format!(
            "{}: its Gaussians are marked antialiased (trained with a mip filter); rendered without it",
            src.display()
        ));
    }
    Ok(decode(&body, n as usize, version, degree, bits))
}

/// The cloud of a payload body (after the header) already checked to hold `n` Gaussians of
/// `version` and `degree`.
fn decode(body: &[u8], n: usize, version: u32, degree: usize, bits: u8) -> GaussianCloud {
    let rot_bytes = if version >= 3 { 4 } else { 3 };
    let k_per = COEFFS[degree];
    let (positions, rest) = body.split_at(9 * n);
    let (alphas, rest) = rest.split_at(n);
    let (colors, rest) = rest.split_at(3 * n);
    let (scales, rest) = rest.split_at(3 * n);
    let (rotations, sh) = rest.split_at(rot_bytes * n);
    debug_assert_eq!(sh.len(), 3 * k_per * n);
    let unit = 1.0 / f64::from(1u32 << bits);
    let triple = |b: &[u8], f: &dyn Fn(u8) -> f64| [f(b[0]) as f32, f(b[1]) as f32, f(b[2]) as f32];
    let means = positions
        .chunks_exact(9)
        .map(|p| {
            let c = |o: usize| (i32::from_le_bytes([0, p[o], p[o + 1], p[o + 2]]) >> 8) as f64 * unit;
            [c(0) as f32, c(3) as f32, c(6) as f32]
        })
        .collect();
    let opacity_logits = alphas
        .iter()
        .map(|&b| {
            let a = (f64::from(b) / 255.0).clamp(ALPHA_EDGE, 1.0 - ALPHA_EDGE);
            (a / (1.0 - a)).ln() as f32
        })
        .collect();
    let sh_dc = colors.chunks_exact(3).map(|b| triple(b, &|b| (f64::from(b) / 255.0 - 0.5) / COLOR_SCALE)).collect();
    let log_scales = scales.chunks_exact(3).map(|b| triple(b, &|b| f64::from(b) / 16.0 - 10.0)).collect();
    let quats = rotations
        .chunks_exact(rot_bytes)
        .map(|r| {
            let [x, y, z, w] = if version >= 3 {
                from_smallest_three(u32::from_le_bytes([r[0], r[1], r[2], r[3]]))
            } else {
                let [x, y, z] = [r[0], r[1], r[2]].map(|b| f64::from(b) / 127.5 - 1.0);
                [x, y, z, (1.0 - x * x - y * y - z * z).max(0.0).sqrt()]
            };
            [w as f32, x as f32, y as f32, z as f32]
        })
        .collect();
    // spz's coefficient-major SH rest (channel innermost) to Inria's channel-major f_rest order
    let rest = 3 * k_per;
    let mut sh_rest = vec![0f32; n * rest];
    if rest > 0 {
        for (i, g) in sh.chunks_exact(rest).enumerate() {
            for k in 0..k_per {
                for c in 0..3 {
                    sh_rest[i * rest + c * k_per + k] = (f32::from(g[k * 3 + c]) - 128.0) / 128.0;
                }
            }
        }
    }
    GaussianCloud {
        means,
        log_scales,
        quats,
        opacity_logits,
        sh_dc,
        sh_rest,
        rest_per_gaussian: rest,
        extra: Default::default(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// A cloud of `n` random Gaussians of SH `degree`, every value within the format's range: most
    /// within a room, every 50th near the ±2048 edge of the positions, every 7th turned by nearly
    /// 180° (w near 0, where v2 rotations lose most); with an extra channel, which spz drops.
    fn random_cloud(n: usize, degree: usize, seed: u64) -> GaussianCloud {
        let mut r = Rng::new(seed);
        let rest = 3 * COEFFS[degree];
        let mut c = GaussianCloud { rest_per_gaussian: rest, ..Default::default() };
        for i in 0..n {
            let span = if i % 50 == 0 { 2047.9 } else { 20.0 };
            c.means.push([(); 3].map(|_| r.range(-span, span)));
            c.log_scales.push([(); 3].map(|_| r.range(-10.0, 5.9375)));
            c.opacity_logits.push(r.range(-9.0, 9.0));
            c.sh_dc.push([(); 3].map(|_| r.range(-3.33, 3.33)));
            let mut q = [(); 4].map(|_| r.normal());
            if i % 7 == 0 {
                q[0] = r.range(-0.02, 0.02);
            }
            c.quats.push(q);
            c.sh_rest.extend((0..rest).map(|_| r.range(-1.0, 1.0)));
        }
        c.extra.insert("identity".into(), (1, vec![0.5; n]));
        c
    }

    /// Largest round-trip errors per attribute.
    #[derive(Debug, Default)]
    struct Errors {
        position: f64,
        alpha: f64,
        dc: f64,
        log_scale: f64,
        /// 1 - |q·q'| of the unit quaternions.
        rotation: f64,
        sh1: f64,
        sh23: f64,
    }

    fn errors(a: &GaussianCloud, b: &GaussianCloud) -> Errors {
        assert_eq!((a.len(), a.rest_per_gaussian), (b.len(), b.rest_per_gaussian));
        assert_eq!(b.sh_rest.len(), b.len() * b.rest_per_gaussian);
        let d = |x: f32, y: f32| (f64::from(x) - f64::from(y)).abs();
        let max3 = |x: &[f32; 3], y: &[f32; 3]| (0..3).map(|k| d(x[k], y[k])).fold(0.0, f64::max);
        let mut e = Errors::default();
        let k_per = a.rest_per_gaussian / 3;
        for i in 0..a.len() {
            e.position = e.position.max(max3(&a.means[i], &b.means[i]));
            let s = |l: f32| sigmoid(f64::from(l));
            e.alpha = e.alpha.max((s(a.opacity_logits[i]) - s(b.opacity_logits[i])).abs());
            e.dc = e.dc.max(max3(&a.sh_dc[i], &b.sh_dc[i]));
            e.log_scale = e.log_scale.max(max3(&a.log_scales[i], &b.log_scales[i]));
            let (qa, qb) = (unit_quat(a.quats[i]), unit_quat(b.quats[i]));
            let dot: f64 = (0..4).map(|k| qa[k] * qb[k]).sum();
            e.rotation = e.rotation.max(1.0 - dot.abs());
            for c in 0..3 {
                for k in 0..k_per {
                    let j = i * a.rest_per_gaussian + c * k_per + k;
                    let err = d(a.sh_rest[j], b.sh_rest[j]);
                    if k < 3 {
                        e.sh1 = e.sh1.max(err);
                    } else {
                        e.sh23 = e.sh23.max(err);
                    }
                }
            }
        }
        e
    }

    /// The quantisation bounds (half a step) of everything but the rotation, plus f32 rounding.
    fn assert_within_bounds(e: &Errors) {
        let eps = 1e-6;
        assert!(e.position <= 2f64.powi(-13) + 1e-9, "{e:?}");
        assert!(e.alpha <= 0.5 / 255.0 + eps, "{e:?}");
        assert!(e.dc <= 0.5 / 255.0 / 0.15 + eps, "{e:?}");
        assert!(e.log_scale <= 1.0 / 32.0 + eps, "{e:?}");
        assert!(e.sh1 <= 4.0 / 128.0 + eps, "{e:?}");
        assert!(e.sh23 <= 8.0 / 128.0 + eps, "{e:?}");
    }

    /// v2: x, y, z are within d = 1/255 each (half of a 2/255 step) and w is rebuilt from them. The
    /// worst case is w = 0: then 1 - q.q' = |q - q'|^2 / 2 = (|e|^2 + w'^2) / 2 with w'^2 = -2 v.e - |e|^2,
    /// i.e. -v.e <= |v|_1 d <= sqrt(3) d = 6.8e-3 (v along a diagonal, every byte off the same way);
    /// 7e-3 leaves room for f32.
    const V2_ROTATION_BOUND: f64 = 7e-3;

    /// v3: each of the three smaller components is within d = sqrt(1/2) / 511 / 2 = 6.9e-4 and the
    /// largest L (>= 1/2), rebuilt from them, within sum(|s|) d / L <= 3 d (all four 1/2), so
    /// 1 - q.q' = |q - q'|^2 / 2 <= (3 d^2 + 9 d^2) / 2 = 6 d^2 = 2.9e-6 (0.28 degrees).
    const V3_ROTATION_BOUND: f64 = 6.0 * (0.5 / 511.0 / 2.0 / 511.0 / 2.0);

    fn payload(file: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        flate2::read::GzDecoder::new(file).read_to_end(&mut out).unwrap();
        out
    }

    fn gzip(payload: &[u8]) -> Vec<u8> {
        let mut gz = GzEncoder::new(Vec::new(), Compression::default());
        gz.write_all(payload).unwrap();
        gz.finish().unwrap()
    }

    #[test]
    fn degree3_round_trip_within_quantisation_bounds() {
        let cloud = random_cloud(600, 3, 11);
        let bytes = encode(&cloud).unwrap();
        let back = parse(&bytes, "mem.spz").unwrap();
        assert!(back.extra.is_empty(), "spz holds no extra channels");
        let e = errors(&cloud, &back);
        println!("v2 round trip, degree 3, {} Gaussians: {e:?}", cloud.len());
        assert_within_bounds(&e);
        assert!(e.rotation <= V2_ROTATION_BOUND, "{e:?}");
        let mut no_extra = cloud.clone();
        no_extra.extra.clear();
        let ply = crate::ply::encode(&no_extra).len();
        println!(
            "{} Gaussians of degree 3 (random values): .spz {} bytes, .ply {ply} bytes ({:.1}x smaller)",
            cloud.len(),
            bytes.len(),
            ply as f64 / bytes.len() as f64
        );
        // the header as written
        let p = payload(&bytes);
        assert_eq!(p[..16], [b'N', b'G', b'S', b'P', 2, 0, 0, 0, 0x58, 0x02, 0, 0, 3, 12, 0, 0]);
        assert_eq!(p.len(), 16 + 600 * (19 + 45));
    }

    #[test]
    fn v3_round_trip_and_bit_layout() {
        let cloud = random_cloud(600, 3, 12);
        let bytes = encode_version(&cloud, 3).unwrap();
        assert_eq!(payload(&bytes)[4], 3);
        let back = parse(&bytes, "mem.spz").unwrap();
        let e = errors(&cloud, &back);
        println!("v3 round trip, degree 3, {} Gaussians: {e:?}", cloud.len());
        assert_within_bounds(&e);
        assert!(e.rotation <= V3_ROTATION_BOUND, "{e:?}");
        // Niantic's layout: index of the largest (x, y, z, w order) in the top 2 bits, then the
        // others in index order from the high bits down (the highest index in the lowest 10 bits),
        // each a sign bit over a 9-bit magnitude.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let word = smallest_three([0.5, -0.5, 0.0, h]);
        assert_eq!(word, (3 << 30) | (361 << 20) | ((512 | 361) << 10), "{word:#034b}");
        let q = from_smallest_three(word);
        assert!((q[0] - 0.5).abs() < 1e-3 && (q[1] + 0.5).abs() < 1e-3 && q[2] == 0.0 && (q[3] - h).abs() < 1e-3);
        // a negative largest component: the whole quaternion is negated
        assert_eq!(smallest_three([0.1, 0.2, -0.9, 0.3]) >> 30, 2);
        let q = from_smallest_three(smallest_three([0.1, 0.2, -0.9, 0.3]));
        assert!(q[2] > 0.0 && q[0] < 0.0 && q[3] < 0.0, "{q:?}");
    }

    #[test]
    fn v2_rotation_error_over_many_rotations() {
        // the v2 rotation bound: random rotations, and a sweep of w down to 0
        let mut r = Rng::new(5);
        let mut quats: Vec<[f32; 4]> = (0..100_000).map(|_| [(); 4].map(|_| r.normal())).collect();
        for i in 0..20_000 {
            let w = i as f32 / 20_000.0 * 0.05;
            let v = [r.normal(), r.normal(), r.normal()];
            let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            quats.push([w, v[0] / n, v[1] / n, v[2] / n]);
        }
        let n = quats.len();
        let cloud = GaussianCloud {
            means: vec![[0.0; 3]; n],
            log_scales: vec![[-3.0; 3]; n],
            quats,
            opacity_logits: vec![0.0; n],
            sh_dc: vec![[0.0; 3]; n],
            ..Default::default()
        };
        for version in [2, 3] {
            let back = parse(&encode_version(&cloud, version).unwrap(), "mem.spz").unwrap();
            let e = errors(&cloud, &back);
            let angle = 2.0 * (1.0 - e.rotation).acos().to_degrees();
            println!("v{version} rotations ({n}): max 1 - |q.q'| = {:.3e} ({angle:.2} degrees)", e.rotation);
            let bound = if version == 2 { V2_ROTATION_BOUND } else { V3_ROTATION_BOUND };
            assert!(e.rotation <= bound, "v{version}: {e:?}");
        }
    }

    #[test]
    fn degree0_round_trip_and_exact_bytes() {
        let cloud = GaussianCloud {
            means: vec![[1.0, -1.0 / 4096.0, 0.0], [2047.0, -2048.0, 0.5]],
            log_scales: vec![[-10.0, 0.0, 5.9375], [-20.0, 9.0, -4.0]],
            quats: vec![[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]],
            opacity_logits: vec![0.0, 100.0],
            sh_dc: vec![[0.0, -10.0, 10.0], [1.0, -1.0, 0.0]],
            ..Default::default()
        };
        let bytes = encode(&cloud).unwrap();
        let p = payload(&bytes);
        assert_eq!(p[12], 0, "degree 0");
        assert_eq!(p.len(), 16 + 2 * 19);
        let body = &p[16..];
        assert_eq!(body[..9], [0x00, 0x10, 0x00, 0xff, 0xff, 0xff, 0, 0, 0], "1, -1/4096, 0 in 24 bits");
        assert_eq!(body[18..20], [128, 255], "alphas: sigmoid 0.5 and 1");
        assert_eq!(body[20..23], [128, 0, 255], "DC 0 and the clamped ±10");
        assert_eq!(body[26..29], [0, 160, 255], "log scales -10, 0, 5.9375");
        assert_eq!(body[32..38], [128, 128, 128, 128, 128, 128], "identity, and a zero quaternion as the identity");
        let back = parse(&bytes, "mem.spz").unwrap();
        assert_eq!(back.means, cloud.means);
        assert_eq!(back.rest_per_gaussian, 0);
        assert!(back.sh_rest.is_empty());
        // the identity as near as v2 bytes get (0 is between two of them: 127.5)
        let near_identity = |q: [f32; 4]| q[0] > 0.9999 && q[1..].iter().all(|v| v.abs() <= 1.0 / 255.0 + 1e-6);
        assert!(near_identity(back.quats[0]) && near_identity(back.quats[1]), "{:?}", back.quats);
        assert!(back.opacity_logits[1].is_finite() && back.opacity_logits[1] > 5.0, "{:?}", back.opacity_logits);
        let e = errors(&cloud, &back);
        assert!(e.position == 0.0 && e.alpha <= 0.5 / 255.0 + 1e-6, "{e:?}");
        // a cloud of no Gaussians
        let empty = parse(&encode(&GaussianCloud::default()).unwrap(), "mem.spz").unwrap();
        assert!(empty.is_empty());
    }

    #[test]
    fn degree1_and_2_round_trip() {
        for degree in [1, 2] {
            let cloud = random_cloud(200, degree, 20 + degree as u64);
            let back = parse(&encode(&cloud).unwrap(), "mem.spz").unwrap();
            assert_eq!(back.rest_per_gaussian, 3 * COEFFS[degree]);
            assert_within_bounds(&errors(&cloud, &back));
        }
    }

    #[test]
    fn clouds_spz_cannot_hold_are_refused() {
        let msg = |c: &GaussianCloud| encode(c).unwrap_err().to_string();
        let mut c = random_cloud(10, 1, 1);
        c.rest_per_gaussian = 6;
        c.sh_rest.truncate(60);
        assert!(msg(&c).contains("no SH degree"), "{}", msg(&c));
        let mut c = random_cloud(10, 0, 1);
        c.means[3][1] = 2048.0;
        assert!(msg(&c).contains("Gaussian 3 has y = 2048"), "{}", msg(&c));
        let mut c = random_cloud(10, 0, 1);
        c.opacity_logits[4] = f32::NAN;
        assert!(msg(&c).contains("Gaussian 4: its opacity holds NaN"), "{}", msg(&c));
        let mut c = random_cloud(10, 0, 1);
        c.quats.pop();
        assert!(msg(&c).contains("quats holds 9 entries for 10"), "{}", msg(&c));
        assert!(encode_version(&random_cloud(2, 0, 1), 4).unwrap_err().to_string().contains("version 4"));
    }

    #[test]
    fn bad_inputs_are_errors_naming_the_file() {
        let src = Path::new("some/dir/bad.spz");
        let good = encode(&random_cloud(10, 1, 3)).unwrap();
        let p = payload(&good);
        let with = |f: &dyn Fn(&mut Vec<u8>)| {
            let mut q = p.clone();
            f(&mut q);
            gzip(&q)
        };
        let set_u32 = |at: usize, v: u32| move |q: &mut Vec<u8>| q[at..at + 4].copy_from_slice(&v.to_le_bytes());
        let mut bad_crc = good.clone();
        let k = bad_crc.len() - 6;
        bad_crc[k] ^= 0xff;
        let mut after = good.clone();
        after.extend_from_slice(b"junk");
        let cases: Vec<(&str, Vec<u8>, &str)> = vec![
            ("not gzip", b"ply\nformat binary_little_endian 1.0\n".to_vec(), "not gzip-compressed (no gzip magic"),
            ("empty", vec![], "not gzip-compressed"),
            ("truncated gzip", good[..good.len() / 2].to_vec(), "corrupt or truncated gzip"),
            ("gzip header only", good[..12].to_vec(), "corrupt or truncated gzip"),
            ("bad CRC", bad_crc, "corrupt or truncated gzip"),
            ("short payload", gzip(&p[..10]), "10 bytes, shorter than the 16-byte header"),
            ("wrong magic", with(&|q| q[0] = b'X'), "not the magic 0x5053474e"),
            ("version 1", with(&set_u32(4, 1)), "version 1 (float16"),
            ("version 4", with(&set_u32(4, 4)), "unsupported .spz version 4"),
            ("degree 5", with(&|q| q[12] = 5), "SH degree 5"),
            ("fractional bits", with(&|q| q[13] = 40), "40 fractional bits"),
            ("extensions", with(&|q| q[14] = 2), "extension blocks"),
            ("one Gaussian more", with(&set_u32(8, 11)), "declares 11 Gaussians of 28 bytes (308 bytes after"),
            ("one Gaussian less", with(&set_u32(8, 9)), "more than the header's 9 Gaussians"),
            ("absurd count", with(&set_u32(8, 100_000_000)), "cannot hold that many"),
            ("count over the limit", with(&set_u32(8, u32::MAX)), "at most 134217728 are read"),
            ("trailing payload byte", with(&|q| q.push(0)), "more than the header's 10 Gaussians"),
            ("bytes after the gzip stream", after, "4 bytes follow the gzip stream"),
        ];
        for (name, bytes, expect) in cases {
            let e = parse(&bytes, src).expect_err(name);
            let m = e.to_string();
            assert!(matches!(e, Error::Invalid { .. }), "{name}: {m}");
            assert!(m.starts_with("some/dir/bad.spz: "), "{name}: {m}");
            assert!(m.contains(expect), "{name}: `{m}` lacks `{expect}`");
        }
        // the degree changes the size: degree 1 read as degree 2 is too short
        let m = parse(&with(&|q| q[12] = 2), src).unwrap_err().to_string();
        assert!(m.contains("truncated"), "{m}");
        // a v2 payload labelled v3 (one rotation byte more per Gaussian)
        let m = parse(&with(&set_u32(4, 3)), src).unwrap_err().to_string();
        assert!(m.contains("truncated"), "{m}");
    }

    #[test]
    fn files_written_and_read_by_name_or_magic() {
        let dir = std::env::temp_dir().join(format!("chatsplat-spz-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let cloud = random_cloud(50, 3, 4);
        let spz = dir.join("scene.SPZ");
        write(&spz, &cloud).unwrap();
        assert!(!dir.join("scene.SPZ.tmp").exists());
        let a = read(&spz).unwrap();
        assert_eq!(read_any(&spz).unwrap(), a);
        // spz bytes under another name: found by the gzip magic
        let other = dir.join("scene.bin");
        std::fs::copy(&spz, &other).unwrap();
        assert_eq!(read_any(&other).unwrap(), a);
        // a .ply is read as one
        let ply = dir.join("scene.ply");
        crate::ply::write(&ply, &cloud).unwrap();
        assert_eq!(read_any(&ply).unwrap(), crate::ply::read(&ply).unwrap());
        // a .ply named .spz: an error that says what it is
        let named = dir.join("ply.spz");
        std::fs::copy(&ply, &named).unwrap();
        let m = read_any(&named).unwrap_err().to_string();
        assert!(m.contains("ply.spz") && m.contains("it is a .ply file"), "{m}");
        // writing a cloud spz cannot hold names the file and leaves nothing
        let mut bad = cloud.clone();
        bad.means[0][0] = 1e6;
        let m = write(&dir.join("far.spz"), &bad).unwrap_err().to_string();
        assert!(m.contains("far.spz") && m.contains("outside the ±2048"), "{m}");
        assert!(!dir.join("far.spz").exists() && !dir.join("far.spz.tmp").exists());
        let m = read(&dir.join("missing.spz")).unwrap_err().to_string();
        assert!(m.contains("missing.spz") && m.contains("cannot read"), "{m}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn size_of_100k_gaussians_of_degree_3() {
        // Real-looking: the synthetic tabletop's surfels (the positions, scales and colours of a
        // scene), with SH rest of trained-scene magnitudes (mostly small, higher bands smaller);
        // then the same jittered as training leaves Gaussians (positions off the grid by ~2 mm,
        // any rotation, varied opacity, scale and colour); and i.i.d. uniform values, the worst case.
        let (mut scene, _) = crate::data::synth::gaussians::tabletop(7, 283);
        let n = scene.len();
        let mut r = Rng::new(9);
        scene.rest_per_gaussian = 45;
        scene.sh_rest = (0..n * 45).map(|j| r.normal() * if j % 15 < 3 { 0.08 } else { 0.03 }).collect();
        scene.extra.clear();
        let mut jittered = scene.clone();
        for i in 0..n {
            jittered.means[i] = jittered.means[i].map(|v| v + 0.002 * r.normal());
            jittered.log_scales[i] = jittered.log_scales[i].map(|v| v + 0.3 * r.normal());
            jittered.sh_dc[i] = jittered.sh_dc[i].map(|v| v + 0.1 * r.normal());
            jittered.quats[i] = [(); 4].map(|_| r.normal());
            jittered.opacity_logits[i] = 2.0 + 3.0 * r.normal();
        }
        let mut random = random_cloud(n, 3, 10);
        random.extra.clear();
        for (what, cloud) in
            [("tabletop + SH", &scene), ("jittered tabletop + SH", &jittered), ("uniform random", &random)]
        {
            let spz = encode(cloud).unwrap();
            let ply = crate::ply::encode(cloud).len();
            let raw = 16 + n * bytes_per_point(2, 3);
            println!(
                "{n} Gaussians of degree 3 ({what}): .ply {ply} bytes, .spz {} bytes ({:.2} bytes per Gaussian; \
                 {raw} before gzip): {:.1}x smaller",
                spz.len(),
                spz.len() as f64 / n as f64,
                ply as f64 / spz.len() as f64
            );
            assert!(spz.len() * 4 < ply, "spz at least 4x smaller than ply");
            let back = parse(&spz, "mem.spz").unwrap();
            assert_eq!(back.len(), n);
        }
        assert!(n > 90_000, "{n}");
    }
}
