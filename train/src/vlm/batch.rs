//! Packing samples into one forward pass. Images first (llava-hf's layout): every sample is its
//! prompt prefix (`<|im_start|> user` and its image tokens) followed by its questions as separate
//! segments; each segment sees the prefix and itself only, at the positions it would have alone,
//! so one pass answers many questions exactly as single-turn inference would. Text first: one row
//! per question (the image tokens depend on the question before them), the tower's tokens of an
//! image gathered into every row that asks about it. The loss is cross-entropy on the answer
//! tokens (and the closing `<|im_end|>`), plus an auxiliary per-token classification of colour,
//! shape and size on the vision tokens.

use super::data::{Sample, SampleKind};
use burn::module::Module;
use burn::nn::Linear;
use burn::tensor::{Device, Int, Tensor, TensorData, activation};
use model::data::synth::questions::{Kind, Qa};
use model::error::{Error, Result};
use model::rng::Rng;
use model::vlm::{LlavaOnevision, PromptLayout, Turn};

/// The model being trained: the VLM and the auxiliary per-token head.
#[derive(Module, Debug)]
pub struct Trainable {
    pub vlm: LlavaOnevision,
    /// `[vision D, 8 + 1 + 6 + 1 + 2 + 1]`: colour, shape and size logits per vision token.
    pub aux: Linear,
    /// `[text D, 1]`: text first, whether an image token shows an object the question names, read
    /// off the LLM's residual stream halfway up (the first hop of every look-up question,
    /// supervised so that a small LLM learns it).
    pub relevance: Linear,
}

/// Class counts of the auxiliary head (none + each value).
pub const AUX_CLASSES: [usize; 3] = [9, 7, 3];

/// A packed batch on the host.
pub struct Packed {
    pub kind: SampleKind,
    /// Samples in the batch.
    pub b: usize,
    /// Rows of the LLM batch (`b` images first, one per question text first).
    pub rows: usize,
    /// Text first: per position of the `[rows, t]` batch, the row of `[text embeddings of ids
    /// (rows * t); image rows (b * images * (tokens + 1))]` it reads.
    pub gather: Option<Vec<i64>>,
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
    /// Text first: flat `row * t + i` of every image token (not the newline rows) of a question
    /// that names objects, and whether the token shows one of them.
    pub relevance: Vec<(usize, f32)>,
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
    if vlm.tokenizer.layout == PromptLayout::TextFirst {
        return pack_text_first(vlm, samples);
    }
    let g2 = vlm.cfg.vision.tokens();
    let rows = images * (g2 + 1);
    let tok = &vlm.tokenizer;
    let image_id = tok.image_token_id as i64;
    // head: the template's tokens before the first <image>; segments: after the last one
    let mut head_ids: Option<Vec<i64>> = None;
    let mut segments: Vec<Vec<(Vec<i64>, usize, Kind)>> = Vec::with_capacity(samples.len());
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
            let mut seg = p[last_img + 1..].to_vec();
            let prompt_len = seg.len();
            seg.extend(a);
            segs.push((seg, prompt_len, qa.kind));
        }
        segments.push(segs);
    }
    let head_ids = head_ids.unwrap_or_default();
    let head = head_ids.len();
    let prefix = head + rows;
    let k = segments.iter().map(|s| s.len()).max().unwrap_or(0);
    let l = segments.iter().flatten().map(|s| s.0.len()).max().unwrap_or(0);
    let t = prefix + k * l;
    let b = samples.len();
    let pad = 0i64;
    let mut ids = vec![pad; b * t];
    let mut targets = Vec::new();
    let mut questions = Vec::new();
    for (bi, segs) in segments.iter().enumerate() {
        let row = &mut ids[bi * t..(bi + 1) * t];
        row[..head].copy_from_slice(&head_ids);
        for (si, (seg, prompt_len, kind)) in segs.iter().enumerate() {
            let start = prefix + si * l;
            row[start..start + seg.len()].copy_from_slice(seg);
            let first = targets.len();
            // the token at offset j predicts offset j + 1; answers start at prompt_len
            for j in prompt_len - 1..seg.len() - 1 {
                targets.push((bi * t + start + j, seg[j + 1]));
            }
            questions.push((*kind, first..targets.len()));
        }
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
        rows: b,
        gather: None,
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
        relevance: Vec::new(),
    })
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

/// [`pack`] for a text-first model: one causal row per question, `prompt + answer`, its
/// `<image>` placeholders expanded to the image's tokens and newline row.
fn pack_text_first(vlm: &LlavaOnevision, samples: &[(Sample, Vec<Qa>)]) -> Result<Packed> {
    let (kind, images) = (samples[0].0.kind, samples[0].0.images.len());
    let per_image = vlm.cfg.vision.tokens() + 1;
    let tok = &vlm.tokenizer;
    let image_id = tok.image_token_id as i64;
    // per row: the ids (image rows as `image_id`), which image each image run is, the prompt length, the kind
    let mut seqs: Vec<(Vec<i64>, usize, usize, Kind)> = Vec::new();
    let mut named: Vec<Vec<(u8, u8)>> = Vec::new();
    for (si, (_, qas)) in samples.iter().enumerate() {
        for qa in qas {
            let prompt = tok.prompt(&[Turn::user(images, qa.question.clone())], true);
            let mut ids = Vec::new();
            for id in tok.encode(&prompt)? {
                let n = if id as i64 == image_id { per_image } else { 1 };
                ids.extend(std::iter::repeat_n(id as i64, n));
            }
            if ids.iter().filter(|&&i| i == image_id).count() != images * per_image {
                return Err(Error::input("the prompt does not hold one <image> per image"));
            }
            let prompt_len = ids.len();
            ids.extend(tok.encode(&format!("{}<|im_end|>", qa.answer))?.into_iter().map(|i| i as i64));
            seqs.push((ids, si, prompt_len, qa.kind));
            named.push(named_objects(&qa.question));
        }
    }
    let rows = seqs.len();
    let t = seqs.iter().map(|s| s.0.len()).max().unwrap_or(0);
    let mut ids = vec![0i64; rows * t];
    let mut gather: Vec<i64> = (0..(rows * t) as i64).collect();
    let (pixels, labels, depth) = tower_inputs(samples);
    let g2 = per_image - 1;
    let (mut targets, mut questions, mut relevance) = (Vec::new(), Vec::new(), Vec::new());
    for (r, (seq, si, prompt_len, kind)) in seqs.iter().enumerate() {
        ids[r * t..r * t + seq.len()].copy_from_slice(seq);
        let mut k = 0;
        for (j, &id) in seq[..*prompt_len].iter().enumerate() {
            if id == image_id {
                gather[r * t + j] = (rows * t + si * images * per_image + k) as i64;
                let (img, tok_in) = (si * images + k / per_image, k % per_image);
                if !named[r].is_empty() && tok_in < g2 {
                    let (c, s) = (labels[0][img * g2 + tok_in] as u8, labels[1][img * g2 + tok_in] as u8);
                    let hit = c > 0 && named[r].iter().any(|&(nc, ns)| (nc == 0 || nc == c) && (ns == 0 || ns == s));
                    relevance.push((r * t + j, if hit { 1.0 } else { 0.0 }));
                }
                k += 1;
            }
        }
        let first = targets.len();
        for j in prompt_len - 1..seq.len() - 1 {
            targets.push((r * t + j, seq[j + 1]));
        }
        questions.push((*kind, first..targets.len()));
    }
    let mut mask = vec![f32::NEG_INFINITY; t * t];
    for i in 0..t {
        mask[i * t..=i * t + i].fill(0.0);
    }
    let b = samples.len();
    Ok(Packed {
        kind,
        b,
        rows,
        gather: Some(gather),
        images,
        ids,
        t,
        head: 0,
        prefix: 0,
        positions: (0..t).collect(),
        mask,
        targets,
        questions,
        pixels,
        labels,
        depth,
        label_tokens: vec![false; b * images],
        relevance,
    })
}

/// The (colour, shape) classes a question names (1-based as in the token labels; 0 = not
/// named): a colour word names the shape after it, or any shape when none follows.
pub fn named_objects(question: &str) -> Vec<(u8, u8)> {
    use model::data::synth::scene::{Color, Shape};
    let mut out = Vec::new();
    let mut colour = 0u8;
    for w in question.split(|c: char| !c.is_alphanumeric()).filter(|w| !w.is_empty()) {
        if let Some(i) = Color::ALL.iter().position(|c| c.word() == w) {
            if colour > 0 {
                out.push((colour, 0));
            }
            colour = i as u8 + 1;
        } else if let Some(i) = Shape::ALL.iter().position(|s| s.word() == w || s.plural() == w) {
            out.push((colour, i as u8 + 1));
            colour = 0;
        }
    }
    if colour > 0 {
        out.push((colour, 0));
    }
    out
}

/// What one forward pass gives.
pub struct Forward {
    /// Mean cross-entropy of the answer tokens.
    pub answer_loss: Tensor<1>,
    /// Mean cross-entropy of the auxiliary classes.
    pub aux_loss: Tensor<1>,
    /// Mean squared error of the tower's tokens against the label tokens (zero without them).
    pub label_loss: Tensor<1>,
    /// Binary cross-entropy of [`Trainable::relevance`] (zero without relevance targets).
    pub relevance_loss: Tensor<1>,
    /// Log-probabilities `[targets, vocab]` at the answer positions.
    pub log_probs: Tensor<2>,
}

/// Runs the packed batch through the model. `noise` (with its generator): the std of Gaussian
/// noise added to the vision tokens before the projector, relative to their RMS (training the LLM
/// to read tokens that are close to, not equal to, the tower's: what ChatSplat's encoder gives);
/// `None` at evaluation.
pub fn forward(
    m: &Trainable,
    p: &Packed,
    label_tokens: Option<&LabelTokens>,
    noise: Option<(f32, &mut Rng)>,
    device: &Device,
) -> Forward {
    let vlm = &m.vlm;
    let s = vlm.cfg.vision.image_size;
    let n_img = p.b * p.images;
    let pixels = Tensor::<4>::from_data(TensorData::new(p.pixels.clone(), [n_img, 3, s, s]), device);
    let vis = vlm.vision.forward(pixels); // [N, g2, Dv]
    let [_, g2, dv] = vis.dims();
    // auxiliary per-token classification
    let aux_logits = m.aux.forward(vis.clone().reshape([n_img * g2, dv]));
    let mut aux_loss: Option<Tensor<1>> = None;
    let mut off = 0;
    for (k, &c) in AUX_CLASSES.iter().enumerate() {
        let lp = activation::log_softmax(aux_logits.clone().narrow(1, off, c), 1);
        let lab = Tensor::<1, Int>::from_data(TensorData::new(p.labels[k].clone(), [n_img * g2]), device);
        let l = lp.gather(1, lab.reshape([n_img * g2, 1])).mean().neg();
        aux_loss = Some(match aux_loss {
            Some(a) => a + l,
            None => l,
        });
        off += c;
    }
    let (vis, label_loss) = match label_tokens {
        Some(lt) => {
            let e = Tensor::<3>::from_data(TensorData::new(lt.tokens(p), [n_img, g2, dv]), device);
            let loss = (vis.clone() - e.clone()).powf_scalar(2.0).mean();
            let flags: Vec<f32> = p.label_tokens.iter().map(|&f| if f { 1.0 } else { 0.0 }).collect();
            let m = Tensor::<3>::from_data(TensorData::new(flags, [n_img, 1, 1]), device);
            (vis * (m.clone().neg() + 1.0) + e * m, loss)
        }
        None => (vis, Tensor::zeros([1], device)),
    };
    let vis = match noise {
        Some((std, rng)) if std > 0.0 => {
            let rms = vis.clone().powf_scalar(2.0).mean().sqrt().detach();
            let eps: Vec<f32> = (0..n_img * g2 * dv).map(|_| rng.normal()).collect();
            let eps = Tensor::<3>::from_data(TensorData::new(eps, [n_img, g2, dv]), device);
            vis + eps * rms.unsqueeze_dim::<2>(0).unsqueeze_dim::<3>(0) * std
        }
        _ => vis,
    };
    let proj = vlm.projector.forward(vis); // [N, g2, Dt]
    let dt = proj.dims()[2];
    let newline = vlm.image_newline.val().reshape([1, 1, dt]).expand([n_img, 1, dt]);
    let image_rows = Tensor::cat(vec![proj, newline], 1); // [N, g2 + 1, Dt]
    let ids = Tensor::<2, Int>::from_data(TensorData::new(p.ids.clone(), [p.rows, p.t]), device);
    let text = vlm.llm.embed.forward(ids); // [rows, t, Dt]
    let x = match &p.gather {
        Some(g) => {
            let table =
                Tensor::cat(vec![text.reshape([p.rows * p.t, dt]), image_rows.reshape([n_img * (g2 + 1), dt])], 0);
            let idx = Tensor::<1, Int>::from_data(TensorData::new(g.clone(), [p.rows * p.t]), device);
            table.select(0, idx).reshape([p.rows, p.t, dt])
        }
        None => {
            let mut parts = Vec::new();
            if p.head > 0 {
                parts.push(text.clone().narrow(1, 0, p.head));
            }
            parts.push(image_rows.reshape([p.b, p.images * (g2 + 1), dt]));
            if p.t > p.prefix {
                parts.push(text.narrow(1, p.prefix, p.t - p.prefix));
            }
            Tensor::cat(parts, 1)
        }
    };
    let mask = Tensor::<2>::from_data(TensorData::new(p.mask.clone(), [p.t, p.t]), device);
    let (hidden, relevance_loss) = if p.relevance.is_empty() {
        (vlm.llm.forward_masked(x, &p.positions, mask), Tensor::zeros([1], device))
    } else {
        let tap = vlm.cfg.text.num_layers / 2;
        let (hidden, mid) = vlm.llm.forward_masked_tapped(x, &p.positions, mask, tap);
        let n = p.relevance.len();
        let at: Vec<i64> = p.relevance.iter().map(|&(i, _)| i as i64).collect();
        let at = Tensor::<1, Int>::from_data(TensorData::new(at, [n]), device);
        let h = mid.reshape([p.rows * p.t, dt]).select(0, at);
        let h = h.clone() / (h.powf_scalar(2.0).mean_dim(1) + 1e-6).sqrt();
        let z = m.relevance.forward(h).reshape([n]);
        let y: Vec<f32> = p.relevance.iter().map(|&(_, y)| y).collect();
        let y = Tensor::<1>::from_data(TensorData::new(y, [n]), device);
        // softplus(z) - y z: binary cross-entropy with logits
        let loss = (activation::softplus(z.clone(), 1.0) - y * z).mean();
        (hidden, loss)
    };
    let idx: Vec<i64> = p.targets.iter().map(|&(i, _)| i as i64).collect();
    let n = idx.len();
    let idx = Tensor::<1, Int>::from_data(TensorData::new(idx, [n]), device);
    let h = hidden.reshape([p.rows * p.t, dt]).select(0, idx);
    let log_probs = activation::log_softmax(vlm.llm.logits(h), 1);
    let tgt: Vec<i64> = p.targets.iter().map(|&(_, t)| t).collect();
    let tgt = Tensor::<1, Int>::from_data(TensorData::new(tgt, [n]), device).reshape([n, 1]);
    let answer_loss = log_probs.clone().gather(1, tgt).mean().neg();
    Forward {
        answer_loss,
        aux_loss: aux_loss.expect("three tasks") / AUX_CLASSES.len() as f32,
        label_loss,
        relevance_loss,
        log_probs,
    }
}

/// Per question of a packed batch: whether greedy decoding gives exactly the reference answer
/// (every answer token, and the closing `<|im_end|>`, is the most likely one).
pub fn exact(p: &Packed, log_probs: Tensor<2>) -> Vec<(Kind, bool)> {
    let best = log_probs.argmax(1).into_data().convert::<i64>().to_vec::<i64>().expect("i64 argmax");
    p.questions.iter().map(|(kind, range)| (*kind, range.clone().all(|i| best[i] == p.targets[i].1))).collect()
}
