//! Inria-layout 3DGS `.ply` files (as written by Inria 3DGS, gsplat, Brush): one `vertex` element
//! with `x y z`, `f_dc_0..2`, `opacity` (logit), `scale_0..2` (log), `rot_0..3` (w, x, y, z), all
//! required, and optional normals, `f_rest_*`, plus any extra float properties (kept by name, grouped by the
//! prefix before the last `_`, e.g. `identity_0..15`).
//!
//! Reads `binary_little_endian`, `binary_big_endian` and `ascii`; writes `binary_little_endian`.

use crate::GaussianCloud;
use crate::error::{Error, IoContext, Result};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
    fn read(self, b: &[u8], big: bool) -> f32 {
        macro_rules! rd {
            ($t:ty, $n:expr) => {{
                let a: [u8; $n] = b[..$n].try_into().unwrap();
                (if big { <$t>::from_be_bytes(a) } else { <$t>::from_le_bytes(a) }) as f32
            }};
        }
        match self {
            Scalar::I8 => b[0] as i8 as f32,
            Scalar::U8 => b[0] as f32,
            Scalar::I16 => rd!(i16, 2),
            Scalar::U16 => rd!(u16, 2),
            Scalar::I32 => rd!(i32, 4),
            Scalar::U32 => rd!(u32, 4),
            Scalar::F32 => rd!(f32, 4),
            Scalar::F64 => rd!(f64, 8),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Format {
    Ascii,
    BinaryLe,
    BinaryBe,
}

/// The properties every Gaussian must have (no default is silently assumed for any of them).
const REQUIRED: [&str; 14] = [
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2",
    "rot_3",
];

/// Reads an Inria-layout `.ply` file.
pub fn read(path: &Path) -> Result<GaussianCloud> {
    let bytes = std::fs::read(path).at(path, "cannot read")?;
    parse(&bytes, path)
}

/// Parses `.ply` bytes; `src` names the input in errors. Counts in the header are checked
/// against the bytes present before anything is allocated.
pub fn parse(bytes: &[u8], src: impl AsRef<Path>) -> Result<GaussianCloud> {
    let src = src.as_ref();
    let err = |m: String| Error::invalid(src, m);
    let end = find_header_end(bytes).ok_or_else(|| err("not a PLY file (no `end_header` line)".to_string()))?;
    let header = std::str::from_utf8(&bytes[..end.0]).map_err(|_| err("PLY header is not UTF-8".to_string()))?;
    let mut lines = header.lines();
    if lines.next().map(str::trim) != Some("ply") {
        return Err(err("not a PLY file (missing `ply` magic)".to_string()));
    }
    let mut format = None;
    let mut count = None;
    let mut props: Vec<(String, Scalar)> = vec![];
    let mut in_vertex = false;
    let mut other_elements_before = false;
    let mut other_elements_after = false;
    for line in lines {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.as_slice() {
            ["format", f, _] => {
                format = Some(match *f {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::BinaryLe,
                    "binary_big_endian" => Format::BinaryBe,
                    other => return Err(err(format!("unsupported PLY format `{other}`"))),
                })
            }
            ["element", "vertex", n] => {
                count = Some(n.parse::<usize>().map_err(|_| err(format!("bad vertex count `{n}`")))?);
                in_vertex = true;
            }
            ["element", name, _] => {
                if count.is_none() {
                    other_elements_before = true;
                } else {
                    other_elements_after = true;
                }
                let _ = name;
                in_vertex = false;
            }
            ["property", "list", ..] if in_vertex => {
                return Err(err("list properties in the vertex element are not supported".to_string()));
            }
            ["property", ty, name] if in_vertex => {
                let s = Scalar::parse(ty).ok_or_else(|| err(format!("unknown property type `{ty}` for `{name}`")))?;
                props.push((name.to_string(), s));
            }
            _ => {}
        }
    }
    let format = format.ok_or_else(|| err("PLY header has no `format` line".to_string()))?;
    let n = count.ok_or_else(|| err("PLY header has no `element vertex` line".to_string()))?;
    if other_elements_before {
        return Err(err("elements before `vertex` are not supported".to_string()));
    }
    let index: BTreeMap<&str, usize> = props.iter().enumerate().map(|(i, (p, _))| (p.as_str(), i)).collect();
    for req in REQUIRED {
        if !index.contains_key(req) {
            let what = if ["x", "y", "z"].iter().all(|p| index.contains_key(p)) {
                " (a point cloud, not 3D Gaussians? no default is assumed for a Gaussian's opacity, scale, \
                 rotation or colour)"
            } else {
                ""
            };
            return Err(err(format!(
                "vertex element lacks the `{req}` property{what}: a 3DGS .ply has {}",
                REQUIRED.join(" ")
            )));
        }
    }
    let width = props.len();
    let body = &bytes[end.1..];
    // Every vertex takes at least one byte per property (ASCII: a digit and a separator), so a
    // count the body cannot hold is refused before allocating for it.
    let min_bytes = match format {
        Format::Ascii => n.checked_mul(width * 2),
        _ => n.checked_mul(props.iter().map(|(_, s)| s.size()).sum()),
    };
    if min_bytes.is_none_or(|b| b > body.len() + 1) {
        return Err(err(format!(
            "truncated: header declares {n} vertices of {width} properties but only {} bytes follow",
            body.len()
        )));
    }
    let mut values = vec![0f32; n * width];
    match format {
        Format::Ascii => {
            let text = std::str::from_utf8(body).map_err(|_| err("ASCII body is not UTF-8".to_string()))?;
            let mut it = text.split_ascii_whitespace();
            for (k, v) in values.iter_mut().enumerate() {
                let tok = it.next().ok_or_else(|| err(format!("truncated: vertex {} of {n} is missing", k / width)))?;
                *v = tok.parse::<f32>().map_err(|_| err(format!("bad number `{tok}` in vertex {}", k / width)))?;
            }
            if !other_elements_after && it.next().is_some() {
                return Err(err(format!(
                    "the body holds more than the header's {n} vertices: the vertex count disagrees with the body"
                )));
            }
        }
        Format::BinaryLe | Format::BinaryBe => {
            let stride: usize = props.iter().map(|(_, s)| s.size()).sum();
            if body.len() < n * stride {
                return Err(err(format!(
                    "truncated: header declares {n} vertices of {stride} bytes ({} bytes) but {} bytes follow",
                    n * stride,
                    body.len()
                )));
            }
            if !other_elements_after && body.len() > n * stride {
                return Err(err(format!(
                    "the body has {} bytes more than the header's {n} vertices of {stride} bytes: the vertex count \
                     disagrees with the body",
                    body.len() - n * stride
                )));
            }
            let big = format == Format::BinaryBe;
            for i in 0..n {
                let mut off = i * stride;
                for (j, (_, s)) in props.iter().enumerate() {
                    values[i * width + j] = s.read(&body[off..], big);
                    off += s.size();
                }
            }
        }
    }
    if let Some(k) = values.iter().position(|v| !v.is_finite()) {
        let (name, v) = (&props[k % width].0, values[k]);
        return Err(err(format!("vertex {} property `{name}` is not finite ({v})", k / width)));
    }
    let get = |name: &str| index.get(name).copied();
    let col = |j: Option<usize>, default: f32| -> Vec<f32> {
        (0..n).map(|i| j.map(|j| values[i * width + j]).unwrap_or(default)).collect()
    };
    let triple = |names: [&str; 3], default: f32| -> Vec<[f32; 3]> {
        let c: Vec<Vec<f32>> = names.iter().map(|nm| col(get(nm), default)).collect();
        (0..n).map(|i| [c[0][i], c[1][i], c[2][i]]).collect()
    };
    let mut cloud = GaussianCloud {
        means: triple(["x", "y", "z"], 0.0),
        log_scales: triple(["scale_0", "scale_1", "scale_2"], (0.01f32).ln()),
        sh_dc: triple(["f_dc_0", "f_dc_1", "f_dc_2"], 0.0),
        opacity_logits: col(get("opacity"), 2.0),
        ..Default::default()
    };
    let q: Vec<Vec<f32>> = ["rot_0", "rot_1", "rot_2", "rot_3"]
        .iter()
        .enumerate()
        .map(|(k, nm)| col(get(nm), if k == 0 { 1.0 } else { 0.0 }))
        .collect();
    cloud.quats = (0..n).map(|i| [q[0][i], q[1][i], q[2][i], q[3][i]]).collect();
    // f_rest_* in numeric order.
    let mut rest: Vec<(usize, usize)> = props
        .iter()
        .enumerate()
        .filter_map(|(j, (p, _))| p.strip_prefix("f_rest_").and_then(|k| k.parse().ok()).map(|k| (k, j)))
        .collect();
    rest.sort();
    cloud.rest_per_gaussian = rest.len();
    let vals = &values;
    cloud.sh_rest = (0..n).flat_map(|i| rest.iter().map(move |&(_, j)| vals[i * width + j])).collect();
    // Extra properties, grouped by prefix (`name_K`).
    let known = |p: &str| {
        matches!(p, "x" | "y" | "z" | "nx" | "ny" | "nz" | "opacity")
            || p.starts_with("f_dc_")
            || p.starts_with("f_rest_")
            || p.starts_with("scale_")
            || p.starts_with("rot_")
    };
    let mut groups: BTreeMap<String, Vec<(usize, usize)>> = BTreeMap::new();
    for (j, (p, _)) in props.iter().enumerate() {
        if known(p) {
            continue;
        }
        let (prefix, k) = match p.rsplit_once('_').and_then(|(a, b)| b.parse::<usize>().ok().map(|k| (a, k))) {
            Some((a, k)) => (a.to_string(), k),
            None => (p.clone(), 0),
        };
        groups.entry(prefix).or_default().push((k, j));
    }
    for (name, mut cols) in groups {
        cols.sort();
        let w = cols.len();
        let vals = &values;
        let data = (0..n).flat_map(|i| cols.iter().map(move |&(_, j)| vals[i * width + j])).collect();
        cloud.extra.insert(name, (w, data));
    }
    Ok(cloud)
}

/// Returns (header length up to and including `end_header`, body start).
fn find_header_end(bytes: &[u8]) -> Option<(usize, usize)> {
    let pat = b"end_header";
    let pos = bytes.windows(pat.len()).position(|w| w == pat)?;
    let mut body = pos + pat.len();
    if bytes.get(body) == Some(&b'\r') {
        body += 1;
    }
    if bytes.get(body) == Some(&b'\n') {
        body += 1;
    }
    Some((pos, body))
}

/// `cloud` as the bytes of a binary little-endian Inria-layout `.ply` (what [`write`] writes;
/// the viewer serves it to the browser's splat renderer).
pub fn encode(cloud: &GaussianCloud) -> Vec<u8> {
    let n = cloud.len();
    let mut names: Vec<String> =
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"].iter().map(|s| s.to_string()).collect();
    names.extend((0..cloud.rest_per_gaussian).map(|k| format!("f_rest_{k}")));
    names.push("opacity".into());
    names.extend(["scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"].map(String::from));
    for (name, (w, _)) in &cloud.extra {
        names.extend((0..*w).map(|k| format!("{name}_{k}")));
    }
    let mut out = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n");
    for nm in &names {
        out.push_str(&format!("property float {nm}\n"));
    }
    out.push_str("end_header\n");
    let mut bytes = out.into_bytes();
    bytes.reserve(n * names.len() * 4);
    for i in 0..n {
        let mut row: Vec<f32> = Vec::with_capacity(names.len());
        row.extend_from_slice(&cloud.means[i]);
        row.extend_from_slice(&[0.0; 3]);
        row.extend_from_slice(&cloud.sh_dc[i]);
        row.extend_from_slice(&cloud.sh_rest[i * cloud.rest_per_gaussian..(i + 1) * cloud.rest_per_gaussian]);
        row.push(cloud.opacity_logits[i]);
        row.extend_from_slice(&cloud.log_scales[i]);
        row.extend_from_slice(&cloud.quats[i]);
        for (w, data) in cloud.extra.values() {
            row.extend_from_slice(&data[i * w..(i + 1) * w]);
        }
        for v in row {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    bytes
}

/// Writes `cloud` as a binary little-endian Inria-layout `.ply` (atomically: temp file + rename).
pub fn write(path: &Path, cloud: &GaussianCloud) -> Result<()> {
    let bytes = encode(cloud);
    crate::io::write_atomic_with(path, |tmp| {
        let mut f = std::fs::File::create(tmp).at(tmp, "cannot write")?;
        f.write_all(&bytes).at(tmp, "cannot write")?;
        f.sync_all().at(tmp, "cannot write")
    })
}
