//! Checkpoint files shared by the training stages: f32 safetensors and JSON, each written to a
//! temporary file and renamed (a killed run never leaves a half-written checkpoint), plus the
//! burn Adam moments stored beside their parameter.

use burn::optim::{AdamState, AdaptiveMomentumState};
use burn::tensor::{Device, Tensor, TensorData};
use model::splats::host;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use std::collections::HashMap;
use std::path::Path;

/// Named f32 tensors: name, shape, values.
pub type Named = Vec<(String, Vec<usize>, Vec<f32>)>;
/// Tensors read back by name, with the file's metadata.
pub type NamedMap = HashMap<String, (Vec<usize>, Vec<f32>)>;

fn tmp_of(path: &Path) -> std::path::PathBuf {
    let mut name = path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(".tmp");
    path.with_file_name(name)
}

/// Writes `bytes` to `path` through a temporary file and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), String> {
    let tmp = tmp_of(path);
    std::fs::write(&tmp, bytes).map_err(|e| format!("{}: cannot write: {e}", tmp.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| format!("{}: cannot rename: {e}", path.display()))
}

/// Pretty JSON, atomically.
pub fn write_json(path: &Path, value: &serde_json::Value) -> Result<(), String> {
    write_atomic(path, serde_json::to_string_pretty(value).expect("JSON").as_bytes())
}

pub fn read_json(path: &Path) -> Result<serde_json::Value, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    serde_json::from_str(&text).map_err(|e| format!("{}: invalid JSON: {e}", path.display()))
}

/// f32 safetensors with optional metadata, atomically.
pub fn write_f32(path: &Path, tensors: Named, meta: Option<HashMap<String, String>>) -> Result<(), String> {
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = tensors.into_iter().map(|(n, s, v)| (n, s, v.iter().flat_map(|x| x.to_le_bytes()).collect())).collect();
    let views: Vec<(String, TensorView)> =
        bytes.iter().map(|(n, s, b)| (n.clone(), TensorView::new(Dtype::F32, s.clone(), b).expect("tensor view"))).collect();
    let out = safetensors::serialize(views, meta).map_err(|e| format!("{}: {e}", path.display()))?;
    write_atomic(path, &out)
}

/// Reads every f32 tensor of a safetensors file and its metadata.
pub fn read_f32(path: &Path) -> Result<(NamedMap, HashMap<String, String>), String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let st = SafeTensors::deserialize(&bytes).map_err(|e| format!("{}: not a valid safetensors file: {e}", path.display()))?;
    let (_, meta) = SafeTensors::read_metadata(&bytes).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut out = HashMap::new();
    for (name, t) in st.tensors() {
        if t.dtype() != Dtype::F32 {
            return Err(format!("{}: {name} has dtype {:?}, expected F32", path.display(), t.dtype()));
        }
        let v = t.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        out.insert(name, (t.shape().to_vec(), v));
    }
    Ok((out, meta.metadata().clone().unwrap_or_default()))
}

/// The Adam moments of one parameter, as stored tensors `adam.{name}.m1` / `.m2`.
pub struct AdamTensors {
    name: String,
    moments: Option<(Vec<usize>, Vec<f32>, Vec<f32>)>,
}

impl AdamTensors {
    pub fn of(name: &str, state: Option<&AdamState<2>>) -> Self {
        let moments = state.map(|s| (s.momentum.moment_1.dims().to_vec(), host(s.momentum.moment_1.clone()), host(s.momentum.moment_2.clone())));
        Self { name: name.to_string(), moments }
    }

    pub fn tensors(&self) -> Named {
        match &self.moments {
            Some((shape, m1, m2)) => vec![
                (format!("adam.{}.m1", self.name), shape.clone(), m1.clone()),
                (format!("adam.{}.m2", self.name), shape.clone(), m2.clone()),
            ],
            None => vec![],
        }
    }

    /// Rebuilds the state of `name` (step count `time`) from `tensors`, removing its moments.
    pub fn take(name: &str, time: Option<usize>, tensors: &mut NamedMap, device: &Device) -> Result<Option<AdamState<2>>, String> {
        let m1 = tensors.remove(&format!("adam.{name}.m1"));
        let m2 = tensors.remove(&format!("adam.{name}.m2"));
        let (Some(time), Some((s1, v1)), Some((s2, v2))) = (time, m1, m2) else { return Ok(None) };
        if s1.len() != 2 || s1 != s2 {
            return Err(format!("Adam moments of {name} have shapes {s1:?} / {s2:?}"));
        }
        let t = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, [s1[0], s1[1]]), device);
        Ok(Some(AdamState::new(AdaptiveMomentumState::new(time, t(v1), t(v2)))))
    }
}
