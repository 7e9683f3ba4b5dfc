//! Generation with the KV cache: greedy or temperature / top-p sampling, stop tokens, a token
//! budget, and a callback that receives printable text as it is produced (streaming).

use super::VlmError;
use super::llava::LlavaOnevision;
use super::qwen2::KvCache;
use base::Rng;
use burn::tensor::Tensor;
use std::ops::ControlFlow;

/// The most tokens one answer may ask for (`serve` bounds a request's `max_new_tokens` by it).
pub const MAX_NEW_TOKENS: usize = 1024;

/// How long an answer may be with a model of `max_positions` tokens of context: at most
/// [`MAX_NEW_TOKENS`] and a quarter of the context, so a conversation keeps room for its images
/// and its earlier turns.
pub fn max_new_tokens_limit(max_positions: usize) -> usize {
    MAX_NEW_TOKENS.min(max_positions / 4).max(1)
}

/// How to pick tokens.
#[derive(Clone, Debug, PartialEq)]
pub struct GenerateOptions {
    pub max_new_tokens: usize,
    /// 0 = greedy (argmax).
    pub temperature: f32,
    /// Nucleus sampling mass (1.0 = off). Ignored when greedy.
    pub top_p: f32,
    pub seed: u64,
    /// Generate exactly `max_new_tokens`, ignoring stop tokens (for parity checks).
    pub ignore_stop: bool,
}

impl Default for GenerateOptions {
    fn default() -> Self {
        Self { max_new_tokens: 128, temperature: 0.0, top_p: 1.0, seed: 0, ignore_stop: false }
    }
}

/// What came out.
#[derive(Clone, Debug, PartialEq)]
pub struct Generation {
    pub ids: Vec<u32>,
    pub text: String,
    /// Whether a stop token ended it (the stop token is not in `ids`).
    pub stopped: bool,
    /// Whether the caller stopped it (`generate_until`'s callback returned `Break`).
    pub cancelled: bool,
    /// Prompt length in tokens.
    pub prompt_tokens: usize,
    /// Leading prompt tokens whose keys and values came from a conversation's cache (not
    /// prefilled again: [`LlavaOnevision::generate_cached`]).
    pub cached_tokens: usize,
}

/// Picks the next token from `logits`: argmax when greedy, else temperature + nucleus (top-p) sampling.
pub fn pick(logits: &[f32], opts: &GenerateOptions, rng: &mut Rng) -> u32 {
    if opts.temperature <= 0.0 {
        let mut best = 0;
        for (i, v) in logits.iter().enumerate() {
            if *v > logits[best] {
                best = i;
            }
        }
        return best as u32;
    }
    let max = logits.iter().cloned().fold(f32::NEG_INFINITY, f32::max);
    let mut p: Vec<(usize, f64)> =
        logits.iter().enumerate().map(|(i, v)| (i, (((v - max) / opts.temperature) as f64).exp())).collect();
    let z: f64 = p.iter().map(|x| x.1).sum();
    p.sort_by(|a, b| b.1.total_cmp(&a.1));
    let mut kept = Vec::new();
    let mut mass = 0.0;
    for (i, w) in p {
        kept.push((i, w / z));
        mass += w / z;
        if mass >= opts.top_p as f64 {
            break;
        }
    }
    let mut u = rng.f() as f64 * mass;
    for (i, w) in &kept {
        if u < *w {
            return *i as u32;
        }
        u -= w;
    }
    kept.last().map(|k| k.0 as u32).unwrap_or(0)
}

/// The last row of `t` `[T, V]` on the host (the next-token logits).
pub fn last_row(t: Tensor<2>) -> Vec<f32> {
    let [n, v] = t.dims();
    t.narrow(0, n - 1, 1).reshape([v]).into_data().convert::<f32>().try_to_vec::<f32>().unwrap_or_default()
}

impl LlavaOnevision {
    /// Generates after a prompt given as input embeddings `[T, D]`; `on_text` receives new text pieces.
    pub fn generate(
        &self,
        prompt: Tensor<2>,
        opts: &GenerateOptions,
        mut on_text: impl FnMut(&str),
    ) -> Result<Generation, VlmError> {
        self.generate_until(prompt, opts, |piece| {
            if !piece.is_empty() {
                on_text(piece);
            }
            ControlFlow::Continue(())
        })
    }

    /// [`generate`](Self::generate), where `on_step` is called after every decoding step with the
    /// new text (empty while a piece is held back) and stops the generation by returning `Break`
    /// (`Generation::cancelled`).
    pub fn generate_until(
        &self,
        prompt: Tensor<2>,
        opts: &GenerateOptions,
        on_step: impl FnMut(&str) -> ControlFlow<()>,
    ) -> Result<Generation, VlmError> {
        let prompt_tokens = prompt.dims()[0];
        self.check_prompt_len(prompt_tokens)?;
        let mut cache = KvCache::with_capacity(prompt_tokens + self.answer_room(prompt_tokens, opts));
        let hidden = self.llm.forward(prompt, &mut cache);
        self.decode(hidden, prompt_tokens, &mut cache, opts, on_step, |_| {})
    }

    /// An error when a prompt of `tokens` leaves no room in the model's context.
    pub(crate) fn check_prompt_len(&self, tokens: usize) -> Result<(), VlmError> {
        let max = self.cfg.text.max_positions;
        if tokens >= max {
            return Err(VlmError::prompt(format!("the prompt is {tokens} tokens but the model takes at most {max}")));
        }
        Ok(())
    }

    /// New tokens an answer after a prompt of `tokens` may have: the answer stops at the context.
    pub(crate) fn answer_room(&self, tokens: usize, opts: &GenerateOptions) -> usize {
        opts.max_new_tokens.min(self.cfg.text.max_positions.saturating_sub(tokens))
    }

    /// Decodes after a prefill of `prompt_tokens` tokens whose last hidden states are `hidden`
    /// (`[T, D]`, `T` >= 1) and whose keys and values `cache` holds; `fed` sees every generated
    /// token as the cache takes its keys (all but a stop token and the last one).
    pub(crate) fn decode(
        &self,
        hidden: Tensor<2>,
        prompt_tokens: usize,
        cache: &mut KvCache,
        opts: &GenerateOptions,
        mut on_step: impl FnMut(&str) -> ControlFlow<()>,
        mut fed: impl FnMut(u32),
    ) -> Result<Generation, VlmError> {
        let new_tokens = self.answer_room(prompt_tokens, opts);
        let mut rng = Rng::new(opts.seed);
        let [t, d] = hidden.dims();
        let mut logits = last_row(self.llm.logits(hidden.narrow(0, t - 1, 1).reshape([1, d])));
        let mut ids = Vec::new();
        let mut printed = String::new();
        let (mut stopped, mut cancelled) = (false, false);
        for step in 0..new_tokens {
            let next = pick(&logits, opts, &mut rng);
            if !opts.ignore_stop && self.tokenizer.stop_ids.contains(&next) {
                stopped = true;
                break;
            }
            ids.push(next);
            let text = self.tokenizer.decode(&ids, true)?;
            // Hold back an incomplete UTF-8 sequence (decoded as U+FFFD) until its bytes arrive.
            let piece = if !text.ends_with('\u{fffd}') && text.len() > printed.len() && text.starts_with(&printed) {
                let piece = text[printed.len()..].to_string();
                printed = text;
                piece
            } else {
                String::new()
            };
            if on_step(&piece).is_break() {
                cancelled = true;
                break;
            }
            if step + 1 == new_tokens {
                break;
            }
            let x = self.llm.embed(&[next]);
            let h = self.llm.forward(x, cache);
            fed(next);
            logits = last_row(self.llm.logits(h));
        }
        let text = self.tokenizer.decode(&ids, true)?;
        if !cancelled && text.len() > printed.len() && text.starts_with(&printed) {
            let _ = on_step(&text[printed.len()..]);
        }
        Ok(Generation { ids, text, stopped, cancelled, prompt_tokens, cached_tokens: 0 })
    }
}
