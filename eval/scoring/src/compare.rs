//! The paper's comparison, offline: every question of a question file answered three ways,
//! scored by exact match (normalised as SQA3D / ScanQA do; lists as multisets of items, counts by
//! their one number: [`offline_score`]):
//!
//! * (a) **ground truth** — the VLM on the dataset's own image (object level: the ground-truth
//!   masked crop): the upper bound;
//! * (b) **rendered RGB** — the VLM on the geometry's render of the view (object level: the
//!   rendered crop cut by the ground-truth mask, the SAM + LLaVA baseline);
//! * (c) **ChatSplat** — the trained scene's tokens (object level: by click, the rendered
//!   identity picking the object).
//!
//! All three feed the LLM the same layout: one token grid per image, projector, newline.

use crate::score::{normalize, offline_score};
use model::ObjectId;
use model::chat::{ChatSession, DEFAULT_SCENE_VIEWS, answer};
use model::data::Dataset;
use model::error::{Error, Result};
use model::find::FindTally;
use model::language::ObjectCrop;
use model::vlm::{GenerateOptions, LlavaOnevision, RgbImage};
use model::vqa::{FindOptions, Level, Question, QuestionFile, find_objects, target_of};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// Where the image tokens come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    // the aliases read vqa-bench's bench.json, whose keys are the Debug names
    #[serde(alias = "GroundTruth")]
    GroundTruth,
    #[serde(alias = "RenderedRgb")]
    RenderedRgb,
    #[serde(alias = "ChatSplat")]
    ChatSplat,
}

impl Source {
    pub const ALL: [Source; 3] = [Source::GroundTruth, Source::RenderedRgb, Source::ChatSplat];

    pub fn label(self) -> &'static str {
        match self {
            Source::GroundTruth => "(a) VLM on the ground-truth image",
            Source::RenderedRgb => "(b) VLM on the rendered RGB",
            Source::ChatSplat => "(c) ChatSplat tokens",
        }
    }
}

/// Exact-match counts (right, asked) by level and by kind.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Tally {
    pub by_level: BTreeMap<Level, (usize, usize)>,
    pub by_kind: BTreeMap<String, (usize, usize)>,
}

impl Tally {
    pub fn add(&mut self, q: &Question, right: bool) {
        for e in [
            self.by_level.entry(q.level).or_default(),
            self.by_kind.entry(q.kind.clone().unwrap_or_else(|| "-".into())).or_default(),
        ] {
            e.0 += right as usize;
            e.1 += 1;
        }
    }

    pub fn merge(&mut self, o: &Tally) {
        for (k, (r, n)) in &o.by_level {
            let e = self.by_level.entry(*k).or_default();
            e.0 += r;
            e.1 += n;
        }
        for (k, (r, n)) in &o.by_kind {
            let e = self.by_kind.entry(k.clone()).or_default();
            e.0 += r;
            e.1 += n;
        }
    }

    /// Percent right at `level` (`None` when nothing was asked there).
    pub fn level(&self, level: Level) -> Option<f64> {
        self.by_level.get(&level).filter(|(_, n)| *n > 0).map(|(r, n)| 100.0 * *r as f64 / *n as f64)
    }

    /// Percent right overall.
    pub fn overall(&self) -> f64 {
        let (r, n) = self.by_level.values().fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        100.0 * r as f64 / n.max(1) as f64
    }
}

/// Whether `answer` is exactly `reference` after normalisation (plain text: the probes' check;
/// question files are scored by [`offline_score`]).
pub fn exact(answer: &str, reference: &str) -> bool {
    normalize(answer) == normalize(reference)
}

/// Greedy options for short canonical answers.
pub fn greedy() -> GenerateOptions {
    GenerateOptions { max_new_tokens: 24, ..Default::default() }
}

/// The dataset image of frame `frame` (an index into the question file's `views`) and its view.
fn frame_view<'a>(file: &QuestionFile, ds: &'a Dataset, frame: usize) -> Result<&'a model::data::View> {
    let frames = file.views.as_ref().ok_or_else(|| Error::input("the question file lists no views"))?;
    let name = Path::new(frames.get(frame).ok_or_else(|| Error::input(format!("no frame {frame}")))?)
        .file_name()
        .map(|n| n.to_os_string());
    ds.train
        .iter()
        .chain(&ds.test)
        .find(|v| v.image_path.file_name().map(|n| n.to_os_string()) == name)
        .ok_or_else(|| Error::input(format!("frame {frame} is not in the dataset")))
}

fn image_of(v: &model::data::View, rgb: &[f32]) -> RgbImage {
    RgbImage::from_f32(v.camera.width as usize, v.camera.height as usize, rgb)
}

/// The masked crop of the object under the question's click, cut by the ground-truth mask.
fn object_crop(q: &Question, v: &model::data::View, img: &RgbImage, margin: f32) -> Result<RgbImage> {
    let ids = v.instance_ids.as_ref().ok_or_else(|| Error::input("object questions need masks"))?;
    let [x, y] = q.object.unwrap_or([0.0, 0.0]).map(|c| c as usize);
    let (w, h) = (v.camera.width as usize, v.camera.height as usize);
    if x >= w || y >= h {
        return Err(Error::input(format!("{}: click ({x}, {y}) outside the {w}x{h} view", q.id)));
    }
    let id = ids[y * w + x];
    let crop = ObjectCrop::of(ids, w, h, id, margin).ok_or_else(|| Error::input(format!("{}: no object", q.id)))?;
    Ok(crop.masked_image(img, ids, id))
}

/// The token grids of question `q` from images: the dataset's (`rendered` = `None`) or the
/// scene's renders.
fn image_tokens(
    vlm: &LlavaOnevision,
    file: &QuestionFile,
    q: &Question,
    ds: &Dataset,
    rendered: Option<&ChatSession>,
    margin: f32,
) -> Result<Vec<burn::tensor::Tensor<2>>> {
    let picture = |frame: usize| -> Result<(RgbImage, &model::data::View)> {
        let v = frame_view(file, ds, frame)?;
        let rgb = match rendered {
            None => v.rgb.clone(),
            Some(s) => {
                let view = model::vqa::scene_view(file, &s.images, frame)?;
                s.scene.render_rgb(s.camera(view)?)?
            }
        };
        Ok((image_of(v, &rgb), v))
    };
    let frames: Vec<usize> = match q.level {
        Level::Scene => {
            q.views.clone().ok_or_else(|| Error::input(format!("{}: scene question without views", q.id)))?
        }
        _ => vec![q.view.unwrap_or(0)],
    };
    let mut out = Vec::new();
    for f in frames {
        let (img, v) = picture(f)?;
        let img = if q.level == Level::Object { object_crop(q, v, &img, margin)? } else { img };
        out.push(vlm.teacher_tokens(&img));
    }
    Ok(out)
}

/// Seconds spent making the token grids of each level, and how many targets they were made for
/// (questions about one target share its grids).
pub type TokenSeconds = BTreeMap<Level, (f64, usize)>;

/// What [`answer_file`] gives back.
#[derive(Clone, Debug, Default)]
pub struct Answered {
    pub tally: Tally,
    /// Per question, the answer given.
    pub answers: Vec<String>,
    /// Time to make the token grids (images or field to tokens; not the answers), by level: once
    /// per target.
    pub token_seconds: TokenSeconds,
}

/// Answers every question of `file` from `source` and scores it; `ds` is the dataset the file
/// is about, `session` the trained scene (needed for (b) and (c)). A question ChatSplat's scene
/// cannot be asked (a click on no object) counts as answered wrong.
pub fn answer_file(
    vlm: &LlavaOnevision,
    file: &QuestionFile,
    ds: &Dataset,
    session: Option<&ChatSession>,
    source: Source,
    margin: f32,
) -> Result<Answered> {
    let opts = greedy();
    let mut out = Answered { answers: Vec::with_capacity(file.questions.len()), ..Default::default() };
    // questions about the same target (view, clicked object, scene views) share its token grids:
    // each is made once, and timed once
    let mut made: BTreeMap<TargetKey, Vec<burn::tensor::Tensor<2>>> = BTreeMap::new();
    for q in &file.questions {
        if q.level == Level::Find || q.follows.is_some() {
            // a phrase is scored by the objects found ([`find_file`]); a follow-up needs its
            // conversation (`chatsplat vqa` asks it): neither is a single-turn answer
            out.answers.push(String::new());
            continue;
        }
        let key = target_key(q);
        if let Some(tokens) = made.get(&key) {
            let g = answer(vlm, tokens, &q.question, &opts, |_| {})?;
            out.tally.add(q, offline_score(&g.text, q).exact);
            out.answers.push(g.text);
            continue;
        }
        let t0 = std::time::Instant::now();
        let tokens = match source {
            Source::GroundTruth => image_tokens(vlm, file, q, ds, None, margin)?,
            Source::RenderedRgb => {
                let s = session.ok_or_else(|| Error::input("the rendered-RGB baseline needs a trained scene"))?;
                image_tokens(vlm, file, q, ds, Some(s), margin)?
            }
            Source::ChatSplat => {
                let s = session.ok_or_else(|| Error::input("ChatSplat needs a trained scene"))?;
                // a question the scene cannot be asked (a click that hits no object, e.g. in a
                // pruned field) is answered wrong, as `chatsplat vqa` does; failures of the
                // backend or of files stop the run
                match target_of(file, q, s, DEFAULT_SCENE_VIEWS).and_then(|t| s.tokens(&t)) {
                    Ok(tokens) => tokens,
                    Err(e @ (Error::Backend { .. } | Error::Io { .. })) => return Err(e),
                    Err(e) => {
                        out.tally.add(q, false);
                        out.answers.push(format!("(not asked: {e})"));
                        continue;
                    }
                }
            }
        };
        let e = out.token_seconds.entry(q.level).or_default();
        e.0 += t0.elapsed().as_secs_f64();
        e.1 += 1;
        let g = answer(vlm, &tokens, &q.question, &opts, |_| {})?;
        out.tally.add(q, offline_score(&g.text, q).exact);
        out.answers.push(g.text);
        made.insert(key, tokens);
    }
    Ok(out)
}

/// What a question's token grids depend on: its level, its frame or frames, and its click (the
/// click's coordinates as bits).
type TargetKey = (Level, Option<usize>, Option<Vec<usize>>, Option<[u32; 2]>);

fn target_key(q: &Question) -> TargetKey {
    let click = q.object.filter(|_| q.level == Level::Object).map(|[x, y]| [x.to_bits(), y.to_bits()]);
    let frames = q.views.clone().filter(|_| q.level == Level::Scene);
    (q.level, q.view.filter(|_| q.level != Level::Scene), frames, click)
}

/// The objects ChatSplat's scene `session` finds for each `find` phrase of `file` against those
/// the phrase names, by the phrase's kind, and the seconds the searches took (the first one
/// builds the finder).
pub fn find_file(session: &ChatSession, file: &QuestionFile, opts: &FindOptions) -> Result<(FindKinds, f64)> {
    find_file_as(session, file, opts, &|id| id)
}

/// [`find_file`] for a scene whose object ids are not the question file's (masks matched across
/// views number objects their own way): each id found is taken to the one the file names the
/// same object by (`as_named`), an object found in two pieces counting once.
pub fn find_file_as(
    session: &ChatSession,
    file: &QuestionFile,
    opts: &FindOptions,
    as_named: &dyn Fn(ObjectId) -> ObjectId,
) -> Result<(FindKinds, f64)> {
    let (mut kinds, mut finder) = (FindKinds::new(), None);
    let t0 = std::time::Instant::now();
    for q in file.questions.iter().filter(|q| q.level == Level::Find) {
        let mut found: Vec<ObjectId> = Vec::new();
        for id in find_objects(session, &mut finder, opts, &q.question)?.into_iter().map(as_named) {
            if !found.contains(&id) {
                found.push(id);
            }
        }
        let kind = q.kind.clone().unwrap_or_else(|| "-".into());
        kinds.entry(kind).or_default().add(q.objects.as_deref().unwrap_or_default(), &found);
    }
    Ok((kinds, t0.elapsed().as_secs_f64()))
}

/// Find tallies by phrase kind (`find_color`, `find_absent_name`, ...).
pub type FindKinds = BTreeMap<String, FindTally>;

/// Every single question of `file` answered from each of the three sources in turn (the scene
/// `s` for (b) and (c), its dataset `ds` for (a) and the ground-truth masks), object crops with
/// the teacher's margin.
pub fn three_ways(s: &ChatSession, file: &QuestionFile, ds: &Dataset) -> Result<Vec<(Source, Answered)>> {
    let margin = model::language::CROP_MARGIN;
    Source::ALL.iter().map(|&source| Ok((source, answer_file(&s.vlm, file, ds, Some(s), source, margin)?))).collect()
}

/// Token grids made per second at `level` (`None` where none were).
pub fn per_second(a: &Answered, level: Level) -> Option<f64> {
    a.token_seconds.get(&level).filter(|(_, n)| *n > 0).map(|(t, n)| *n as f64 / t.max(1e-9))
}

/// The comparison as a Markdown table: exact match per level and overall, and how many view
/// token grids (and object crops) each path makes per second, then ChatSplat's speed-up over
/// rendering RGB through the vision tower.
pub fn table(rows: &[(Source, Answered)]) -> String {
    let pct = |t: &Tally, l: Level| t.level(l).map_or("-".into(), |v| format!("{v:.1}"));
    let rate = |a: &Answered, l: Level| per_second(a, l).map_or("-".into(), |v| format!("{v:.1}"));
    let mut out = String::from(
        "| answers from | view | object | scene | overall | questions | views/s | objects/s |\n\
         |---|---|---|---|---|---|---|---|\n",
    );
    for (source, a) in rows {
        let asked: usize = a.tally.by_level.values().map(|(_, n)| n).sum();
        out += &format!(
            "| {} | {} | {} | {} | {:.1} | {asked} | {} | {} |\n",
            source.label(),
            pct(&a.tally, Level::View),
            pct(&a.tally, Level::Object),
            pct(&a.tally, Level::Scene),
            a.tally.overall(),
            rate(a, Level::View),
            rate(a, Level::Object),
        );
    }
    let of = |s: Source| rows.iter().find(|(x, _)| *x == s).map(|(_, a)| a);
    if let (Some(b), Some(c)) = (of(Source::RenderedRgb), of(Source::ChatSplat))
        && let (Some(rb), Some(rc)) = (per_second(b, Level::View), per_second(c, Level::View))
    {
        out += &format!(
            "\nChatSplat makes a view's tokens {:.1}x as fast as rendering its RGB and running the vision tower \
             (views/s: the image tokens only; the answers take the same LLM time on every path).",
            rc / rb
        );
    }
    out
}

/// The comparison as JSON: per source, exact match by level and overall, questions, token grids
/// per second by level, and every single question's answer and whether it is right (`file`, read
/// from `questions`, in its order).
pub fn summary_json(rows: &[(Source, Answered)], (questions, file): (&Path, &QuestionFile)) -> serde_json::Value {
    let sources: serde_json::Map<String, serde_json::Value> = rows
        .iter()
        .map(|(source, a)| {
            let levels: serde_json::Map<String, serde_json::Value> = a
                .tally
                .by_level
                .iter()
                .map(|(l, (right, n))| {
                    let per_s = per_second(a, *l);
                    (l.to_string(), serde_json::json!({"right": right, "asked": n, "per_second": per_s}))
                })
                .collect();
            let key = serde_json::to_value(source).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default();
            let answers: Vec<serde_json::Value> = file
                .questions
                .iter()
                .zip(&a.answers)
                .filter(|(q, _)| q.level != Level::Find && q.follows.is_none())
                .map(|(q, text)| serde_json::json!({"id": q.id, "answer": text, "right": offline_score(text, q).exact}))
                .collect();
            let summary = serde_json::json!({
                "label": source.label(), "exact_match": a.tally.overall(), "levels": levels, "answers": answers,
            });
            (key, summary)
        })
        .collect();
    serde_json::json!({"questions": questions.display().to_string(), "comparison": sources})
}
