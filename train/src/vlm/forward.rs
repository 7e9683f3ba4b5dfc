//! The model being trained ([`Trainable`]) and one forward pass over a packed batch with its
//! losses: cross-entropy on the answer tokens (and the closing `<|im_end|>`), an auxiliary
//! per-token classification of colour, shape and size on the vision tokens, the supervised
//! reasoning hops of [`super::hops`] (where the LLM's attention should go while it answers), and
//! the slot and place heads.

use super::data::Sample;
use super::hops::{HopKind, SLOT_LAYER};
use super::pack::{AUX_CLASSES, LabelTokens, Packed, tower_inputs};
use crate::dist::{self, Collective};
use burn::module::Module;
use burn::nn::Linear;
use burn::tensor::{Device, Int, Tensor, TensorData, activation};
use model::data::synth::questions::{Kind, Qa};
use model::error::{Error, Result};
use model::rng::Rng;
use model::vlm::LlavaOnevision;
use model::vlm::qwen2::Probe;

/// The model being trained: the VLM, the auxiliary per-token head and the slot head.
#[derive(Module, Debug)]
pub struct Trainable {
    pub vlm: LlavaOnevision,
    /// `[vision D, 8 + 1 + 6 + 1 + 2 + 1]`: colour, shape and size logits per vision token.
    pub aux: Linear,
    /// `[text D, 2 x (9 + 7)]`: the colour and shape of the first two objects a question names,
    /// read off the answer position's residual stream after layer 1 ([`super::hops`]).
    pub slots: Linear,
    /// `[text D, 2 x (1 + grid)]`: the image column of the same two objects (none + each column),
    /// read off the same position after the find layer (whose hops gather their tokens).
    pub places: Linear,
}

impl Trainable {
    /// A loaded model wrapped for [`forward`] and evaluation: zero auxiliary and slot heads (neither
    /// is part of the llava-hf files; evaluation reads only the answers).
    pub fn reading(vlm: LlavaOnevision, device: &Device) -> Self {
        let zeros = |d_in: usize, d_out: usize| {
            model::vlm::layers::init_linear(&mut Rng::new(0), d_in, d_out, true, 0.0, device)
        };
        let classes = AUX_CLASSES.iter().sum();
        let (dv, dt) = (vlm.cfg.vision.hidden_size, vlm.cfg.text.hidden_size);
        let places = zeros(dt, 2 * place_classes(&vlm));
        Self { aux: zeros(dv, classes), slots: zeros(dt, SLOT_CLASSES.iter().sum()), places, vlm }
    }
}

/// Weights of the auxiliary tasks (colour, shape, size) in the auxiliary loss (their weighted
/// mean). Shape weighs more: it is the one the tower must look across tokens for, and with equal
/// weights the colour and size gradients drown it (per-token shape accuracy stayed near chance;
/// eval/journal/2026-11-24.md, "The tower does not learn shape in burn where the same ViT does in
/// PyTorch").
pub const AUX_TASK_WEIGHTS: [f32; 3] = [1.0, 4.0, 1.0];

/// What one forward pass gives.
pub struct Forward {
    /// Mean cross-entropy of the answer tokens.
    pub answer_loss: Tensor<1>,
    /// Mean cross-entropy of the auxiliary classes.
    pub aux_loss: Tensor<1>,
    /// The auxiliary head's logits `[images * tokens, 18]`.
    pub aux_logits: Tensor<2>,
    /// Mean squared error of the tower's tokens against the label tokens (zero without them).
    pub label_loss: Tensor<1>,
    /// Per [`HopKind`] (in `HopKind::ALL` order): mean cross-entropy of the supervised attention
    /// rows (zero when not supervised).
    pub hop_loss: [Tensor<1>; 3],
    /// Mean cross-entropy of the slot head (zero when not supervised).
    pub slot_loss: Tensor<1>,
    /// Mean cross-entropy of the place head over the named objects that have a place (zero when
    /// not supervised or none has).
    pub place_loss: Tensor<1>,
    /// Log-probabilities `[targets, vocab]` at the answer positions.
    pub log_probs: Tensor<2>,
}

/// Runs the packed batch through the model. `noise`: the std of Gaussian noise added to the
/// vision tokens before the projector, relative to their RMS (training the LLM to read tokens that
/// are close to, not equal to, the tower's: what ChatSplat's encoder gives), and the standard
/// normal draws `[b * images * tokens * D]`; `None` at evaluation. `supervise`: compute the hop
/// and slot losses. `dp`: on a rank of a data-parallel run, its [`Parts`] of the whole batch's
/// means and the collective (the noise's RMS is the whole batch's); `None` on one process.
pub fn forward(
    m: &Trainable,
    p: &Packed,
    label_tokens: Option<&LabelTokens>,
    noise: Option<(f32, &[f32])>,
    supervise: bool,
    dp: Option<(&Parts, &dyn Collective)>,
    device: &Device,
) -> Result<Forward> {
    let vlm = &m.vlm;
    let n_img = p.b * p.images;
    let share = dp.map(|d| d.0);
    let (vis, aux_logits, aux_loss) = tower(m, &p.pixels, &p.labels, n_img, device);
    let aux_loss = weighted(aux_loss, share.map(|w| w.tokens));
    let aux_logits_out = aux_logits.detach();
    let [_, g2, dv] = vis.dims();
    let (vis, label_loss) = match label_tokens {
        Some(lt) => {
            let e = Tensor::<3>::from_data(TensorData::new(lt.tokens(p), [n_img, g2, dv]), device);
            let loss = weighted((vis.clone() - e.clone()).powf_scalar(2.0).mean(), share.map(|w| w.tokens));
            let flags: Vec<f32> = p.label_tokens.iter().map(|&f| if f { 1.0 } else { 0.0 }).collect();
            let m = Tensor::<3>::from_data(TensorData::new(flags, [n_img, 1, 1]), device);
            (vis * (m.clone().neg() + 1.0) + e * m, loss)
        }
        None => (vis, Tensor::zeros([1], device)),
    };
    let vis = match noise {
        Some((std, eps)) if std > 0.0 => {
            let rms = match dp {
                None => vis.clone().powf_scalar(2.0).mean().sqrt().detach(),
                Some((_, c)) => {
                    let sum = model::splats::host(vis.clone().powf_scalar(2.0).sum().detach())[0];
                    let mut s = [sum as f64, (n_img * g2 * dv) as f64];
                    c.sum_f64("the vision tokens' RMS", &mut s)?;
                    Tensor::<1>::from_data(TensorData::new(vec![(s[0] / s[1].max(1.0)).sqrt() as f32], [1]), device)
                }
            };
            if eps.len() != n_img * g2 * dv {
                return Err(Error::input(format!("{} noise draws for {} vision values", eps.len(), n_img * g2 * dv)));
            }
            let eps = Tensor::<3>::from_data(TensorData::new(eps.to_vec(), [n_img, g2, dv]), device);
            vis + eps * rms.unsqueeze_dim::<2>(0).unsqueeze_dim::<3>(0) * std
        }
        _ => vis,
    };
    let proj = vlm.projector.forward(vis); // [N, g2, Dt]
    let dt = proj.dims()[2];
    let newline = vlm.image_newline.val().reshape([1, 1, dt]).expand([n_img, 1, dt]);
    let image_rows = Tensor::cat(vec![proj, newline], 1); // [N, g2 + 1, Dt]
    let ids = Tensor::<2, Int>::from_data(TensorData::new(p.ids.clone(), [p.b, p.t]), device);
    let text = vlm.llm.embed.forward(ids); // [b, t, Dt]
    let mut parts = Vec::new();
    if p.head > 0 {
        parts.push(text.clone().narrow(1, 0, p.head));
    }
    parts.push(image_rows.reshape([p.b, p.images * (g2 + 1), dt]));
    if p.t > p.prefix {
        parts.push(text.narrow(1, p.prefix, p.t - p.prefix));
    }
    let x = Tensor::cat(parts, 1);
    let mask = Tensor::<2>::from_data(TensorData::new(p.mask.clone(), [p.t, p.t]), device);
    let mut probe = Probe::default();
    if supervise {
        probe.layers = vec![0, HopKind::Find.layer()];
        probe.residual_at = vec![SLOT_LAYER + 1, HopKind::Find.layer() + 1];
    }
    let hidden = vlm.llm.forward_masked(x, &p.positions, mask, supervise.then_some(&mut probe));
    let zero = || Tensor::<1>::zeros([1], device);
    let mut hop_loss = [zero(), zero(), zero()];
    let (mut slot_loss, mut place_loss) = (zero(), zero());
    if supervise {
        let heads = vlm.cfg.text.num_heads;
        for (i, kind) in HopKind::ALL.into_iter().enumerate() {
            let probs = probe.probs.iter().find(|(l, _)| *l == kind.layer()).map(|(_, t)| t.clone());
            if let Some(probs) = probs {
                hop_loss[i] = weighted(hop_cross_entropy(probs, p, kind, heads, device), share.map(|w| w.hops[i]));
            }
        }
        let residual = |layer: usize| probe.residual(layer).filter(|_| !p.slots.is_empty());
        if let Some(r) = residual(SLOT_LAYER + 1) {
            let classes = SLOT_CLASSES.map(|c| (c, true)).to_vec();
            let w = share.map(|w| &w.slots[..]);
            slot_loss = slot_cross_entropy(&m.slots, r.reshape([p.b * p.t, dt]), &p.slots, 0, &classes, w, device);
        }
        if let Some(r) = residual(HopKind::Find.layer() + 1) {
            // an object the image does not show, or one the question does not single out, has no place
            let classes = vec![(place_classes(vlm), false); 2];
            let (w, r) = (share.map(|w| &w.places[..]), r.reshape([p.b * p.t, dt]));
            place_loss = slot_cross_entropy(&m.places, r, &p.slots, 4, &classes, w, device);
        }
    }
    let idx: Vec<i64> = p.targets.iter().map(|&(i, _)| i as i64).collect();
    let n = idx.len();
    let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [n]), device);
    let h = hidden.reshape([p.b * p.t, dt]).select(0, idx);
    let log_probs = activation::log_softmax(vlm.llm.logits(h), 1);
    let tgt: Vec<i64> = p.targets.iter().map(|&(_, t)| t).collect();
    let tgt = Tensor::<1, Int>::from_data(TensorData::new(tgt, [n]), device).reshape([n, 1]);
    let answer_loss = weighted(log_probs.clone().gather(1, tgt).mean().neg(), share.map(|w| w.answer));
    Ok(Forward {
        answer_loss,
        aux_loss,
        aux_logits: aux_logits_out,
        label_loss,
        hop_loss,
        slot_loss,
        place_loss,
        log_probs,
    })
}

/// `loss` times this rank's part `w` of the whole batch's mean (untouched on one process).
fn weighted(loss: Tensor<1>, w: Option<f32>) -> Tensor<1> {
    match w {
        Some(w) if w != 1.0 => loss * w,
        _ => loss,
    }
}

/// The item counts behind each mean of [`forward`]'s losses in a packed batch: answer targets,
/// vision tokens, the rows of each supervised hop kind, the slot head's rows, and the rows of each
/// place task. Summed over ranks they give the whole batch's ([`Parts`]).
pub fn counts(p: &Packed, heads: usize) -> [usize; 8] {
    let hop_rows = |kind: HopKind| p.hops.iter().flatten().filter(|h| h.kind == kind && h.head < heads).count();
    let places = |k: usize| p.slots.iter().filter(|s| s.1[4 + k] > 0).count();
    let [h0, h1, h2] = HopKind::ALL.map(hop_rows);
    [p.targets.len(), p.labels[0].len(), h0, h1, h2, p.slots.len(), places(0), places(1)]
}

/// A data-parallel rank's part of each mean in the whole batch's loss (see [`crate::dist`]):
/// `size` times its share of the mean's items, divided among the tasks that have items anywhere;
/// summed over ranks and averaged, the gradients are those of one process on the whole batch.
#[derive(Clone, Debug, PartialEq)]
pub struct Parts {
    pub answer: f32,
    /// The auxiliary and label losses (per vision token).
    pub tokens: f32,
    pub hops: [f32; 3],
    /// Per slot task, and per place task.
    pub slots: [f32; 4],
    pub places: [f32; 2],
}

impl Parts {
    /// From this rank's [`counts`] and their sums over the `size` ranks.
    pub fn new(local: &[usize; 8], global: &[usize; 8], size: usize) -> Self {
        let w = |i: usize| size as f32 * dist::part(local[i], global[i]);
        let slot_tasks = if global[5] > 0 { SLOT_CLASSES.len() } else { 0 };
        let place_tasks = (6..8).filter(|&i| global[i] > 0).count();
        Self {
            answer: w(0),
            tokens: w(1),
            hops: [w(2), w(3), w(4)],
            slots: [w(5) / slot_tasks.max(1) as f32; 4],
            places: [w(6) / place_tasks.max(1) as f32, w(7) / place_tasks.max(1) as f32],
        }
    }
}

/// The vision tower and the auxiliary head on `n_img` images (`pixels` `[n_img, 3, S, S]`
/// flattened, `labels` per token of each auxiliary task): the tokens `[n_img, g2, Dv]`, the
/// auxiliary logits `[n_img * g2, 19]` and their cross-entropy, weighted over the tasks.
fn tower(
    m: &Trainable,
    pixels: &[f32],
    labels: &[Vec<i64>; 3],
    n_img: usize,
    device: &Device,
) -> (Tensor<3>, Tensor<2>, Tensor<1>) {
    let s = m.vlm.cfg.vision.image_size;
    let pixels = Tensor::<4>::from_data(TensorData::new(pixels.to_vec(), [n_img, 3, s, s]), device);
    let vis = m.vlm.vision.forward(pixels); // [N, g2, Dv]
    let [_, g2, dv] = vis.dims();
    let aux_logits = m.aux.forward(vis.clone().reshape([n_img * g2, dv]));
    let mut aux_loss = Tensor::zeros([1], device);
    let mut off = 0;
    for (k, &c) in AUX_CLASSES.iter().enumerate() {
        let lab = Tensor::<1, Int>::from_data(TensorData::new(labels[k].clone(), [n_img * g2]), device);
        aux_loss = aux_loss + cross_entropy(aux_logits.clone().narrow(1, off, c), lab) * AUX_TASK_WEIGHTS[k];
        off += c;
    }
    (vis, aux_logits, aux_loss / AUX_TASK_WEIGHTS.iter().sum::<f32>())
}

/// The tower's pre-training step (no LLM): the auxiliary loss on every image of `samples` and
/// how often the head names each object token's colour, shape and size.
/// `part`: a data-parallel rank's part of the whole batch's mean (`None` on one process).
pub fn tower_loss(
    m: &Trainable,
    samples: &[(Sample, Vec<Qa>)],
    part: Option<f32>,
    device: &Device,
) -> (Tensor<1>, [(usize, usize); 3]) {
    let (pixels, labels, _) = tower_inputs(samples);
    let n_img = samples.iter().map(|(s, _)| s.images.len()).sum();
    let (_, logits, loss) = tower(m, &pixels, &labels, n_img, device);
    (weighted(loss, part), label_accuracy(&labels, logits.detach()))
}

/// The vision tokens of `samples` (what the tower's loss is a mean over).
pub fn tower_tokens(vlm: &LlavaOnevision, samples: &[(Sample, Vec<Qa>)]) -> usize {
    samples.iter().map(|(s, _)| s.images.len()).sum::<usize>() * vlm.cfg.vision.tokens()
}

/// Mean cross-entropy of `logits` `[n, c]` against the classes `labels` `[n]`.
fn cross_entropy(logits: Tensor<2>, labels: Tensor<1, Int>) -> Tensor<1> {
    let n = labels.dims()[0];
    activation::log_softmax(logits, 1).gather(1, labels.reshape([n, 1])).mean().neg()
}

/// The hops of `kind` against the attention weights `probs` (`[B * heads * T, T]`, from
/// [`Probe`]): `-log` of the weight on the targets, or (uniform hops) the cross-entropy against an
/// even spread over them; the mean over rows. Zero when the batch has none.
fn hop_cross_entropy(probs: Tensor<2>, p: &Packed, kind: HopKind, heads: usize, device: &Device) -> Tensor<1> {
    let t = p.t;
    let (mut rows, mut weights, mut uniform) = (Vec::new(), Vec::new(), Vec::new());
    for (b, hops) in p.hops.iter().enumerate() {
        for h in hops.iter().filter(|h| h.kind == kind && h.head < heads) {
            rows.push(((b * heads + h.head) * t + h.query) as i64);
            let mut w = vec![0f32; t];
            let share = if h.uniform { 1.0 / h.targets.len() as f32 } else { 1.0 };
            for &j in &h.targets {
                w[j] = share;
            }
            weights.extend(w);
            uniform.push(if h.uniform { 1f32 } else { 0.0 });
        }
    }
    let n = rows.len();
    if n == 0 {
        return Tensor::zeros([1], device);
    }
    let rows = Tensor::<1, Int>::from_data(TensorData::new(rows, [n]), device);
    let w = Tensor::<2>::from_data(TensorData::new(weights, [n, t]), device);
    let u = Tensor::<1>::from_data(TensorData::new(uniform, [n]), device);
    let a = probs.select(0, rows); // [n, T]
    let eps = 1e-6;
    // on the targets: -log(sum of weights); spread evenly: -sum(share * log weight)
    let on = (a.clone() * w.clone()).sum_dim(1).reshape([n]).add_scalar(eps).log().neg();
    let even = (a.add_scalar(eps).log() * w).sum_dim(1).reshape([n]).neg();
    (on * (u.clone().neg() + 1.0) + even * u).mean()
}

/// A slot-style head's cross-entropy at the first answer positions (`residual` `[B * T, D]`, the
/// stream the head reads): `classes[k]` is the class count of task `k`, whose labels are
/// `slots[..].1[first + k]`, and whether its class 0 ("none") is trained too (else those rows
/// are left out of that task). The mean over the tasks that have rows; with `weights` (a
/// data-parallel rank's, per task) their weighted sum instead.
fn slot_cross_entropy(
    head: &Linear,
    residual: Tensor<2>,
    slots: &[(usize, [i64; 6])],
    first: usize,
    classes: &[(usize, bool)],
    weights: Option<&[f32]>,
    device: &Device,
) -> Tensor<1> {
    let n = slots.len();
    let at: Vec<i64> = slots.iter().map(|s| s.0 as i64).collect();
    let h = residual.select(0, Tensor::<1, Int>::from_data(TensorData::new(at, [n]), device));
    let h = h.clone() / (h.powf_scalar(2.0).mean_dim(1) + 1e-6).sqrt();
    let logits = head.forward(h);
    let mut loss = Tensor::zeros([1], device);
    let (mut off, mut tasks) = (0, 0);
    for (k, &(c, with_none)) in classes.iter().enumerate() {
        let rows: Vec<usize> = (0..n).filter(|&i| with_none || slots[i].1[first + k] > 0).collect();
        if !rows.is_empty() {
            tasks += 1;
            let lab: Vec<i64> = rows.iter().map(|&i| slots[i].1[first + k]).collect();
            let lab = Tensor::<1, Int>::from_data(TensorData::new(lab, [rows.len()]), device);
            let idx: Vec<i64> = rows.iter().map(|&i| i as i64).collect();
            let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [rows.len()]), device);
            let ce = cross_entropy(logits.clone().narrow(1, off, c).select(0, idx), lab);
            loss = loss + weights.map_or(ce.clone(), |w| ce * w[k]);
        }
        off += c;
    }
    // a data-parallel rank's weights already divide by the tasks that have rows on any rank
    if weights.is_some() { loss } else { loss / tasks.max(1) as f32 }
}

/// Class counts of the slot head: colour (none + 8) and shape (none + 6) of two objects.
pub const SLOT_CLASSES: [usize; 4] = [9, 7, 9, 7];

/// Class count of each place task: none + the image grid's columns.
pub fn place_classes(vlm: &LlavaOnevision) -> usize {
    1 + vlm.cfg.vision.grid()
}

/// How often the auxiliary head names the colour, shape and size of the tokens that show an
/// object (`aux_logits` from [`Forward`]): what the tower has learned to see, as (right, object
/// tokens) per task.
pub fn tower_accuracy(p: &Packed, aux_logits: Tensor<2>) -> [(usize, usize); 3] {
    label_accuracy(&p.labels, aux_logits)
}

fn label_accuracy(labels: &[Vec<i64>; 3], aux_logits: Tensor<2>) -> [(usize, usize); 3] {
    let [n, _] = aux_logits.dims();
    let mut out = [(0, 0); 3];
    let objects: Vec<usize> = (0..n).filter(|&i| labels[0][i] > 0).collect();
    let mut off = 0;
    for (k, c) in AUX_CLASSES.into_iter().enumerate() {
        let best = aux_logits.clone().narrow(1, off, c).argmax(1).into_data().convert::<i64>().to_vec::<i64>();
        let best = best.expect("i64 argmax");
        let right = objects.iter().filter(|&&i| best[i] == labels[k][i]).count();
        out[k] = (right, objects.len());
        off += c;
    }
    out
}

/// Per question of a packed batch: whether greedy decoding gives exactly the reference answer
/// (every answer token, and the closing `<|im_end|>`, is the most likely one).
pub fn exact(p: &Packed, log_probs: Tensor<2>) -> Vec<(Kind, bool)> {
    let best = log_probs.argmax(1).into_data().convert::<i64>().to_vec::<i64>().expect("i64 argmax");
    p.questions.iter().map(|(kind, range)| (*kind, range.clone().all(|i| best[i] == p.targets[i].1))).collect()
}
