//! Training and evaluation samples for the tabletop VLM, in exactly the token layouts ChatSplat
//! feeds the LLM: a whole view (view questions), the masked crop of one object (object
//! questions, through the one crop rule), several views of a scene (scene questions). Scenes are
//! drawn from seeds and ray-cast on the fly; every answer is true by construction
//! (`model::data::synth::questions`).

use model::ObjectId;
use model::data::synth::questions::{
    CLICK_FRACTION, FollowUp, Kind, Qa, VISIBLE_FRACTION, ViewFacts, covering_views, object_follow_ups,
    object_questions, scene_questions, view_follow_ups, view_questions,
};
use model::data::synth::raycast::{SynthView, render_view_supersampled};
use model::data::synth::scene::SynthScene;
use model::data::synth::{SCENE_VIEWS, random_camera};
use model::language::ObjectCrop;
use model::question_file::Level;
use model::rng::Rng;
use model::vlm::preprocess::ImagePatches;
use model::vlm::preprocess::{RgbImage, resize};
use model::vlm::{LlavaConfig, ProcessorConfig};
use serde::{Deserialize, Serialize};

/// What a sample shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SampleKind {
    View,
    Object,
    Scene,
}

impl SampleKind {
    pub const ALL: [SampleKind; 3] = [SampleKind::View, SampleKind::Object, SampleKind::Scene];

    /// The level of the questions asked about such a sample.
    pub fn level(self) -> Level {
        match self {
            SampleKind::View => Level::View,
            SampleKind::Object => Level::Object,
            SampleKind::Scene => Level::Scene,
        }
    }
}

/// One image as the vision tower sees it, and what each of its tokens shows: the labels of the
/// auxiliary loss and of the label tokens (the symbolic stand-in for the tower's output that the
/// LLM first learns on).
#[derive(Clone, Debug)]
pub struct TowerImage {
    /// Normalised `[3, S, S]`.
    pub pixels: Vec<f32>,
    /// Per token (row-major grid): (colour, shape, size) class of the object with the most
    /// pixels in the token's patch (at least [`MIN_TOKEN_PIXELS`] of them), 0 = none (else colour
    /// 1..=8, shape 1..=6, size 1..=2).
    pub labels: Vec<[u8; 3]>,
    /// Per token: camera-space depth of that object's pixels in the patch (0 for none).
    pub depth: Vec<f32>,
}

/// The (colour, shape, size) classes (1-based) of object `id` of `scene`; zeros for anything else.
fn token_label(scene: &SynthScene, id: ObjectId) -> [u8; 3] {
    use model::data::synth::scene::{Color, Shape, Size};
    match scene.object(id) {
        Some(o) => [
            1 + Color::ALL.iter().position(|c| *c == o.color).unwrap_or(0) as u8,
            1 + Shape::ALL.iter().position(|c| *c == o.shape).unwrap_or(0) as u8,
            1 + Size::ALL.iter().position(|c| *c == o.size).unwrap_or(0) as u8,
        ],
        None => [0; 3],
    }
}

/// Fraction of a token's patch an object must cover to label the token.
pub const MIN_TOKEN_PIXELS: f32 = 0.04;

/// A sample: its images and the questions asked about them.
#[derive(Clone, Debug)]
pub struct Sample {
    pub kind: SampleKind,
    pub images: Vec<TowerImage>,
    pub qas: Vec<Qa>,
    /// View samples: the pixels (at the rendered resolution) of the smallest object the
    /// questions count as seen; `None` for other samples and for views that see nothing.
    pub smallest: Option<usize>,
}

impl Sample {
    /// The follow-ups of its questions (view and object samples; none for the scene).
    pub fn follow_ups(&self) -> Vec<FollowUp> {
        match self.kind {
            SampleKind::View => view_follow_ups(&self.qas),
            SampleKind::Object => object_follow_ups(&self.qas),
            SampleKind::Scene => Vec::new(),
        }
    }
}

/// How samples are made.
#[derive(Clone, Debug)]
pub struct DataSpec {
    /// Rendered view side (the synthetic datasets' resolution); resized to the tower's input.
    pub resolution: u32,
    /// Rays per pixel side on edges (`render_view_supersampled`; 1: one per pixel).
    pub supersample: usize,
    pub fov_deg: f32,
    /// Object crop margin (the teacher's).
    pub margin: f32,
    pub processor: ProcessorConfig,
    /// The tower's input side, patch and token grid.
    pub image_size: usize,
    pub patch: usize,
    pub grid: usize,
}

impl DataSpec {
    pub fn new(cfg: &LlavaConfig, processor: &ProcessorConfig, resolution: u32, margin: f32) -> Self {
        Self {
            resolution,
            supersample: 1,
            fov_deg: model::data::synth::FOV_DEG,
            margin,
            processor: processor.clone(),
            image_size: cfg.vision.image_size,
            patch: cfg.vision.patch_size,
            grid: cfg.vision.grid(),
        }
    }

    /// The samples a training configuration draws: its render side, crop margin and edge
    /// supersampling, for a model of shape `llava` read through `processor`.
    pub fn of(cfg: &super::VlmTrainConfig, llava: &LlavaConfig, processor: &ProcessorConfig) -> Self {
        Self { supersample: cfg.supersample, ..Self::new(llava, processor, cfg.resolution, cfg.margin) }
    }

    /// The tower input of an image, its id map and depth (`[h, w]`, same size), resized like
    /// the processor's base view (the ids and depths by nearest sample).
    fn tower_image(&self, img: &RgbImage, ids: &[ObjectId], depth: &[f32], scene: &SynthScene) -> TowerImage {
        let s = self.image_size;
        let resized = resize(img, s, s, self.processor.resample);
        let patches = ImagePatches { views: vec![resized], orig_hw: (img.height, img.width), anyres: false };
        let pixels = patches.pixel_values(&self.processor);
        let (g, p) = (self.grid, self.patch);
        let mut labels = Vec::with_capacity(g * g);
        let mut depths = Vec::with_capacity(g * g);
        // per object id: (its pixels in each token, depth sums), for the visibility pass below
        let mut per_object: std::collections::BTreeMap<ObjectId, Vec<(usize, f32)>> = Default::default();
        for ty in 0..g {
            for tx in 0..g {
                let mut count = [0usize; 256];
                let mut dsum = [0f32; 256];
                for y in ty * p..(ty + 1) * p {
                    for x in tx * p..(tx + 1) * p {
                        let sx = (x * img.width / s).min(img.width - 1);
                        let sy = (y * img.height / s).min(img.height - 1);
                        let i = ids[sy * img.width + sx] as usize;
                        count[i] += 1;
                        dsum[i] += depth[sy * img.width + sx];
                    }
                }
                for (i, &n) in count.iter().enumerate().skip(2) {
                    if n > 0 {
                        per_object.entry(i as ObjectId).or_insert_with(|| vec![(0, 0.0); g * g])[ty * g + tx] =
                            (n, dsum[i]);
                    }
                }
                let (best, n) =
                    (2..256).map(|i| (i, count[i])).max_by_key(|&(i, n)| (n, usize::MAX - i)).unwrap_or((0, 0));
                let enough = n as f32 >= MIN_TOKEN_PIXELS * (p * p) as f32;
                depths.push(if enough { dsum[best] / n as f32 } else { 0.0 });
                labels.push(if enough { token_label(scene, best as ObjectId) } else { [0; 3] });
            }
        }
        // every object the questions count as seen shows in at least one token: one that no
        // patch is mostly made of takes the token where it has most pixels among those it can take
        // without leaving another object with none (a token shown by nothing, or by an object
        // that shows in other tokens too)
        for (id, tokens) in per_object {
            let total: usize = tokens.iter().map(|t| t.0).sum();
            let label = token_label(scene, id);
            if (total as f32) < VISIBLE_FRACTION * (s * s) as f32 || label == [0; 3] || labels.contains(&label) {
                continue;
            }
            let free = |i: usize| labels[i] == [0; 3] || labels.iter().filter(|l| **l == labels[i]).count() > 1;
            let best = tokens.iter().enumerate().filter(|(i, t)| t.0 > 0 && free(*i));
            if let Some((at, &(n, d))) = best.max_by_key(|(i, t)| (t.0, usize::MAX - i)) {
                labels[at] = label;
                depths[at] = d / n as f32;
            }
        }
        TowerImage { pixels, labels, depth: depths }
    }

    fn render(&self, scene: &SynthScene, rng: &mut Rng) -> (SynthView, ViewFacts, RgbImage) {
        let r = self.resolution;
        let cam = random_camera(rng, self.fov_deg, r, r);
        let v = render_view_supersampled(&cam, scene, self.supersample);
        let facts = ViewFacts::of(scene, &v.ids, &v.depth, r as usize, r as usize);
        let img = RgbImage::from_f32(r as usize, r as usize, &v.rgb);
        (v, facts, img)
    }

    /// A sample of `kind` from the scene of `seed` (random cameras from `rng`); `None` when the
    /// drawn views give nothing to ask (e.g. an ambiguous view, or no object large enough).
    pub fn sample(&self, kind: SampleKind, seed: u64, rng: &mut Rng) -> Option<Sample> {
        let scene = SynthScene::from_seed(seed);
        match kind {
            SampleKind::View => {
                let (v, facts, img) = self.render(&scene, rng);
                let qas = view_questions(&scene, &facts, rng);
                let image = self.tower_image(&img, &v.ids, &v.depth, &scene);
                (!qas.is_empty() && shows_every_seen_object(&image, &facts, &scene)).then(|| Sample {
                    kind,
                    images: vec![image],
                    qas,
                    smallest: facts.seen.iter().map(|s| s.pixels).min(),
                })
            }
            SampleKind::Object => {
                let (v, facts, img) = self.render(&scene, rng);
                if facts.ambiguous {
                    return None;
                }
                let r = self.resolution as usize;
                let big: Vec<ObjectId> = facts
                    .seen
                    .iter()
                    .filter(|s| s.pixels as f32 >= CLICK_FRACTION * (r * r) as f32)
                    .map(|s| s.id)
                    .collect();
                if big.is_empty() {
                    return None;
                }
                let id = big[(rng.next_u64() % big.len() as u64) as usize];
                let crop = ObjectCrop::of(&v.ids, r, r, id, self.margin)?;
                let obj_img = crop.masked_image(&img, &v.ids, id);
                // the crop's id map: the object where it is, nothing elsewhere
                let side = crop.side;
                let mut ids: Vec<ObjectId> = vec![0; side * side];
                let mut depth = vec![0f32; side * side];
                let [bx0, by0, bx1, by1] = crop.bbox;
                for y in by0..by1 {
                    for x in bx0..bx1 {
                        if v.ids[y * r + x] == id {
                            let o = (y - by0 + crop.offset[1]) * side + (x - bx0 + crop.offset[0]);
                            ids[o] = id;
                            depth[o] = v.depth[y * r + x];
                        }
                    }
                }
                let o = scene.object(id)?;
                let image = self.tower_image(&obj_img, &ids, &depth, &scene);
                Some(Sample { kind, images: vec![image], qas: object_questions(o), smallest: None })
            }
            SampleKind::Scene => {
                // candidate views around the scene; the first SCENE_VIEWS that together see everything
                let renders: Vec<_> = (0..8).map(|_| self.render(&scene, rng)).collect();
                let facts: Vec<ViewFacts> = renders.iter().map(|r| r.1.clone()).collect();
                let chosen = covering_views(&scene, &facts, SCENE_VIEWS)?;
                let images: Vec<TowerImage> = chosen
                    .iter()
                    .map(|&i| self.tower_image(&renders[i].2, &renders[i].0.ids, &renders[i].0.depth, &scene))
                    .collect();
                let shown = chosen.iter().zip(&images).all(|(&i, im)| shows_every_seen_object(im, &facts[i], &scene));
                shown.then(|| Sample { kind, images, qas: scene_questions(&scene), smallest: None })
            }
        }
    }
}

/// Whether every object a view's questions count as seen shows in at least one token of its
/// image (objects that share their only tokens with others cannot all show; such views are not
/// asked about, so that answers and hop targets agree with what the tokens show).
fn shows_every_seen_object(image: &TowerImage, facts: &ViewFacts, scene: &SynthScene) -> bool {
    facts.seen.iter().all(|s| image.labels.contains(&token_label(scene, s.id)))
}

/// Picks up to `k` questions of a sample, spread over kinds (a kind drawn with probability
/// proportional to `weight`, then a question of it), without repeats.
pub fn pick_questions(qas: &[Qa], k: usize, weight: impl Fn(Kind) -> f32, rng: &mut Rng) -> Vec<Qa> {
    let mut left: Vec<Qa> = qas.to_vec();
    let mut out = Vec::with_capacity(k);
    while out.len() < k && !left.is_empty() {
        let mut kinds: Vec<_> = left.iter().map(|q| q.kind).collect();
        kinds.sort();
        kinds.dedup();
        let w: Vec<f32> = kinds.iter().map(|&k| weight(k).max(1e-6)).collect();
        let kind = kinds[rng.weighted(&w)];
        let of: Vec<usize> = (0..left.len()).filter(|&i| left[i].kind == kind).collect();
        let i = of[(rng.next_u64() % of.len() as u64) as usize];
        out.push(left.swap_remove(i));
    }
    out
}
