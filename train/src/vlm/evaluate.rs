//! Exact match on held-out seeds: the samples, teacher-forced greedy answers, per kind and level.

use super::data::{DataSpec, Sample, SampleKind};
use super::forward::{Trainable, exact, forward};
use super::pack::{LabelTokens, pack};
use super::{TRAIN_SEEDS, VlmTrainConfig};
use burn::tensor::Device;
use model::data::synth::questions::{Kind, Qa};
use model::error::{Error, Result};
use model::rng::Rng;
use model::vlm::LlavaOnevision;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Upper bounds (pixels at the rendered resolution) of the buckets that split view questions by
/// the smallest object their view sees: under 8 x 8, 12 x 12 and 20 x 20 pixels; the last
/// bucket holds the rest. (At 96 px an object is seen from 28 pixels on.)
pub const SMALLEST_BUCKETS: [usize; 3] = [64, super::config::SMALL_OBJECT, 400];

/// Exact-match results by question kind: (right, asked).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Accuracy {
    pub by_kind: BTreeMap<String, (usize, usize)>,
    /// View questions by the bucket ([`SMALLEST_BUCKETS`]) of the smallest object their view
    /// sees, then by kind: (right, asked). Empty where no sizes were given.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub view_by_smallest: Vec<BTreeMap<String, (usize, usize)>>,
}

impl Accuracy {
    pub fn add(&mut self, kind: Kind, right: bool) {
        self.add_named(kind.as_str(), right);
    }

    /// Files a result under `name`, which is not a [`Kind`] (a follow-up's `follow_color`, ...):
    /// the levels and [`Accuracy::by_kind_line`] leave it out.
    pub fn add_named(&mut self, name: &str, right: bool) {
        let e = self.by_kind.entry(name.to_string()).or_default();
        e.0 += right as usize;
        e.1 += 1;
    }

    /// The follow-ups' (right, asked) by kind (`follow_color`, ...; their twins left out).
    fn follow_up_kinds(&self) -> impl Iterator<Item = (&String, &(usize, usize))> {
        self.by_kind.iter().filter(|(k, _)| k.starts_with("follow_") && !k.ends_with("_twin"))
    }

    /// The follow-ups, all kinds together: (right, asked); their twins left out.
    pub fn follow_ups(&self) -> (usize, usize) {
        self.follow_up_kinds().fold((0, 0), |a, (_, v)| (a.0 + v.0, a.1 + v.1))
    }

    /// "follow_color 98.0 (twin 100.0) ... all 91.2 (twins 95.1) of 412": percent right of the
    /// follow-ups and of their twins (`KIND_twin`: the referent spelled out, asked on its own), or
    /// `None` where none were asked.
    pub fn follow_up_line(&self) -> Option<String> {
        let pct = |(r, n): (usize, usize)| 100.0 * r as f64 / n.max(1) as f64;
        let (mut all, mut twins) = ((0, 0), (0, 0));
        let mut parts = Vec::new();
        for (k, &v) in self.follow_up_kinds() {
            let t = self.by_kind.get(&format!("{k}_twin")).copied().unwrap_or_default();
            parts.push(format!("{k} {:.1} (twin {:.1})", pct(v), pct(t)));
            all = (all.0 + v.0, all.1 + v.1);
            twins = (twins.0 + t.0, twins.1 + t.1);
        }
        parts.push(format!("all {:.1} (twins {:.1}) of {}", pct(all), pct(twins), all.1));
        (all.1 > 0).then(|| parts.join(" "))
    }

    /// As [`Accuracy::add`], also filing a view question under the size of the smallest object
    /// its view sees (`smallest`, pixels; `None` for other questions).
    pub fn add_sized(&mut self, kind: Kind, right: bool, smallest: Option<usize>) {
        self.add(kind, right);
        let Some(px) = smallest else { return };
        let bucket = SMALLEST_BUCKETS.iter().position(|&b| px < b).unwrap_or(SMALLEST_BUCKETS.len());
        self.view_by_smallest.resize_with(SMALLEST_BUCKETS.len() + 1, Default::default);
        let e = self.view_by_smallest[bucket].entry(kind.as_str().to_string()).or_default();
        e.0 += right as usize;
        e.1 += 1;
    }

    /// One line per size bucket of the smallest object seen: how many view questions, the share
    /// right, and the shape questions (`shapes`, `objects`, `shape_of`) apart.
    pub fn smallest_lines(&self) -> Vec<String> {
        let pct = |(r, n): (usize, usize)| format!("{:.0}% of {n}", 100.0 * r as f64 / n.max(1) as f64);
        let mut lines = Vec::new();
        for (i, m) in self.view_by_smallest.iter().enumerate() {
            let lo = if i == 0 { 0 } else { SMALLEST_BUCKETS[i - 1] };
            let range = match SMALLEST_BUCKETS.get(i) {
                Some(hi) => format!("{lo}-{} px", hi - 1),
                None => format!(">= {lo} px"),
            };
            let view = m.values().fold((0, 0), |a, v| (a.0 + v.0, a.1 + v.1));
            let mut line = format!("smallest seen object {range}: view {}", pct(view));
            for k in ["shapes", "objects", "shape_of"] {
                if let Some(&v) = m.get(k) {
                    line.push_str(&format!(", {k} {}", pct(v)));
                }
            }
            lines.push(line);
        }
        lines
    }

    /// Fraction right over the kinds of `level` (`None`: all).
    pub fn level(&self, level: Option<model::question_file::Level>) -> f64 {
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
        use model::question_file::Level;
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
        let of: Vec<(Sample, Vec<Qa>)> =
            samples.iter().filter(|s| s.kind == kind).map(|s| (s.clone(), s.qas.clone())).collect();
        for chunk in of.chunks(8) {
            let mut p = pack(&m.vlm, chunk)?;
            p.label_tokens.iter_mut().for_each(|f| *f = labels.is_some());
            let f = forward(m, &p, labels, None, false, None, device)?;
            // `pack` lays out the questions sample by sample, each sample's in order
            let sizes = chunk.iter().flat_map(|(s, qas)| qas.iter().map(|_| s.smallest));
            for ((k, right), smallest) in exact(&p, f.log_probs).into_iter().zip(sizes) {
                acc.add_sized(k, right, smallest);
            }
        }
    }
    if m.vlm.tokenizer.id("it").is_some() {
        follow_ups(m, samples, labels, &mut acc, device)?;
    }
    Ok(acc)
}

/// Every follow-up of the view and object `samples` asked as a second turn, filed under its kind
/// (`follow_left_of`, `follow_color`, ...), and its twin asked on its own (`KIND_twin`): for a
/// model whose vocabulary has "it".
fn follow_ups(
    m: &Trainable,
    samples: &[Sample],
    labels: Option<&LabelTokens>,
    acc: &mut Accuracy,
    device: &Device,
) -> Result<()> {
    for kind in [SampleKind::View, SampleKind::Object] {
        let mut of = Vec::new();
        let mut names = Vec::new();
        for s in samples.iter().filter(|s| s.kind == kind) {
            let f = s.follow_ups();
            if !f.is_empty() {
                // each follow-up, then its twin (the referent spelled out) asked on its own
                names.extend(f.iter().map(|f| (f.kind, false)).chain(f.iter().map(|f| (f.kind, true))));
                let twins = f.iter().map(|f| s.qas[f.twin].clone());
                of.push((s.clone(), f.iter().map(|f| f.qa(&s.qas)).chain(twins).collect::<Vec<Qa>>()));
            }
        }
        let mut names = names.into_iter();
        for chunk in of.chunks(8) {
            let mut p = pack(&m.vlm, chunk)?;
            p.label_tokens.iter_mut().for_each(|f| *f = labels.is_some());
            let f = forward(m, &p, labels, None, false, None, device)?;
            for ((_, right), (name, twin)) in exact(&p, f.log_probs).into_iter().zip(names.by_ref()) {
                acc.add_named(&if twin { format!("{name}_twin") } else { name.to_string() }, right);
            }
        }
    }
    Ok(())
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
    let spec = DataSpec::of(cfg, &vlm.cfg, &vlm.processor);
    let samples = eval_samples(&spec, seeds, views, objects);
    evaluate(&Trainable::reading(vlm, device), &samples, device)
}
