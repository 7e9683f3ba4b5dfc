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

use burn::tensor::{Device, Tensor, TensorData};
use model::language::{Encoder, LanguageConfig};
use model::splats::host;
use std::collections::HashMap;
use std::path::Path;

/// Metadata key of the JSON header.
pub const HEADER_KEY: &str = "chatsplat_encoder";

/// Writes `enc` to `path` (atomically); returns the number of parameters.
pub fn write_encoder(path: &Path, enc: &Encoder, cfg: &LanguageConfig, teacher_model: &str) -> Result<usize, String> {
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
    let header = serde_json::json!({
        "format": "chatsplat-encoder",
        "version": 1,
        "in_channels": cfg.feature_channels(),
        "hidden": cfg.hidden,
        "lifting": !enc.lift_weights.is_empty(),
        "activation": "gelu (erf)",
        "dim": cfg.dim,
        "grid": cfg.grid,
        "patch": cfg.patch,
        "tokens": cfg.tokens(),
        "scale_shift": enc.scale.is_some(),
        "scale_shift_per_level": enc.object_scale.is_some(),
        "teacher_model": teacher_model,
        "teacher_image": cfg.teacher_image,
        "teacher_patch": cfg.teacher_patch,
        "tensors": tensors.iter().map(|(n, s, _)| (n.clone(), serde_json::json!(s))).collect::<serde_json::Map<_, _>>(),
    });
    let mut meta = HashMap::new();
    meta.insert(HEADER_KEY.to_string(), header.to_string());
    crate::ckpt::write_f32(path, tensors, Some(meta))?;
    Ok(params)
}

/// Reads an exported encoder back: the encoder and its shapes.
pub fn read_encoder(path: &Path, device: &Device) -> Result<(Encoder, LanguageConfig), String> {
    let (mut tensors, meta) = crate::ckpt::read_f32(path)?;
    let header = meta.get(HEADER_KEY).ok_or_else(|| format!("{}: no {HEADER_KEY} header (not a chatsplat encoder export)", path.display()))?;
    let h: serde_json::Value = serde_json::from_str(header).map_err(|e| format!("{}: invalid {HEADER_KEY} header: {e}", path.display()))?;
    let num = |k: &str| h[k].as_u64().map(|v| v as usize).ok_or_else(|| format!("{}: header field \"{k}\" missing", path.display()));
    let lifting = h["lifting"].as_bool().unwrap_or(true);
    let cfg = LanguageConfig {
        view_channels: num("in_channels")?,
        object_channels: num("in_channels")?,
        hidden: num("hidden")?,
        lifting,
        scale_shift: h["scale_shift"].as_bool().unwrap_or(true),
        scale_shift_per_level: h["scale_shift_per_level"].as_bool().unwrap_or(false),
        dim: num("dim")?,
        grid: num("grid")?,
        patch: num("patch")?,
        teacher_image: num("teacher_image")?,
        teacher_patch: num("teacher_patch")?,
    };
    let mut take = |name: &str| tensors.remove(name).ok_or_else(|| format!("{}: tensor {name} missing", path.display()));
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
    if s.len() != 4 {
        return Err(format!("{}: patch.weight has shape {s:?}, expected [D, D, p, p]", path.display()));
    }
    let (d, d_in, p) = (s[0], s[1], s[2]);
    let w = Tensor::<1>::from_data(TensorData::new(v, [d * d_in * p * p]), device).reshape([d, d_in, p, p]).permute([2, 3, 1, 0]).reshape([p * p * d_in, d]);
    named.push(("patch.weight".into(), w));
    let (s, v) = take("patch.bias")?;
    named.push(("patch.bias".into(), Tensor::from_data(TensorData::new(v, [1, s[0]]), device)));
    let names: &[&str] = match (cfg.scale_shift, cfg.scale_shift_per_level) {
        (false, _) => &[],
        (true, false) => &["scale", "shift"],
        (true, true) => &["scale", "shift", "object_scale", "object_shift"],
    };
    for &n in names {
        let (s, v) = take(n)?;
        named.push((n.to_string(), Tensor::from_data(TensorData::new(v, [s[0], s[1]]), device)));
    }
    Ok((Encoder::from_named(named)?, cfg))
}
