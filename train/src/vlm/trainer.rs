//! The training state and one step: samples drawn by running accuracy, the packed forward, the
//! gradients all-reduced over the ranks, AdamW.

use super::config::Frozen;
use super::data::{DataSpec, Sample, SampleKind, pick_questions};
use super::forward::{
    Parts, SLOT_CLASSES, Trainable, counts, exact, forward, place_classes, tower_accuracy, tower_loss, tower_tokens,
};
use super::pack::{AUX_CLASSES, LabelTokens, Packed, pack};
use super::{Accuracy, RunningAccuracy, SCENE_IMAGES, VlmTrainConfig, init_model, train_seed};
use crate::dist::{self, Collective};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::tensor::Device;
use model::data::synth::questions::{Kind, Qa};
use model::error::{Error, Result};
use model::io;
use model::rng::Rng;
use model::vlm::LlavaOnevision;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The file beside a stage's model that keeps its training-only heads (auxiliary, slot, place:
/// not part of the llava-hf files), for a next stage with `carry_heads`.
pub const HEADS_FILE: &str = "heads.safetensors";

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

/// The samples of one step: a level drawn by `cfg.mix` (adaptive: weighted by how much its kinds
/// still need), fresh scenes until the step's images are filled, questions picked per sample.
pub fn step_samples(
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
            let need: f32 = kinds.iter().map(|k| cfg.need(*k, running)).sum::<f32>();
            p * need / kinds.len().max(1) as f32
        })
        .collect();
    let kind = SampleKind::ALL[rng.weighted(&weights)];
    let per = if kind == SampleKind::Scene { SCENE_IMAGES } else { 1 };
    let want = (cfg.images_per_step / per).max(1);
    let mut out = Vec::with_capacity(want);
    while out.len() < want {
        let seed = train_seed(rng);
        if let Some(s) = spec.sample(kind, seed, rng).filter(|s| !drawn_again(cfg, s, rng)) {
            let asked: Vec<Qa> = s.qas.iter().filter(|q| allowed(q.kind)).cloned().collect();
            if !asked.is_empty() {
                let mut qs = pick_questions(&asked, cfg.questions_per_sample, |k| cfg.question_weight(k, running), rng);
                if cfg.two_turn > 0.0 {
                    let weight = |k: Kind| if cfg.adaptive { running.need_second(k, cfg.adaptive_floor) } else { 1.0 };
                    qs = second_turns(&s, qs, cfg.two_turn, |k| if allowed(k) { weight(k) } else { 0.0 }, rng);
                }
                out.push((s, qs));
            }
        }
    }
    out
}

/// The picked questions `qs` of `s`, each asked as a second turn with probability `share`: three
/// times in four, where the sample has follow-ups (a question with its referent replaced by "it",
/// after the question that named it), one of them in place of the question, drawn by `weight` of
/// its twin's kind (when adaptive, how much that kind's second turns still need: not by the
/// picked question's kind, as adaptive picking seldom draws a kind its single questions get
/// right, and the follow-ups of such a kind would go untaught), else the question after another
/// of the sample's. Follow-ups of weight 0 (kinds the configuration leaves out) are not drawn.
/// Scene samples stay single-turn: a count asked after another count teaches nothing a
/// conversation needs, and trained as second turns they cost the scene's single questions three
/// points (BENCHMARKS, "Conversations and find"). The generator is asked only when `share` is
/// above 0, so single-turn configurations draw as before.
fn second_turns(s: &Sample, qs: Vec<Qa>, share: f32, weight: impl Fn(Kind) -> f32, rng: &mut Rng) -> Vec<Qa> {
    if s.kind == SampleKind::Scene {
        return qs;
    }
    let mut follow_ups = s.follow_ups();
    follow_ups.retain(|f| weight(s.qas[f.twin].kind) > 0.0);
    let weights: Vec<f32> = follow_ups.iter().map(|f| weight(s.qas[f.twin].kind)).collect();
    qs.into_iter()
        .map(|q| {
            if rng.f() >= share {
                return q;
            }
            if !follow_ups.is_empty() && rng.f() < 0.75 {
                return follow_ups[rng.weighted(&weights)].qa(&s.qas);
            }
            let others: Vec<&Qa> = s.qas.iter().filter(|o| **o != q).collect();
            match others.len() {
                0 => q,
                n => {
                    let earlier = others[(rng.next_u64() % n as u64) as usize];
                    q.after(earlier)
                }
            }
        })
        .collect()
}

/// Whether a view sample without a small object is drawn again (`cfg.small_views`; the generator
/// is only asked when the knob is on, so configurations without it draw as before).
fn drawn_again(cfg: &VlmTrainConfig, s: &Sample, rng: &mut Rng) -> bool {
    cfg.small_views > 0.0 && s.smallest.is_some_and(|px| px >= super::config::SMALL_OBJECT) && rng.f() < cfg.small_views
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
    pub(super) rng: Rng,
    pub(super) optim: burn::optim::ModuleOptimizer,
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
        let spec = DataSpec::of(cfg, &vlm.cfg, &vlm.processor);
        let classes: usize = AUX_CLASSES.iter().sum();
        let mut rng = Rng::new(cfg.seed ^ 0xDA7A);
        let aux = model::vlm::layers::init_linear(&mut rng, vlm.cfg.vision.hidden_size, classes, true, 0.02, &ad);
        let vlm_dim = vlm.cfg.vision.hidden_size;
        let slot_classes = SLOT_CLASSES.iter().sum();
        let slots = model::vlm::layers::init_linear(&mut rng, vlm.cfg.text.hidden_size, slot_classes, true, 0.02, &ad);
        // its own generator: `rng` goes on to draw the data, which must not depend on this head
        let (mut place_rng, place_classes) = (Rng::new(cfg.seed ^ 0x91ACE), 2 * place_classes(&vlm));
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

    /// Writes the auxiliary, slot and place heads to `dir`/[`HEADS_FILE`] (one flat tensor each).
    pub fn save_heads(&self, dir: &Path) -> Result<()> {
        let m = &self.model;
        let named = [("aux", &m.aux), ("slots", &m.slots), ("places", &m.places)]
            .map(|(name, head)| {
                let flat = dist::flat_params(head);
                (name.to_string(), vec![flat.len()], flat)
            })
            .to_vec();
        io::write_f32(&dir.join(HEADS_FILE), named, None)
    }

    /// Replaces the auxiliary, slot and place heads with those [`Trainer::save_heads`] wrote to
    /// `dir` (a model of the same shape's stage).
    pub fn load_heads(&mut self, dir: &Path) -> Result<()> {
        let path = dir.join(HEADS_FILE);
        if !path.is_file() {
            return Err(Error::invalid(
                &path,
                "is missing: carry_heads starts from the heads its base stage wrote beside its model (train the base \
                 stage again with this version, or set carry_heads to false)",
            ));
        }
        let (mut tensors, _) = io::read_f32(&path)?;
        let mut take = |name: &str, head: burn::nn::Linear| {
            let (_, flat) =
                tensors.remove(name).ok_or_else(|| Error::invalid(&path, format!("tensor {name} is missing")))?;
            dist::set_flat_params(head, &flat).map_err(|e| Error::invalid(&path, format!("{name}: {e}")))
        };
        let m = &mut self.model;
        m.aux = take("aux", m.aux.clone())?;
        m.slots = take("slots", m.slots.clone())?;
        m.places = take("places", m.places.clone())?;
        Ok(())
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
                let local = counts(&p, self.model.vlm.cfg.text.num_heads);
                let global = dist::global_counts(c, "the step's item counts", &local)?;
                Some(Parts::new(&local, &global.try_into().expect("8 counts"), size))
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
        let tower = tower_accuracy(&p, f.aux_logits.clone());
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
        // in the order of the step's questions (every rank's, gathered)
        let seconds = samples.iter().flat_map(|s| s.1.iter().map(|q| q.follows.is_some()));
        for ((kind, right), second) in results.into_iter().zip(seconds) {
            match second {
                true => self.running.add_second(kind, right),
                false => self.running.add(kind, right),
            }
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
                let all = tower_tokens(&self.model.vlm, &samples);
                let local = tower_tokens(&self.model.vlm, &samples[mine.clone()]);
                Some(size as f32 * dist::part(local, all))
            }
        };
        let (loss, tower) = tower_loss(&self.model, &samples[mine], part, &self.device);
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
        self.drop_frozen(&mut grads);
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

    /// Drops the gradients of the parts the stage leaves as they are (`cfg.frozen`): the
    /// optimizer then leaves them untouched, weight decay included. Every rank drops the same.
    fn drop_frozen(&self, grads: &mut burn::tensor::Gradients) {
        let vlm = &self.model.vlm;
        for name in &self.cfg.frozen {
            let Some(part) = Frozen::parse(name, vlm.llm.layers.len()) else { continue };
            match part {
                Frozen::Projector => {
                    GradientsParams::from_module(grads, &vlm.projector);
                    GradientsParams::from_module(grads, &vlm.image_newline);
                }
                Frozen::Embed => {
                    GradientsParams::from_module(grads, &vlm.llm.embed);
                }
                Frozen::Layer(n) => {
                    GradientsParams::from_module(grads, &vlm.llm.layers[n]);
                }
            }
        }
    }
}
