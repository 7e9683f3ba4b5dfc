//! Files written so that nothing the user had is lost: every write goes to a temporary file
//! beside the target and is renamed over it (a killed process leaves the old file or the new
//! one, never half of one). JSON in and out with errors naming the file; f32 safetensors.

use crate::error::{Error, IoContext, Result};
use llava_onevision::weights::F32View;
use safetensors::{Dtype, SafeTensors};
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Named f32 tensors: name, shape, values.
pub type Named = Vec<(String, Vec<usize>, Vec<f32>)>;
/// Tensors read back by name: shape and values.
pub type NamedMap = HashMap<String, (Vec<usize>, Vec<f32>)>;

fn tmp_of(path: &Path) -> PathBuf {
    let mut name = path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(".tmp");
    path.with_file_name(name)
}

/// Writes `bytes` to `path` through a temporary file and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |tmp| std::fs::write(tmp, bytes).at(tmp, "cannot write"))
}

/// Writes `path` atomically through `write`, which receives the temporary path to fill.
pub fn write_atomic_with(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    if path.is_dir() {
        return Err(Error::invalid(path, "is a directory: give the path of a file to write"));
    }
    let tmp = tmp_of(path);
    if let Err(e) = write(&tmp) {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    std::fs::rename(&tmp, path).at(path, "cannot rename into place").inspect_err(|_| {
        let _ = std::fs::remove_file(&tmp);
    })
}

/// Creates `dir` and its parents.
pub fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).at(dir, "cannot create directory")
}

/// Pretty JSON of `value`, atomically.
pub fn write_json<T: Serialize + ?Sized>(path: &Path, value: &T) -> Result<()> {
    let text =
        serde_json::to_string_pretty(value).map_err(|e| Error::invalid(path, format!("cannot encode JSON: {e}")))?;
    write_atomic(path, text.as_bytes())
}

/// Reads and parses a JSON file; errors name the file, the line and the column.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).at(path, "cannot read")?;
    serde_json::from_str(&text)
        .map_err(|e| Error::invalid(path, format!("invalid JSON at line {}, column {}: {e}", e.line(), e.column())))
}

/// Reads a JSON file whose top level must be an object (`shape` says which, e.g.
/// `{"questions": [...]}`): another top level is refused saying what it must be, other errors
/// name the line and column.
pub fn read_json_object<T: DeserializeOwned>(path: &Path, shape: &str) -> Result<T> {
    let text = std::fs::read_to_string(path).at(path, "cannot read")?;
    let at = |e: serde_json::Error| {
        Error::invalid(path, format!("invalid JSON at line {}, column {}: {e}", e.line(), e.column()))
    };
    let top = match serde_json::from_str::<serde_json::Value>(&text).map_err(at)? {
        serde_json::Value::Object(_) => return serde_json::from_str(&text).map_err(at),
        serde_json::Value::Array(_) => "an array",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Null => "null",
    };
    Err(Error::invalid(path, format!("the top level is {top}; it must be an object {shape}")))
}

/// Reads a config file a user wrote: a JSON object (not an array, which serde would map onto the
/// fields by position), unknown keys refused by the type.
/// A value that does not fit is refused naming its key (`soup.weights[1]`), line and column.
pub fn read_config<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).at(path, "cannot read")?;
    let value: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::invalid(path, format!("invalid JSON at line {}, column {}: {e}", e.line(), e.column())))?;
    if !value.is_object() {
        return Err(Error::invalid(path, "a config must be a JSON object of settings, e.g. {\"iters\": 1000}"));
    }
    let mut de = serde_json::Deserializer::from_str(&text);
    serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let key = e.path().to_string();
        // serde_json's message ends with the line and column
        let e = e.into_inner();
        Error::invalid(path, if key == "." { format!("config: {e}") } else { format!("config key `{key}`: {e}") })
    })
}

/// f32 safetensors with optional metadata, atomically. A non-finite value is refused (naming the
/// tensor) and nothing is written: [`read_f32`] would refuse the file, so a file already there is
/// better kept.
pub fn write_f32(path: &Path, tensors: Named, meta: Option<HashMap<String, String>>) -> Result<()> {
    for (name, shape, v) in &tensors {
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(Error::invalid(
                path,
                format!("not written: {name} holds a non-finite value ({}) at flat index {i}", v[i]),
            ));
        }
        if shape.iter().product::<usize>() != v.len() {
            return Err(Error::invalid(
                path,
                format!("not written: {name} has shape {shape:?} but {} values", v.len()),
            ));
        }
    }
    let views = tensors.iter().map(|(n, shape, values)| (n.as_str(), F32View { shape, values, as_bf16: false }));
    write_atomic_with(path, |tmp| {
        safetensors::serialize_to_file(views, meta, tmp).map_err(|e| Error::invalid(tmp, format!("cannot write: {e}")))
    })
}

/// Reads every f32 tensor of a safetensors file and its metadata. Non-finite values are refused
/// with the tensor and the flat index named.
pub fn read_f32(path: &Path) -> Result<(NamedMap, HashMap<String, String>)> {
    let bytes = std::fs::read(path).at(path, "cannot read")?;
    let st = SafeTensors::deserialize(&bytes)
        .map_err(|e| Error::invalid(path, format!("not a valid safetensors file: {e}")))?;
    let (_, meta) = SafeTensors::read_metadata(&bytes).map_err(|e| Error::invalid(path, e.to_string()))?;
    let mut out = HashMap::new();
    for (name, t) in st.tensors() {
        if t.dtype() != Dtype::F32 {
            return Err(Error::invalid(path, format!("{name} has dtype {:?}, expected F32", t.dtype())));
        }
        let v: Vec<f32> = t.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(Error::invalid(path, format!("{name} holds a non-finite value ({}) at flat index {i}", v[i])));
        }
        out.insert(name, (t.shape().to_vec(), v));
    }
    Ok((out, meta.metadata().clone().unwrap_or_default()))
}

/// Removes tensor `name` from `tensors`, checking it is rank 2: `(rows, cols, values)`.
pub fn take_rank2(tensors: &mut NamedMap, name: &str, path: &Path) -> Result<(usize, usize, Vec<f32>)> {
    let (shape, v) = tensors.remove(name).ok_or_else(|| Error::invalid(path, format!("tensor {name} is missing")))?;
    match shape[..] {
        [r, c] => Ok((r, c, v)),
        _ => Err(Error::invalid(path, format!("tensor {name} has shape {shape:?}, expected rank 2"))),
    }
}

/// Where `path` leads: its canonical form (links followed, `..` resolved) when it exists; else its
/// deepest existing ancestor's canonical form joined with the rest.
pub fn resolved(path: &Path) -> PathBuf {
    let abs = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let mut rest = Vec::new();
    let mut at = abs.as_path();
    loop {
        if let Ok(c) = std::fs::canonicalize(at) {
            return rest.iter().rev().fold(c, |p: PathBuf, part| p.join(part));
        }
        match (at.parent(), at.file_name()) {
            (Some(parent), Some(name)) => {
                rest.push(name.to_os_string());
                at = parent;
            }
            _ => return abs,
        }
    }
}

/// Refuses two outputs of one command (`option`, path) that lead to the same file.
pub fn refuse_shared_outputs(outputs: &[(&str, &Path)]) -> Result<()> {
    for (i, (a, p)) in outputs.iter().enumerate() {
        if let Some((b, _)) = outputs[i + 1..].iter().find(|(_, q)| resolved(q) == resolved(p)) {
            return Err(Error::invalid(p, format!("{a} and {b} are the same file: give each output its own path")));
        }
    }
    Ok(())
}

/// `to` relative to directory `base` when `to` lies inside it (or both are relative), else `to`
/// made absolute: how paths are stored in run files, so a run can be moved or used from anywhere.
pub fn relative_to(to: &Path, base: &Path) -> PathBuf {
    let abs = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    let (to_abs, base_abs) = (abs(to), abs(base));
    let (t, b): (Vec<_>, Vec<_>) = (to_abs.components().collect(), base_abs.components().collect());
    let common = t.iter().zip(&b).take_while(|(x, y)| x == y).count();
    if common == 0 {
        return to_abs;
    }
    let mut out = PathBuf::new();
    for _ in common..b.len() {
        out.push("..");
    }
    for c in &t[common..] {
        out.push(c);
    }
    if out.as_os_str().is_empty() { PathBuf::from(".") } else { out }
}

#[cfg(test)]
mod tests {
    use super::*;
    use safetensors::tensor::TensorView;

    /// The streamed file is byte for byte what safetensors makes from the tensors' bytes in memory
    /// (so files written before read the same), reads back bit for bit with its metadata, and a
    /// tensor whose shape does not match its values is refused with the file left as it was.
    #[test]
    fn f32_tensors_stream_to_the_same_file_and_a_mis_shaped_one_is_refused() {
        let dir = std::env::temp_dir().join(format!("chatsplat-io-{}", std::process::id()));
        create_dir(&dir).unwrap();
        let path = dir.join("t.safetensors");
        let named: Named = vec![
            ("b".into(), vec![2, 3], vec![1.5, -0.0, 3.25e-30, f32::MAX, -7.0, 0.1]),
            ("a".into(), vec![4], vec![9.0, 8.0, 7.0, f32::MIN_POSITIVE]),
        ];
        let meta = HashMap::from([("k".to_string(), "v".to_string())]);
        write_f32(&path, named.clone(), Some(meta.clone())).unwrap();
        let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = named
            .iter()
            .map(|(n, s, v)| (n.clone(), s.clone(), v.iter().flat_map(|x| x.to_le_bytes()).collect()))
            .collect();
        let views = bytes.iter().map(|(n, s, b)| (n.clone(), TensorView::new(Dtype::F32, s.clone(), b).unwrap()));
        let in_memory = safetensors::serialize(views, Some(meta.clone())).unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), in_memory, "the streamed file differs from the in-memory one");
        let (back, m) = read_f32(&path).unwrap();
        assert_eq!(m, meta);
        for (n, s, v) in &named {
            let (bs, bv) = &back[n];
            assert_eq!(bs, s);
            assert_eq!(
                bv.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                v.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
            );
        }
        let bad: Named = vec![("c".into(), vec![2, 2], vec![1.0; 3])];
        let e = write_f32(&path, bad, None).unwrap_err().to_string();
        assert!(e.contains("t.safetensors") && e.contains("shape [2, 2] but 3 values"), "{e}");
        assert_eq!(std::fs::read(&path).unwrap(), in_memory, "a refused write changed the file");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
