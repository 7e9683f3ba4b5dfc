//! `config.json` / `preprocessor_config.json` of a Hugging Face LLaVA-OneVision directory, parsed
//! into the few numbers the port needs; anything we do not implement is refused by name.

use super::VlmError;
use serde_json::Value;
use std::path::Path;

/// Activation functions named in Hugging Face configs that the port implements.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Act {
    /// `gelu`: exact, erf-based.
    Gelu,
    /// `gelu_pytorch_tanh` / `gelu_new`: the tanh approximation.
    GeluTanh,
    /// `silu` / `swish`.
    Silu,
}

impl Act {
    fn parse(name: &str, file: &Path, key: &str) -> Result<Self, VlmError> {
        match name {
            "gelu" => Ok(Act::Gelu),
            "gelu_pytorch_tanh" | "gelu_new" | "gelu_fast" => Ok(Act::GeluTanh),
            "silu" | "swish" => Ok(Act::Silu),
            other => Err(VlmError::config(
                file,
                format!("{key} = \"{other}\" is not supported (gelu, gelu_pytorch_tanh, silu)"),
            )),
        }
    }
}

/// SigLIP vision tower settings (`vision_config`).
#[derive(Clone, Debug, PartialEq)]
pub struct VisionConfig {
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_layers: usize,
    pub num_heads: usize,
    pub image_size: usize,
    pub patch_size: usize,
    pub layer_norm_eps: f64,
    pub act: Act,
}

impl VisionConfig {
    /// Patch tokens per side (27 for 384 / 14: the stride-14 conv drops the last 6 pixels).
    pub fn grid(&self) -> usize {
        self.image_size / self.patch_size
    }
    /// Patch tokens per image (729 for 384 / 14).
    pub fn tokens(&self) -> usize {
        self.grid() * self.grid()
    }
}

/// Qwen2 decoder settings (`text_config`).
#[derive(Clone, Debug, PartialEq)]
pub struct TextConfig {
    pub vocab_size: usize,
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_layers: usize,
    pub num_heads: usize,
    pub num_kv_heads: usize,
    pub head_dim: usize,
    pub rms_norm_eps: f64,
    pub rope_theta: f64,
    /// Longest sequence (prompt + answer) the model takes (`max_position_embeddings`).
    pub max_positions: usize,
    pub tie_word_embeddings: bool,
    pub eos_token_ids: Vec<u32>,
    pub act: Act,
}

/// The whole `LlavaOnevisionForConditionalGeneration` config.
#[derive(Clone, Debug, PartialEq)]
pub struct LlavaConfig {
    pub vision: VisionConfig,
    pub text: TextConfig,
    pub image_token_id: u32,
    /// Index into the vision tower's hidden states (embeddings = 0, layer i = i + 1; negative from the end).
    pub vision_feature_layer: i64,
    pub projector_act: Act,
    pub projector_bias: bool,
    /// anyres grid pinpoints, (height, width) in pixels.
    pub pinpoints: Vec<(usize, usize)>,
    /// N of `anyres_max_N`: the anyres feature grid is shrunk to about N base grids.
    pub max_num_patches: usize,
}

impl LlavaConfig {
    /// Number of vision layers that must run to produce the selected hidden state.
    pub fn vision_layers_needed(&self) -> usize {
        let n = self.vision.num_layers as i64;
        let idx =
            if self.vision_feature_layer < 0 { n + 1 + self.vision_feature_layer } else { self.vision_feature_layer };
        idx as usize
    }

    /// Parameter counts (vision tower layers actually used, projector, LLM) for memory estimates.
    pub fn parameter_counts(&self) -> ParameterCounts {
        let v = &self.vision;
        let (d, f) = (v.hidden_size, v.intermediate_size);
        let vision_layer = 4 * (d * d + d) + 2 * (2 * d) + (d * f + f) + (f * d + d);
        let vision =
            3 * v.patch_size * v.patch_size * d + d + v.tokens() * d + self.vision_layers_needed() * vision_layer;
        let t = &self.text;
        let dm = t.hidden_size;
        let projector = d * dm + dm + dm * dm + dm + dm; // + image_newline
        let kv = t.num_kv_heads * t.head_dim;
        let q = t.num_heads * t.head_dim;
        let text_layer = dm * q + q + 2 * (dm * kv + kv) + q * dm + 3 * dm * t.intermediate_size + 2 * dm;
        let embed = t.vocab_size * dm;
        let head = if t.tie_word_embeddings { 0 } else { t.vocab_size * dm };
        let text = embed + head + t.num_layers * text_layer + dm;
        ParameterCounts { vision, projector, text }
    }

    /// The published `llava-hf/llava-onevision-qwen2-0.5b-ov-hf` architecture (for size estimates only).
    pub fn onevision_0_5b() -> Self {
        Self::published(TextConfig {
            vocab_size: 152_000,
            hidden_size: 896,
            intermediate_size: 4864,
            num_layers: 24,
            num_heads: 14,
            num_kv_heads: 2,
            head_dim: 64,
            rms_norm_eps: 1e-6,
            rope_theta: 1e6,
            max_positions: 32_768,
            tie_word_embeddings: true,
            eos_token_ids: vec![151_645],
            act: Act::Silu,
        })
    }

    /// The published `llava-hf/llava-onevision-qwen2-7b-ov-hf` architecture (for size estimates only).
    pub fn onevision_7b() -> Self {
        Self::published(TextConfig {
            vocab_size: 152_128,
            hidden_size: 3584,
            intermediate_size: 18_944,
            num_layers: 28,
            num_heads: 28,
            num_kv_heads: 4,
            head_dim: 128,
            rms_norm_eps: 1e-6,
            rope_theta: 1e6,
            max_positions: 32_768,
            tie_word_embeddings: false,
            eos_token_ids: vec![151_645],
            act: Act::Silu,
        })
    }

    fn published(text: TextConfig) -> Self {
        LlavaConfig {
            vision: VisionConfig {
                hidden_size: 1152,
                intermediate_size: 4304,
                num_layers: 26,
                num_heads: 16,
                image_size: 384,
                patch_size: 14,
                layer_norm_eps: 1e-6,
                act: Act::GeluTanh,
            },
            text,
            image_token_id: 151_646,
            vision_feature_layer: -1,
            projector_act: Act::Gelu,
            projector_bias: true,
            pinpoints: (1..=6).flat_map(|h| (1..=6).map(move |w| (384 * h, 384 * w))).collect(),
            max_num_patches: 9,
        }
    }
}

/// Parameter counts by part.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ParameterCounts {
    pub vision: usize,
    pub projector: usize,
    pub text: usize,
}

impl ParameterCounts {
    pub fn total(&self) -> usize {
        self.vision + self.projector + self.text
    }
}

/// The image processor settings (`preprocessor_config.json`, or `processor_config.json["image_processor"]`).
#[derive(Clone, Debug, PartialEq)]
pub struct ProcessorConfig {
    pub mean: [f32; 3],
    pub std: [f32; 3],
    pub rescale_factor: f64,
    /// Base view size (height, width).
    pub size: (usize, usize),
    /// PIL resample filter: 2 = bilinear, 3 = bicubic.
    pub resample: u32,
    pub pinpoints: Vec<(usize, usize)>,
}

pub fn read_json(path: &Path) -> Result<Value, VlmError> {
    let text = std::fs::read_to_string(path).map_err(|e| VlmError::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| VlmError::config(path, format!("not valid JSON: {e}")))
}

struct Obj<'a> {
    v: &'a Value,
    file: &'a Path,
    prefix: &'a str,
}

impl<'a> Obj<'a> {
    fn get(&self, key: &str) -> Option<&'a Value> {
        self.v.get(key).filter(|v| !v.is_null())
    }
    fn name(&self, key: &str) -> String {
        if self.prefix.is_empty() { key.to_string() } else { format!("{}.{key}", self.prefix) }
    }
    fn usize(&self, key: &str, default: Option<usize>) -> Result<usize, VlmError> {
        match self.get(key) {
            Some(v) => v.as_u64().map(|x| x as usize).ok_or_else(|| {
                VlmError::config(self.file, format!("{} must be a non-negative integer, got {v}", self.name(key)))
            }),
            None => default.ok_or_else(|| VlmError::config(self.file, format!("{} is missing", self.name(key)))),
        }
    }
    fn f64(&self, key: &str, default: Option<f64>) -> Result<f64, VlmError> {
        match self.get(key) {
            Some(v) => v
                .as_f64()
                .ok_or_else(|| VlmError::config(self.file, format!("{} must be a number, got {v}", self.name(key)))),
            None => default.ok_or_else(|| VlmError::config(self.file, format!("{} is missing", self.name(key)))),
        }
    }
    fn str(&self, key: &str, default: Option<&'a str>) -> Result<&'a str, VlmError> {
        match self.get(key) {
            Some(v) => v
                .as_str()
                .ok_or_else(|| VlmError::config(self.file, format!("{} must be a string, got {v}", self.name(key)))),
            None => default.ok_or_else(|| VlmError::config(self.file, format!("{} is missing", self.name(key)))),
        }
    }
    fn bool(&self, key: &str, default: bool) -> Result<bool, VlmError> {
        match self.get(key) {
            Some(v) => v.as_bool().ok_or_else(|| {
                VlmError::config(self.file, format!("{} must be true or false, got {v}", self.name(key)))
            }),
            None => Ok(default),
        }
    }
    fn pinpoints(&self, key: &str) -> Result<Option<Vec<(usize, usize)>>, VlmError> {
        let Some(v) = self.get(key) else { return Ok(None) };
        let bad = || VlmError::config(self.file, format!("{} must be a list of [height, width] pairs", self.name(key)));
        let list = v.as_array().ok_or_else(bad)?;
        let mut out = Vec::with_capacity(list.len());
        for p in list {
            let p = p.as_array().filter(|p| p.len() == 2).ok_or_else(bad)?;
            let h = p[0].as_u64().ok_or_else(bad)? as usize;
            let w = p[1].as_u64().ok_or_else(bad)? as usize;
            out.push((h, w));
        }
        if out.is_empty() {
            return Err(bad());
        }
        Ok(Some(out))
    }
}

fn token_ids(v: Option<&Value>) -> Vec<u32> {
    match v {
        Some(Value::Number(n)) => n.as_u64().map(|x| vec![x as u32]).unwrap_or_default(),
        Some(Value::Array(a)) => a.iter().filter_map(|x| x.as_u64().map(|x| x as u32)).collect(),
        _ => Vec::new(),
    }
}

/// The rotary base of the text model, read from every form Hugging Face writes: `rope_theta` in
/// `text_config`; a scaled rope as `rope_scaling` (`{"type" | "rope_type": ..., "factor": ...}`,
/// in `text_config` or, in older files, at the top); and, since transformers 4.56, both together as
/// `rope_parameters` (`{"rope_type", "rope_theta", ...}`). This port rotates by unscaled positions,
/// so any type but `"default"` (or a `factor` other than 1 without a type) is refused, naming the
/// key: a checkpoint with a scaled rope would otherwise answer with the wrong positions.
fn rope_theta(top: &Obj, to: &Obj, file: &Path) -> Result<f64, VlmError> {
    let mut theta = to.f64("rope_theta", Some(10_000.0))?;
    let places = [(top, "rope_scaling"), (to, "rope_scaling"), (to, "rope_parameters")];
    for (obj, key) in places {
        let Some(v) = obj.get(key) else { continue };
        let name = obj.name(key);
        if !v.is_object() {
            return Err(VlmError::config(file, format!("{name} must be an object, got {v}")));
        }
        let ro = Obj { v, file, prefix: &name };
        let mut typed = false;
        for k in ["rope_type", "type"] {
            let t = ro.str(k, Some("default"))?;
            typed |= ro.get(k).is_some();
            if t != "default" {
                return Err(VlmError::config(
                    file,
                    format!(
                        "{name}.{k} is \"{t}\": scaled rotary positions are not supported (only \"default\"); \
                         the model would answer with the wrong positions"
                    ),
                ));
            }
        }
        let factor = ro.f64("factor", Some(1.0))?;
        if !typed && factor != 1.0 {
            return Err(VlmError::config(
                file,
                format!("{name}.factor is {factor} without a type: a scaled rope is not supported"),
            ));
        }
        if ro.get("rope_theta").is_some() {
            theta = ro.f64("rope_theta", None)?;
        }
    }
    if !(theta.is_finite() && theta > 1.0) {
        return Err(VlmError::config(file, format!("text_config rope_theta must be a number above 1, got {theta}")));
    }
    Ok(theta)
}

/// Parses `config.json` of a LLaVA-OneVision model directory.
pub fn parse_llava_config(file: &Path, root: &Value) -> Result<LlavaConfig, VlmError> {
    let top = Obj { v: root, file, prefix: "" };
    let archs: Vec<&str> = root
        .get("architectures")
        .and_then(|a| a.as_array())
        .map(|a| a.iter().filter_map(|x| x.as_str()).collect())
        .unwrap_or_default();
    let model_type = top.str("model_type", Some(""))?;
    if model_type != "llava_onevision" && !archs.contains(&"LlavaOnevisionForConditionalGeneration") {
        return Err(VlmError::config(
            file,
            format!(
                "unsupported architecture {archs:?} (model_type \"{model_type}\"); expected \
                    LlavaOnevisionForConditionalGeneration"
            ),
        ));
    }
    let vision_v = top.get("vision_config").ok_or_else(|| VlmError::config(file, "vision_config is missing"))?;
    let text_v = top.get("text_config").ok_or_else(|| VlmError::config(file, "text_config is missing"))?;
    let vo = Obj { v: vision_v, file, prefix: "vision_config" };
    let vt = vo.str("model_type", Some("siglip_vision_model"))?;
    if vt != "siglip_vision_model" {
        return Err(VlmError::config(
            file,
            format!("vision_config.model_type \"{vt}\" is not supported (siglip_vision_model)"),
        ));
    }
    if vo.bool("vision_use_head", false)? {
        // The pooling head is unused by LLaVA; its weights are simply ignored.
    }
    let vision = VisionConfig {
        hidden_size: vo.usize("hidden_size", Some(768))?,
        intermediate_size: vo.usize("intermediate_size", Some(3072))?,
        num_layers: vo.usize("num_hidden_layers", Some(12))?,
        num_heads: vo.usize("num_attention_heads", Some(12))?,
        image_size: vo.usize("image_size", Some(224))?,
        patch_size: vo.usize("patch_size", Some(16))?,
        layer_norm_eps: vo.f64("layer_norm_eps", Some(1e-6))?,
        act: Act::parse(vo.str("hidden_act", Some("gelu_pytorch_tanh"))?, file, "vision_config.hidden_act")?,
    };
    if vo.usize("num_channels", Some(3))? != 3 {
        return Err(VlmError::config(file, "vision_config.num_channels must be 3"));
    }
    if vision.patch_size == 0
        || vision.patch_size > vision.image_size
        || vision.num_heads == 0
        || !vision.hidden_size.is_multiple_of(vision.num_heads)
    {
        return Err(VlmError::config(
            file,
            "vision_config: patch_size must be in 1..=image_size and hidden_size a multiple of num_attention_heads",
        ));
    }

    let to = Obj { v: text_v, file, prefix: "text_config" };
    let tt = to.str("model_type", Some("qwen2"))?;
    if tt != "qwen2" {
        return Err(VlmError::config(file, format!("text_config.model_type \"{tt}\" is not supported (qwen2)")));
    }
    if to.bool("use_sliding_window", false)? {
        return Err(VlmError::config(file, "text_config.use_sliding_window = true is not supported"));
    }
    let rope_theta = rope_theta(&top, &to, file)?;
    let hidden = to.usize("hidden_size", Some(4096))?;
    let heads = to.usize("num_attention_heads", Some(32))?;
    if heads == 0 {
        return Err(VlmError::config(file, "text_config.num_attention_heads must be positive"));
    }
    let kv_heads = to.usize("num_key_value_heads", Some(heads))?;
    if kv_heads == 0 || heads % kv_heads != 0 {
        return Err(VlmError::config(
            file,
            "text_config.num_attention_heads must be a multiple of num_key_value_heads",
        ));
    }
    let head_dim = to.usize("head_dim", Some(hidden / heads))?;
    if head_dim % 2 != 0 {
        return Err(VlmError::config(file, "text_config head_dim must be even for rotary embeddings"));
    }
    let tie_text = to.bool("tie_word_embeddings", false)?;
    let mut eos = token_ids(to.get("eos_token_id"));
    eos.extend(token_ids(top.get("eos_token_id")));
    let text = TextConfig {
        vocab_size: to.usize("vocab_size", Some(151_936))?,
        hidden_size: hidden,
        intermediate_size: to.usize("intermediate_size", Some(22_016))?,
        num_layers: to.usize("num_hidden_layers", Some(32))?,
        num_heads: heads,
        num_kv_heads: kv_heads,
        head_dim,
        rms_norm_eps: to.f64("rms_norm_eps", Some(1e-6))?,
        rope_theta,
        max_positions: to.usize("max_position_embeddings", Some(32_768))?,
        tie_word_embeddings: tie_text || top.bool("tie_word_embeddings", false)?,
        eos_token_ids: eos,
        act: Act::parse(to.str("hidden_act", Some("silu"))?, file, "text_config.hidden_act")?,
    };

    let layer = match top.get("vision_feature_layer") {
        None => -1,
        Some(v) => v.as_i64().ok_or_else(|| {
            VlmError::config(file, format!("vision_feature_layer = {v}: only a single layer index is supported"))
        })?,
    };
    let n = vision.num_layers as i64;
    if layer > n || layer < -(n + 1) {
        return Err(VlmError::config(
            file,
            format!("vision_feature_layer {layer} is outside the {n}-layer vision tower"),
        ));
    }
    let strategy = top.str("vision_feature_select_strategy", Some("full"))?;
    if strategy != "full" {
        // "default" drops a CLS token, which SigLIP does not have; LLaVA-OneVision uses "full".
        return Err(VlmError::config(
            file,
            format!("vision_feature_select_strategy \"{strategy}\" is not supported (full)"),
        ));
    }
    let aspect = top.str("vision_aspect_ratio", Some("anyres_max_9"))?;
    let max_num_patches =
        aspect.strip_prefix("anyres_max_").and_then(|n| n.parse::<usize>().ok()).filter(|n| *n > 0).ok_or_else(
            || VlmError::config(file, format!("vision_aspect_ratio \"{aspect}\" is not supported (anyres_max_N)")),
        )?;
    let pinpoints = top.pinpoints("image_grid_pinpoints")?.unwrap_or_else(|| LlavaConfig::onevision_0_5b().pinpoints);
    Ok(LlavaConfig {
        vision,
        text,
        image_token_id: top.usize("image_token_index", None).or_else(|_| top.usize("image_token_id", Some(151_646)))?
            as u32,
        vision_feature_layer: layer,
        projector_act: Act::parse(top.str("projector_hidden_act", Some("gelu"))?, file, "projector_hidden_act")?,
        projector_bias: top.bool("multimodal_projector_bias", true)?,
        pinpoints,
        max_num_patches,
    })
}

/// Reads the image processor settings from `preprocessor_config.json`, or from the
/// `image_processor` entry of `processor_config.json` (how transformers 5 saves it).
pub fn load_processor_config(dir: &Path, model: &LlavaConfig) -> Result<ProcessorConfig, VlmError> {
    let pre = dir.join("preprocessor_config.json");
    let proc = dir.join("processor_config.json");
    let (file, root) = if pre.exists() {
        (pre.clone(), read_json(&pre)?)
    } else if proc.exists() {
        let v = read_json(&proc)?;
        let inner =
            v.get("image_processor").cloned().ok_or_else(|| VlmError::config(&proc, "has no image_processor entry"))?;
        (proc.clone(), inner)
    } else {
        return Err(VlmError::config(dir, "neither preprocessor_config.json nor processor_config.json is present"));
    };
    let o = Obj { v: &root, file: &file, prefix: "" };
    let triple = |key: &str, default: f32| -> Result<[f32; 3], VlmError> {
        match o.get(key) {
            None => Ok([default; 3]),
            Some(Value::Number(n)) => Ok([n.as_f64().unwrap_or(default as f64) as f32; 3]),
            Some(Value::Array(a)) if a.len() == 3 && a.iter().all(|x| x.is_number()) => {
                Ok([a[0].as_f64().unwrap() as f32, a[1].as_f64().unwrap() as f32, a[2].as_f64().unwrap() as f32])
            }
            Some(v) => Err(VlmError::config(&file, format!("{key} must be 3 numbers, got {v}"))),
        }
    };
    let size = match o.get("size") {
        Some(s) => {
            let so = Obj { v: s, file: &file, prefix: "size" };
            match so.get("shortest_edge") {
                Some(_) => {
                    let e = so.usize("shortest_edge", None)?;
                    (e, e)
                }
                None => (so.usize("height", None)?, so.usize("width", None)?),
            }
        }
        None => (model.vision.image_size, model.vision.image_size),
    };
    if size != (model.vision.image_size, model.vision.image_size) {
        return Err(VlmError::config(
            &file,
            format!("size {size:?} differs from the vision tower's {0}x{0}", model.vision.image_size),
        ));
    }
    let resample = o.usize("resample", Some(3))? as u32;
    if resample != 2 && resample != 3 {
        return Err(VlmError::config(&file, format!("resample = {resample} is not supported (2 bilinear, 3 bicubic)")));
    }
    let std = triple("image_std", 0.5)?;
    if std.contains(&0.0) {
        return Err(VlmError::config(&file, "image_std must not contain 0"));
    }
    Ok(ProcessorConfig {
        mean: triple("image_mean", 0.5)?,
        std,
        rescale_factor: o.f64("rescale_factor", Some(1.0 / 255.0))?,
        size,
        resample,
        pinpoints: o.pinpoints("image_grid_pinpoints")?.unwrap_or_else(|| model.pinpoints.clone()),
    })
}

fn act_name(a: Act) -> &'static str {
    match a {
        Act::Gelu => "gelu",
        Act::GeluTanh => "gelu_pytorch_tanh",
        Act::Silu => "silu",
    }
}

impl LlavaConfig {
    /// `config.json` of this configuration in the llava-hf layout: what [`parse_llava_config`]
    /// (and transformers' `LlavaOnevisionConfig`) reads.
    pub fn to_hf_json(&self) -> Value {
        let (v, t) = (&self.vision, &self.text);
        let pinpoints: Vec<[usize; 2]> = self.pinpoints.iter().map(|&(h, w)| [h, w]).collect();
        serde_json::json!({
            "architectures": ["LlavaOnevisionForConditionalGeneration"],
            "model_type": "llava_onevision",
            "image_token_index": self.image_token_id,
            "video_token_index": self.image_token_id + 1,
            "vision_feature_layer": self.vision_feature_layer,
            "vision_feature_select_strategy": "full",
            "vision_aspect_ratio": format!("anyres_max_{}", self.max_num_patches),
            "image_grid_pinpoints": pinpoints,
            "projector_hidden_act": act_name(self.projector_act),
            "multimodal_projector_bias": self.projector_bias,
            "tie_word_embeddings": t.tie_word_embeddings,
            "dtype": "bfloat16",
            "vision_config": {
                "model_type": "siglip_vision_model",
                "hidden_size": v.hidden_size,
                "intermediate_size": v.intermediate_size,
                "num_hidden_layers": v.num_layers,
                "num_attention_heads": v.num_heads,
                "image_size": v.image_size,
                "patch_size": v.patch_size,
                "num_channels": 3,
                "layer_norm_eps": v.layer_norm_eps,
                "hidden_act": act_name(v.act),
                "attention_dropout": 0.0,
                "vision_use_head": false,
            },
            "text_config": {
                "model_type": "qwen2",
                "vocab_size": t.vocab_size,
                "hidden_size": t.hidden_size,
                "intermediate_size": t.intermediate_size,
                "num_hidden_layers": t.num_layers,
                "num_attention_heads": t.num_heads,
                "num_key_value_heads": t.num_kv_heads,
                "head_dim": t.head_dim,
                "rms_norm_eps": t.rms_norm_eps,
                "rope_parameters": {"rope_type": "default", "rope_theta": t.rope_theta},
                "max_position_embeddings": t.max_positions,
                "hidden_act": act_name(t.act),
                "tie_word_embeddings": t.tie_word_embeddings,
                "use_sliding_window": false,
                "sliding_window": null,
                "attention_dropout": 0.0,
                "eos_token_id": t.eos_token_ids,
                "layer_types": vec!["full_attention"; t.num_layers],
            },
        })
    }
}

impl ProcessorConfig {
    /// `processor_config.json` in the transformers-5 layout (the image processor entry holds
    /// these settings).
    pub fn to_hf_json(&self, model: &LlavaConfig) -> Value {
        let pinpoints: Vec<[usize; 2]> = self.pinpoints.iter().map(|&(h, w)| [h, w]).collect();
        serde_json::json!({
            "image_processor": {
                "image_processor_type": "LlavaOnevisionImageProcessor",
                "do_convert_rgb": true,
                "do_normalize": true,
                "do_pad": true,
                "do_rescale": true,
                "do_resize": true,
                "image_grid_pinpoints": pinpoints,
                "image_mean": self.mean,
                "image_std": self.std,
                "resample": self.resample,
                "rescale_factor": self.rescale_factor,
                "size": {"height": self.size.0, "width": self.size.1},
            },
            "image_token": "<image>",
            "num_image_tokens": model.vision.tokens(),
            "processor_class": "LlavaOnevisionProcessor",
            "video_token": "<video>",
            "vision_aspect_ratio": format!("anyres_max_{}", model.max_num_patches),
            "vision_feature_select_strategy": "full",
        })
    }
}
