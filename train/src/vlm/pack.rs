//! Packing samples into one forward pass, in llava-hf's images-first layout: every sample is its
//! prompt prefix (`<|im_start|> user` and its image tokens) followed by its questions as separate
//! segments; each segment sees the prefix and itself only, at the positions it would have alone,
//! so one pass answers many questions exactly as single-turn inference would (a second turn's
//! segment holds the earlier question and its answer too, as a conversation's prompt would). Also the symbolic
//! label tokens the LLM first learns on ([`LabelTokens`]).

use super::data::{Sample, SampleKind};
use super::hops::{Hop, Ident, Tokens, Word, question_hops};
use model::data::synth::questions::{Kind, Qa};
use model::error::{Error, Result};
use model::rng::Rng;
use model::vlm::{LlavaOnevision, Turn};

/// Class counts of the auxiliary head (none + each value): the per-token labels a batch packs.
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
    pub(super) fn tokens(&self, p: &Packed) -> Vec<f32> {
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
            // a second turn: the earlier question (with the images) and its answer come first
            let mut turns = Vec::with_capacity(3);
            if let Some(e) = &qa.follows {
                turns.extend([Turn::user(images, e.question.clone()), Turn::assistant(e.answer.clone())]);
            }
            turns.push(Turn::user(if turns.is_empty() { images } else { 0 }, qa.question.clone()));
            let prompt = tok.prompt(&turns, true);
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
            segs.push(Segment { ids, words, prompt_len, kind: qa.kind, second: qa.follows.is_some() });
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
            if seg.second {
                continue; // the hops and slots read a single question's words
            }
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

/// One question's part of a packed row: its prompt after the images (a second turn's: the earlier
/// question, its answer and the question), then the answer.
struct Segment {
    ids: Vec<i64>,
    words: Vec<Word>,
    prompt_len: usize,
    kind: Kind,
    /// A second turn: no hops or slots (they read a single question's words).
    second: bool,
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
pub(super) fn tower_inputs(samples: &[(Sample, Vec<Qa>)]) -> (Vec<f32>, [Vec<i64>; 3], Vec<f32>) {
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
