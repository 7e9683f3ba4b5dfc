//! Questions with short canonical answers about a synthetic [`SynthScene`], true by construction: the
//! view-level facts are read off the rendered instance mask and depth of that very view (an
//! object counts as seen when it covers at least [`VISIBLE_FRACTION`] of the image; views where
//! some object shows only a sliver are not asked about), object-level ones off the clicked
//! object, scene-level ones off the whole scene (views are chosen so that together they see every
//! object, each of them possibly hidden in some).
//!
//! | level | kind | question | answer |
//! |---|---|---|---|
//! | view | count | How many objects are there? | `3` |
//! | view | colors | What colors are there? | `red blue` (colour order of [`Color::ALL`]) |
//! | view | shapes | What shapes are there? | `cube cone` (order of [`Shape::ALL`]) |
//! | view | objects | What objects are there? | `red cube blue cone` (colour, then shape order) |
//! | view | color_of | What color is the cube? (one cube in view) | `red` |
//! | view | shape_of | What shape is the red object? (one red object in view) | `cube` |
//! | view | exists | Is there a red cube? | `yes` / `no` |
//! | view | left_of | Is the red cube left of the blue cone? | `yes` / `no` |
//! | view | nearest | Which object is nearest? | `red cube` |
//! | object | name / color / shape / size | What is this? / What color is this? / ... | `red cube` / `red` / ... |
//! | scene | total | How many objects are in the scene? | `4` |
//! | scene | list | What objects are in the scene? | `red cube blue cone` (colour, then shape order) |
//! | scene | count_color | How many red objects are in the scene? | `2` |
//! | scene | count_shape | How many cubes are in the scene? | `1` |
//! | view | follow_left_of | (after shape_of) Is it left of the blue cone? | `yes` / `no` |
//! | object | follow_color / follow_shape / follow_size | (after name) What color is it? / ... | `red` / ... |
//! | find | find_color / find_shape / find_name (`find_absent_*`) | `red` / `cone` / `red cone` | ids named |

use super::scene::{Color, Object, Shape, Size, SynthScene};
use crate::ObjectId;
use crate::question_file::Level;
use base::rng::Rng;
use serde::{Deserialize, Serialize};

/// An object is seen in a view when it covers at least this fraction of the image.
pub const VISIBLE_FRACTION: f32 = 0.003;
/// Objects are asked about (clicked) when they cover at least this fraction of the image.
pub const CLICK_FRACTION: f32 = 0.006;
/// Left/right questions need the two centres this far apart (fraction of the image width).
pub const LEFT_RIGHT_GAP: f32 = 0.08;
/// "Nearest" needs the second-nearest object this much farther (ratio of camera depths).
pub const NEAREST_RATIO: f32 = 1.1;

/// The question types.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    Count,
    Colors,
    Shapes,
    Objects,
    ColorOf,
    ShapeOf,
    Exists,
    LeftOf,
    Nearest,
    Name,
    Color,
    Shape,
    Size,
    Total,
    List,
    CountColor,
    CountShape,
}

impl Kind {
    pub const ALL: [Kind; 17] = [
        Kind::Count,
        Kind::Colors,
        Kind::Shapes,
        Kind::Objects,
        Kind::ColorOf,
        Kind::ShapeOf,
        Kind::Exists,
        Kind::LeftOf,
        Kind::Nearest,
        Kind::Name,
        Kind::Color,
        Kind::Shape,
        Kind::Size,
        Kind::Total,
        Kind::List,
        Kind::CountColor,
        Kind::CountShape,
    ];

    /// The name used in question files (`kind`).
    pub fn as_str(self) -> &'static str {
        match self {
            Kind::Count => "count",
            Kind::Colors => "colors",
            Kind::Shapes => "shapes",
            Kind::Objects => "objects",
            Kind::ColorOf => "color_of",
            Kind::ShapeOf => "shape_of",
            Kind::Exists => "exists",
            Kind::LeftOf => "left_of",
            Kind::Nearest => "nearest",
            Kind::Name => "name",
            Kind::Color => "color",
            Kind::Shape => "shape",
            Kind::Size => "size",
            Kind::Total => "total",
            Kind::List => "list",
            Kind::CountColor => "count_color",
            Kind::CountShape => "count_shape",
        }
    }

    pub fn level(self) -> Level {
        match self {
            Kind::Name | Kind::Color | Kind::Shape | Kind::Size => Level::Object,
            Kind::Total | Kind::List | Kind::CountColor | Kind::CountShape => Level::Scene,
            _ => Level::View,
        }
    }
}

/// A question and its canonical answer.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Qa {
    pub kind: Kind,
    pub question: String,
    pub answer: String,
    /// The exchange this question is asked after in its conversation (`None`: asked first).
    pub follows: Option<Box<Qa>>,
}

impl Qa {
    fn new(kind: Kind, question: String, answer: impl Into<String>) -> Self {
        Self { kind, question, answer: answer.into(), follows: None }
    }

    /// This question asked after `earlier` (and its answer) in one conversation.
    pub fn after(self, earlier: &Qa) -> Self {
        Self { follows: Some(Box::new(Qa { follows: None, ..earlier.clone() })), ..self }
    }

    /// A list answer's items (colours, shapes, or "colour shape" names; none for "none"), `None`
    /// for the other kinds: what a question file's `items` holds.
    pub fn items(&self) -> Option<Vec<String>> {
        let per_item = match self.kind {
            Kind::Colors | Kind::Shapes => 1,
            Kind::Objects | Kind::List => 2,
            _ => return None,
        };
        if self.answer == "none" {
            return Some(vec![]);
        }
        let words: Vec<&str> = self.answer.split_whitespace().collect();
        Some(words.chunks(per_item).map(|c| c.join(" ")).collect())
    }
}

/// One object as a view shows it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Seen {
    pub id: ObjectId,
    pub pixels: usize,
    /// Mask centroid (pixels).
    pub cx: f32,
    pub cy: f32,
    /// Camera-space depth of the object's nearest visible pixel.
    pub depth: f32,
}

/// What one view shows, read off its rendered instance mask.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewFacts {
    pub width: usize,
    pub height: usize,
    /// Objects covering at least [`VISIBLE_FRACTION`] of the image, by id.
    pub seen: Vec<Seen>,
    /// Whether some object shows only a sliver (more than nothing, less than visible): counting
    /// in such a view is ambiguous, so no view-level question is asked about it.
    pub ambiguous: bool,
}

impl ViewFacts {
    /// The facts of a view of `scene` from its instance ids and camera-space depth (`[h, w]`).
    pub fn of(scene: &SynthScene, ids: &[ObjectId], depth: &[f32], width: usize, height: usize) -> Self {
        let area = (width * height) as f32;
        let mut seen = Vec::new();
        let mut ambiguous = false;
        for o in &scene.objects {
            let (mut n, mut sx, mut sy, mut near) = (0usize, 0f64, 0f64, f32::MAX);
            for (p, &i) in ids.iter().enumerate() {
                if i == o.id {
                    n += 1;
                    sx += (p % width) as f64 + 0.5;
                    sy += (p / width) as f64 + 0.5;
                    near = near.min(depth[p]);
                }
            }
            let frac = n as f32 / area;
            if frac >= VISIBLE_FRACTION {
                let (cx, cy) = ((sx / n as f64) as f32, (sy / n as f64) as f32);
                seen.push(Seen { id: o.id, pixels: n, cx, cy, depth: near });
            } else if n > 0 {
                ambiguous = true;
            }
        }
        Self { width, height, seen, ambiguous }
    }

    fn objects<'a>(&self, scene: &'a SynthScene) -> Vec<&'a Object> {
        self.seen.iter().filter_map(|s| scene.object(s.id)).collect()
    }
}

fn sorted_words<T: Ord + Copy>(items: impl Iterator<Item = T>, word: impl Fn(T) -> &'static str) -> String {
    let mut v: Vec<T> = items.collect();
    v.sort();
    v.dedup();
    if v.is_empty() { "none".to_string() } else { v.into_iter().map(word).collect::<Vec<_>>().join(" ") }
}

fn list_names(objects: &[&Object]) -> String {
    let mut v: Vec<(Color, Shape)> = objects.iter().map(|o| (o.color, o.shape)).collect();
    v.sort();
    if v.is_empty() {
        return "none".into();
    }
    v.iter().map(|(c, s)| format!("{} {}", c.word(), s.word())).collect::<Vec<_>>().join(" ")
}

fn yes(b: bool) -> &'static str {
    if b { "yes" } else { "no" }
}

/// Every view-level question about a view (empty for an ambiguous view). `rng` picks the
/// negative examples of `exists` and the pairs of `left_of`.
pub fn view_questions(scene: &SynthScene, facts: &ViewFacts, rng: &mut Rng) -> Vec<Qa> {
    if facts.ambiguous {
        return vec![];
    }
    let objs = facts.objects(scene);
    let mut out = vec![
        Qa::new(Kind::Count, "How many objects are there?".into(), objs.len().to_string()),
        Qa::new(Kind::Colors, "What colors are there?".into(), sorted_words(objs.iter().map(|o| o.color), Color::word)),
        Qa::new(Kind::Shapes, "What shapes are there?".into(), sorted_words(objs.iter().map(|o| o.shape), Shape::word)),
        Qa::new(Kind::Objects, "What objects are there?".into(), list_names(&objs)),
    ];
    for shape in Shape::ALL {
        let with: Vec<_> = objs.iter().filter(|o| o.shape == shape).collect();
        if let [o] = with[..] {
            out.push(Qa::new(Kind::ColorOf, format!("What color is the {}?", shape.word()), o.color.word()));
        }
    }
    for color in Color::ALL {
        let with: Vec<_> = objs.iter().filter(|o| o.color == color).collect();
        if let [o] = with[..] {
            out.push(Qa::new(Kind::ShapeOf, format!("What shape is the {} object?", color.word()), o.shape.word()));
        }
    }
    // exists: every visible object, and as many absent (colour, shape) pairs
    for o in &objs {
        out.push(Qa::new(Kind::Exists, format!("Is there a {}?", o.name()), "yes"));
    }
    let mut absent = 0;
    let mut tries = 0;
    while absent < objs.len().max(1) && tries < 100 {
        tries += 1;
        // half of the negatives are objects of the scene hidden in this view, when there are
        let hidden: Vec<&Object> = scene.objects.iter().filter(|o| !objs.iter().any(|v| v.id == o.id)).collect();
        let (c, s) = if !hidden.is_empty() && rng.f() < 0.5 {
            let h = hidden[(rng.next_u64() % hidden.len() as u64) as usize];
            (h.color, h.shape)
        } else {
            (Color::ALL[(rng.next_u64() % 8) as usize], Shape::ALL[(rng.next_u64() % 6) as usize])
        };
        if objs.iter().any(|o| o.color == c && o.shape == s) {
            continue;
        }
        out.push(Qa::new(Kind::Exists, format!("Is there a {} {}?", c.word(), s.word()), "no"));
        absent += 1;
    }
    // left / right of each other, as seen from this view
    let gap = LEFT_RIGHT_GAP * facts.width as f32;
    for (i, a) in facts.seen.iter().enumerate() {
        for b in facts.seen.iter().skip(i + 1) {
            if (a.cx - b.cx).abs() < gap {
                continue;
            }
            let (first, second) = if rng.f() < 0.5 { (a, b) } else { (b, a) };
            let (fo, so) = (scene.object(first.id).expect("seen"), scene.object(second.id).expect("seen"));
            let q = format!("Is the {} left of the {}?", fo.name(), so.name());
            out.push(Qa::new(Kind::LeftOf, q, yes(first.cx < second.cx)));
        }
    }
    // nearest to the camera, when clearly so
    let mut by_depth: Vec<&Seen> = facts.seen.iter().collect();
    by_depth.sort_by(|a, b| a.depth.total_cmp(&b.depth));
    if let Some(first) = by_depth.first()
        && by_depth.get(1).is_none_or(|second| second.depth >= first.depth * NEAREST_RATIO)
    {
        let o = scene.object(first.id).expect("seen");
        out.push(Qa::new(Kind::Nearest, "Which object is nearest?".into(), o.name()));
    }
    out
}

/// The object-level questions about object `o` (asked by clicking it).
pub fn object_questions(o: &Object) -> Vec<Qa> {
    vec![
        Qa::new(Kind::Name, "What is this?".into(), o.name()),
        Qa::new(Kind::Color, "What color is this?".into(), o.color.word()),
        Qa::new(Kind::Shape, "What shape is this?".into(), o.shape.word()),
        Qa::new(Kind::Size, "What size is this?".into(), o.size.word()),
    ]
}

/// The scene-level questions: counts and the list of all objects, counts by every colour and
/// every shape (zero included).
pub fn scene_questions(scene: &SynthScene) -> Vec<Qa> {
    let all: Vec<&Object> = scene.objects.iter().collect();
    let mut out = vec![
        Qa::new(Kind::Total, "How many objects are in the scene?".into(), all.len().to_string()),
        Qa::new(Kind::List, "What objects are in the scene?".into(), list_names(&all)),
    ];
    for c in Color::ALL {
        let n = all.iter().filter(|o| o.color == c).count();
        out.push(Qa::new(Kind::CountColor, format!("How many {} objects are in the scene?", c.word()), n.to_string()));
    }
    for s in Shape::ALL {
        let n = all.iter().filter(|o| o.shape == s).count();
        out.push(Qa::new(Kind::CountShape, format!("How many {} are in the scene?", s.plural()), n.to_string()));
    }
    out
}

/// A follow-up: a question that refers to an earlier answer by "it", asked after that question
/// in its conversation; `first` and `twin` index the list it was made from (the question it
/// follows, and the same question with its referent spelled out).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FollowUp {
    /// `follow_left_of`, `follow_color`, `follow_shape`, `follow_size`.
    pub kind: &'static str,
    pub question: String,
    pub answer: String,
    pub first: usize,
    pub twin: usize,
}

impl FollowUp {
    /// The follow-up as a question asked after its first question (both from `qas`, the list it
    /// was made from), of its twin's kind.
    pub fn qa(&self, qas: &[Qa]) -> Qa {
        Qa::new(qas[self.twin].kind, self.question.clone(), self.answer.clone()).after(&qas[self.first])
    }
}

/// The follow-ups of a view's questions ([`view_questions`]): after "What shape is the red
/// object?" ("cube"), "Is it left of the blue cone?" for each `left_of` question about the red
/// cube (its twin).
pub fn view_follow_ups(qas: &[Qa]) -> Vec<FollowUp> {
    let mut out = Vec::new();
    for (first, qa) in qas.iter().enumerate().filter(|(_, q)| q.kind == Kind::ShapeOf) {
        let Some(c) = Color::ALL.into_iter().find(|c| qa.question == format!("What shape is the {} object?", c.word()))
        else {
            continue;
        };
        let prefix = format!("Is the {} {} left of the ", c.word(), qa.answer);
        for (twin, lq) in qas.iter().enumerate().filter(|(_, q)| q.kind == Kind::LeftOf) {
            if let Some(other) = lq.question.strip_prefix(&prefix) {
                let question = format!("Is it left of the {other}");
                out.push(FollowUp { kind: "follow_left_of", question, answer: lq.answer.clone(), first, twin });
            }
        }
    }
    out
}

/// The follow-ups of a clicked object's questions ([`object_questions`]): after "What is this?",
/// "What color is it?", "What shape is it?" and "What size is it?" (twins: "... is this?").
pub fn object_follow_ups(qas: &[Qa]) -> Vec<FollowUp> {
    let Some(first) = qas.iter().position(|q| q.kind == Kind::Name) else { return vec![] };
    let mut out = Vec::new();
    for (twin, qa) in qas.iter().enumerate() {
        let (kind, what) = match qa.kind {
            Kind::Color => ("follow_color", "color"),
            Kind::Shape => ("follow_shape", "shape"),
            Kind::Size => ("follow_size", "size"),
            _ => continue,
        };
        out.push(FollowUp { kind, question: format!("What {what} is it?"), answer: qa.answer.clone(), first, twin });
    }
    out
}

/// A phrase to find among a scene's objects (a question file's `find` level) and the objects it
/// names.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FindQuery {
    /// `find_color`, `find_shape`, `find_name`; `find_absent_color`, ... for a phrase that names
    /// no object of the scene.
    pub kind: String,
    pub phrase: String,
    /// The instance ids it names, in id order (empty for an absent phrase).
    pub objects: Vec<ObjectId>,
}

/// The find queries of a scene: each colour, shape and name (colour and shape) it holds, and as
/// many absent ones of each sort as present ones, where there are (the absent names pair a colour
/// and a shape the scene holds apart before any other pair). `rng` picks the absent ones.
pub fn find_queries(scene: &SynthScene, rng: &mut Rng) -> Vec<FindQuery> {
    let objs = &scene.objects;
    let ids = |f: &dyn Fn(&Object) -> bool| -> Vec<ObjectId> { objs.iter().filter(|o| f(o)).map(|o| o.id).collect() };
    let query = |kind: &str, phrase: String, objects: Vec<ObjectId>| {
        let kind = if objects.is_empty() { kind.replace("find_", "find_absent_") } else { kind.to_string() };
        FindQuery { kind, phrase, objects }
    };
    let mut out = Vec::new();
    let (mut colors, mut absent_colors): (Vec<Color>, Vec<Color>) =
        Color::ALL.into_iter().partition(|&c| objs.iter().any(|o| o.color == c));
    let (mut shapes, mut absent_shapes): (Vec<Shape>, Vec<Shape>) =
        Shape::ALL.into_iter().partition(|&s| objs.iter().any(|o| o.shape == s));
    let mut names: Vec<(Color, Shape)> = objs.iter().map(|o| (o.color, o.shape)).collect();
    names.sort();
    for &c in &colors {
        out.push(query("find_color", c.word().into(), ids(&|o| o.color == c)));
    }
    for &s in &shapes {
        out.push(query("find_shape", s.word().into(), ids(&|o| o.shape == s)));
    }
    for &(c, s) in &names {
        out.push(query("find_name", format!("{} {}", c.word(), s.word()), ids(&|o| o.color == c && o.shape == s)));
    }
    let k = colors.len();
    rng.partial_shuffle(&mut absent_colors, k);
    for &c in absent_colors.iter().take(k) {
        out.push(query("find_color", c.word().into(), vec![]));
    }
    let k = shapes.len();
    rng.partial_shuffle(&mut absent_shapes, k);
    for &s in absent_shapes.iter().take(k) {
        out.push(query("find_shape", s.word().into(), vec![]));
    }
    // absent names: a held colour with a held shape first (the hard ones), then any other pair
    rng.shuffle(&mut colors);
    rng.shuffle(&mut shapes);
    let held: Vec<(Color, Shape)> =
        colors.iter().flat_map(|&c| shapes.iter().map(move |&s| (c, s))).filter(|p| !names.contains(p)).collect();
    let mut others: Vec<(Color, Shape)> = Color::ALL
        .into_iter()
        .flat_map(|c| Shape::ALL.into_iter().map(move |s| (c, s)))
        .filter(|p| !names.contains(p) && !held.contains(p))
        .collect();
    rng.shuffle(&mut others);
    for (c, s) in held.into_iter().chain(others).take(names.len()) {
        out.push(query("find_name", format!("{} {}", c.word(), s.word()), vec![]));
    }
    out
}

/// Views (indices into `facts`) that together see every object of the scene: greedily the view
/// adding most unseen objects, at most `k`; `None` when some object is seen in none of them.
pub fn covering_views(scene: &SynthScene, facts: &[ViewFacts], k: usize) -> Option<Vec<usize>> {
    let mut chosen = Vec::new();
    let mut covered: Vec<ObjectId> = Vec::new();
    let usable: Vec<usize> = (0..facts.len()).filter(|&i| !facts[i].ambiguous).collect();
    while chosen.len() < k {
        let gain = |i: usize| facts[i].seen.iter().filter(|s| !covered.contains(&s.id)).count();
        let best = usable.iter().copied().filter(|i| !chosen.contains(i)).max_by_key(|&i| (gain(i), usize::MAX - i))?;
        chosen.push(best);
        covered.extend(facts[best].seen.iter().map(|s| s.id));
    }
    scene.objects.iter().all(|o| covered.contains(&o.id)).then_some(chosen)
}

/// Every word the questions and answers use (for a word-level tokenizer).
pub fn vocabulary() -> Vec<String> {
    let mut words: Vec<String> = Vec::new();
    let mut add = |s: &str| {
        for w in s.split(|c: char| c.is_whitespace() || c == '?').filter(|w| !w.is_empty()) {
            if !words.iter().any(|x| x == w) {
                words.push(w.to_string());
            }
        }
    };
    let fixed = [
        "How many objects are there?",
        "What colors are there?",
        "What shapes are there?",
        "What objects are there?",
        "What color is the",
        "What shape is the object?",
        "Is there a",
        "Is the left of the",
        "Which object is nearest?",
        "What is this?",
        "What color is this?",
        "What shape is this?",
        "What size is this?",
        "How many objects are in the scene?",
        "What objects are in the scene?",
        "yes no none",
    ];
    for s in fixed {
        add(s);
    }
    for c in Color::ALL {
        add(c.word());
    }
    for s in Shape::ALL {
        add(s.word());
        add(s.plural());
    }
    for s in Size::ALL {
        add(s.word());
    }
    for d in 0..10 {
        add(&d.to_string());
    }
    add("?");
    words.push("?".into());
    words.dedup();
    words
}

/// The words of conversations: [`vocabulary`] and then "it", which follow-ups refer to an earlier
/// answer by; every word of [`vocabulary`] keeps its place (its token id).
pub fn conversation_vocabulary() -> Vec<String> {
    let mut words = vocabulary();
    words.push("it".into());
    words
}
