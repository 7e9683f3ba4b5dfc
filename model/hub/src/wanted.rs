//! Which files of a repo a model needs: some by name, some when the repo has them, and its
//! safetensors weights (one `model.safetensors`, or the shards its index names).

use crate::HubError;
use std::path::PathBuf;

/// The files a model folder needs.
#[derive(Clone, Copy, Debug)]
pub struct Wanted {
    /// Needed: a repo without one is refused.
    pub required: &'static [&'static str],
    /// Fetched when the repo has them.
    pub optional: &'static [&'static str],
    /// `model.safetensors`, else `model.safetensors.index.json` and every shard it names.
    pub safetensors: bool,
}

/// LLaVA-OneVision as transformers saves it (`llava-hf/llava-onevision-qwen2-*-hf`).
pub const VLM: Wanted = Wanted {
    required: &["config.json", "tokenizer.json"],
    optional: &[
        "preprocessor_config.json",
        "processor_config.json",
        "tokenizer_config.json",
        "chat_template.json",
        "chat_template.jinja",
        "generation_config.json",
    ],
    safetensors: true,
};

/// Segment Anything as transformers saves it (`facebook/sam-vit-base`, `-large`, `-huge`).
pub const SAM: Wanted =
    Wanted { required: &["config.json"], optional: &["preprocessor_config.json"], safetensors: true };

const SINGLE: &str = "model.safetensors";
const INDEX: &str = "model.safetensors.index.json";

/// Why the wanted files could not all be had.
#[derive(Debug)]
pub enum Missing {
    /// The repo has no such file.
    File(String),
    /// The hub failed otherwise.
    Hub(HubError),
    /// The index of the shards is unreadable: `(file, why)`.
    Index(String, String),
}

/// The shards `index` (a `model.safetensors.index.json`) names, sorted, each once.
pub fn shards(index: &std::path::Path) -> Result<Vec<String>, String> {
    let text = std::fs::read_to_string(index).map_err(|e| e.to_string())?;
    let json: serde_json::Value = serde_json::from_str(&text).map_err(|e| format!("not JSON: {e}"))?;
    let map = json.get("weight_map").and_then(|m| m.as_object()).ok_or("has no weight_map object")?;
    let mut names: Vec<String> = map.values().filter_map(|v| v.as_str().map(String::from)).collect();
    names.sort();
    names.dedup();
    if names.is_empty() || names.iter().any(|n| n.contains("..") || n.starts_with('/')) {
        return Err(format!("names no shard, or one outside the repo: {names:?}"));
    }
    Ok(names)
}

impl Wanted {
    /// Every file fetched through `fetch` (`None`: the repo, or the cache when `fetch` only looks
    /// there, has no such file); the needed ones returned.
    pub fn fetch(
        &self,
        mut fetch: impl FnMut(&str) -> Result<Option<PathBuf>, HubError>,
    ) -> Result<Vec<PathBuf>, Missing> {
        let mut get = |f: &str| fetch(f).map_err(Missing::Hub);
        let mut files = Vec::new();
        for f in self.required {
            files.push(get(f)?.ok_or_else(|| Missing::File(f.to_string()))?);
        }
        for f in self.optional {
            get(f)?;
        }
        if self.safetensors {
            match get(SINGLE)? {
                Some(p) => files.push(p),
                None => {
                    let index = get(INDEX)?.ok_or_else(|| Missing::File(format!("{SINGLE} (nor {INDEX})")))?;
                    for s in shards(&index).map_err(|m| Missing::Index(INDEX.into(), m))? {
                        files.push(get(&s)?.ok_or(Missing::File(s))?);
                    }
                    files.push(index);
                }
            }
        }
        Ok(files)
    }
}
