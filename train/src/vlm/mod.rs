//! Training a LLaVA-OneVision from scratch for the synthetic tabletops (burn autodiff, burn's
//! AdamW): the same architecture and files as a llava-hf model (SigLIP tower, projector, Qwen2
//! with tied embeddings, a word-level `tokenizer.json`, the chat template), small enough to train
//! on a CPU in an hour, so that every stage of chatsplat can be checked with answers that are
//! right or wrong.
//!
//! Each step draws fresh scenes (seeds from [`TRAIN_SEEDS`], never the held-out ones), ray-casts
//! them, and asks questions in the token layouts ChatSplat feeds the LLM ([`data`]); many
//! questions share one image prefix in a packed forward pass ([`batch`]). An auxiliary per-token
//! colour/shape/size classification speeds up the vision tower; Gaussian noise on the vision
//! tokens teaches the LLM to read tokens that are close to the tower's (what ChatSplat's encoder
//! gives). Evaluation is exact match on held-out seeds ([`evaluate`]).

pub mod batch;
pub mod checkpoint;
pub mod data;
pub mod hops;

use crate::dist::{self, Collective, Solo};
use crate::schedule::warmup_cosine;
use batch::{AUX_CLASSES, LabelTokens, Packed, Trainable, exact, forward, pack};
use burn::module::Module;
use burn::optim::{AdamWConfig, GradientsParams};
use burn::tensor::Device;
use data::{DataSpec, Sample, SampleKind, pick_questions};
use model::data::synth::questions::{Kind, Qa, vocabulary};
use model::error::{Error, Result};
use model::io;
use model::rng::Rng;
use model::vlm::config::{Act, TextConfig, VisionConfig};
use model::vlm::tokenizer::{ChatTokenizer, word_level_tokenizer_json};
use model::vlm::{LlavaConfig, LlavaOnevision, ProcessorConfig};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// Scene seeds training draws from (`TRAIN_SEEDS..`); every seed below is held out.
pub const TRAIN_SEEDS: u64 = 1_000_000;
/// The held-out seeds evaluation uses by default (`EVAL_SEEDS..EVAL_SEEDS + n`).
pub const EVAL_SEEDS: u64 = 10_000;

/// The model's size.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Shape {
    pub image_size: usize,
    pub patch_size: usize,
    pub vision_width: usize,
    pub vision_layers: usize,
    pub vision_heads: usize,
    pub vision_mlp: usize,
    pub text_width: usize,
    pub text_layers: usize,
    pub text_heads: usize,
    pub text_kv_heads: usize,
    pub text_mlp: usize,
}

impl Default for Shape {
    fn default() -> Self {
        Self {
            image_size: 96,
            patch_size: 12,
            vision_width: 128,
            vision_layers: 4,
            vision_heads: 4,
            vision_mlp: 384,
            text_width: 128,
            text_layers: 4,
            text_heads: 4,
            text_kv_heads: 2,
            text_mlp: 384,
        }
    }
}

/// Every knob of VLM training (saved beside the model as `train_config.json`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VlmTrainConfig {
    pub seed: u64,
    pub steps: usize,
    pub model: Shape,
    /// Peak learning rate (AdamW), reached after `warmup` steps, cosine-decayed to `min_lr`.
    pub lr: f64,
    pub min_lr: f64,
    pub warmup: usize,
    pub weight_decay: f32,
    /// Images per step (a scene sample counts its views).
    pub images_per_step: usize,
    /// Questions asked per sample (at most).
    pub questions_per_sample: usize,
    /// Train on these question kinds only (empty: all); for curricula and ablations.
    pub kinds: Vec<Kind>,
    /// Extra weight of a question kind when a sample's questions are picked (absent: 1): more
    /// of a kind that lags, e.g. `{"left_of": 4}`.
    pub kind_weights: BTreeMap<Kind, f32>,
    /// Probability of a view, object and scene step.
    pub mix: [f32; 3],
    /// Weight of the auxiliary per-token loss.
    pub aux_weight: f32,
    /// The first this many steps train the tower and the auxiliary head alone (no LLM), on
    /// `tower_images` object crops and views per step: shape, the slowest thing for a small ViT to
    /// see, is learned in cheap steps before the LLM starts reading the tokens.
    pub tower_steps: usize,
    pub tower_images: usize,
    /// Peak learning rate of the tower's phase (0: `lr`); a ViT this small learns shape sooner
    /// at a higher rate than the LLM tolerates.
    pub tower_lr: f64,
    /// Rate the tower's phase decays to (cosine, after the warm-up); 0: no decay (constant at the
    /// phase's peak).
    pub tower_min_lr: f64,
    /// After the tower's phase the vision tower learns at this multiple of the rate (1: like the
    /// rest); below 1 the LLM's first steps, whose gradients are large and noisy, do not wash out
    /// the shapes the tower's phase taught it.
    pub tower_lr_scale: f64,
    /// Weights of the supervised hops ([`hops`]): dedupe, words, find (in `HopKind::ALL` order),
    /// and of the slot and place heads; all zero: the answers alone teach the LLM.
    pub hop_weights: [f32; 3],
    pub slot_weight: f32,
    pub place_weight: f32,
    /// Draw question kinds (and the level of each step) in proportion to their recent training
    /// error (plus `adaptive_floor`) instead of uniformly: steps go where answers are still wrong.
    pub adaptive: bool,
    pub adaptive_floor: f32,
    /// Std of the noise on the vision tokens, relative to their RMS.
    pub feature_noise: f32,
    /// Side of the rendered views (the synthetic datasets' resolution).
    pub resolution: u32,
    /// Object crop margin (the teacher's).
    pub margin: f32,
    /// Label tokens (the curriculum): every image's tokens are the label tokens until this
    /// fraction of the steps, then the tower's take over linearly until `label_tokens_end`.
    pub label_tokens_until: f32,
    pub label_tokens_end: f32,
    /// Weight of the tower's mean squared error against the label tokens.
    pub label_weight: f32,
    /// Evaluate on held-out seeds every this many steps (0: only at the end).
    pub eval_every: usize,
    /// Held-out seeds for evaluation during training.
    pub eval_seeds: u64,
    /// Write a checkpoint (`OUT/checkpoint/`, what `--resume` reads) every this many steps and
    /// at every evaluation (0: only at evaluations).
    pub checkpoint_every: usize,
    /// The backend this stage trains on (absent: the command's `--backend`). Backends differ in
    /// the last bits of a float, and a training run amplifies them, so a committed model's
    /// configuration names the backend each of its stages was trained on.
    pub backend: Option<model::Backend>,
    /// A first stage: train this configuration (same model shape) before this one, which then
    /// starts from its weights with a fresh optimizer and fresh heads (auxiliary, slot, place;
    /// they are not part of the llava-hf files), so a fine-tuned model is reproduced from its seeds
    /// by one command.
    pub base: Option<Box<VlmTrainConfig>>,
}

impl Default for VlmTrainConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            steps: 3000,
            model: Shape::default(),
            lr: 2e-3,
            min_lr: 1e-4,
            warmup: 100,
            weight_decay: 0.01,
            images_per_step: 16,
            questions_per_sample: 6,
            kinds: Vec::new(),
            kind_weights: BTreeMap::new(),
            mix: [0.45, 0.3, 0.25],
            aux_weight: 0.5,
            tower_steps: 0,
            tower_images: 32,
            tower_lr: 0.0,
            tower_min_lr: 0.0,
            tower_lr_scale: 1.0,
            hop_weights: [0.3, 0.5, 0.5],
            slot_weight: 0.3,
            place_weight: 0.0,
            adaptive: true,
            adaptive_floor: 0.05,
            feature_noise: 0.1,
            resolution: 96,
            margin: model::language::CROP_MARGIN,
            label_tokens_until: 0.3,
            label_tokens_end: 0.6,
            label_weight: 1.0,
            eval_every: 500,
            eval_seeds: 8,
            checkpoint_every: 250,
            backend: None,
            base: None,
        }
    }
}

impl VlmTrainConfig {
    /// The LLaVA-OneVision configuration of this shape with a vocabulary of `vocab` words.
    pub fn llava_config(&self, vocab: usize) -> LlavaConfig {
        let m = &self.model;
        LlavaConfig {
            vision: VisionConfig {
                hidden_size: m.vision_width,
                intermediate_size: m.vision_mlp,
                num_layers: m.vision_layers,
                num_heads: m.vision_heads,
                image_size: m.image_size,
                patch_size: m.patch_size,
                layer_norm_eps: 1e-6,
                act: Act::GeluTanh,
            },
            text: TextConfig {
                vocab_size: vocab,
                hidden_size: m.text_width,
                intermediate_size: m.text_mlp,
                num_layers: m.text_layers,
                num_heads: m.text_heads,
                num_kv_heads: m.text_kv_heads,
                head_dim: m.text_width / m.text_heads,
                rms_norm_eps: 1e-6,
                rope_theta: 10_000.0,
                max_positions: 4096,
                tie_word_embeddings: true,
                eos_token_ids: vec![2],
                act: Act::Silu,
            },
            image_token_id: 3,
            vision_feature_layer: -1,
            projector_act: Act::Gelu,
            projector_bias: true,
            pinpoints: vec![(m.image_size, m.image_size)],
            max_num_patches: 1,
        }
    }

    /// The image processor: the tower's size, SigLIP's normalisation, Pillow bicubic.
    pub fn processor(&self) -> ProcessorConfig {
        let s = self.model.image_size;
        ProcessorConfig {
            mean: [0.5; 3],
            std: [0.5; 3],
            rescale_factor: 1.0 / 255.0,
            size: (s, s),
            resample: 3,
            pinpoints: vec![(s, s)],
        }
    }

    /// Refuses values out of range, naming the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, why: &str| Err(Error::input(format!("vlm config: {key} {why}")));
        let m = &self.model;
        if m.patch_size == 0 || m.image_size < m.patch_size {
            return bad("model.patch_size", "must be in 1..=image_size");
        }
        if m.vision_heads == 0 || !m.vision_width.is_multiple_of(m.vision_heads) {
            return bad("model.vision_width", "must be a multiple of vision_heads");
        }
        if m.text_heads == 0
            || !m.text_width.is_multiple_of(m.text_heads)
            || !(m.text_width / m.text_heads).is_multiple_of(2)
        {
            return bad("model.text_width", "must be text_heads times an even head width");
        }
        if m.text_kv_heads == 0 || !m.text_heads.is_multiple_of(m.text_kv_heads) {
            return bad("model.text_kv_heads", "must divide text_heads");
        }
        if !(self.lr > 0.0 && self.lr.is_finite() && self.min_lr >= 0.0) {
            return bad("lr", "must be > 0 (and min_lr >= 0)");
        }
        if !(self.tower_lr >= 0.0 && self.tower_lr.is_finite()) {
            return bad("tower_lr", "must be >= 0 (0: lr)");
        }
        if !(self.tower_min_lr >= 0.0 && self.tower_min_lr.is_finite()) {
            return bad("tower_min_lr", "must be >= 0 (0: no decay)");
        }
        if !(self.tower_lr_scale >= 0.0 && self.tower_lr_scale.is_finite()) {
            return bad("tower_lr_scale", "must be >= 0 (1: the tower learns like the rest)");
        }
        if self.tower_steps > 0 && (self.tower_steps >= self.steps || self.tower_images == 0) {
            return bad("tower_steps", "must be below steps (and tower_images at least 1)");
        }
        if self.images_per_step < SCENE_IMAGES || self.questions_per_sample == 0 {
            return bad("images_per_step", "must be at least 4 and questions_per_sample at least 1");
        }
        if self.mix.iter().any(|p| !(*p >= 0.0)) || self.mix.iter().sum::<f32>() <= 0.0 {
            return bad("mix", "must be three non-negative weights, not all zero");
        }
        for (sample, p) in SampleKind::ALL.iter().zip(self.mix) {
            let level = sample.level();
            if p > 0.0 && !self.kinds.is_empty() && !self.kinds.iter().any(|k| k.level() == level) {
                return bad("kinds", "must include a question kind of every level that mix draws");
            }
        }
        if self.kind_weights.values().any(|w| !(*w > 0.0 && w.is_finite())) {
            return bad("kind_weights", "must be finite and > 0");
        }
        if self.resolution < m.patch_size as u32 {
            return bad("resolution", "must be at least the patch size");
        }
        if self.head_weights().any(|w| !(w >= 0.0 && w.is_finite())) {
            return bad("hop_weights", "must be finite and non-negative (and slot_weight, place_weight too)");
        }
        if self.supervised() && (m.text_layers < hops::MIN_LAYERS || m.text_heads < hops::MIN_HEADS) {
            return bad(
                "hop_weights",
                &format!(
                    "need model.text_layers >= {} and model.text_heads >= {} (or all weights 0)",
                    hops::MIN_LAYERS,
                    hops::MIN_HEADS
                ),
            );
        }
        if !(self.adaptive_floor > 0.0 && self.adaptive_floor.is_finite()) {
            return bad("adaptive_floor", "must be > 0");
        }
        if self.eval_every > 0 && self.eval_seeds == 0 {
            return bad("eval_seeds", "must be at least 1 when eval_every is set (0 seeds would report 0 %)");
        }
        if let Some(base) = &self.base {
            if base.model != self.model {
                return bad("base.model", "must be the same model shape as this stage's");
            }
            base.validate().map_err(|e| Error::input(format!("{e} (in base)")))?;
        }
        Ok(())
    }

    /// Probability that an image's LLM input is its label tokens at step `i`.
    pub fn label_probability(&self, i: usize) -> f32 {
        let t = i as f32 / self.steps.max(1) as f32;
        if t < self.label_tokens_until {
            1.0
        } else if t >= self.label_tokens_end {
            0.0
        } else {
            1.0 - (t - self.label_tokens_until) / (self.label_tokens_end - self.label_tokens_until).max(1e-6)
        }
    }

    /// How likely a question of `kind` is to be picked from a sample's questions: its
    /// `kind_weights` entry times, when adaptive, how much it still needs (`running`).
    pub fn question_weight(&self, kind: Kind, running: &RunningAccuracy) -> f32 {
        let w = self.kind_weights.get(&kind).copied().unwrap_or(1.0);
        w * if self.adaptive { running.need(kind, self.adaptive_floor) } else { 1.0 }
    }

    /// The weights of the supervised hops, then of the slot and place heads.
    fn head_weights(&self) -> impl Iterator<Item = f32> + '_ {
        self.hop_weights.iter().copied().chain([self.slot_weight, self.place_weight])
    }

    /// Whether any hop or head is supervised (the forward then records what they need).
    pub fn supervised(&self) -> bool {
        self.head_weights().any(|w| w > 0.0)
    }

    /// The learning rate of step `i`: in the tower's phase a warm-up to its peak (`tower_lr`, else
    /// `lr`), then a cosine to `tower_min_lr` (0: held at the peak); after it the warm-up again,
    /// then a cosine from `lr` to `min_lr`.
    pub fn lr_at(&self, i: usize) -> f64 {
        if i < self.tower_steps {
            let peak = if self.tower_lr > 0.0 { self.tower_lr } else { self.lr };
            let floor = if self.tower_min_lr > 0.0 { self.tower_min_lr } else { peak };
            return warmup_cosine(i, self.tower_steps, self.warmup, peak, floor);
        }
        warmup_cosine(i - self.tower_steps, self.steps - self.tower_steps, self.warmup, self.lr, self.min_lr)
    }
}

/// A fresh training scene's seed (never a held-out one).
fn train_seed(rng: &mut Rng) -> u64 {
    TRAIN_SEEDS + rng.next_u64() % 1_000_000_000
}

const SCENE_IMAGES: usize = model::data::synth::SCENE_VIEWS;

/// A fresh tabletop VLM of `cfg`'s shape, with its word-level tokenizer.
pub fn init_model(cfg: &VlmTrainConfig, device: &Device) -> Result<LlavaOnevision> {
    let json = word_level_tokenizer_json(&vocabulary())?;
    let tokenizer = ChatTokenizer::from_json(&json, 3)?;
    let llava = cfg.llava_config(tokenizer.vocab_size());
    Ok(LlavaOnevision::init(llava, cfg.processor(), tokenizer, cfg.seed, device))
}

/// Writes a model directory a llava-hf loader reads: `config.json`, `processor_config.json`,
/// `tokenizer.json`, `tokenizer_config.json`, `chat_template.jinja`, `generation_config.json`
/// and `model.safetensors` (f32), each atomically.
pub fn save_model(vlm: &LlavaOnevision, dir: &Path) -> Result<usize> {
    save_model_as(vlm, dir, false)
}

/// [`save_model`], with the weights in bf16 when `bf16` (as the llava-hf checkpoints store them).
pub fn save_model_as(vlm: &LlavaOnevision, dir: &Path, bf16: bool) -> Result<usize> {
    io::create_dir(dir)?;
    io::write_json(&dir.join("config.json"), &vlm.cfg.to_hf_json())?;
    io::write_json(&dir.join("processor_config.json"), &vlm.processor.to_hf_json(&vlm.cfg))?;
    io::write_atomic(&dir.join("tokenizer.json"), vlm.tokenizer.to_json()?.as_bytes())?;
    let tok_cfg = serde_json::json!({
        "backend": "tokenizers", "eos_token": "<|im_end|>", "pad_token": "<|endoftext|>", "unk_token": "<unk>",
        "image_token": "<image>", "video_token": "<video>", "model_max_length": 4096,
        "processor_class": "LlavaOnevisionProcessor", "tokenizer_class": "PreTrainedTokenizerFast",
    });
    io::write_json(&dir.join("tokenizer_config.json"), &tok_cfg)?;
    io::write_atomic(&dir.join("chat_template.jinja"), vlm.tokenizer.layout.jinja().as_bytes())?;
    let gen_cfg = serde_json::json!({"eos_token_id": vlm.cfg.text.eos_token_ids, "pad_token_id": 0});
    io::write_json(&dir.join("generation_config.json"), &gen_cfg)?;
    let tensors = vlm.export();
    tensors.write(&dir.join("model.safetensors"), bf16)?;
    Ok(tensors.count())
}

/// Exact-match results by question kind: (right, asked).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Accuracy {
    pub by_kind: BTreeMap<String, (usize, usize)>,
}

impl Accuracy {
    pub fn add(&mut self, kind: Kind, right: bool) {
        let e = self.by_kind.entry(kind.as_str().to_string()).or_default();
        e.0 += right as usize;
        e.1 += 1;
    }

    /// Fraction right over the kinds of `level` (`None`: all).
    pub fn level(&self, level: Option<model::vqa::Level>) -> f64 {
        let (mut r, mut n) = (0, 0);
        for k in Kind::ALL {
            if level.is_none_or(|l| k.level() == l)
                && let Some(&(a, b)) = self.by_kind.get(k.as_str())
            {
                r += a;
                n += b;
            }
        }
        r as f64 / n.max(1) as f64
    }

    /// "count 90 colors 100 ...": percent right per kind, in `Kind::ALL` order.
    pub fn by_kind_line(&self) -> String {
        let mut parts = Vec::new();
        for k in Kind::ALL {
            if let Some(&(r, n)) = self.by_kind.get(k.as_str()) {
                parts.push(format!("{} {:.0}", k.as_str(), 100.0 * r as f64 / n.max(1) as f64));
            }
        }
        parts.join(" ")
    }

    /// "view 97.1% object 99.0% scene 93.8%".
    pub fn summary(&self) -> String {
        use model::vqa::Level;
        format!(
            "view {:.1}% object {:.1}% scene {:.1}%",
            100.0 * self.level(Some(Level::View)),
            100.0 * self.level(Some(Level::Object)),
            100.0 * self.level(Some(Level::Scene))
        )
    }
}

/// Held-out samples: per seed, `views` view samples, `objects` object samples and one scene
/// sample, every question of each.
pub fn eval_samples(spec: &DataSpec, seeds: std::ops::Range<u64>, views: usize, objects: usize) -> Vec<Sample> {
    let mut out = Vec::new();
    for seed in seeds {
        let mut rng = Rng::new(seed ^ 0xE7A1);
        for (kind, n) in [(SampleKind::View, views), (SampleKind::Object, objects), (SampleKind::Scene, 1)] {
            let mut got = 0;
            for _ in 0..20 * n {
                if got == n {
                    break;
                }
                if let Some(s) = spec.sample(kind, seed, &mut rng) {
                    out.push(s);
                    got += 1;
                }
            }
        }
    }
    out
}

/// Exact match of greedy answers (teacher-forced: a question is right when every answer token
/// and the closing `<|im_end|>` is the model's most likely next token, which is what greedy
/// decoding then generates) over `samples`, every question of each.
pub fn evaluate(m: &Trainable, samples: &[Sample], device: &Device) -> Result<Accuracy> {
    evaluate_with(m, samples, None, device)
}

/// As [`evaluate`], with the LLM reading the images' label tokens instead of the tower's when
/// `labels` is given (how far the LLM has learned to reason, apart from the tower).
pub fn evaluate_with(
    m: &Trainable,
    samples: &[Sample],
    labels: Option<&LabelTokens>,
    device: &Device,
) -> Result<Accuracy> {
    let mut acc = Accuracy::default();
    for kind in SampleKind::ALL {
        let of: Vec<(Sample, Vec<model::data::synth::questions::Qa>)> =
            samples.iter().filter(|s| s.kind == kind).map(|s| (s.clone(), s.qas.clone())).collect();
        for chunk in of.chunks(8) {
            let mut p = pack(&m.vlm, chunk)?;
            p.label_tokens.iter_mut().for_each(|f| *f = labels.is_some());
            let f = forward(m, &p, labels, None, false, None, device)?;
            for (k, right) in exact(&p, f.log_probs) {
                acc.add(k, right);
            }
        }
    }
    Ok(acc)
}

/// Exact match of a trained (or loaded) model on ground-truth images of the held-out `seeds`:
/// per seed `views` view samples, `objects` object samples and one scene sample, every question of
/// each; `resolution` and `margin` as the model was trained with (its `train_config.json`).
pub fn evaluate_model(
    vlm: LlavaOnevision,
    seeds: std::ops::Range<u64>,
    (views, objects): (usize, usize),
    cfg: &VlmTrainConfig,
    device: &Device,
) -> Result<Accuracy> {
    if seeds.end > TRAIN_SEEDS {
        return Err(Error::Input(format!("evaluation seeds must be held out (below {TRAIN_SEEDS}), got {seeds:?}")));
    }
    let spec = DataSpec::new(&vlm.cfg, &vlm.processor, cfg.resolution, cfg.margin);
    let samples = eval_samples(&spec, seeds, views, objects);
    evaluate(&Trainable::reading(vlm, device), &samples, device)
}

/// One line of `training_log.json`, also what [`train`]'s progress callback sees after every step.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LogLine {
    /// Steps done.
    pub step: usize,
    /// Steps of this stage (for progress; not logged).
    #[serde(skip)]
    pub steps: usize,
    pub seconds: f64,
    pub lr: f64,
    pub answer_loss: f32,
    pub aux_loss: f32,
    /// The supervised hops' losses (dedupe, words, find) and the slot head's.
    #[serde(default)]
    pub hop_loss: [f32; 3],
    #[serde(default)]
    pub slot_loss: f32,
    #[serde(default)]
    pub place_loss: f32,
    /// The auxiliary head's accuracy on the step's object tokens: colour, shape, size.
    #[serde(default)]
    pub tower_accuracy: [f32; 3],
    /// Held-out accuracy, when this step evaluated.
    pub eval: Option<Accuracy>,
    /// Held-out accuracy reading label tokens, when this step evaluated.
    pub eval_labels: Option<Accuracy>,
    /// Seconds of `seconds` spent drawing samples (every rank draws the whole step).
    #[serde(default)]
    pub drawing_seconds: f64,
}

/// Recent training accuracy per question kind (exponential moving average of exact match over
/// training batches), what adaptive sampling draws by.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct RunningAccuracy {
    acc: BTreeMap<Kind, f32>,
}

impl RunningAccuracy {
    const DECAY: f32 = 0.95;

    pub fn add(&mut self, kind: Kind, right: bool) {
        let a = self.acc.entry(kind).or_insert(0.0);
        *a = Self::DECAY * *a + (1.0 - Self::DECAY) * right as u8 as f32;
    }

    /// How much a kind is still worth drawing: its error plus `floor`.
    pub fn need(&self, kind: Kind, floor: f32) -> f32 {
        1.0 - self.acc.get(&kind).copied().unwrap_or(0.0) + floor
    }
}

/// The samples of one step: a level drawn by `cfg.mix` (adaptive: weighted by how much its kinds
/// still need), fresh scenes until the step's images are filled, questions picked per sample.
fn step_samples(
    cfg: &VlmTrainConfig,
    spec: &DataSpec,
    running: &RunningAccuracy,
    rng: &mut Rng,
) -> Vec<(Sample, Vec<Qa>)> {
    let allowed = |k: Kind| cfg.kinds.is_empty() || cfg.kinds.contains(&k);
    let weights: Vec<f32> = SampleKind::ALL
        .iter()
        .zip(cfg.mix)
        .map(|(sample, p)| {
            if !cfg.adaptive || p <= 0.0 {
                return p;
            }
            let kinds: Vec<Kind> =
                Kind::ALL.into_iter().filter(|k| sample.level() == k.level() && allowed(*k)).collect();
            let need: f32 = kinds.iter().map(|k| running.need(*k, cfg.adaptive_floor)).sum::<f32>();
            p * need / kinds.len().max(1) as f32
        })
        .collect();
    let kind = SampleKind::ALL[rng.weighted(&weights)];
    let per = if kind == SampleKind::Scene { SCENE_IMAGES } else { 1 };
    let want = (cfg.images_per_step / per).max(1);
    let mut out = Vec::with_capacity(want);
    while out.len() < want {
        let seed = train_seed(rng);
        if let Some(s) = spec.sample(kind, seed, rng) {
            let asked: Vec<Qa> = s.qas.iter().filter(|q| allowed(q.kind)).cloned().collect();
            if !asked.is_empty() {
                let qs = pick_questions(&asked, cfg.questions_per_sample, |k| cfg.question_weight(k, running), rng);
                out.push((s, qs));
            }
        }
    }
    out
}

/// The losses of one training step (before its update).
#[derive(Clone, Copy, Debug, Default)]
pub struct StepLosses {
    pub answer: f32,
    pub aux: f32,
    /// dedupe, words, find ([`hops::HopKind::ALL`] order)
    pub hops: [f32; 3],
    pub slots: f32,
    pub places: f32,
    /// The auxiliary head's accuracy on object tokens: colour, shape, size.
    pub tower: [f32; 3],
}

/// The training state: the model (on the autodiff device), AdamW, the data generator.
pub struct Trainer {
    pub cfg: VlmTrainConfig,
    pub model: Trainable,
    pub step: usize,
    spec: DataSpec,
    rng: Rng,
    optim: burn::optim::ModuleOptimizer,
    device: Device,
    pub labels: LabelTokens,
    pub running: RunningAccuracy,
    /// Time spent drawing samples (rendering the scenes, picking questions, the noise): every rank
    /// of a data-parallel run draws the whole step.
    pub drawing: std::time::Duration,
}

impl Trainer {
    /// A fresh model of `cfg` on `device` (autodiff is added here).
    pub fn new(cfg: &VlmTrainConfig, device: &Device) -> Result<Self> {
        cfg.validate()?;
        let ad = device.clone().autodiff();
        let vlm = init_model(cfg, &ad)?;
        Self::starting_from(cfg, vlm, &ad)
    }

    /// A trainer of `cfg` that starts from `vlm` (on `device`, which must carry autodiff), with
    /// fresh heads and optimizer.
    pub fn starting_from(cfg: &VlmTrainConfig, vlm: LlavaOnevision, device: &Device) -> Result<Self> {
        cfg.validate()?;
        let ad = device.clone();
        let spec = DataSpec::new(&vlm.cfg, &vlm.processor, cfg.resolution, cfg.margin);
        let classes: usize = AUX_CLASSES.iter().sum();
        let mut rng = Rng::new(cfg.seed ^ 0xDA7A);
        let aux = model::vlm::layers::init_linear(&mut rng, vlm.cfg.vision.hidden_size, classes, true, 0.02, &ad);
        let vlm_dim = vlm.cfg.vision.hidden_size;
        let slot_classes = batch::SLOT_CLASSES.iter().sum();
        let slots = model::vlm::layers::init_linear(&mut rng, vlm.cfg.text.hidden_size, slot_classes, true, 0.02, &ad);
        // its own generator: `rng` goes on to draw the data, which must not depend on this head
        let (mut place_rng, place_classes) = (Rng::new(cfg.seed ^ 0x91ACE), 2 * batch::place_classes(&vlm));
        let places =
            model::vlm::layers::init_linear(&mut place_rng, vlm.cfg.text.hidden_size, place_classes, true, 0.02, &ad);
        Ok(Self {
            cfg: cfg.clone(),
            model: Trainable { vlm, aux, slots, places },
            step: 0,
            spec,
            rng,
            optim: AdamWConfig::new().with_weight_decay(cfg.weight_decay).init(),
            labels: LabelTokens::new(vlm_dim, cfg.seed),
            device: ad,
            running: RunningAccuracy::default(),
            drawing: std::time::Duration::ZERO,
        })
    }

    /// The data generator (held-out samples for evaluation come from it too).
    pub fn spec(&self) -> &DataSpec {
        &self.spec
    }

    /// One optimisation step on fresh samples; the losses before the update. On a rank of a
    /// data-parallel run (`c`) every rank draws the whole step (samples, label-token flags, noise)
    /// from the same generator and runs its share ([`crate::dist`]); the losses, the exact-match
    /// results and the gradients are the whole batch's on every rank.
    pub fn step(&mut self, c: &dyn Collective) -> Result<StepLosses> {
        if self.step < self.cfg.tower_steps {
            return self.tower_step(c);
        }
        let t0 = std::time::Instant::now();
        let samples = step_samples(&self.cfg, &self.spec, &self.running, &mut self.rng);
        let mine = dist::share(samples.len(), c.rank(), c.size());
        if mine.is_empty() {
            return Err(too_few_samples(samples.len(), c.size()));
        }
        let mut p: Packed = pack(&self.model.vlm, &samples[mine.clone()])?;
        let prob = self.cfg.label_probability(self.step);
        let per = p.images;
        let flags: Vec<bool> = (0..samples.len() * per).map(|_| self.rng.f() < prob).collect();
        p.label_tokens.copy_from_slice(&flags[mine.start * per..mine.end * per]);
        let labels = (self.cfg.label_weight > 0.0 || prob > 0.0).then_some(&self.labels);
        let cfg = &self.cfg;
        let supervise = cfg.supervised();
        let vision = &self.model.vlm.cfg.vision;
        let values = per * vision.tokens() * vision.hidden_size;
        let eps: Vec<f32> = if cfg.feature_noise > 0.0 {
            (0..samples.len() * values).map(|_| self.rng.normal()).collect()
        } else {
            vec![]
        };
        let noise = Some((cfg.feature_noise, eps.get(mine.start * values..mine.end * values).unwrap_or(&[])));
        self.drawing += t0.elapsed();
        let parts = match c.size() {
            1 => None,
            size => {
                let local = batch::counts(&p, self.model.vlm.cfg.text.num_heads);
                let global = dist::global_counts(c, "the step's item counts", &local)?;
                Some(batch::Parts::new(&local, &global.try_into().expect("8 counts"), size))
            }
        };
        let f = forward(&self.model, &p, labels, noise, supervise, parts.as_ref().map(|w| (w, c)), &self.device)?;
        let mut loss = f.answer_loss.clone()
            + f.aux_loss.clone() * cfg.aux_weight
            + f.label_loss * cfg.label_weight
            + f.slot_loss.clone() * cfg.slot_weight
            + f.place_loss.clone() * cfg.place_weight;
        for (h, w) in f.hop_loss.iter().zip(cfg.hop_weights) {
            loss = loss + h.clone() * w;
        }
        let one = |t: &burn::tensor::Tensor<1>| model::splats::host(t.clone())[0];
        let mut values = [
            one(&f.answer_loss),
            one(&f.aux_loss),
            one(&f.hop_loss[0]),
            one(&f.hop_loss[1]),
            one(&f.hop_loss[2]),
            one(&f.slot_loss),
            one(&f.place_loss),
        ];
        let tower = batch::tower_accuracy(&p, f.aux_logits.clone());
        let results = exact(&p, f.log_probs.clone());
        let (values, tower, results) = if c.size() == 1 {
            (values, tower.map(|(r, n)| r as f32 / n.max(1) as f32), results)
        } else {
            let first: usize = samples[..mine.start].iter().map(|s| s.1.len()).sum();
            let total: usize = samples.iter().map(|s| s.1.len()).sum();
            (sum_losses(c, &mut values)?, sum_accuracy(c, tower)?, gather_results(c, &samples, first, total, &results)?)
        };
        let [answer, aux, h0, h1, h2, slots, places] = values;
        let losses = StepLosses { answer, aux, hops: [h0, h1, h2], slots, places, tower };
        if !(losses.answer.is_finite() && losses.aux.is_finite() && losses.hops.iter().all(|h| h.is_finite())) {
            return Err(Error::Diverged { iter: self.step, loss: losses.answer + losses.aux, detail: String::new() });
        }
        for (kind, right) in results {
            self.running.add(kind, right);
        }
        self.update(loss, c)?;
        Ok(losses)
    }
}

/// A step's samples are fewer than the ranks.
fn too_few_samples(samples: usize, ranks: usize) -> Error {
    Error::input(format!(
        "a step drew {samples} samples for {ranks} ranks: every rank needs at least one (raise images_per_step \
         to at least 4 x the ranks, and tower_images to at least the ranks, or run fewer ranks)"
    ))
}

/// The losses of every rank's part summed, divided by the ranks: the whole batch's.
fn sum_losses(c: &dyn Collective, values: &mut [f32; 7]) -> Result<[f32; 7]> {
    let mut v: Vec<f64> = values.iter().map(|&x| x as f64).collect();
    c.sum_f64("the step's losses", &mut v)?;
    Ok(std::array::from_fn(|i| (v[i] / c.size() as f64) as f32))
}

/// The tower's accuracy per task over every rank's object tokens.
fn sum_accuracy(c: &dyn Collective, tower: [(usize, usize); 3]) -> Result<[f32; 3]> {
    let counts: Vec<usize> = tower.iter().flat_map(|&(r, n)| [r, n]).collect();
    let g = dist::global_counts(c, "the tower's accuracy", &counts)?;
    Ok(std::array::from_fn(|k| g[2 * k] as f32 / g[2 * k + 1].max(1) as f32))
}

/// Every rank's exact-match results in the whole step's question order (this rank's start at
/// question `first` of `total`).
fn gather_results(
    c: &dyn Collective,
    samples: &[(Sample, Vec<Qa>)],
    first: usize,
    total: usize,
    mine: &[(Kind, bool)],
) -> Result<Vec<(Kind, bool)>> {
    let mut right = vec![0f64; total];
    for (i, (_, r)) in mine.iter().enumerate() {
        right[first + i] = *r as u8 as f64;
    }
    c.sum_f64("the step's exact-match results", &mut right)?;
    let kinds = samples.iter().flat_map(|s| s.1.iter().map(|q| q.kind));
    Ok(kinds.zip(right).map(|(k, r)| (k, r > 0.5)).collect())
}

impl Trainer {
    /// A pre-training step of the tower alone (object crops and views, half each on average).
    fn tower_step(&mut self, c: &dyn Collective) -> Result<StepLosses> {
        let t0 = std::time::Instant::now();
        let (mut samples, mut images) = (Vec::new(), 0);
        while images < self.cfg.tower_images {
            let kind = if self.rng.f() < 0.5 { SampleKind::Object } else { SampleKind::View };
            let seed = train_seed(&mut self.rng);
            if let Some(s) = self.spec.sample(kind, seed, &mut self.rng) {
                images += s.images.len();
                samples.push((s, Vec::new()));
            }
        }
        self.drawing += t0.elapsed();
        let mine = dist::share(samples.len(), c.rank(), c.size());
        if mine.is_empty() {
            return Err(too_few_samples(samples.len(), c.size()));
        }
        let part = match c.size() {
            1 => None,
            size => {
                let all = batch::tower_tokens(&self.model.vlm, &samples);
                let local = batch::tower_tokens(&self.model.vlm, &samples[mine.clone()]);
                Some(size as f32 * dist::part(local, all))
            }
        };
        let (loss, tower) = batch::tower_loss(&self.model, &samples[mine], part, &self.device);
        let mut aux = model::splats::host(loss.clone())[0];
        let tower = if c.size() == 1 {
            tower.map(|(r, n)| r as f32 / n.max(1) as f32)
        } else {
            let mut v = [aux as f64];
            c.sum_f64("the step's losses", &mut v)?;
            aux = (v[0] / c.size() as f64) as f32;
            sum_accuracy(c, tower)?
        };
        if !aux.is_finite() {
            return Err(Error::Diverged { iter: self.step, loss: aux, detail: String::new() });
        }
        self.update(loss, c)?;
        Ok(StepLosses { aux, tower, ..Default::default() })
    }

    /// Backward pass of `loss`, the gradients averaged over the ranks, one AdamW update at this
    /// step's learning rate (the vision tower's scaled by `tower_lr_scale` after its own phase),
    /// next step.
    fn update(&mut self, loss: burn::tensor::Tensor<1>, c: &dyn Collective) -> Result<()> {
        let mut grads = loss.backward();
        let lr = self.cfg.lr_at(self.step);
        let scale = self.cfg.tower_lr_scale;
        let split = self.step >= self.cfg.tower_steps && scale != 1.0;
        if c.size() == 1 {
            if split {
                // AdamW normalises the gradient away, so the tower gets its own update at its own rate
                let tower = GradientsParams::from_module(&mut grads, &self.model.vlm.vision);
                self.model = self.optim.step(lr * scale, self.model.clone(), tower);
            }
            let rest = GradientsParams::from_grads(grads, &self.model);
            self.model = self.optim.step(lr, self.model.clone(), rest);
        } else {
            let mut all = dist::reduce_grads(c, &self.model, GradientsParams::from_grads(grads, &self.model))?;
            if split {
                let tower = dist::take_grads(&mut all, &self.model.vlm.vision);
                self.model = self.optim.step(lr * scale, self.model.clone(), tower);
            }
            self.model = self.optim.step(lr, self.model.clone(), all);
        }
        self.step += 1;
        Ok(())
    }
}

/// Trains a tabletop VLM from `cfg` on `device` (autodiff is added here) and writes it to `out`
/// (with `train_config.json` and `training_log.json`); `progress` sees every step.
pub fn train(cfg: &VlmTrainConfig, out: &Path, device: &Device, progress: impl FnMut(&LogLine)) -> Result<Accuracy> {
    train_from(cfg, out, None, device, &Solo, false, progress)
}

/// Ranks compare their weights' checksums every this many steps (and at the end of each stage).
pub const CHECK_EVERY: usize = 100;

/// [`train`]; a configuration with a `base` stage trains it first into `out/base` (`progress`
/// sees its steps too), and so on down the chain, except that the stage whose configuration is
/// exactly `base_model`'s `train_config.json` is read from that model directory instead (it and
/// the stages before it are not trained again).
///
/// On the ranks of a data-parallel run (`c`), every rank runs this with the same arguments: each
/// takes its share of every step, rank 0 alone evaluates, writes and reports progress, and the
/// others read a base stage from the `out` rank 0 wrote (a folder every rank sees). The held-out
/// accuracy it returns is rank 0's (the default on the others).
///
/// `resume`: a stage whose model `out` already holds (same configuration) is not trained again,
/// and a stage with a checkpoint goes on from it, exactly as if it had never stopped.
pub fn train_from(
    cfg: &VlmTrainConfig,
    out: &Path,
    base_model: Option<&Path>,
    device: &Device,
    c: &dyn Collective,
    resume: bool,
    mut progress: impl FnMut(&LogLine),
) -> Result<Accuracy> {
    if resume && !out.join("train_config.json").is_file() && !checkpoint::exists(out) && !out.join("base").is_dir() {
        return Err(Error::invalid(out, "--resume: there is no train-vlm run here to resume"));
    }
    train_stages(cfg, out, base_model, device, c, resume, &mut progress)
}

/// How many of `cfg`'s stages (the innermost first) a run into `out` does not train: those
/// `base_model` holds and, with `resume`, those already finished under `out` (stage `k` from the
/// end lives in `out/base/.../base`, `k` deep).
pub fn stages_done(cfg: &VlmTrainConfig, out: &Path, base_model: Option<&Path>, resume: bool) -> usize {
    let chain: Vec<&VlmTrainConfig> = std::iter::successors(Some(cfg), |c| c.base.as_deref()).collect();
    let read = |d: &Path| io::read_config::<VlmTrainConfig>(&d.join("train_config.json")).ok();
    let given =
        base_model.and_then(read).and_then(|b| chain.iter().position(|c| **c == b)).map_or(0, |i| chain.len() - i);
    if !resume {
        return given;
    }
    let mut dir = out.to_path_buf();
    for (i, c) in chain.iter().enumerate() {
        if finished(c, &dir) {
            return given.max(chain.len() - i);
        }
        dir = dir.join("base");
    }
    given
}

/// Whether `out` holds the finished model of a stage of `cfg` (its configuration, its model, no
/// checkpoint of an unfinished run).
fn finished(cfg: &VlmTrainConfig, out: &Path) -> bool {
    out.join("model.safetensors").is_file()
        && !checkpoint::exists(out)
        && io::read_config::<VlmTrainConfig>(&out.join("train_config.json")).is_ok_and(|c| c == *cfg)
}

fn train_stages(
    cfg: &VlmTrainConfig,
    out: &Path,
    base_model: Option<&Path>,
    device: &Device,
    c: &dyn Collective,
    resume: bool,
    progress: &mut dyn FnMut(&LogLine),
) -> Result<Accuracy> {
    cfg.validate()?;
    if resume && finished(cfg, out) {
        let log: Vec<LogLine> = io::read_json(&out.join("training_log.json"))?;
        return Ok(log.iter().rev().find_map(|l| l.eval.clone()).unwrap_or_default());
    }
    let command_device = device;
    let device = &cfg.backend.map_or_else(|| device.clone(), |b| b.device());
    let mut t = match &cfg.base {
        None => {
            if let Some(dir) = base_model {
                let path = dir.join("train_config.json");
                return Err(Error::invalid(&path, "was trained with none of this configuration's stages"));
            }
            Trainer::new(cfg, device)?
        }
        Some(base) => {
            let dir = match base_model {
                Some(dir) if io::read_config::<VlmTrainConfig>(&dir.join("train_config.json"))? == **base => {
                    dir.to_path_buf()
                }
                _ => {
                    let dir = out.join("base");
                    train_stages(base, &dir, base_model, command_device, c, resume, progress)?;
                    dir
                }
            };
            let ad = device.clone().autodiff();
            let vlm = LlavaOnevision::load(&dir, &ad)?;
            Trainer::starting_from(cfg, vlm, &ad)?
        }
    };
    if c.size() > 1 {
        t.model = dist::broadcast_params(c, t.model)?;
    }
    let root = c.is_root();
    if root {
        io::create_dir(out)?;
        io::write_json(&out.join("train_config.json"), cfg)?;
    }
    let held = if root { eval_samples(t.spec(), EVAL_SEEDS..EVAL_SEEDS + cfg.eval_seeds, 2, 2) } else { Vec::new() };
    let mut log = if resume && checkpoint::exists(out) { t.restore(out)? } else { Vec::new() };
    // a resumed run's clock goes on from its log
    let before = log.last().map_or(0.0, |l| l.seconds);
    let start = std::time::Instant::now();
    let mut last = log.iter().rev().find_map(|l| l.eval.clone()).unwrap_or_default();
    while t.step < cfg.steps {
        let lr = cfg.lr_at(t.step);
        let losses = t.step(c)?;
        let step = t.step;
        if step.is_multiple_of(CHECK_EVERY) {
            dist::check_in_step(c, &t.model, step)?;
        }
        if !root {
            continue;
        }
        let (eval, eval_labels) = if cfg.eval_every > 0 && step.is_multiple_of(cfg.eval_every) || step == cfg.steps {
            let valid = t.model.valid();
            let a = evaluate(&valid, &held, device)?;
            let b = (cfg.label_probability(step) > 0.0).then(|| evaluate_with(&valid, &held, Some(&t.labels), device));
            last = a.clone();
            (Some(a), b.transpose()?)
        } else {
            (None, None)
        };
        let evaluated = eval.is_some();
        let line = LogLine {
            step,
            steps: cfg.steps,
            seconds: before + start.elapsed().as_secs_f64(),
            lr,
            answer_loss: losses.answer,
            aux_loss: losses.aux,
            hop_loss: losses.hops,
            slot_loss: losses.slots,
            place_loss: losses.places,
            tower_accuracy: losses.tower,
            eval,
            eval_labels,
            drawing_seconds: t.drawing.as_secs_f64(),
        };
        progress(&line);
        log.push(line);
        if evaluated {
            io::write_json(&out.join("training_log.json"), &log)?;
        }
        if (evaluated || cfg.checkpoint_every > 0 && step.is_multiple_of(cfg.checkpoint_every)) && step < cfg.steps {
            t.save_checkpoint(out, &log)?;
        }
    }
    if root {
        save_model(&t.model.valid().vlm, out)?;
        io::write_json(&out.join("training_log.json"), &log)?;
        // finished: the model is the stage's state from now on
        checkpoint::remove(out);
    }
    // every rank waits here for rank 0's files (the next stage reads them) and checks the weights
    dist::check_in_step(c, &t.model, t.step)?;
    Ok(last)
}
