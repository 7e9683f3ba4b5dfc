//! Text search over a scene's objects (`chatsplat find`, the viewer's search box): every object
//! is scored against a phrase through ChatSplat's own object tokens, as how well the phrase
//! answers the object-level questions "What is this?", "What color is this?", "What shape is
//! this?" and "What size is this?" about it: the probability per token (geometric mean) of the
//! phrase and then the end of the turn, best over the questions. So "red cone" scores as a name,
//! "red" as a colour and "cone" as a shape, and a phrase the model would never say about an object
//! scores near 0. Each object is seen through the training view where it shows most (its masked
//! object map, encoded once); each question's prompt about it is prefilled once and kept, so a
//! query prefills only its own few tokens per object and question.

use crate::ObjectId;
use crate::chat::{ChatSession, Picked};
use crate::error::{Error, Result};
use crate::run::GeometryRun;
use crate::vlm::PromptCache;
use burn::tensor::Tensor;
use splat_kernels::Camera;
use std::collections::BTreeMap;

/// The questions a phrase is scored as the answer of.
pub const FIND_QUESTIONS: [&str; 4] =
    ["What is this?", "What color is this?", "What shape is this?", "What size is this?"];
/// Score from which an object matches, by default.
pub const DEFAULT_THRESHOLD: f32 = 0.5;
/// Longest phrase, in characters.
pub const MAX_PHRASE: usize = 200;
/// Identity renders that list a scene's objects are made this small (longest side).
pub const LIST_SIDE: u32 = 128;
/// An object is listed when it covers at least this fraction of some training view.
pub const LIST_FRACTION: f32 = 0.002;

/// Object names by instance id: the synthetic scene's own (`scene.json` beside its dataset:
/// "red cube", id 1 the table), else "object N".
#[derive(Clone, Debug, Default)]
pub struct ObjectNames {
    names: BTreeMap<ObjectId, String>,
    /// A synthetic scene's objects (not its table); `None` where the dataset does not say.
    objects: Option<Vec<ObjectId>>,
    /// The surfaces (ground, table) of a run whose ids come from a matched masks folder, as its
    /// `masks.json` marks them (`chatsplat masks`): never searched.
    surfaces: Vec<ObjectId>,
}

/// What [`ObjectNames`] reads of a matched masks folder's `masks.json`.
#[derive(serde::Deserialize)]
struct MatchedMasks {
    objects: Vec<MatchedObject>,
}

#[derive(serde::Deserialize)]
struct MatchedObject {
    id: ObjectId,
    #[serde(default)]
    surface: bool,
}

impl ObjectNames {
    /// The names the run's dataset knows (none when it has no `scene.json`, or when the run's
    /// ids come from other masks than the dataset's own, `--masks`: `scene.json` names its own
    /// ids); a `scene.json` that cannot be read is reported in `warnings`.
    pub fn of_run(run: &GeometryRun, warnings: &mut Vec<String>) -> Self {
        use crate::data::synth::scene::SynthScene;
        let Ok(state) = run.read_state() else { return Self::default() };
        if let Some(dir) = &state.data.mask_dir {
            // no names; the surfaces `chatsplat masks` found, where it made the masks
            let path = dir.resolve(&run.dir).join("masks.json");
            if !path.is_file() {
                return Self::default();
            }
            return match crate::io::read_json::<MatchedMasks>(&path) {
                Ok(m) => {
                    Self { surfaces: m.objects.iter().filter(|o| o.surface).map(|o| o.id).collect(), ..Self::default() }
                }
                Err(e) => {
                    warnings.push(format!("surfaces unknown: {e}"));
                    Self::default()
                }
            };
        }
        let path = state.data.dir.resolve(&run.dir).join("scene.json");
        if !path.exists() {
            return Self::default();
        }
        match crate::io::read_json::<SynthScene>(&path) {
            Ok(scene) => {
                let mut names: BTreeMap<ObjectId, String> = scene.objects.iter().map(|o| (o.id, o.name())).collect();
                names.insert(crate::data::synth::TABLE_ID, "table".into());
                Self { names, objects: Some(scene.objects.iter().map(|o| o.id).collect()), surfaces: Vec::new() }
            }
            Err(e) => {
                warnings.push(format!("object names unavailable: {e}"));
                Self::default()
            }
        }
    }

    /// No names; a search looks at `objects` alone (e.g. a capture's objects less the ground it
    /// stands on, known from elsewhere).
    pub fn only(objects: Vec<ObjectId>) -> Self {
        Self { names: BTreeMap::new(), objects: Some(objects), surfaces: Vec::new() }
    }

    pub fn name(&self, id: ObjectId) -> String {
        self.names.get(&id).cloned().unwrap_or_else(|| format!("object {id}"))
    }

    /// The names of a synthetic scene's objects (not its table), in id order; none where the
    /// dataset does not say.
    pub fn objects(&self) -> Vec<String> {
        self.objects.iter().flatten().map(|&id| self.name(id)).collect()
    }

    /// Whether `id` is one of a synthetic scene's objects (its table is not); `None` where the
    /// dataset does not list its objects.
    pub fn lists(&self, id: ObjectId) -> Option<bool> {
        self.objects.as_ref().map(|o| o.contains(&id))
    }

    /// Whether `id` is a surface a matched masks folder marked (the ground or a table).
    pub fn surface(&self, id: ObjectId) -> bool {
        self.surfaces.contains(&id)
    }

    /// Whether a search looks at instance `id`: every instance, except a synthetic scene's table
    /// (the ground its objects stand on, which its questions and the built-in model never name)
    /// and the surfaces of matched masks, which stand for it in a capture without labels.
    pub fn searched(&self, id: ObjectId) -> bool {
        !self.surface(id) && self.objects.as_ref().is_none_or(|o| o.contains(&id))
    }
}

/// An object of the scene and the training view where it shows most.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneObject {
    pub id: ObjectId,
    pub view: usize,
    /// The fraction of that view it covers.
    pub fraction: f32,
}

/// `cam` scaled so that its longest side is at most `side` pixels.
pub fn scaled(cam: &Camera, side: u32) -> Camera {
    let s = (side as f32 / cam.width.max(cam.height) as f32).min(1.0);
    let mut c = *cam;
    c.width = ((cam.width as f32 * s).round() as u32).max(1);
    c.height = ((cam.height as f32 * s).round() as u32).max(1);
    c.fx *= s;
    c.fy *= s;
    c.cx *= s;
    c.cy *= s;
    c
}

/// The objects the training views show (each covering at least [`LIST_FRACTION`] of one, in
/// identity renders at [`LIST_SIDE`]), by id; none for a scene trained without masks.
pub fn scene_objects(s: &ChatSession) -> Result<Vec<SceneObject>> {
    let mut best: BTreeMap<ObjectId, SceneObject> = BTreeMap::new();
    if !s.scene.masks {
        return Ok(Vec::new());
    }
    for (view, c) in s.cameras[..s.train_views].iter().enumerate() {
        let ids = s.scene.splats.render_ids(&scaled(c, LIST_SIDE))?;
        for (id, n) in crate::language::pixel_counts(&ids).into_iter().filter(|&(id, _)| id != 0) {
            let fraction = n as f32 / ids.len() as f32;
            if best.get(&id).is_none_or(|b| fraction > b.fraction) {
                best.insert(id, SceneObject { id, view, fraction });
            }
        }
    }
    Ok(best.into_values().filter(|o| o.fraction >= LIST_FRACTION).collect())
}

/// One object scored against a phrase.
#[derive(Clone, Debug, PartialEq)]
pub struct Scored {
    pub id: ObjectId,
    /// 0-1: the phrase's probability per token as the best-fitting question's answer.
    pub score: f32,
    /// That question.
    pub question: &'static str,
}

/// An object ready to be searched: its pick at its best view (the tokens), their prompt
/// embeddings, and each question's prompt and keys and values.
struct Searchable {
    object: SceneObject,
    _picked: Picked,
    images: Vec<Tensor<2>>,
    prompts: Vec<(Vec<u32>, PromptCache)>,
}

/// What a search keeps between queries.
pub struct Finder {
    objects: Vec<Searchable>,
}

impl Finder {
    /// The objects of the scene ([`scene_objects`]) that `names` says a search looks at, made
    /// searchable: their object tokens at their best training view; each question's prompt is
    /// prefilled at the first query.
    pub fn new(s: &ChatSession, names: &ObjectNames) -> Result<Self> {
        s.scene.check_masks()?;
        let mut objects = Vec::new();
        for object in scene_objects(s)?.into_iter().filter(|o| names.searched(o.id)) {
            let Some(picked) = s.select(&s.cameras[object.view], object.id)? else { continue };
            let images = vec![s.vlm.token_embeds(s.object_tokens(&picked)?)];
            let counts = [images[0].dims()[0]];
            let prompts = FIND_QUESTIONS
                .iter()
                .map(|q| Ok((s.vlm.conversation_ids(&[], q, &counts)?, PromptCache::default())))
                .collect::<Result<_>>()?;
            objects.push(Searchable { object, _picked: picked, images, prompts });
        }
        Ok(Self { objects })
    }

    /// The objects searched.
    pub fn objects(&self) -> impl Iterator<Item = &SceneObject> {
        self.objects.iter().map(|o| &o.object)
    }

    /// Every object scored against `phrase`, best first. An error for an empty phrase or one of
    /// more than [`MAX_PHRASE`] characters.
    pub fn rank(&mut self, s: &ChatSession, phrase: &str) -> Result<Vec<Scored>> {
        let phrase = normalize(phrase)?;
        let mut out = Vec::with_capacity(self.objects.len());
        for o in &mut self.objects {
            let mut best = Scored { id: o.object.id, score: 0.0, question: FIND_QUESTIONS[0] };
            for ((ids, cache), question) in o.prompts.iter_mut().zip(FIND_QUESTIONS) {
                let lp = s.vlm.answer_logprobs(ids, &o.images, cache, &phrase)?;
                let score = (lp.iter().sum::<f32>() / lp.len() as f32).exp();
                if score > best.score {
                    best = Scored { id: o.object.id, score, question };
                }
            }
            out.push(best);
        }
        out.sort_by(|a, b| b.score.total_cmp(&a.score).then(a.id.cmp(&b.id)));
        Ok(out)
    }
}

/// The phrase as scored: trimmed, lower case, without final punctuation; an error when empty
/// or longer than [`MAX_PHRASE`] characters.
pub fn normalize(phrase: &str) -> Result<String> {
    let p = phrase.trim().trim_end_matches(['.', '?', '!']).trim().to_lowercase();
    if p.is_empty() {
        return Err(Error::input("the phrase to find is empty"));
    }
    let n = p.chars().count();
    if n > MAX_PHRASE {
        return Err(Error::input(format!("the phrase to find is {n} characters; at most {MAX_PHRASE}")));
    }
    Ok(p)
}

/// Checks a match threshold: a number in 0-1.
pub fn check_threshold(t: f32) -> Result<f32> {
    if (0.0..=1.0).contains(&t) { Ok(t) } else { Err(Error::input(format!("the threshold is {t}; it must be in 0-1"))) }
}

/// The ids of the objects of `ranked` scoring at least `threshold` (the matches), best first.
pub fn matches(ranked: &[Scored], threshold: f32) -> Vec<ObjectId> {
    ranked.iter().filter(|r| r.score >= threshold).map(|r| r.id).collect()
}

/// Objects found against the objects phrases name, added up over phrases (a question file's
/// `find` level): precision, recall and F1 of the objects found, and how often a phrase that
/// names no object finds nothing.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FindTally {
    pub phrases: usize,
    /// Phrases that found exactly the objects they name.
    pub exact: usize,
    pub true_pos: usize,
    pub false_pos: usize,
    pub false_neg: usize,
    /// Phrases that name no object, and of them those that found nothing.
    pub absent: usize,
    pub absent_empty: usize,
}

impl FindTally {
    /// Adds one phrase: the ids it names and the ids found (each set without repeats).
    pub fn add(&mut self, named: &[ObjectId], found: &[ObjectId]) {
        let hit = found.iter().filter(|f| named.contains(f)).count();
        self.phrases += 1;
        self.true_pos += hit;
        self.false_pos += found.len() - hit;
        self.false_neg += named.len() - hit;
        self.exact += (hit == named.len() && hit == found.len()) as usize;
        if named.is_empty() {
            self.absent += 1;
            self.absent_empty += found.is_empty() as usize;
        }
    }

    pub fn merge(&mut self, o: &FindTally) {
        self.phrases += o.phrases;
        self.exact += o.exact;
        self.true_pos += o.true_pos;
        self.false_pos += o.false_pos;
        self.false_neg += o.false_neg;
        self.absent += o.absent;
        self.absent_empty += o.absent_empty;
    }

    /// Of the objects found, the share that the phrases name (1 when nothing was found).
    pub fn precision(&self) -> f32 {
        ratio(self.true_pos, self.true_pos + self.false_pos)
    }

    /// Of the objects the phrases name, the share found (1 when they name none).
    pub fn recall(&self) -> f32 {
        ratio(self.true_pos, self.true_pos + self.false_neg)
    }

    pub fn f1(&self) -> f32 {
        let (p, r) = (self.precision(), self.recall());
        if p + r == 0.0 { 0.0 } else { 2.0 * p * r / (p + r) }
    }

    /// One line: `find (N phrases): precision .. recall .. F1 ..; exact ..; absent: k of n found nothing`.
    pub fn summary(&self) -> String {
        format!(
            "find ({} phrases): precision {:.3} recall {:.3} F1 {:.3}; exactly the named objects {:.1} %; \
             phrases naming nothing found nothing: {} of {} ({:.1} %)",
            self.phrases,
            self.precision(),
            self.recall(),
            self.f1(),
            100.0 * ratio(self.exact, self.phrases),
            self.absent_empty,
            self.absent,
            100.0 * ratio(self.absent_empty, self.absent)
        )
    }
}

fn ratio(a: usize, b: usize) -> f32 {
    if b == 0 { 1.0 } else { a as f32 / b as f32 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn find_tally_counts_objects_found_against_those_named() {
        let mut t = FindTally::default();
        t.add(&[3, 5], &[5, 3]); // exact
        t.add(&[4], &[4, 6]); // one invented
        t.add(&[2, 7], &[7]); // one missed
        t.add(&[], &[]); // absent, nothing found
        t.add(&[], &[2]); // absent, one found
        assert_eq!((t.phrases, t.exact, t.true_pos, t.false_pos, t.false_neg), (5, 2, 4, 2, 1));
        assert_eq!((t.absent, t.absent_empty), (2, 1));
        assert!((t.precision() - 4.0 / 6.0).abs() < 1e-6 && (t.recall() - 0.8).abs() < 1e-6);
        assert!((t.f1() - 2.0 * (4.0 / 6.0) * 0.8 / (4.0 / 6.0 + 0.8)).abs() < 1e-6);
        let mut u = FindTally::default();
        u.merge(&t);
        u.merge(&t);
        assert_eq!((u.phrases, u.true_pos, u.absent_empty), (10, 8, 2));
        assert_eq!(u.f1(), t.f1());
        let none = FindTally::default();
        assert_eq!((none.precision(), none.recall(), none.f1()), (1.0, 1.0, 1.0));
        let ranked = [(3, 0.9), (5, 0.5), (2, 0.49)].map(|(id, score)| Scored { id, score, question: "" });
        assert_eq!(matches(&ranked, 0.5), vec![3, 5]);
    }
}
