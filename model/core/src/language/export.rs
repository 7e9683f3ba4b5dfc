//! Encoder export: the lifting network, the patch convolution and the scaling adjustment as f32
//! safetensors in PyTorch's `Conv2d` layout, with a JSON header in the file's metadata
//! (`chatsplat_encoder`: shapes, channel counts, activation, teacher model id).
//!
//! | tensor             | shape                  | meaning                                  |
//! |--------------------|------------------------|------------------------------------------|
//! | `lift.{i}.weight`  | `[out, in, 1, 1]`      | 1x1 convolution `i` (GELU between them)  |
//! | `lift.{i}.bias`    | `[out]`                |                                          |
//! | `patch.weight`     | `[D, D, patch, patch]` | non-overlapping convolution, stride patch|
//! | `patch.bias`       | `[D]`                  |                                          |
//! | `scale`, `shift`   | `[T, D]`               | tokens * scale + shift (T = grid²)       |
//! | `object_scale`, `object_shift` | `[T, D]`   | the same for object-level maps (optional)|
//! | `mix.pos`          | `[T, D]`               | token mixer (optional, `token_mixer`):   |
//! | `mix.q/k/v/o`      | `[D, D]`               | `x @ W` projections, see `TokenMixer`    |

use super::{Encoder, LanguageConfig};
use crate::error::{Error, Result};
use crate::splats::host;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

/// Metadata key of the JSON header.
pub const HEADER_KEY: &str = "chatsplat_encoder";

/// The JSON header stored under [`HEADER_KEY`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderHeader {
    /// Always `chatsplat-encoder`.
    pub format: String,
    pub version: u32,
    pub in_channels: usize,
    pub hidden: usize,
    pub lifting: bool,
    pub activation: String,
    pub dim: usize,
    pub grid: usize,
    pub patch: usize,
    pub tokens: usize,
    pub scale_shift: bool,
    pub scale_shift_per_level: bool,
    pub teacher_model: String,
    pub teacher_image: usize,
    pub teacher_patch: usize,
    /// Whether the file holds a token mixer (`mix.*`; absent in files written before it).
    #[serde(default)]
    pub token_mixer: bool,
    /// The tokens are the teacher tower's state before its last this many layers, which must
    /// run on them before the projector (0, and absent in older files: its output).
    #[serde(default)]
    pub tower_tail: usize,
    /// Shape of every tensor in the file.
    pub tensors: BTreeMap<String, Vec<usize>>,
}

/// Writes `enc` to `path` (atomically); returns the number of parameters.
pub fn write_encoder(path: &Path, enc: &Encoder, cfg: &LanguageConfig, teacher_model: &str) -> Result<usize> {
    let mut tensors = Vec::new();
    for (name, t) in enc.named() {
        let [r, c] = t.dims();
        let (shape, t): (Vec<usize>, Tensor<2>) = match name.as_str() {
            n if n.starts_with("lift.") && n.ends_with(".weight") => (vec![c, r, 1, 1], t.transpose()),
            n if n.ends_with(".bias") => (vec![c], t),
            "patch.weight" => {
                let p = enc.patch();
                let d_in = r / (p * p);
                let conv = t.reshape([p, p, d_in, c]).permute([3, 2, 0, 1]);
                (vec![c, d_in, p, p], conv.reshape([c, d_in * p * p]))
            }
            _ => (vec![r, c], t),
        };
        tensors.push((name, shape, host(t)));
    }
    let params: usize = tensors.iter().map(|(_, _, v)| v.len()).sum();
    let header = EncoderHeader {
        format: "chatsplat-encoder".into(),
        version: 1,
        in_channels: cfg.feature_channels(),
        hidden: cfg.hidden,
        lifting: !enc.lift_weights.is_empty(),
        activation: "gelu (erf)".into(),
        dim: cfg.dim,
        grid: cfg.grid,
        patch: cfg.patch,
        tokens: cfg.tokens(),
        scale_shift: enc.scale.is_some(),
        scale_shift_per_level: enc.object_scale.is_some(),
        teacher_model: teacher_model.to_string(),
        teacher_image: cfg.teacher_image,
        teacher_patch: cfg.teacher_patch,
        token_mixer: enc.mixer.is_some(),
        tower_tail: cfg.tower_tail,
        tensors: tensors.iter().map(|(n, s, _)| (n.clone(), s.clone())).collect(),
    };
    let mut meta = HashMap::new();
    let json = serde_json::to_string(&header).map_err(|e| Error::invalid(path, e.to_string()))?;
    meta.insert(HEADER_KEY.to_string(), json);
    crate::io::write_f32(path, tensors, Some(meta))?;
    Ok(params)
}

/// Reads an exported encoder back: the encoder and its shapes.
pub fn read_encoder(path: &Path, device: &Device) -> Result<(Encoder, LanguageConfig)> {
    let (mut tensors, meta) = crate::io::read_f32(path)?;
    let header = meta
        .get(HEADER_KEY)
        .ok_or_else(|| Error::invalid(path, format!("no {HEADER_KEY} header (not a chatsplat encoder export)")))?;
    let h: EncoderHeader =
        serde_json::from_str(header).map_err(|e| Error::invalid(path, format!("invalid {HEADER_KEY} header: {e}")))?;
    let lifting = h.lifting;
    let cfg = LanguageConfig {
        view_channels: h.in_channels,
        object_channels: h.in_channels,
        hidden: h.hidden,
        lifting,
        scale_shift: h.scale_shift,
        scale_shift_per_level: h.scale_shift_per_level,
        dim: h.dim,
        grid: h.grid,
        patch: h.patch,
        teacher_image: h.teacher_image,
        teacher_patch: h.teacher_patch,
        token_mixer: h.token_mixer,
        tower_tail: h.tower_tail,
    };
    let mut take = |name: &str| {
        let (s, v) = tensors.remove(name).ok_or_else(|| Error::invalid(path, format!("tensor {name} is missing")))?;
        let want = match name {
            n if n.ends_with(".weight") => 4,
            n if n.ends_with(".bias") => 1,
            _ => 2,
        };
        if s.len() != want {
            return Err(Error::invalid(path, format!("tensor {name} has shape {s:?}, expected rank {want}")));
        }
        Ok((s, v))
    };
    let mut named = Vec::new();
    let layers = if lifting { 2 } else { 0 };
    for i in 0..layers {
        let (s, v) = take(&format!("lift.{i}.weight"))?;
        let w = Tensor::<2>::from_data(TensorData::new(v, [s[0], s[1]]), device).transpose();
        named.push((format!("lift.{i}.weight"), w));
        let (s, v) = take(&format!("lift.{i}.bias"))?;
        named.push((format!("lift.{i}.bias"), Tensor::from_data(TensorData::new(v, [1, s[0]]), device)));
    }
    let (s, v) = take("patch.weight")?;
    let (d, d_in, p) = (s[0], s[1], s[2]);
    let w = Tensor::<1>::from_data(TensorData::new(v, [d * d_in * p * p]), device)
        .reshape([d, d_in, p, p])
        .permute([2, 3, 1, 0])
        .reshape([p * p * d_in, d]);
    named.push(("patch.weight".into(), w));
    let (s, v) = take("patch.bias")?;
    named.push(("patch.bias".into(), Tensor::from_data(TensorData::new(v, [1, s[0]]), device)));
    if h.token_mixer {
        for n in super::mix::MIXER_TENSORS {
            let name = format!("mix.{n}");
            let (s, v) = take(&name)?;
            named.push((name, Tensor::from_data(TensorData::new(v, [s[0], s[1]]), device)));
        }
    }
    let names: &[&str] = match (cfg.scale_shift, cfg.scale_shift_per_level) {
        (false, _) => &[],
        (true, false) => &["scale", "shift"],
        (true, true) => &["scale", "shift", "object_scale", "object_shift"],
    };
    for &n in names {
        let (s, v) = take(n)?;
        named.push((n.to_string(), Tensor::from_data(TensorData::new(v, [s[0], s[1]]), device)));
    }
    Ok((Encoder::from_named(named).map_err(|e| Error::invalid(path, e.to_string()))?, cfg))
}
