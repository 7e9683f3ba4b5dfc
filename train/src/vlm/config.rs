//! What a train-vlm run is: the model's shape and every knob of the training ([`VlmTrainConfig`]),
//! the seeds it draws from and holds out.

use super::data::SampleKind;
use super::hops;
use crate::schedule::warmup_cosine;
use model::data::synth::questions::Kind;
use model::error::{Error, Result};
use model::rng::Rng;
use model::vlm::config::{Act, TextConfig, VisionConfig};
use model::vlm::{LlavaConfig, ProcessorConfig};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

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

/// Bounds of a trained model's shape, checked before any work ([`VlmTrainConfig::validate`]).
const MAX_IMAGE: usize = 1024;
const MAX_WIDTH: usize = 4096;
const MAX_LAYERS: usize = 64;
/// 4 GB of f32 weights, 16 GB with AdamW's moments.
const MAX_PARAMETERS: usize = 1_000_000_000;

impl Shape {
    /// About how many weights the model has (the towers' layers, the projector, the word
    /// embeddings of a tabletop vocabulary of ~100 words left out).
    pub fn parameters(&self) -> usize {
        let (vw, tw) = (self.vision_width, self.text_width);
        let kv = tw / self.text_heads.max(1) * self.text_kv_heads;
        let vision = self.vision_layers.saturating_mul(4 * vw * vw + 2 * vw * self.vision_mlp);
        let text = self.text_layers.saturating_mul(2 * tw * tw + 2 * tw * kv + 3 * tw * self.text_mlp);
        let patch = 3 * self.patch_size * self.patch_size * vw;
        vision.saturating_add(text).saturating_add(patch + vw * tw + tw * tw)
    }
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

/// Pixels (at the rendered resolution) below which a seen object is small for
/// [`VlmTrainConfig::small_views`]: 12 x 12, a patch and a half of an 8-px patch.
pub const SMALL_OBJECT: usize = 144;

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
    /// Rays per pixel side on the views' edges (`render_view_supersampled`): 1 = one ray
    /// through each pixel's centre, as the synthetic datasets are rendered.
    pub supersample: usize,
    /// Share of the view samples whose every seen object covers at least [`SMALL_OBJECT`] pixels
    /// that are drawn again (0: views as they come): steps on the views where a small object's
    /// shape is the hard part.
    pub small_views: f32,
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
    /// Share of the picked questions asked after an earlier exchange of the same sample, as the
    /// second turn of a conversation: the question's follow-up where it has one ("What color is
    /// it?" after "What is this?" and its answer; "Is it left of the blue cone?" after "What shape
    /// is the red object?"), else after another of the sample's questions. Above 0 the model's
    /// vocabulary is the conversations' (a base stage's model grows it: "it") and the model holds
    /// conversations ([`model::vlm::LlavaOnevision::converses`]); 0: single questions, as before.
    pub two_turn: f32,
    /// Start from the base stage's auxiliary, slot and place heads (its [`super::HEADS_FILE`], which
    /// every stage writes beside its model) instead of fresh ones: the tower's first steps then
    /// follow a head that already reads it, not the gradients of a random one.
    pub carry_heads: bool,
    /// Share of the base stage's weights kept in the model this stage ends with: after its last
    /// step every weight becomes `keep_base * base + (1 - keep_base) * trained` (weight-space
    /// ensembling of a fine-tuned model with its start, WiSE-FT: the fine-tuned skill stays while
    /// the start's robustness to inputs the stage did not see, here a field's tokens, comes back).
    /// The last evaluation scores the blended model. 0: the trained weights, as before.
    pub keep_base: f32,
    /// Parts of the VLM this stage leaves as its start had them (their gradients are dropped
    /// before each update): "projector" (with the image newline: how the LLM is handed image
    /// tokens), "embed" (the token embeddings, the output head too where tied), "layer.N" (decoder
    /// layer N of the LLM). A stage that teaches a text skill (second turns) can so keep how the
    /// model reads a field's tokens. Empty: every part learns (the tower at `tower_lr_scale`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub frozen: Vec<String>,
    /// Seeds of more runs of this stage (each in `OUT/soup-seed<N>/`, trained first, from the same
    /// start): the stage ends with its weights the average of its own run's and theirs (a model
    /// soup; runs of one recipe that differ in their draws average into a model that keeps what
    /// each learnt and loses less through a field's tokens; BENCHMARKS, "Conversations and find").
    /// Before `keep_base`. The last evaluation scores the average. Empty: the run's own weights.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub soup: Vec<u64>,
    /// A first stage: train this configuration (same model shape) before this one, which then
    /// starts from its weights with a fresh optimizer and fresh heads (auxiliary, slot, place;
    /// they are not part of the llava-hf files; unless `carry_heads`), so a fine-tuned model is
    /// reproduced from its seeds by one command.
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
            supersample: 1,
            small_views: 0.0,
            margin: model::language::CROP_MARGIN,
            label_tokens_until: 0.3,
            label_tokens_end: 0.6,
            label_weight: 1.0,
            eval_every: 500,
            eval_seeds: 8,
            checkpoint_every: 250,
            backend: None,
            two_turn: 0.0,
            carry_heads: false,
            keep_base: 0.0,
            frozen: Vec::new(),
            soup: Vec::new(),
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
        ProcessorConfig::siglip(s, vec![(s, s)])
    }

    /// Refuses values out of range, naming the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, why: &str| Err(Error::input(format!("vlm config: {key} {why}")));
        let m = &self.model;
        if self.steps == 0 {
            return bad("steps", "must be at least 1 (0 would save an untrained model)");
        }
        if !(self.weight_decay >= 0.0 && self.weight_decay.is_finite()) {
            return bad("weight_decay", "must be finite and >= 0");
        }
        let sizes = [
            ("model.image_size", m.image_size, MAX_IMAGE),
            ("model.vision_width", m.vision_width, MAX_WIDTH),
            ("model.vision_layers", m.vision_layers, MAX_LAYERS),
            ("model.vision_mlp", m.vision_mlp, MAX_WIDTH * 4),
            ("model.text_width", m.text_width, MAX_WIDTH),
            ("model.text_layers", m.text_layers, MAX_LAYERS),
            ("model.text_mlp", m.text_mlp, MAX_WIDTH * 4),
        ];
        for (key, v, max) in sizes {
            if !(1..=max).contains(&v) {
                return bad(key, &format!("must be in 1..={max} (is {v})"));
            }
        }
        if m.parameters() > MAX_PARAMETERS {
            return bad(
                "model",
                &format!(
                    "has about {:.2e} parameters (over {MAX_PARAMETERS:.0e}): train-vlm trains small tabletop \
                     models (the built-in one has about {:.1e}); real LLaVA-OneVision weights load with --vlm",
                    m.parameters() as f64,
                    Shape::default().parameters() as f64
                ),
            );
        }
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
        if !(0.0..=1.0).contains(&self.two_turn) {
            return bad("two_turn", "must be a share in 0..=1");
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
        if !(1..=8).contains(&self.supersample) {
            return bad("supersample", "must be in 1..=8 (rays per pixel side on edges; 1: one per pixel)");
        }
        if !(0.0..=0.95).contains(&self.small_views) {
            return bad("small_views", "must be in 0..=0.95 (the share of views without a small object drawn again)");
        }
        if !(0.0..1.0).contains(&self.keep_base) {
            return bad("keep_base", "must be a share in 0..1");
        }
        if self.keep_base > 0.0 && self.base.is_none() {
            return bad("keep_base", "needs a base stage (whose weights are kept)");
        }
        if let Some(bad_part) = self.frozen.iter().find(|p| Frozen::parse(p, m.text_layers).is_none()) {
            let why = format!(
                "\"{bad_part}\" is not a part: \"projector\", \"embed\" or \"layer.N\" with N below {}",
                m.text_layers
            );
            return bad("frozen", &why);
        }
        if self.soup.contains(&self.seed) || (1..self.soup.len()).any(|i| self.soup[..i].contains(&self.soup[i])) {
            return bad(
                "soup",
                "must name seeds other than `seed`, each once (a run averaged with itself adds nothing)",
            );
        }
        if self.carry_heads && self.base.is_none() {
            return bad("carry_heads", "needs a base stage (whose heads this stage starts from)");
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
        w * if self.adaptive { self.need(kind, running) } else { 1.0 }
    }

    /// How much `kind` still needs (`running`): its single questions' error plus the floor, and
    /// where questions are asked as second turns too (`two_turn`), that blended by the share with
    /// its second turns' (a kind answered alone need not be answered in a conversation).
    pub fn need(&self, kind: Kind, running: &RunningAccuracy) -> f32 {
        let alone = running.need(kind, self.adaptive_floor);
        match self.two_turn {
            s if s > 0.0 => (1.0 - s) * alone + s * running.need_second(kind, self.adaptive_floor),
            _ => alone,
        }
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
pub(super) fn train_seed(rng: &mut Rng) -> u64 {
    TRAIN_SEEDS + rng.next_u64() % 1_000_000_000
}

pub(super) const SCENE_IMAGES: usize = model::data::synth::SCENE_VIEWS;

/// Recent training accuracy per question kind (exponential moving average of exact match over
/// training batches), what adaptive sampling draws by.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct RunningAccuracy {
    acc: BTreeMap<Kind, f32>,
    /// The same, of questions asked as second turns (by their kind).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    second: BTreeMap<Kind, f32>,
}

impl RunningAccuracy {
    const DECAY: f32 = 0.95;

    pub fn add(&mut self, kind: Kind, right: bool) {
        Self::blend(&mut self.acc, kind, right);
    }

    /// A question of `kind` asked as a second turn.
    pub fn add_second(&mut self, kind: Kind, right: bool) {
        Self::blend(&mut self.second, kind, right);
    }

    fn blend(acc: &mut BTreeMap<Kind, f32>, kind: Kind, right: bool) {
        let a = acc.entry(kind).or_insert(0.0);
        *a = Self::DECAY * *a + (1.0 - Self::DECAY) * right as u8 as f32;
    }

    /// How much a kind is still worth drawing: its error plus `floor`.
    pub fn need(&self, kind: Kind, floor: f32) -> f32 {
        Self::error(&self.acc, kind) + floor
    }

    /// The same as a second turn.
    pub fn need_second(&self, kind: Kind, floor: f32) -> f32 {
        Self::error(&self.second, kind) + floor
    }

    fn error(acc: &BTreeMap<Kind, f32>, kind: Kind) -> f32 {
        1.0 - acc.get(&kind).copied().unwrap_or(0.0)
    }
}

/// A part of the VLM a stage can leave as it is ([`VlmTrainConfig::frozen`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Frozen {
    /// The projector and the image newline.
    Projector,
    /// The token embeddings (and the output head where tied to them).
    Embed,
    /// A decoder layer of the LLM.
    Layer(usize),
}

impl Frozen {
    /// `name` as a part of a model with `layers` decoder layers (`None`: not one).
    pub fn parse(name: &str, layers: usize) -> Option<Self> {
        match name {
            "projector" => Some(Self::Projector),
            "embed" => Some(Self::Embed),
            _ => name.strip_prefix("layer.")?.parse().ok().filter(|n| *n < layers).map(Self::Layer),
        }
    }
}
