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
pub mod data;

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
use model::vlm::tokenizer::{ChatTokenizer, PromptLayout, word_level_tokenizer_json};
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
    /// Put the question before the images in the prompt (the model's chat template says so), so
    /// that the image tokens are read knowing the question (and the relevance loss can supervise
    /// that); else llava-hf's images-first layout, where many questions share one pass over an
    /// image (half the time per step). Neither layout has yet taught a small LLM to look up what
    /// a question names (BENCHMARKS.md).
    pub text_first: bool,
    /// Train on these question kinds only (empty: all); for curricula and ablations.
    pub kinds: Vec<Kind>,
    /// Probability of a view, object and scene step.
    pub mix: [f32; 3],
    /// Weight of the auxiliary per-token loss.
    pub aux_weight: f32,
    /// Weight of the relevance loss (text first: which image tokens show what the question names).
    pub relevance_weight: f32,
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
            text_first: false,
            kinds: Vec::new(),
            mix: [0.45, 0.3, 0.25],
            aux_weight: 0.5,
            relevance_weight: 1.0,
            feature_noise: 0.1,
            resolution: 96,
            margin: 0.1,
            label_tokens_until: 0.3,
            label_tokens_end: 0.6,
            label_weight: 1.0,
            eval_every: 500,
            eval_seeds: 8,
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
        if self.images_per_step < SCENE_IMAGES || self.questions_per_sample == 0 {
            return bad("images_per_step", "must be at least 4 and questions_per_sample at least 1");
        }
        if self.mix.iter().any(|p| !(*p >= 0.0)) || self.mix.iter().sum::<f32>() <= 0.0 {
            return bad("mix", "must be three non-negative weights, not all zero");
        }
        for (sample, p) in SampleKind::ALL.iter().zip(self.mix) {
            let level = match sample {
                SampleKind::View => model::vqa::Level::View,
                SampleKind::Object => model::vqa::Level::Object,
                SampleKind::Scene => model::vqa::Level::Scene,
            };
            if p > 0.0 && !self.kinds.is_empty() && !self.kinds.iter().any(|k| k.level() == level) {
                return bad("kinds", "must include a question kind of every level that mix draws");
            }
        }
        if self.resolution < m.patch_size as u32 {
            return bad("resolution", "must be at least the patch size");
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

    /// The learning rate of step `i`: linear warm-up, then cosine decay to `min_lr`.
    pub fn lr_at(&self, i: usize) -> f64 {
        if i < self.warmup {
            return self.lr * (i + 1) as f64 / self.warmup as f64;
        }
        let t = ((i - self.warmup) as f64 / (self.steps.saturating_sub(self.warmup)).max(1) as f64).min(1.0);
        self.min_lr + 0.5 * (self.lr - self.min_lr) * (1.0 + (std::f64::consts::PI * t).cos())
    }
}

const SCENE_IMAGES: usize = model::data::synth::SCENE_VIEWS;

/// A fresh tabletop VLM of `cfg`'s shape, with its word-level tokenizer.
pub fn init_model(cfg: &VlmTrainConfig, device: &Device) -> Result<LlavaOnevision> {
    let json = word_level_tokenizer_json(&vocabulary())?;
    let layout = if cfg.text_first { PromptLayout::TextFirst } else { PromptLayout::ImagesFirst };
    let tokenizer = ChatTokenizer::from_json(&json, 3)?.with_layout(layout);
    let llava = cfg.llava_config(tokenizer.vocab_size());
    Ok(LlavaOnevision::init(llava, cfg.processor(), tokenizer, cfg.seed, device))
}

/// Writes a model directory a llava-hf loader reads: `config.json`, `processor_config.json`,
/// `tokenizer.json`, `tokenizer_config.json`, `chat_template.jinja`, `generation_config.json`
/// and `model.safetensors` (f32), each atomically.
pub fn save_model(vlm: &LlavaOnevision, dir: &Path) -> Result<usize> {
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
    tensors.write(&dir.join("model.safetensors"), false)?;
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
            let f = forward(m, &p, labels, None, device);
            for (k, right) in exact(&p, f.log_probs) {
                acc.add(k, right);
            }
        }
    }
    Ok(acc)
}

/// One line of `training_log.json`, also what [`train`]'s progress callback sees after every step.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct LogLine {
    /// Steps done.
    pub step: usize,
    pub seconds: f64,
    pub lr: f64,
    pub answer_loss: f32,
    pub aux_loss: f32,
    /// The relevance loss (0 without relevance targets).
    #[serde(default)]
    pub relevance_loss: f32,
    /// Held-out accuracy, when this step evaluated.
    pub eval: Option<Accuracy>,
    /// Held-out accuracy reading label tokens, when this step evaluated.
    pub eval_labels: Option<Accuracy>,
}

/// The samples of one step: a kind drawn by `cfg.mix`, fresh scenes until the step's images are
/// filled, questions picked per sample.
fn step_samples(
    cfg: &VlmTrainConfig,
    spec: &DataSpec,
    rng: &mut Rng,
) -> Vec<(Sample, Vec<model::data::synth::questions::Qa>)> {
    let total: f32 = cfg.mix.iter().sum();
    let mut u = rng.f() * total;
    let mut kind = SampleKind::Scene;
    for (k, p) in SampleKind::ALL.iter().zip(cfg.mix) {
        if u < p {
            kind = *k;
            break;
        }
        u -= p;
    }
    let per = if kind == SampleKind::Scene { SCENE_IMAGES } else { 1 };
    let want = (cfg.images_per_step / per).max(1);
    let mut out = Vec::with_capacity(want);
    while out.len() < want {
        let seed = TRAIN_SEEDS + rng.next_u64() % 1_000_000_000;
        if let Some(s) = spec.sample(kind, seed, rng) {
            let asked: Vec<Qa> =
                s.qas.iter().filter(|q| cfg.kinds.is_empty() || cfg.kinds.contains(&q.kind)).cloned().collect();
            if !asked.is_empty() {
                let qs = pick_questions(&asked, cfg.questions_per_sample, rng);
                out.push((s, qs));
            }
        }
    }
    out
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
}

impl Trainer {
    /// A fresh model of `cfg` on `device` (autodiff is added here).
    pub fn new(cfg: &VlmTrainConfig, device: &Device) -> Result<Self> {
        cfg.validate()?;
        let ad = device.clone().autodiff();
        let vlm = init_model(cfg, &ad)?;
        let spec = DataSpec::new(&vlm.cfg, &vlm.processor, cfg.resolution, cfg.margin);
        let classes: usize = AUX_CLASSES.iter().sum();
        let mut rng = Rng::new(cfg.seed ^ 0xDA7A);
        let aux = model::vlm::layers::init_linear(&mut rng, vlm.cfg.vision.hidden_size, classes, true, 0.02, &ad);
        let vlm_dim = vlm.cfg.vision.hidden_size;
        let relevance = model::vlm::layers::init_linear(&mut rng, vlm.cfg.text.hidden_size, 1, true, 0.02, &ad);
        Ok(Self {
            cfg: cfg.clone(),
            model: Trainable { vlm, aux, relevance },
            step: 0,
            spec,
            rng,
            optim: AdamWConfig::new().with_weight_decay(cfg.weight_decay).init(),
            labels: LabelTokens::new(vlm_dim, cfg.seed),
            device: ad,
        })
    }

    /// The data generator (held-out samples for evaluation come from it too).
    pub fn spec(&self) -> &DataSpec {
        &self.spec
    }

    /// One optimisation step on fresh samples: (answer, auxiliary, relevance loss) before the update.
    pub fn step(&mut self) -> Result<(f32, f32, f32)> {
        let samples = step_samples(&self.cfg, &self.spec, &mut self.rng);
        let mut p: Packed = pack(&self.model.vlm, &samples)?;
        let prob = self.cfg.label_probability(self.step);
        for f in p.label_tokens.iter_mut() {
            *f = self.rng.f() < prob;
        }
        let labels = (self.cfg.label_weight > 0.0 || prob > 0.0).then_some(&self.labels);
        let f = forward(&self.model, &p, labels, Some((self.cfg.feature_noise, &mut self.rng)), &self.device);
        let loss = f.answer_loss.clone()
            + f.aux_loss.clone() * self.cfg.aux_weight
            + f.label_loss * self.cfg.label_weight
            + f.relevance_loss.clone() * self.cfg.relevance_weight;
        let (al, xl) = (model::splats::host(f.answer_loss)[0], model::splats::host(f.aux_loss)[0]);
        let rl = model::splats::host(f.relevance_loss)[0];
        if !(al.is_finite() && xl.is_finite()) {
            return Err(Error::Diverged { iter: self.step, loss: al + xl });
        }
        let grads = GradientsParams::from_grads(loss.backward(), &self.model);
        let lr = self.cfg.lr_at(self.step);
        self.model = self.optim.step(lr, self.model.clone(), grads);
        self.step += 1;
        Ok((al, xl, rl))
    }
}

/// Trains a tabletop VLM from `cfg` on `device` (autodiff is added here) and writes it to `out`
/// (with `train_config.json` and `training_log.json`); `progress` sees every step.
pub fn train(
    cfg: &VlmTrainConfig,
    out: &Path,
    device: &Device,
    mut progress: impl FnMut(&LogLine),
) -> Result<Accuracy> {
    let mut t = Trainer::new(cfg, device)?;
    io::create_dir(out)?;
    io::write_json(&out.join("train_config.json"), cfg)?;
    let held = eval_samples(t.spec(), EVAL_SEEDS..EVAL_SEEDS + cfg.eval_seeds, 2, 2);
    let mut log = Vec::new();
    let start = std::time::Instant::now();
    let mut last = Accuracy::default();
    while t.step < cfg.steps {
        let lr = cfg.lr_at(t.step);
        let (al, xl, rl) = t.step()?;
        let step = t.step;
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
            seconds: start.elapsed().as_secs_f64(),
            lr,
            answer_loss: al,
            aux_loss: xl,
            relevance_loss: rl,
            eval,
            eval_labels,
        };
        progress(&line);
        log.push(line);
        if evaluated {
            io::write_json(&out.join("training_log.json"), &log)?;
        }
    }
    save_model(&t.model.valid().vlm, out)?;
    io::write_json(&out.join("training_log.json"), &log)?;
    Ok(last)
}
