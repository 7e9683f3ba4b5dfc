//! Hugging Face safetensors checkpoints: a single `model.safetensors` or shards listed in
//! `model.safetensors.index.json`, memory-mapped, converted from bf16/f16/f32 to f32 on load.
//! Both key layouts are accepted: the llava-hf hub one (`language_model.model.layers.0...`,
//! `vision_tower.vision_model...`) and the transformers-5 in-memory one (`model.language_model.layers.0...`).

use super::VlmError;
use burn::tensor::{DType, Device, Tensor, TensorData};
use safetensors::{Dtype, SafeTensors};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Lets the kernel drop the resident pages of `bytes` (a slice of `map`) once they are read, so
/// that loading does not hold the whole checkpoint file in memory on top of the weights made from
/// it (0.5B model: 1.7 GB of bf16 pages). Only pages wholly inside `bytes` are released; a later
/// read faults them back in from the file.
fn release_pages(map: &memmap2::Mmap, bytes: &[u8]) {
    #[cfg(unix)]
    {
        const PAGE: usize = 4096;
        let start = bytes.as_ptr() as usize - map.as_ptr() as usize;
        let (first, end) = (start.div_ceil(PAGE) * PAGE, (start + bytes.len()) / PAGE * PAGE);
        if end > first {
            // SAFETY: a read-only, file-backed mapping: MADV_DONTNEED only drops resident pages,
            // whose contents the next access reads again from the file, so every slice of the map
            // stays valid. Failure (e.g. another page size) only means the pages stay resident.
            let _ = unsafe { map.unchecked_advise_range(memmap2::UncheckedAdvice::DontNeed, first, end - first) };
        }
    }
    #[cfg(not(unix))]
    let _ = (map, bytes);
}

struct Shard {
    path: PathBuf,
    map: memmap2::Mmap,
}

/// The tensors of a model directory, read on demand.
pub struct WeightStore {
    shards: Vec<Shard>,
    /// tensor name -> shard index
    names: BTreeMap<String, usize>,
    device: Device,
    /// Hold the weights of linear layers and embeddings in f16 (see [`WeightStore::with_half`]).
    half: bool,
}

impl WeightStore {
    /// Opens `model.safetensors.index.json` (sharded) or `model.safetensors` in `dir`.
    pub fn open(dir: &Path, device: &Device) -> Result<Self, VlmError> {
        let index = dir.join("model.safetensors.index.json");
        let files: Vec<PathBuf> = if index.exists() {
            let v = super::config::read_json(&index)?;
            let map = v
                .get("weight_map")
                .and_then(|m| m.as_object())
                .ok_or_else(|| VlmError::weights(&index, "has no weight_map object"))?;
            let mut files: Vec<String> = map.values().filter_map(|f| f.as_str().map(str::to_string)).collect();
            files.sort();
            files.dedup();
            files.into_iter().map(|f| dir.join(f)).collect()
        } else if dir.join("model.safetensors").exists() {
            vec![dir.join("model.safetensors")]
        } else {
            return Err(VlmError::weights(dir, "no model.safetensors or model.safetensors.index.json"));
        };
        let mut shards = Vec::new();
        let mut names = BTreeMap::new();
        for path in files {
            let file = std::fs::File::open(&path).map_err(|e| VlmError::io(&path, e))?;
            // SAFETY: the file is opened read-only and only read through this map; a concurrent
            // writer could change what we read, as with any reader of the file.
            let map = unsafe { memmap2::Mmap::map(&file) }.map_err(|e| VlmError::io(&path, e))?;
            let st = SafeTensors::deserialize(&map)
                .map_err(|e| VlmError::weights(&path, format!("not a valid safetensors file: {e}")))?;
            for name in st.names() {
                names.insert(name.to_string(), shards.len());
            }
            drop(st);
            shards.push(Shard { path, map });
        }
        Ok(Self { shards, names, device: device.clone(), half: false })
    }

    /// Every tensor name present.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.names.keys().map(String::as_str)
    }

    fn resolve(&self, name: &str) -> Option<String> {
        aliases(name).into_iter().find(|n| self.names.contains_key(n))
    }

    /// Whether the checkpoint has `name` (under any accepted key layout).
    pub fn contains(&self, name: &str) -> bool {
        self.resolve(name).is_some()
    }

    /// Reads `name` as f32 host data and checks its shape.
    pub fn host(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>, VlmError> {
        let key = self.resolve(name).ok_or_else(|| {
            let where_ = self
                .shards
                .first()
                .map(|s| s.path.parent().unwrap_or(Path::new(".")).to_path_buf())
                .unwrap_or_default();
            VlmError::weights(&where_, format!("tensor {name} is missing"))
        })?;
        let shard = &self.shards[self.names[&key]];
        let st = SafeTensors::deserialize(&shard.map).map_err(|e| VlmError::weights(&shard.path, e.to_string()))?;
        let view = st.tensor(&key).map_err(|e| VlmError::weights(&shard.path, format!("{key}: {e}")))?;
        if view.shape() != shape {
            return Err(VlmError::weights(
                &shard.path,
                format!("tensor {key} has shape {:?}, the config expects {shape:?}", view.shape()),
            ));
        }
        let bytes = view.data();
        let out: Vec<f32> = match view.dtype() {
            Dtype::F32 => bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
            Dtype::BF16 => bytes.chunks_exact(2).map(|b| half::bf16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
            Dtype::F16 => bytes.chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
            other => {
                return Err(VlmError::weights(
                    &shard.path,
                    format!("tensor {key} has dtype {other:?}; expected F32, BF16 or F16"),
                ));
            }
        };
        release_pages(&shard.map, bytes);
        if let Some(i) = out.iter().position(|x| !x.is_finite()) {
            return Err(VlmError::weights(
                &shard.path,
                format!("tensor {key} has a non-finite value at flat index {i}"),
            ));
        }
        Ok(out)
    }

    /// Reads `name` onto the device with shape `D`.
    pub fn tensor<const D: usize>(&self, name: &str, shape: [usize; D]) -> Result<Tensor<D>, VlmError> {
        let data = self.host(name, &shape)?;
        Ok(Tensor::from_data(TensorData::new(data, shape), &self.device))
    }

    /// A torch `nn.Linear` weight `[out, in]`, returned transposed as `[in, out]` for `x.matmul(w)`.
    pub fn linear_weight(&self, name: &str, d_in: usize, d_out: usize) -> Result<Tensor<2>, VlmError> {
        self.transposed(name, &[d_out, d_in])
    }

    /// A weight stored with `shape = [out, in...]`, flattened to `[out, prod(in)]` and returned
    /// transposed as `[prod(in), out]` (linear layers; a conv kernel `[out, c, k, k]` over unfolded patches).
    pub fn transposed(&self, name: &str, shape: &[usize]) -> Result<Tensor<2>, VlmError> {
        let w = self.host(name, shape)?;
        let d_out = shape[0];
        let d_in: usize = shape[1..].iter().product();
        let mut t = vec![0f32; w.len()];
        for o in 0..d_out {
            for i in 0..d_in {
                t[i * d_out + o] = w[o * d_in + i];
            }
        }
        Ok(Tensor::from_data(TensorData::new(t, [d_in, d_out]), &self.device))
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Hold the weights of linear layers and embeddings in f16 (half the memory; activations stay
    /// f32, see [`super::layers::linear`]): each tensor is converted as it is read, so loading never
    /// holds the whole model in f32.
    pub fn with_half(mut self, half: bool) -> Self {
        self.half = half;
        self
    }

    /// `t` as this store holds matmul weights: f16 with [`WeightStore::with_half`], else as is.
    pub fn hold<const D: usize>(&self, t: Tensor<D>) -> Tensor<D> {
        if self.half { super::host::in_dtype(t, DType::F16) } else { t }
    }
}

/// The key layouts one canonical (llava-hf hub) name may be stored under: the hub layout, the
/// transformers-5 in-memory layout (`model.` prefix, `model.language_model.*`, top-level `lm_head`),
/// and SigLIP with or without its `vision_model.` wrapper (transformers 5 saves it without).
fn aliases(name: &str) -> Vec<String> {
    let mut base = vec![name.to_string()];
    if let Some(rest) = name.strip_prefix("vision_tower.vision_model.") {
        base.push(format!("vision_tower.{rest}"));
    }
    let mut out = Vec::new();
    for n in base {
        if let Some(rest) = n.strip_prefix("language_model.model.") {
            out.push(format!("model.language_model.{rest}"));
        } else if n == "language_model.lm_head.weight" {
            out.push("lm_head.weight".into());
        } else if n.starts_with("vision_tower.") || n.starts_with("multi_modal_projector.") || n == "image_newline" {
            out.push(format!("model.{n}"));
        }
        out.insert(0, n);
    }
    out
}

/// Tensors collected under llava-hf checkpoint names and layouts (the inverse of the loader),
/// written as one safetensors file.
#[derive(Default)]
pub struct HfTensors {
    /// Name, shape, values.
    pub tensors: Vec<(String, Vec<usize>, Vec<f32>)>,
}

impl HfTensors {
    pub fn tensor<const D: usize>(&mut self, name: &str, t: Tensor<D>) {
        let shape = t.dims().to_vec();
        self.tensors.push((
            name.to_string(),
            shape,
            t.into_data().convert::<f32>().to_vec::<f32>().expect("f32 tensor"),
        ));
    }

    pub fn vector(&mut self, name: &str, t: Tensor<1>) {
        self.tensor(name, t);
    }

    /// A `burn::nn::Linear` (`[in, out]`) as torch's `prefix.weight` `[out, in]` and `prefix.bias`.
    pub fn linear(&mut self, prefix: &str, l: &burn::nn::Linear) {
        self.tensor(&format!("{prefix}.weight"), l.weight.val().transpose());
        if let Some(b) = &l.bias {
            self.vector(&format!("{prefix}.bias"), b.val());
        }
    }

    pub fn layer_norm(&mut self, prefix: &str, l: &burn::nn::LayerNorm) {
        self.vector(&format!("{prefix}.weight"), l.gamma.val());
        if let Some(b) = &l.beta {
            self.vector(&format!("{prefix}.bias"), b.val());
        }
    }

    pub fn rms_norm(&mut self, prefix: &str, l: &burn::nn::RmsNorm) {
        self.vector(&format!("{prefix}.weight"), l.gamma.val());
    }

    /// Parameter count.
    pub fn count(&self) -> usize {
        self.tensors.iter().map(|(_, _, v)| v.len()).sum()
    }

    /// Writes the safetensors file `path`, bf16 (how llava-hf checkpoints are stored) or f32,
    /// streaming it out tensor by tensor ([`F32View`]): the peak is these tensors once and one
    /// tensor's bf16 bytes, not the tensors, their bytes and the whole file.
    pub fn write(self, path: &Path, as_bf16: bool) -> Result<(), VlmError> {
        for (n, s, v) in &self.tensors {
            if s.iter().product::<usize>() != v.len() {
                return Err(VlmError::weights(path, format!("tensor {n} has shape {s:?} but {} values", v.len())));
            }
        }
        let views = self.tensors.iter().map(|(n, shape, values)| (n.as_str(), F32View { shape, values, as_bf16 }));
        let mut meta = std::collections::HashMap::new();
        meta.insert("format".to_string(), "pt".to_string());
        safetensors::serialize_to_file(views, Some(meta), path).map_err(|e| VlmError::weights(path, e.to_string()))
    }
}

/// An f32 tensor handed to safetensors as it is written: as f32, its own memory read as
/// little-endian bytes (no copy), or as bf16, converted when the writer reaches it (one tensor's
/// bytes at a time). `shape` must hold `values.len()` elements.
pub struct F32View<'a> {
    pub shape: &'a [usize],
    pub values: &'a [f32],
    pub as_bf16: bool,
}

impl safetensors::View for F32View<'_> {
    fn dtype(&self) -> Dtype {
        if self.as_bf16 { Dtype::BF16 } else { Dtype::F32 }
    }

    fn shape(&self) -> &[usize] {
        self.shape
    }

    fn data(&self) -> std::borrow::Cow<'_, [u8]> {
        use std::borrow::Cow;
        if self.as_bf16 {
            Cow::Owned(self.values.iter().flat_map(|x| half::bf16::from_f32(*x).to_le_bytes()).collect())
        } else if cfg!(target_endian = "little") {
            // SAFETY: the byte slice covers exactly the values' memory, which it only reads (any
            // bytes are valid u8), for as long as the borrowed values live.
            let bytes = unsafe {
                std::slice::from_raw_parts(self.values.as_ptr().cast::<u8>(), std::mem::size_of_val(self.values))
            };
            Cow::Borrowed(bytes)
        } else {
            Cow::Owned(self.values.iter().flat_map(|x| x.to_le_bytes()).collect())
        }
    }

    fn data_len(&self) -> usize {
        self.values.len() * if self.as_bf16 { 2 } else { 4 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Both dtypes stream to the file safetensors makes in memory from the converted bytes, read
    /// back through the loader as those values (bf16: rounded to nearest), and a tensor whose
    /// shape does not hold its values is refused before anything is written.
    #[test]
    fn tensors_stream_as_bf16_or_f32_and_read_back() {
        let dir = std::env::temp_dir().join(format!("llava-weights-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("model.safetensors");
        let values = vec![1.0f32, -2.5, 0.1, 3.0e-3, 65504.0, -1.0e-30];
        let tensors = || HfTensors { tensors: vec![("a.weight".into(), vec![2, 3], values.clone())] };
        let device = Device::flex();
        for as_bf16 in [true, false] {
            tensors().write(&path, as_bf16).unwrap();
            let bytes: Vec<u8> = if as_bf16 {
                values.iter().flat_map(|x| half::bf16::from_f32(*x).to_le_bytes()).collect()
            } else {
                values.iter().flat_map(|x| x.to_le_bytes()).collect()
            };
            let dtype = if as_bf16 { Dtype::BF16 } else { Dtype::F32 };
            let view = safetensors::tensor::TensorView::new(dtype, vec![2, 3], &bytes).unwrap();
            let meta = std::collections::HashMap::from([("format".to_string(), "pt".to_string())]);
            let in_memory = safetensors::serialize([("a.weight", view)], Some(meta)).unwrap();
            assert_eq!(std::fs::read(&path).unwrap(), in_memory, "bf16 {as_bf16}: the streamed file differs");
            let back = WeightStore::open(&dir, &device).unwrap().host("a.weight", &[2, 3]).unwrap();
            let want: Vec<f32> = if as_bf16 {
                values.iter().map(|x| half::bf16::from_f32(*x).to_f32()).collect()
            } else {
                values.clone()
            };
            assert_eq!(back, want, "bf16 {as_bf16}");
        }
        let before = std::fs::read(&path).unwrap();
        let bad = HfTensors { tensors: vec![("b".into(), vec![4], vec![1.0; 3])] };
        let e = bad.write(&path, true).unwrap_err().to_string();
        assert!(e.contains("model.safetensors") && e.contains("shape [4] but 3 values"), "{e}");
        assert_eq!(std::fs::read(&path).unwrap(), before);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
