//! The model's `tokenizer.json` through the Hugging Face `tokenizers` crate, and the
//! LLaVA-OneVision chat template (Qwen2 `<|im_start|>` / `<|im_end|>` turns, `<image>\n` per image
//! at the start of a user turn, or after its text for models trained that way: [`PromptLayout`]),
//! written out in Rust instead of evaluated as Jinja.

use super::VlmError;
use std::path::Path;

/// One turn of a conversation.
#[derive(Clone, Debug, PartialEq)]
pub struct Turn {
    /// `user`, `assistant` or `system`.
    pub role: String,
    /// Images attached to this turn (each becomes `<image>\n`, before the text or after it: [`PromptLayout`]).
    pub images: usize,
    pub text: String,
}

impl Turn {
    pub fn user(images: usize, text: impl Into<String>) -> Self {
        Self { role: "user".into(), images, text: text.into() }
    }
    pub fn assistant(text: impl Into<String>) -> Self {
        Self { role: "assistant".into(), images: 0, text: text.into() }
    }
}

/// Where a user turn's images go relative to its text: llava-hf's template renders images first;
/// a model may ship a template that renders the text first (the tabletop models do: a small LLM
/// trained from scratch reads the image tokens knowing the question, as FiLM-style models do).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PromptLayout {
    #[default]
    ImagesFirst,
    TextFirst,
}

impl PromptLayout {
    /// The layout a Jinja chat template renders: whichever of the `'image'` and `'text'` content
    /// loops comes first; images first when the template has neither (llava-hf's behaviour).
    pub fn of_template(jinja: &str) -> Self {
        let at = |kind: &str| jinja.find(&format!("'equalto', '{kind}')"));
        match (at("image"), at("text")) {
            (Some(i), Some(t)) if t < i => PromptLayout::TextFirst,
            _ => PromptLayout::ImagesFirst,
        }
    }

    /// The Jinja template of this layout (`chat_template.jinja`).
    pub fn jinja(self) -> String {
        match self {
            PromptLayout::ImagesFirst => CHAT_TEMPLATE_JINJA.to_string(),
            PromptLayout::TextFirst => {
                let images = "{# Render all images first #}{% for content in message['content'] | selectattr('type', \
                              'equalto', 'image') %}{{ '<image>\\n' }}{% endfor %}";
                assert!(CHAT_TEMPLATE_JINJA.contains(images), "the template's image loop");
                let rest = CHAT_TEMPLATE_JINJA.replacen(images, "", 1);
                let end = rest.find("{{'<|im_end|>'").expect("the template's turn end");
                format!("{}{}{}", &rest[..end], images.replace("images first", "images after the text"), &rest[end..])
            }
        }
    }
}

/// The llava-hf LLaVA-OneVision chat template (images first).
pub fn chat_template(turns: &[Turn], add_generation_prompt: bool) -> String {
    chat_template_in(turns, add_generation_prompt, PromptLayout::ImagesFirst)
}

/// The chat template with the images of each turn placed by `layout`.
pub fn chat_template_in(turns: &[Turn], add_generation_prompt: bool, layout: PromptLayout) -> String {
    let mut s = String::new();
    for t in turns {
        s.push_str("<|im_start|>");
        s.push_str(&t.role);
        s.push('\n');
        let images = "<image>\n".repeat(t.images);
        match layout {
            PromptLayout::ImagesFirst => {
                s.push_str(&images);
                s.push_str(&t.text);
            }
            PromptLayout::TextFirst => {
                s.push_str(&t.text);
                s.push_str(&images);
            }
        }
        s.push_str("<|im_end|>\n");
    }
    if add_generation_prompt {
        s.push_str("<|im_start|>assistant\n");
    }
    s
}

/// The tokenizer plus the ids the chat needs.
#[derive(Clone)]
pub struct ChatTokenizer {
    inner: tokenizers::Tokenizer,
    pub image_token_id: u32,
    /// `<|im_end|>` and `<|endoftext|>` when present: generation stops on them.
    pub stop_ids: Vec<u32>,
    /// Where images go in a user turn, from the model's chat template.
    pub layout: PromptLayout,
}

impl std::fmt::Debug for ChatTokenizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ChatTokenizer(vocab {}, image {})", self.inner.get_vocab_size(true), self.image_token_id)
    }
}

/// The layout of the chat template in `dir` (`chat_template.jinja`, else `chat_template.json`'s
/// `chat_template`); images first when there is none.
fn template_layout(dir: &Path) -> Result<PromptLayout, VlmError> {
    let jinja = dir.join("chat_template.jinja");
    let json = dir.join("chat_template.json");
    let read = |p: &Path| std::fs::read_to_string(p).map_err(|e| VlmError::config(p, format!("cannot read: {e}")));
    if jinja.exists() {
        return Ok(PromptLayout::of_template(&read(&jinja)?));
    }
    if json.exists() {
        return match super::config::read_json(&json)?.get("chat_template").and_then(|t| t.as_str()) {
            Some(t) => Ok(PromptLayout::of_template(t)),
            None => Err(VlmError::config(&json, "has no \"chat_template\" string")),
        };
    }
    Ok(PromptLayout::ImagesFirst)
}

impl ChatTokenizer {
    pub fn load(dir: &Path, image_token_id: u32) -> Result<Self, VlmError> {
        let path = dir.join("tokenizer.json");
        if !path.exists() {
            return Err(VlmError::config(&path, "is missing"));
        }
        // the tokenizers library panics on some malformed files (found by fuzzing): caught, and
        // reported as a bad file like its errors
        let inner = base::panic::quietly(|| tokenizers::Tokenizer::from_file(&path))
            .map_err(|m| {
                VlmError::config(&path, format!("cannot load tokenizer: the tokenizers library failed on it ({m})"))
            })?
            .map_err(|e| VlmError::config(&path, format!("cannot load tokenizer: {e}")))?;
        let mut tok = Self::new(inner, image_token_id, &path)?;
        tok.layout = template_layout(dir)?;
        Ok(tok)
    }

    /// The same tokenizer with prompts built in `layout`.
    pub fn with_layout(mut self, layout: PromptLayout) -> Self {
        self.layout = layout;
        self
    }

    /// The prompt text of `turns` in this model's layout.
    pub fn prompt(&self, turns: &[Turn], add_generation_prompt: bool) -> String {
        chat_template_in(turns, add_generation_prompt, self.layout)
    }

    /// A tokenizer from the text of a `tokenizer.json`.
    pub fn from_json(json: &str, image_token_id: u32) -> Result<Self, VlmError> {
        let path = Path::new("tokenizer.json");
        let inner: tokenizers::Tokenizer = json
            .parse()
            .map_err(|e: tokenizers::Error| VlmError::config(path, format!("cannot load tokenizer: {e}")))?;
        Self::new(inner, image_token_id, path)
    }

    fn new(inner: tokenizers::Tokenizer, image_token_id: u32, path: &Path) -> Result<Self, VlmError> {
        match inner.id_to_token(image_token_id) {
            Some(t) if t == "<image>" => {}
            other => {
                return Err(VlmError::config(
                    path,
                    format!("image_token_index {image_token_id} of config.json is {other:?} here, not \"<image>\""),
                ));
            }
        }
        let stop_ids = ["<|im_end|>", "<|endoftext|>"].iter().filter_map(|t| inner.token_to_id(t)).collect();
        Ok(Self { inner, image_token_id, stop_ids, layout: PromptLayout::ImagesFirst })
    }

    /// The text of `tokenizer.json`.
    pub fn to_json(&self) -> Result<String, VlmError> {
        self.inner.to_string(true).map_err(|e| VlmError::config(Path::new("tokenizer.json"), e.to_string()))
    }

    /// Token ids of `text` (special tokens such as `<image>` are recognised).
    pub fn encode(&self, text: &str) -> Result<Vec<u32>, VlmError> {
        let enc = self.inner.encode(text, true).map_err(|e| VlmError::prompt(format!("tokenizer: {e}")))?;
        Ok(enc.get_ids().to_vec())
    }

    /// Text of `ids` (special tokens kept unless `skip_special`).
    pub fn decode(&self, ids: &[u32], skip_special: bool) -> Result<String, VlmError> {
        self.inner.decode(ids, skip_special).map_err(|e| VlmError::prompt(format!("tokenizer: {e}")))
    }

    pub fn vocab_size(&self) -> usize {
        self.inner.get_vocab_size(true)
    }

    /// The token of `id` (`None` past the vocabulary).
    pub fn token(&self, id: u32) -> Option<String> {
        self.inner.id_to_token(id)
    }

    /// The id of `token` (`None` when it is not in the vocabulary).
    pub fn id(&self, token: &str) -> Option<u32> {
        self.inner.token_to_id(token)
    }
}

/// The chat template of llava-hf LLaVA-OneVision models as Jinja (`chat_template.jinja`); the
/// same text [`chat_template`] writes.
pub const CHAT_TEMPLATE_JINJA: &str = include_str!("chat_template.jinja");

/// The special tokens of a word-level tokenizer, in id order (`<image>` = 3, `<video>` = 4).
pub const WORD_SPECIALS: [&str; 5] = ["<|endoftext|>", "<|im_start|>", "<|im_end|>", "<image>", "<video>"];

/// `tokenizer.json` of a word-level tokenizer: the [`WORD_SPECIALS`], then `<unk>`, the chat
/// roles and `words`; text splits at whitespace and punctuation (the `Whitespace`
/// pre-tokenizer), decoding joins words with spaces. Built, checked and serialised with the
/// `tokenizers` crate.
pub fn word_level_tokenizer_json(words: &[String]) -> Result<String, VlmError> {
    let mut vocab: Vec<String> = WORD_SPECIALS.iter().map(|s| s.to_string()).collect();
    for w in ["<unk>", "user", "assistant", "system"].iter().map(|s| s.to_string()).chain(words.iter().cloned()) {
        if !vocab.contains(&w) {
            vocab.push(w);
        }
    }
    let added: Vec<serde_json::Value> = WORD_SPECIALS
        .iter()
        .enumerate()
        .map(|(id, t)| {
            serde_json::json!({"id": id, "content": t, "single_word": false, "lstrip": false, "rstrip": false,
                "normalized": false, "special": true})
        })
        .collect();
    let map: serde_json::Map<String, serde_json::Value> =
        vocab.iter().enumerate().map(|(i, w)| (w.clone(), serde_json::json!(i))).collect();
    let json = serde_json::json!({
        "version": "1.0",
        "truncation": null,
        "padding": null,
        "added_tokens": added,
        "normalizer": null,
        "pre_tokenizer": {"type": "Whitespace"},
        "post_processor": null,
        "decoder": null,
        "model": {"type": "WordLevel", "vocab": map, "unk_token": "<unk>"},
    });
    let bad = |e: String| VlmError::config(Path::new("tokenizer.json"), format!("word-level tokenizer: {e}"));
    let tok: tokenizers::Tokenizer = json.to_string().parse().map_err(|e: tokenizers::Error| bad(e.to_string()))?;
    tok.to_string(true).map_err(|e| bad(e.to_string()))
}
