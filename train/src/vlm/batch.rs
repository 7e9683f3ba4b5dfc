//! Packing samples into one forward pass, in llava-hf's images-first layout: every sample is its
//! prompt prefix (`<|im_start|> user` and its image tokens) followed by its questions as separate
//! segments; each segment sees the prefix and itself only, at the positions it would have alone,
//! so one pass answers many questions exactly as single-turn inference would. The loss is
//! cross-entropy on the answer tokens (and the closing `<|im_end|>`), plus an auxiliary per-token
//! classification of colour, shape and size on the vision tokens, and the supervised reasoning
//! hops of [`super::hops`] (where the LLM's attention should go while it answers).

use super::data::{Sample, SampleKind};
use super::hops::{Hop, HopKind, Ident, SLOT_LAYER, Tokens, Word, question_hops};
use crate::dist::{self, Collective};
use burn::module::Module;
use burn::nn::Linear;
use burn::tensor::{Device, Int, Tensor, TensorData, activation};
use model::data::synth::questions::{Kind, Qa};
use model::error::{Error, Result};
use model::rng::Rng;
use model::vlm::qwen2::Probe;
use model::vlm::{LlavaOnevision, Turn};

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
/// BENCHMARKS.md).
pub const AUX_TASK_WEIGHTS: [f32; 3] = [1.0, 4.0, 1.0];

/// Class counts of the auxiliary head (none + each value).
pub const AUX_CLASSES: [usize; 3] = [9, 7, 3];

/// A packed batch on the host.
pub struct Packed {
    pub kind: SampleKind,
    /// Samples in the batch.
    pub b: usize,
    /// Images per sample.
    pub images: usize,
    /// Token ids `[b, t]` (the image rows hold a placeholder).
    pub ids: Vec<i64>,
    pub t: usize,
    /// Prefix tokens before the image rows (`<|im_start|> user`), and the prefix length.
    pub head: usize,
    pub prefix: usize,
    pub positions: Vec<usize>,
    /// Additive attention mask `[t, t]`.
    pub mask: Vec<f32>,
    /// Flat `b * t + i` of every position whose next token is an answer token, and that token.
    pub targets: Vec<(usize, i64)>,
    /// For every question: its kind and the range of its entries in `targets`.
    pub questions: Vec<(Kind, std::ops::Range<usize>)>,
    /// Normalised pixels `[b * images, 3, S, S]`.
    pub pixels: Vec<f32>,
    /// Per vision token `[b * images * tokens]` of each auxiliary task.
    pub labels: [Vec<i64>; 3],
    /// Per vision token: the camera depth of its object (0: none).
    pub depth: Vec<f32>,
    /// Per image: whether the LLM reads its label tokens instead of the tower's.
    pub label_tokens: Vec<bool>,
    /// Supervised attention rows, per sample (`hops[b]`): see [`super::hops`].
    pub hops: Vec<Vec<Hop>>,
    /// Flat `b * t + i` of every first answer position and the slot and place classes of its
    /// question ([`super::hops::question_hops`]).
    pub slots: Vec<(usize, [i64; 6])>,
}

/// The symbolic stand-in for the tower's output: per token a fixed random vector per colour,
/// shape and size class, plus depth, x and y (the token's centre, -1..1) along fixed directions:
/// what a patch shows and where, nothing from other patches (what ChatSplat's per-patch encoder
/// can reproduce). The LLM first learns on these clean tokens while the tower learns to produce
/// them (mean squared error), then on the tower's own.
pub struct LabelTokens {
    dim: usize,
    classes: [Vec<Vec<f32>>; 3],
    depth: Vec<f32>,
    xy: [Vec<f32>; 2],
}

impl LabelTokens {
    pub fn new(dim: usize, seed: u64) -> Self {
        let mut rng = Rng::new(seed ^ 0x1AB1E);
        let mut vecs =
            |n: usize| -> Vec<Vec<f32>> { (0..n).map(|_| (0..dim).map(|_| rng.normal()).collect()).collect() };
        let classes = [vecs(AUX_CLASSES[0]), vecs(AUX_CLASSES[1]), vecs(AUX_CLASSES[2])];
        let depth = vecs(1).remove(0);
        let xy = [vecs(1).remove(0), vecs(1).remove(0)];
        Self { dim, classes, depth, xy }
    }

    /// `[n_tokens * dim]` of a packed batch.
    fn tokens(&self, p: &Packed) -> Vec<f32> {
        let n = p.depth.len();
        let g2 = n / (p.b * p.images).max(1);
        let g = (g2 as f32).sqrt().round() as usize;
        let mut out = vec![0f32; n * self.dim];
        for t in 0..n {
            let row = &mut out[t * self.dim..(t + 1) * self.dim];
            let (gx, gy) = ((t % g2) % g, (t % g2) / g);
            let at = |i: usize| (i as f32 + 0.5) / g as f32 * 2.0 - 1.0;
            for ((r, x), y) in row.iter_mut().zip(&self.xy[0]).zip(&self.xy[1]) {
                *r += at(gx) * x + at(gy) * y;
            }
            for (k, table) in self.classes.iter().enumerate() {
                for (r, v) in row.iter_mut().zip(&table[p.labels[k][t] as usize]) {
                    *r += v;
                }
            }
            if p.depth[t] > 0.0 {
                for (r, v) in row.iter_mut().zip(&self.depth) {
                    *r += (p.depth[t] - 3.4) * v;
                }
            }
        }
        out
    }
}

/// Packs samples of one kind (same number of images) with their picked questions.
pub fn pack(vlm: &LlavaOnevision, samples: &[(Sample, Vec<Qa>)]) -> Result<Packed> {
    let first = samples.first().ok_or_else(|| Error::input("empty batch"))?;
    let (kind, images) = (first.0.kind, first.0.images.len());
    if samples.iter().any(|(s, _)| s.images.len() != images || s.kind != kind) {
        return Err(Error::input("a batch mixes sample kinds"));
    }
    let g2 = vlm.cfg.vision.tokens();
    let rows = images * (g2 + 1);
    let tok = &vlm.tokenizer;
    let image_id = tok.image_token_id as i64;
    let word = |id: i64| -> Result<Word> { Ok(Word::of(&tok.decode(&[id as u32], false)?)) };
    // head: the template's tokens before the first <image>; segments: after the last one
    let mut head_ids: Option<Vec<i64>> = None;
    let mut segments: Vec<Vec<Segment>> = Vec::with_capacity(samples.len());
    for (_, qas) in samples {
        let mut segs = Vec::new();
        for qa in qas {
            let prompt = tok.prompt(&[Turn::user(images, qa.question.clone())], true);
            let p: Vec<i64> = tok.encode(&prompt)?.into_iter().map(|i| i as i64).collect();
            let a: Vec<i64> = tok.encode(&format!("{}<|im_end|>", qa.answer))?.into_iter().map(|i| i as i64).collect();
            let first_img =
                p.iter().position(|&i| i == image_id).ok_or_else(|| Error::input("no <image> in the prompt"))?;
            let last_img = p.iter().rposition(|&i| i == image_id).expect("found");
            let h = p[..first_img].to_vec();
            match &head_ids {
                None => head_ids = Some(h),
                Some(prev) if *prev != h => return Err(Error::input("prompts differ before the image")),
                _ => {}
            }
            let mut ids = p[last_img + 1..].to_vec();
            let prompt_len = ids.len();
            ids.extend(a);
            let words = ids.iter().map(|&i| word(i)).collect::<Result<Vec<_>>>()?;
            segs.push(Segment { ids, words, prompt_len, kind: qa.kind });
        }
        segments.push(segs);
    }
    let head_ids = head_ids.unwrap_or_default();
    let head = head_ids.len();
    let prefix = head + rows;
    let k = segments.iter().map(|s| s.len()).max().unwrap_or(0);
    let l = segments.iter().flatten().map(|s| s.ids.len()).max().unwrap_or(0);
    let t = prefix + k * l;
    let b = samples.len();
    let pad = 0i64;
    let mut ids = vec![pad; b * t];
    let (mut targets, mut questions, mut hops, mut slots) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (bi, segs) in segments.iter().enumerate() {
        let row = &mut ids[bi * t..(bi + 1) * t];
        row[..head].copy_from_slice(&head_ids);
        let ident = prefix_identities(&samples[bi].0, head, g2);
        let tokens = Tokens::new(&ident).with_columns(prefix_columns(head, images, g2, vlm.cfg.vision.grid()));
        let mut sample_hops = tokens.dedupe();
        for (si, seg) in segs.iter().enumerate() {
            let start = prefix + si * l;
            row[start..start + seg.ids.len()].copy_from_slice(&seg.ids);
            let first = targets.len();
            // the token at offset j predicts offset j + 1; answers start at prompt_len
            for j in seg.prompt_len - 1..seg.ids.len() - 1 {
                targets.push((bi * t + start + j, seg.ids[j + 1]));
            }
            questions.push((seg.kind, first..targets.len()));
            let (q, a) = seg.words.split_at(seg.prompt_len);
            let answer_at = start + seg.prompt_len - 1;
            let (h, classes) = question_hops(seg.kind, q, start, a, answer_at, &tokens);
            sample_hops.extend(h);
            slots.push((bi * t + answer_at, classes));
        }
        hops.push(sample_hops);
    }
    let mut positions: Vec<usize> = (0..prefix).collect();
    for _ in 0..k {
        positions.extend(prefix..prefix + l);
    }
    let mut mask = vec![f32::NEG_INFINITY; t * t];
    for i in 0..t {
        let seg_i = (i >= prefix).then(|| (i - prefix) / l);
        for j in 0..=i {
            let ok = j < prefix || Some((j - prefix) / l) == seg_i;
            if ok {
                mask[i * t + j] = 0.0;
            }
        }
    }
    let (pixels, labels, depth) = tower_inputs(samples);
    let label_tokens = vec![false; b * images];
    Ok(Packed {
        kind,
        b,
        images,
        ids,
        t,
        head,
        prefix,
        positions,
        mask,
        targets,
        questions,
        pixels,
        labels,
        depth,
        label_tokens,
        hops,
        slots,
    })
}

/// One question's part of a packed row: its prompt after the images, then the answer.
struct Segment {
    ids: Vec<i64>,
    words: Vec<Word>,
    prompt_len: usize,
    kind: Kind,
}

/// The image column of every prefix position (`images` rows of `g2` tokens and a newline after
/// `head` text tokens; `grid` columns).
fn prefix_columns(head: usize, images: usize, g2: usize, grid: usize) -> Vec<Option<u8>> {
    let mut cols = vec![None; head];
    for _ in 0..images {
        cols.extend((0..g2).map(|i| Some((i % grid) as u8)));
        cols.push(None);
    }
    cols
}

/// The object each position of a sample's prompt prefix shows (`head` text tokens, then per image
/// `g2` tokens and a newline row): its (colour, shape) label, `None` for anything else.
fn prefix_identities(sample: &Sample, head: usize, g2: usize) -> Vec<Option<Ident>> {
    let mut ident = vec![None; head];
    for img in &sample.images {
        ident.extend(img.labels.iter().map(|l| (l[0] > 0 && l[1] > 0).then_some((l[0], l[1]))));
        debug_assert_eq!(img.labels.len(), g2);
        ident.push(None);
    }
    ident
}

/// Pixels, auxiliary labels and depths of every image of `samples`, in order.
#[allow(clippy::type_complexity)]
fn tower_inputs(samples: &[(Sample, Vec<Qa>)]) -> (Vec<f32>, [Vec<i64>; 3], Vec<f32>) {
    let mut pixels = Vec::new();
    let mut labels: [Vec<i64>; 3] = Default::default();
    let mut depth = Vec::new();
    for (s, _) in samples {
        for img in &s.images {
            pixels.extend_from_slice(&img.pixels);
            depth.extend_from_slice(&img.depth);
            for l in &img.labels {
                for (k, v) in l.iter().enumerate() {
                    labels[k].push(*v as i64);
                }
            }
        }
    }
    (pixels, labels, depth)
}

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
