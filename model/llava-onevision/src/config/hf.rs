//! The Hugging Face side of the configs: `config.json` and `preprocessor_config.json` read through
//! serde structs (transformers' defaults put in, what the port does not implement refused by name)
//! and written back in the llava-hf layout.

use super::{Act, LlavaConfig, ProcessorConfig, TextConfig, VisionConfig};
use crate::VlmError;
use serde::Deserialize;
use serde::de::DeserializeOwned;
use serde_json::Value;
use std::path::Path;

pub fn read_json(path: &Path) -> Result<Value, VlmError> {
    let text = std::fs::read_to_string(path).map_err(|e| VlmError::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| VlmError::config(path, format!("not valid JSON: {e}")))
}

/// Reads `v` (found at `at` in `file`, "" for the top) into `T`; a key of the wrong type is named
/// with its whole path, e.g. `text_config.hidden_size: invalid type: string "x", expected usize`.
fn from_json<T: DeserializeOwned>(file: &Path, at: &str, v: &Value) -> Result<T, VlmError> {
    serde_path_to_error::deserialize(v).map_err(|e| {
        let inner = e.inner().to_string();
        let path = match (at, e.path().to_string()) {
            ("", p) => p,
            (at, p) if p == "." => at.to_string(),
            (at, p) => format!("{at}.{p}"),
        };
        VlmError::config(file, if path == "." { inner } else { format!("{path}: {inner}") })
    })
}

/// `config.json` of `LlavaOnevisionForConditionalGeneration` as Hugging Face writes it: the keys
/// this port reads. Every key may be absent or `null`; [`parse_llava_config`] puts in
/// transformers' defaults and checks what the port supports.
#[derive(Deserialize)]
#[serde(expecting = "an object")]
struct HfLlava {
    vision_config: Option<HfVision>,
    text_config: Option<HfText>,
    rope_scaling: Option<Value>,
    tie_word_embeddings: Option<bool>,
    eos_token_id: Option<TokenIds>,
    vision_feature_layer: Option<OneOrMany<i64>>,
    vision_feature_select_strategy: Option<String>,
    vision_aspect_ratio: Option<String>,
    image_grid_pinpoints: Option<Vec<[usize; 2]>>,
    image_token_index: Option<usize>,
    image_token_id: Option<usize>,
    projector_hidden_act: Option<String>,
    multimodal_projector_bias: Option<bool>,
}

/// `vision_config` (SigLIP).
#[derive(Deserialize)]
#[serde(expecting = "an object")]
struct HfVision {
    model_type: Option<String>,
    hidden_size: Option<usize>,
    intermediate_size: Option<usize>,
    num_hidden_layers: Option<usize>,
    num_attention_heads: Option<usize>,
    image_size: Option<usize>,
    patch_size: Option<usize>,
    num_channels: Option<usize>,
    layer_norm_eps: Option<f64>,
    hidden_act: Option<String>,
}

/// `text_config` (Qwen2).
#[derive(Deserialize)]
#[serde(expecting = "an object")]
struct HfText {
    model_type: Option<String>,
    use_sliding_window: Option<bool>,
    vocab_size: Option<usize>,
    hidden_size: Option<usize>,
    intermediate_size: Option<usize>,
    num_hidden_layers: Option<usize>,
    num_attention_heads: Option<usize>,
    num_key_value_heads: Option<usize>,
    head_dim: Option<usize>,
    rms_norm_eps: Option<f64>,
    rope_theta: Option<f64>,
    rope_scaling: Option<Value>,
    rope_parameters: Option<Value>,
    max_position_embeddings: Option<usize>,
    tie_word_embeddings: Option<bool>,
    eos_token_id: Option<TokenIds>,
    hidden_act: Option<String>,
}

/// `rope_scaling` / `rope_parameters`.
#[derive(Deserialize)]
#[serde(expecting = "an object")]
struct HfRope {
    rope_type: Option<String>,
    #[serde(rename = "type")]
    kind: Option<String>,
    factor: Option<f64>,
    rope_theta: Option<f64>,
}

/// One value or a list of them (`eos_token_id`, `vision_feature_layer`).
#[derive(Deserialize)]
#[serde(untagged)]
enum OneOrMany<T> {
    One(T),
    Many(Vec<T>),
}

/// End-of-sequence ids: a number, a list, or entries transformers leaves `null`.
#[derive(Deserialize)]
#[serde(untagged)]
enum TokenIds {
    Ids(OneOrMany<u32>),
    Other(serde::de::IgnoredAny),
}

impl TokenIds {
    fn ids(&self) -> Vec<u32> {
        match self {
            TokenIds::Ids(OneOrMany::One(x)) => vec![*x],
            TokenIds::Ids(OneOrMany::Many(v)) => v.clone(),
            TokenIds::Other(_) => Vec::new(),
        }
    }
}

/// The rotary base of the text model, read from every form Hugging Face writes: `rope_theta` in
/// `text_config`; a scaled rope as `rope_scaling` (`{"type" | "rope_type": ..., "factor": ...}`,
/// in `text_config` or, in older files, at the top); and, since transformers 4.56, both together as
/// `rope_parameters` (`{"rope_type", "rope_theta", ...}`). This port rotates by unscaled positions,
/// so any type but `"default"` (or a `factor` other than 1 without a type) is refused, naming the
/// key: a checkpoint with a scaled rope would otherwise answer with the wrong positions.
fn rope_theta(top: &HfLlava, text: &HfText, file: &Path) -> Result<f64, VlmError> {
    let mut theta = text.rope_theta.unwrap_or(10_000.0);
    let places = [
        ("rope_scaling", &top.rope_scaling),
        ("text_config.rope_scaling", &text.rope_scaling),
        ("text_config.rope_parameters", &text.rope_parameters),
    ];
    for (name, v) in places {
        let Some(v) = v.as_ref().filter(|v| !v.is_null()) else { continue };
        if !v.is_object() {
            return Err(VlmError::config(file, format!("{name} must be an object, got {v}")));
        }
        let rope: HfRope = from_json(file, name, v)?;
        for (k, t) in [("rope_type", &rope.rope_type), ("type", &rope.kind)] {
            if let Some(t) = t.as_deref().filter(|t| *t != "default") {
                return Err(VlmError::config(
                    file,
                    format!(
                        "{name}.{k} is \"{t}\": scaled rotary positions are not supported (only \"default\"); \
                         the model would answer with the wrong positions"
                    ),
                ));
            }
        }
        let typed = rope.rope_type.is_some() || rope.kind.is_some();
        let factor = rope.factor.unwrap_or(1.0);
        if !typed && factor != 1.0 {
            return Err(VlmError::config(
                file,
                format!("{name}.factor is {factor} without a type: a scaled rope is not supported"),
            ));
        }
        theta = rope.rope_theta.unwrap_or(theta);
    }
    if !(theta.is_finite() && theta > 1.0) {
        return Err(VlmError::config(file, format!("text_config rope_theta must be a number above 1, got {theta}")));
    }
    Ok(theta)
}

/// An activation named by `key`, `default` when absent.
fn act(name: &Option<String>, default: &str, file: &Path, key: &str) -> Result<Act, VlmError> {
    Act::parse(name.as_deref().unwrap_or(default), file, key)
}

/// `image_grid_pinpoints`: a non-empty list of [height, width] pairs, `None` when absent.
fn pinpoints(v: Option<Vec<[usize; 2]>>, file: &Path) -> Result<Option<Vec<(usize, usize)>>, VlmError> {
    match v {
        Some(list) if list.is_empty() => {
            Err(VlmError::config(file, "image_grid_pinpoints must be a list of [height, width] pairs"))
        }
        list => Ok(list.map(|l| l.into_iter().map(|[h, w]| (h, w)).collect())),
    }
}

/// Reads `dir/config.json`: the model's shapes, without touching its weights.
pub fn read_llava_config(dir: &Path) -> Result<LlavaConfig, VlmError> {
    let path = dir.join("config.json");
    if !path.exists() {
        return Err(VlmError::config(&path, "is missing"));
    }
    parse_llava_config(&path, &read_json(&path)?)
}

/// Parses `config.json` of a LLaVA-OneVision model directory.
pub fn parse_llava_config(file: &Path, root: &Value) -> Result<LlavaConfig, VlmError> {
    if !root.is_object() {
        return Err(VlmError::config(file, format!("must be a JSON object, got {root}")));
    }
    // The architecture first, so that another model's config is named as such, not by a key.
    let archs: Vec<&str> = root
        .get("architectures")
        .and_then(|a| a.as_array())
        .map(|a| a.iter().filter_map(|x| x.as_str()).collect())
        .unwrap_or_default();
    let model_type = root.get("model_type").and_then(|t| t.as_str()).unwrap_or("");
    if model_type != "llava_onevision" && !archs.contains(&"LlavaOnevisionForConditionalGeneration") {
        return Err(VlmError::config(
            file,
            format!(
                "unsupported architecture {archs:?} (model_type \"{model_type}\"); expected \
                    LlavaOnevisionForConditionalGeneration"
            ),
        ));
    }
    let top: HfLlava = from_json(file, "", root)?;
    let vo = top.vision_config.as_ref().ok_or_else(|| VlmError::config(file, "vision_config is missing"))?;
    let to = top.text_config.as_ref().ok_or_else(|| VlmError::config(file, "text_config is missing"))?;

    let vt = vo.model_type.as_deref().unwrap_or("siglip_vision_model");
    if vt != "siglip_vision_model" {
        return Err(VlmError::config(
            file,
            format!("vision_config.model_type \"{vt}\" is not supported (siglip_vision_model)"),
        ));
    }
    let vision = VisionConfig {
        hidden_size: vo.hidden_size.unwrap_or(768),
        intermediate_size: vo.intermediate_size.unwrap_or(3072),
        num_layers: vo.num_hidden_layers.unwrap_or(12),
        num_heads: vo.num_attention_heads.unwrap_or(12),
        image_size: vo.image_size.unwrap_or(224),
        patch_size: vo.patch_size.unwrap_or(16),
        layer_norm_eps: vo.layer_norm_eps.unwrap_or(1e-6),
        act: act(&vo.hidden_act, "gelu_pytorch_tanh", file, "vision_config.hidden_act")?,
    };
    if vo.num_channels.unwrap_or(3) != 3 {
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

    let tt = to.model_type.as_deref().unwrap_or("qwen2");
    if tt != "qwen2" {
        return Err(VlmError::config(file, format!("text_config.model_type \"{tt}\" is not supported (qwen2)")));
    }
    if to.use_sliding_window.unwrap_or(false) {
        return Err(VlmError::config(file, "text_config.use_sliding_window = true is not supported"));
    }
    let rope_theta = rope_theta(&top, to, file)?;
    let hidden = to.hidden_size.unwrap_or(4096);
    let heads = to.num_attention_heads.unwrap_or(32);
    if heads == 0 {
        return Err(VlmError::config(file, "text_config.num_attention_heads must be positive"));
    }
    let kv_heads = to.num_key_value_heads.unwrap_or(heads);
    if kv_heads == 0 || heads % kv_heads != 0 {
        return Err(VlmError::config(
            file,
            "text_config.num_attention_heads must be a multiple of num_key_value_heads",
        ));
    }
    let head_dim = to.head_dim.unwrap_or(hidden / heads);
    if head_dim % 2 != 0 {
        return Err(VlmError::config(file, "text_config head_dim must be even for rotary embeddings"));
    }
    let mut eos = to.eos_token_id.as_ref().map(TokenIds::ids).unwrap_or_default();
    eos.extend(top.eos_token_id.as_ref().map(TokenIds::ids).unwrap_or_default());
    let text = TextConfig {
        vocab_size: to.vocab_size.unwrap_or(151_936),
        hidden_size: hidden,
        intermediate_size: to.intermediate_size.unwrap_or(22_016),
        num_layers: to.num_hidden_layers.unwrap_or(32),
        num_heads: heads,
        num_kv_heads: kv_heads,
        head_dim,
        rms_norm_eps: to.rms_norm_eps.unwrap_or(1e-6),
        rope_theta,
        max_positions: to.max_position_embeddings.unwrap_or(32_768),
        tie_word_embeddings: to.tie_word_embeddings.unwrap_or(false) || top.tie_word_embeddings.unwrap_or(false),
        eos_token_ids: eos,
        act: act(&to.hidden_act, "silu", file, "text_config.hidden_act")?,
    };

    let layer = match &top.vision_feature_layer {
        None => -1,
        Some(OneOrMany::One(i)) => *i,
        Some(OneOrMany::Many(l)) => {
            return Err(VlmError::config(
                file,
                format!("vision_feature_layer = {l:?}: only a single layer index is supported"),
            ));
        }
    };
    let n = vision.num_layers as i64;
    if layer > n || layer < -(n + 1) {
        return Err(VlmError::config(
            file,
            format!("vision_feature_layer {layer} is outside the {n}-layer vision tower"),
        ));
    }
    let strategy = top.vision_feature_select_strategy.as_deref().unwrap_or("full");
    if strategy != "full" {
        // "default" drops a CLS token, which SigLIP does not have; LLaVA-OneVision uses "full".
        return Err(VlmError::config(
            file,
            format!("vision_feature_select_strategy \"{strategy}\" is not supported (full)"),
        ));
    }
    let aspect = top.vision_aspect_ratio.as_deref().unwrap_or("anyres_max_9");
    let max_num_patches =
        aspect.strip_prefix("anyres_max_").and_then(|n| n.parse::<usize>().ok()).filter(|n| *n > 0).ok_or_else(
            || VlmError::config(file, format!("vision_aspect_ratio \"{aspect}\" is not supported (anyres_max_N)")),
        )?;
    let pinpoints =
        pinpoints(top.image_grid_pinpoints.clone(), file)?.unwrap_or_else(|| LlavaConfig::onevision_0_5b().pinpoints);
    Ok(LlavaConfig {
        vision,
        text,
        image_token_id: top.image_token_index.or(top.image_token_id).unwrap_or(151_646) as u32,
        vision_feature_layer: layer,
        projector_act: act(&top.projector_hidden_act, "gelu", file, "projector_hidden_act")?,
        projector_bias: top.multimodal_projector_bias.unwrap_or(true),
        pinpoints,
        max_num_patches,
    })
}

/// The image processor entry: the keys this port reads.
#[derive(Deserialize)]
#[serde(expecting = "an object")]
struct HfProcessor {
    image_mean: Option<OneOrMany<f32>>,
    image_std: Option<OneOrMany<f32>>,
    rescale_factor: Option<f64>,
    size: Option<HfSize>,
    resample: Option<u32>,
    image_grid_pinpoints: Option<Vec<[usize; 2]>>,
}

/// `size`: `{"shortest_edge": n}` or `{"height": h, "width": w}`.
#[derive(Deserialize)]
#[serde(expecting = "an object")]
struct HfSize {
    shortest_edge: Option<usize>,
    height: Option<usize>,
    width: Option<usize>,
}

/// A per-channel triple written as one number or three.
fn triple(v: Option<OneOrMany<f32>>, default: f32, file: &Path, key: &str) -> Result<[f32; 3], VlmError> {
    match v {
        None => Ok([default; 3]),
        Some(OneOrMany::One(x)) => Ok([x; 3]),
        Some(OneOrMany::Many(l)) => <[f32; 3]>::try_from(l.as_slice())
            .map_err(|_| VlmError::config(file, format!("{key} must be 3 numbers, got {}", l.len()))),
    }
}

/// Reads the image processor settings from `preprocessor_config.json`, or from the
/// `image_processor` entry of `processor_config.json` (how transformers 5 saves it).
pub fn load_processor_config(dir: &Path, model: &LlavaConfig) -> Result<ProcessorConfig, VlmError> {
    let pre = dir.join("preprocessor_config.json");
    let proc = dir.join("processor_config.json");
    let (file, at, root) = if pre.exists() {
        (pre.clone(), "", read_json(&pre)?)
    } else if proc.exists() {
        let v = read_json(&proc)?;
        let inner = v
            .get("image_processor")
            .filter(|v| !v.is_null())
            .cloned()
            .ok_or_else(|| VlmError::config(&proc, "has no image_processor entry"))?;
        (proc.clone(), "image_processor", inner)
    } else {
        return Err(VlmError::config(dir, "neither preprocessor_config.json nor processor_config.json is present"));
    };
    let o: HfProcessor = from_json(&file, at, &root)?;
    let size = match o.size {
        Some(HfSize { shortest_edge: Some(e), .. }) => (e, e),
        Some(HfSize { height: Some(h), width: Some(w), .. }) => (h, w),
        Some(_) => return Err(VlmError::config(&file, "size needs shortest_edge, or height and width")),
        None => (model.vision.image_size, model.vision.image_size),
    };
    if size != (model.vision.image_size, model.vision.image_size) {
        return Err(VlmError::config(
            &file,
            format!("size {size:?} differs from the vision tower's {0}x{0}", model.vision.image_size),
        ));
    }
    let resample = o.resample.unwrap_or(3);
    if resample != 2 && resample != 3 {
        return Err(VlmError::config(&file, format!("resample = {resample} is not supported (2 bilinear, 3 bicubic)")));
    }
    let std = triple(o.image_std, 0.5, &file, "image_std")?;
    if std.contains(&0.0) {
        return Err(VlmError::config(&file, "image_std must not contain 0"));
    }
    Ok(ProcessorConfig {
        mean: triple(o.image_mean, 0.5, &file, "image_mean")?,
        std,
        rescale_factor: o.rescale_factor.unwrap_or(1.0 / 255.0),
        size,
        resample,
        pinpoints: pinpoints(o.image_grid_pinpoints, &file)?.unwrap_or_else(|| model.pinpoints.clone()),
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
    /// SigLIP's preprocessing (pixels rescaled by 1/255, then mean and std 0.5 per channel,
    /// bicubic resampling) to `side` squares, with the anyres `pinpoints`.
    pub fn siglip(side: usize, pinpoints: Vec<(usize, usize)>) -> Self {
        Self { mean: [0.5; 3], std: [0.5; 3], rescale_factor: 1.0 / 255.0, size: (side, side), resample: 3, pinpoints }
    }

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

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn parse(v: &Value) -> Result<LlavaConfig, String> {
        parse_llava_config(Path::new("m/config.json"), v).map_err(|e| e.to_string())
    }

    #[test]
    fn written_configs_read_back_the_same() {
        for cfg in [LlavaConfig::onevision_0_5b(), LlavaConfig::onevision_7b()] {
            assert_eq!(parse(&cfg.to_hf_json()).unwrap(), cfg);
            let dir =
                std::env::temp_dir().join(format!("chatsplat-proc-{}-{}", std::process::id(), cfg.text.num_layers));
            std::fs::create_dir_all(&dir).unwrap();
            let proc = ProcessorConfig {
                mean: [0.1, 0.2, 0.3],
                std: [0.5, 0.25, 0.125],
                rescale_factor: 1.0 / 255.0,
                size: (cfg.vision.image_size, cfg.vision.image_size),
                resample: 2,
                pinpoints: vec![(384, 768)],
            };
            std::fs::write(dir.join("processor_config.json"), proc.to_hf_json(&cfg).to_string()).unwrap();
            assert_eq!(load_processor_config(&dir, &cfg).unwrap(), proc);
            std::fs::remove_dir_all(&dir).unwrap();
        }
    }

    #[test]
    fn a_key_of_the_wrong_type_is_named_by_its_path_and_null_takes_the_default() {
        let base = LlavaConfig::onevision_0_5b().to_hf_json();
        let mut c = base.clone();
        c["text_config"]["hidden_size"] = json!("896");
        let e = parse(&c).unwrap_err();
        assert!(e.starts_with("m/config.json: text_config.hidden_size: invalid type"), "{e}");
        let mut c = base.clone();
        c["image_grid_pinpoints"] = json!([[384, 384], [384]]);
        let e = parse(&c).unwrap_err();
        assert!(e.contains("image_grid_pinpoints[1]"), "{e}");
        let mut c = base.clone();
        c["vision_config"] = json!("siglip");
        let e = parse(&c).unwrap_err();
        assert!(e.contains("vision_config: invalid type: string \"siglip\", expected an object"), "{e}");
        let mut c = base.clone();
        c["text_config"]["num_key_value_heads"] = Value::Null;
        c["image_grid_pinpoints"] = Value::Null;
        let cfg = parse(&c).unwrap();
        assert_eq!(cfg.text.num_kv_heads, cfg.text.num_heads, "null is absent: kv heads default to the heads");
        let mut c = base;
        c["vision_feature_layer"] = json!([-2, -1]);
        assert!(parse(&c).unwrap_err().contains("only a single layer index is supported"));
    }
}
