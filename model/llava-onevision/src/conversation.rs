//! Multi-turn prompts and the keys and values a conversation keeps between its turns.
//!
//! A follow-up question's prompt is the earlier turns (the images in the first user turn), the
//! earlier answers, and the new question, in the model's chat template. The earlier part is what
//! the last answer's prompt and the answer's own tokens were, so its keys and values are already
//! in the conversation's [`PromptCache`]: [`LlavaOnevision::generate_cached`] prefills only the
//! tokens after the longest prefix the cache holds (the end of the last answer's turn and the new
//! question). Whatever the cache holds, the result is that of a fresh prefill of the whole prompt:
//! the prefix is compared token by token, never assumed.

use super::VlmError;
use super::generate::{GenerateOptions, Generation};
use super::llava::LlavaOnevision;
use super::qwen2::KvCache;
use super::tokenizer::{ChatTokenizer, Turn};
use burn::module::Param;
use burn::tensor::{Int, Tensor, TensorData, activation};
use std::ops::ControlFlow;

/// An earlier question of a conversation and the answer it got.
#[derive(Clone, Debug, PartialEq)]
pub struct Exchange {
    pub question: String,
    pub answer: String,
}

/// The keys and values of a conversation's prompt and answers so far, and the ids they are of.
#[derive(Clone, Debug, Default)]
pub struct PromptCache {
    cache: KvCache,
    ids: Vec<u32>,
}

impl PromptCache {
    /// Tokens whose keys and values are held.
    pub fn len(&self) -> usize {
        self.ids.len()
    }
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
    /// The ids held (image placeholders expanded).
    pub fn ids(&self) -> &[u32] {
        &self.ids
    }
}

/// What a model trained on single questions is told to say when it is asked to hold a
/// conversation.
pub const SINGLE_TURN_NOTE: &str = "this model was trained on single questions (chatsplat train-vlm), so each \
    question is asked on its own; a LLaVA-OneVision from Hugging Face holds the conversation";

impl LlavaOnevision {
    /// Whether the model holds a conversation: a model `chatsplat train-vlm` trained (its
    /// `train_config.json` beside the weights) was taught single questions, unless its last stage
    /// asked some of them after an earlier exchange (`"two_turn"` above 0, or `true`); any other
    /// LLaVA-OneVision (llava-hf's were trained on multi-turn chats) does. A single-turn model
    /// answers independent questions worse as follow-ups: on the built-in one before its two-turn
    /// stage, "Is there an orange torus?" after "Is there a blue cone?" was answered "yes".
    pub fn converses(&self) -> bool {
        match std::fs::read_to_string(self.dir.join("train_config.json")) {
            Err(_) => true,
            Ok(text) => serde_json::from_str::<serde_json::Value>(&text)
                .ok()
                .and_then(|v| {
                    let t = v.get("two_turn")?;
                    t.as_bool().or_else(|| t.as_f64().map(|x| x > 0.0))
                })
                .unwrap_or(false),
        }
    }

    /// The same model reading `tokenizer`, whose vocabulary extends the model's own: every token
    /// the model has keeps its id, and the embedding rows of the new ones (tied to the output
    /// layer) start as copies of the rows of the tokens `like` names for them (a new "it" read as
    /// "this"), else as the mean row. An error names the first token whose id differs.
    pub fn with_vocabulary(
        mut self,
        tokenizer: ChatTokenizer,
        like: impl Fn(&str) -> Option<&'static str>,
    ) -> Result<Self, VlmError> {
        let (old, new) = (self.cfg.text.vocab_size, tokenizer.vocab_size());
        let path = std::path::Path::new("tokenizer.json");
        if new < old || self.llm.lm_head.is_some() {
            let why = if new < old { "a vocabulary smaller than the model's" } else { "untied output embeddings" };
            return Err(VlmError::config(path, format!("cannot grow the vocabulary: {why}")));
        }
        for id in 0..old as u32 {
            let (was, is) = (self.tokenizer.token(id), tokenizer.token(id));
            if was != is {
                return Err(VlmError::config(path, format!("token {id} is {is:?} there but {was:?} in the model")));
            }
        }
        let w = self.llm.embed.weight.val();
        let d = w.dims()[1];
        let mut rows = vec![w.clone()];
        for id in old..new {
            let token = tokenizer.token(id as u32).unwrap_or_default();
            rows.push(match like(&token).and_then(|t| self.tokenizer.id(t)) {
                Some(i) => w.clone().narrow(0, i as usize, 1),
                None => w.clone().mean_dim(0),
            });
        }
        self.llm.embed.weight = Param::from_tensor(Tensor::cat(rows, 0).detach());
        debug_assert_eq!(self.llm.embed.weight.dims(), [new, d]);
        self.cfg.text.vocab_size = new;
        self.llm.cfg.vocab_size = new;
        self.tokenizer = tokenizer.with_layout(self.tokenizer.layout);
        Ok(self)
    }

    /// The prompt ids of `question` asked after the `earlier` exchanges about images of `counts`
    /// rows each (their `<image>` tags in the first user turn, each expanded to its rows). Not
    /// checked against the context: [`generate_cached`](Self::generate_cached) does that.
    pub fn conversation_ids(
        &self,
        earlier: &[Exchange],
        question: &str,
        counts: &[usize],
    ) -> Result<Vec<u32>, VlmError> {
        let mut turns = Vec::with_capacity(2 * earlier.len() + 1);
        for e in earlier {
            let images = if turns.is_empty() { counts.len() } else { 0 };
            turns.push(Turn::user(images, e.question.clone()));
            turns.push(Turn::assistant(e.answer.clone()));
        }
        let images = if turns.is_empty() { counts.len() } else { 0 };
        turns.push(Turn::user(images, question.to_string()));
        self.turn_ids(&turns, counts)
    }

    /// How many leading tokens of `ids` `cache` holds the keys and values of: their common
    /// prefix, less the last token of `ids` (the prefill must compute the next token's logits).
    pub fn reusable(&self, cache: &PromptCache, ids: &[u32]) -> usize {
        if cache.cache.len() != cache.ids.len() {
            return 0; // a generation that failed half-way: nothing is trusted
        }
        let common = cache.ids.iter().zip(ids).take_while(|(a, b)| a == b).count();
        common.min(ids.len().saturating_sub(1))
    }

    /// Whether prefilling `ids` after what `cache` holds needs the images' prompt embeddings (an
    /// image placeholder after the reusable prefix).
    pub fn needs_images(&self, cache: &PromptCache, ids: &[u32]) -> bool {
        ids[self.reusable(cache, ids)..].contains(&self.cfg.image_token_id)
    }

    /// Generates after the prompt `ids` (from [`conversation_ids`](Self::conversation_ids)),
    /// prefilling only what `cache` does not hold already ([`reusable`](Self::reusable));
    /// afterwards `cache` holds the prompt and the answer. `images` are the prompt embeddings of
    /// the images (`token_embeds`), needed only where [`needs_images`](Self::needs_images) says
    /// so (else they may be empty). [`Generation::cached_tokens`] says how many prompt tokens
    /// came from the cache.
    pub fn generate_cached(
        &self,
        ids: &[u32],
        images: &[Tensor<2>],
        cache: &mut PromptCache,
        opts: &GenerateOptions,
        on_step: impl FnMut(&str) -> ControlFlow<()>,
    ) -> Result<Generation, VlmError> {
        let (hidden, reuse) = self.prefill(ids, images, cache, ids.len(), self.answer_room(ids.len(), opts))?;
        let PromptCache { cache: kv, ids: held } = cache;
        let mut g = self.decode(hidden, ids.len(), kv, opts, on_step, |t| held.push(t))?;
        g.cached_tokens = reuse;
        Ok(g)
    }

    /// The log-probability of each token of `answer` and then the end of the turn, as the answer
    /// to the prompt `ids` (from [`conversation_ids`](Self::conversation_ids)), prefilling only
    /// what `cache` does not hold (`images` as for [`generate_cached`](Self::generate_cached));
    /// afterwards `cache` holds the prompt and the answer. How well a phrase answers a question
    /// about an image: text search over objects scores phrases so.
    pub fn answer_logprobs(
        &self,
        ids: &[u32],
        images: &[Tensor<2>],
        cache: &mut PromptCache,
        answer: &str,
    ) -> Result<Vec<f32>, VlmError> {
        let end =
            *self.tokenizer.stop_ids.first().ok_or_else(|| VlmError::prompt("the tokenizer has no <|im_end|>"))?;
        let mut said = self.tokenizer.encode(answer)?;
        said.push(end);
        let full: Vec<u32> = ids.iter().chain(&said[..said.len() - 1]).copied().collect();
        // the prompt's last position onwards: the rows that predict the answer's tokens
        let (hidden, reuse) = self.prefill(&full, images, cache, ids.len().saturating_sub(1), 0)?;
        let rows = hidden.dims()[0];
        let from = ids.len() - 1 - reuse;
        let logits = self.llm.logits(hidden.narrow(0, from, rows - from));
        let targets: Vec<i64> = said.iter().map(|&t| t as i64).collect();
        let targets = Tensor::<2, Int>::from_data(TensorData::new(targets, [said.len(), 1]), &logits.device());
        let lp = activation::log_softmax(logits, 1).gather(1, targets).reshape([said.len()]);
        lp.into_data().convert::<f32>().into_vec::<f32>().map_err(|e| VlmError::prompt(format!("log-probs: {e:?}")))
    }

    /// Prefills what of `ids` `cache` does not hold, from position `from` at the latest; returns
    /// the hidden states of the positions prefilled (`[T, D]`) and how many were reused. `room`:
    /// tokens to make room for after the prompt in a new cache.
    fn prefill(
        &self,
        ids: &[u32],
        images: &[Tensor<2>],
        cache: &mut PromptCache,
        from: usize,
        room: usize,
    ) -> Result<(Tensor<2>, usize), VlmError> {
        if ids.is_empty() {
            return Err(VlmError::prompt("the prompt is empty"));
        }
        self.check_prompt_len(ids.len())?;
        let reuse = self.reusable(cache, ids).min(from);
        let rest = &ids[reuse..];
        let embeds = if rest.contains(&self.cfg.image_token_id) {
            self.embed_prompt(ids, images)?.narrow(0, reuse, rest.len())
        } else {
            self.llm.embed(rest)
        };
        if reuse == 0 {
            cache.cache = KvCache::with_capacity(ids.len() + room);
        }
        cache.cache.truncate(reuse);
        cache.ids.truncate(reuse);
        let hidden = self.llm.forward(embeds, &mut cache.cache);
        cache.ids.extend_from_slice(rest);
        Ok((hidden, reuse))
    }
}
