//! Supervised reasoning hops: where the LLM should look while it answers, as extra attention
//! targets (object-level supervision in the spirit of MDETR). A small LLM trained from scratch
//! learns look-up questions ("is there a red cube?") only after a long plateau, because two
//! attention hops must appear together before either helps the answer: the answer position must
//! gather the words that name the object, then find the image tokens that show it
//! (eval/journal/2026-11-23.md, "Why look-up questions stay at chance: layout and relevance
//! probes"). Supervising each hop directly removes the plateau (eval/journal/2026-11-24.md,
//! "Supervised reasoning hops move the look-up plateau; the first committed model"):
//!
//! * **dedupe** (layer 0, heads 0 and 1): every object token of the images looks at earlier
//!   tokens of the same object, else the first token (the "sink");
//! * **words** (layer 0, heads 2 and 3): the first answer position looks at the words naming the
//!   first / second object of the question;
//! * **slots** (out of layer 1): a linear head classifies those objects' colour and shape from the
//!   first answer position's residual stream;
//! * **places** (out of the find layer, optional): a linear head classifies the image column of
//!   each of them from the same position (what `left_of` compares, which the answers alone do not
//!   teach in the mix of all kinds: eval/journal/2026-11-24.md, "A decaying tower phase of 2,000
//!   steps: the third model", paragraph "Left of stays at chance in the mix but is learned alone");
//! * **find** (layer 2, heads 0 and 1): every answer position looks at the tokens of the object
//!   the answer is about (per question kind, below).
//!
//! What "find" looks at: `exists` the named object (the sink when absent); `color_of`/`shape_of`
//! the object with the named shape / colour; `left_of` the first object (head 0) and the second
//! (head 1); `nearest` and the object level the answer's object; counts a uniform spread over the
//! sink and the first token of every object counted (so that the sink's share tells the count);
//! lists (`colors`, `shapes`, `objects`, `list`) the object(s) of the word being written, then the
//! sink before the closing token. Objects are told apart by (colour, shape): unique in a scene.

use model::data::synth::questions::Kind;
use model::data::synth::scene::{Color, Shape};

/// The token every "nothing here" hop looks at: the first of the sequence.
pub const SINK: usize = 0;

/// What a word of a question or answer names.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Word {
    /// 1-based colour class (as in the token labels).
    Color(u8),
    /// 1-based shape class (singular or plural).
    Shape(u8),
    Other,
}

impl Word {
    pub fn of(w: &str) -> Self {
        if let Some(i) = Color::ALL.iter().position(|c| c.word() == w) {
            return Word::Color(i as u8 + 1);
        }
        if let Some(i) = Shape::ALL.iter().position(|s| s.word() == w || s.plural() == w) {
            return Word::Shape(i as u8 + 1);
        }
        Word::Other
    }
}

/// An object's identity in the labels: (colour, shape), 1-based; 0 in one of them: any.
pub type Ident = (u8, u8);

/// The supervised hops (table above).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HopKind {
    Dedupe,
    Words,
    Find,
}

impl HopKind {
    pub const ALL: [HopKind; 3] = [HopKind::Dedupe, HopKind::Words, HopKind::Find];

    /// The decoder layer whose attention the hop supervises.
    pub fn layer(self) -> usize {
        match self {
            HopKind::Dedupe | HopKind::Words => 0,
            HopKind::Find => 2,
        }
    }
}

/// The decoder layer after which the slot head reads the residual stream.
pub const SLOT_LAYER: usize = 1;
/// The fewest decoder layers and query heads the hops need.
pub const MIN_LAYERS: usize = 3;
pub const MIN_HEADS: usize = 4;

/// One supervised attention row: the hop's `head` at position `query` should put its weight on
/// `targets` (all of it somewhere among them, or, `uniform`, spread evenly over them).
#[derive(Clone, Debug, PartialEq)]
pub struct Hop {
    pub kind: HopKind,
    pub head: usize,
    pub query: usize,
    pub targets: Vec<usize>,
    pub uniform: bool,
}

/// The objects a question names, in order: a colour word names the shape after it, or any shape
/// when none follows; a shape word alone names any colour.
pub fn named(words: &[Word]) -> Vec<(Ident, Vec<usize>)> {
    let mut out = Vec::new();
    let mut colour: Option<(u8, usize)> = None;
    for (i, w) in words.iter().enumerate() {
        match *w {
            Word::Color(c) => {
                if let Some((pc, at)) = colour.take() {
                    out.push(((pc, 0), vec![at]));
                }
                colour = Some((c, i));
            }
            Word::Shape(s) => match colour.take() {
                Some((c, at)) => out.push(((c, s), vec![at, i])),
                None => out.push(((0, s), vec![i])),
            },
            Word::Other => {}
        }
    }
    if let Some((c, at)) = colour {
        out.push(((c, 0), vec![at]));
    }
    out
}

/// The image tokens of a prompt: per position, the identity of the object it shows (`None`:
/// anything else, including text and newline rows).
pub struct Tokens<'a> {
    pub ident: &'a [Option<Ident>],
    /// The first position of every object (in sequence order; each object once).
    pub firsts: Vec<usize>,
    /// The image column of every position (`None`: not an image token, or not known).
    pub columns: Vec<Option<u8>>,
}

impl<'a> Tokens<'a> {
    pub fn new(ident: &'a [Option<Ident>]) -> Self {
        let mut firsts = Vec::new();
        let mut seen: Vec<Ident> = Vec::new();
        for (i, t) in ident.iter().enumerate() {
            if let Some(t) = t
                && !seen.contains(t)
            {
                seen.push(*t);
                firsts.push(i);
            }
        }
        Self { ident, firsts, columns: Vec::new() }
    }

    /// The same with the image column of every position (`columns[i]`, as [`Tokens::columns`]).
    pub fn with_columns(mut self, columns: Vec<Option<u8>>) -> Self {
        self.columns = columns;
        self
    }

    /// The place class of the object `want` names: 1 + its tokens' mean column (rounded), or 0
    /// when it names no single object that the image shows or the columns are not known.
    pub fn place(&self, want: Ident) -> i64 {
        let hits = self.matching(want);
        let one = hits.first().map(|&i| self.ident[i]);
        if hits.is_empty() || hits.iter().any(|&i| Some(self.ident[i]) != one) {
            return 0;
        }
        let cols: Vec<f32> =
            hits.iter().filter_map(|&i| self.columns.get(i).copied().flatten()).map(f32::from).collect();
        if cols.len() != hits.len() {
            return 0;
        }
        1 + (cols.iter().sum::<f32>() / cols.len() as f32).round() as i64
    }

    fn matching(&self, want: Ident) -> Vec<usize> {
        let hit = |t: &Ident| (want.0 == 0 || t.0 == want.0) && (want.1 == 0 || t.1 == want.1);
        self.ident.iter().enumerate().filter(|(_, t)| t.is_some_and(|t| hit(&t))).map(|(i, _)| i).collect()
    }

    /// Layer 0's dedupe hops (heads 0 and 1): every object token looks at the earlier tokens of
    /// its object, the first one at the sink.
    pub fn dedupe(&self) -> Vec<Hop> {
        let mut out = Vec::new();
        for (i, t) in self.ident.iter().enumerate() {
            let Some(t) = t else { continue };
            let mut earlier: Vec<usize> = (0..i).filter(|&j| self.ident[j] == Some(*t)).collect();
            if earlier.is_empty() {
                earlier.push(SINK);
            }
            for head in [0, 1] {
                out.push(Hop { kind: HopKind::Dedupe, head, query: i, targets: earlier.clone(), uniform: false });
            }
        }
        out
    }
}

/// The hops of one question: `question` the words of its prompt segment, at positions
/// `start..start + question.len()`, its answer words after them (the closing token last,
/// `Word::Other`); `first` is the position that predicts the first answer word. Also the slot
/// classes `[colour, shape]` of the first two named objects (0 = none), then their place classes
/// ([`Tokens::place`]).
pub fn question_hops(
    kind: Kind,
    question: &[Word],
    start: usize,
    answer: &[Word],
    first: usize,
    tokens: &Tokens,
) -> (Vec<Hop>, [i64; 6]) {
    let names = named(question);
    let mut hops = Vec::new();
    let mut slots = [0i64; 6];
    for (k, (id, _)) in names.iter().take(2).enumerate() {
        slots[2 * k] = id.0 as i64;
        slots[2 * k + 1] = id.1 as i64;
        slots[4 + k] = tokens.place(*id);
    }
    // words: heads 2 and 3 gather the first and the last named object's words
    if let (Some(a), Some(b)) = (names.first(), names.last()) {
        for (head, (_, at)) in [(2, a), (3, b)] {
            let targets = at.iter().map(|&i| start + i).collect();
            hops.push(Hop { kind: HopKind::Words, head, query: first, targets, uniform: true });
        }
    }
    let mut find = |step: usize, head_targets: [Vec<usize>; 2], uniform: bool| {
        for (head, targets) in head_targets.into_iter().enumerate() {
            if !targets.is_empty() {
                hops.push(Hop { kind: HopKind::Find, head, query: first + step, targets, uniform });
            }
        }
    };
    let both = |t: Vec<usize>| [t.clone(), t];
    let named0 = names.first().map(|n| n.0);
    let ends = answer.len().saturating_sub(1); // the step that predicts the closing token
    match kind {
        Kind::Exists => {
            if let Some(id) = named0 {
                let t = tokens.matching(id);
                find(0, both(if t.is_empty() { vec![SINK] } else { t }), false);
            }
        }
        Kind::ColorOf | Kind::ShapeOf => {
            if let Some(id) = named0 {
                find(0, both(tokens.matching(id)), false);
            }
        }
        Kind::LeftOf => {
            if let [a, b, ..] = &names[..] {
                find(0, [tokens.matching(a.0), tokens.matching(b.0)], false);
            }
        }
        Kind::Nearest | Kind::Name | Kind::Color | Kind::Shape | Kind::Size => {
            // the answer's object: named by the answer (nearest), else every object token (a crop)
            let id = match answer {
                [Word::Color(c), Word::Shape(s), ..] if kind == Kind::Nearest => Some((*c, *s)),
                _ => None,
            };
            let t = match id {
                Some(id) => tokens.matching(id),
                None => tokens.matching((0, 0)),
            };
            let steps = if kind == Kind::Nearest { 2.min(ends) } else { ends };
            for step in 0..steps.max(1) {
                find(step, both(t.clone()), false);
            }
        }
        Kind::Count | Kind::Total | Kind::CountColor | Kind::CountShape => {
            let want = if matches!(kind, Kind::Count | Kind::Total) { Some((0, 0)) } else { named0 };
            if let Some(want) = want {
                let counted = tokens.matching(want);
                let mut t = vec![SINK];
                t.extend(tokens.firsts.iter().copied().filter(|i| counted.contains(i)));
                find(0, both(t), true);
            }
        }
        Kind::Colors | Kind::Shapes | Kind::Objects | Kind::List => {
            let mut step = 0;
            while step < ends {
                match (answer[step], answer.get(step + 1)) {
                    (Word::Color(c), Some(Word::Shape(s))) if matches!(kind, Kind::Objects | Kind::List) => {
                        let t = tokens.matching((c, *s));
                        find(step, both(t.clone()), false);
                        find(step + 1, both(t), false);
                        step += 2;
                    }
                    (Word::Color(c), _) if kind == Kind::Colors => {
                        find(step, both(tokens.matching((c, 0))), false);
                        step += 1;
                    }
                    (Word::Shape(s), _) if kind == Kind::Shapes => {
                        find(step, both(tokens.matching((0, s))), false);
                        step += 1;
                    }
                    _ => step += 1,
                }
            }
            find(ends, both(vec![SINK]), false);
        }
    }
    (hops, slots)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(s: &str) -> Vec<Word> {
        s.split(|c: char| !c.is_alphanumeric()).filter(|w| !w.is_empty()).map(Word::of).collect()
    }

    #[test]
    fn named_objects_pair_colours_with_the_next_shape() {
        let n = named(&words("Is the red cube left of the blue cone?"));
        assert_eq!(n, vec![((1, 2), vec![2, 3]), ((6, 4), vec![7, 8])]);
        assert_eq!(named(&words("How many red objects are in the scene?")), vec![((1, 0), vec![2])]);
        assert_eq!(named(&words("How many tori are in the scene?")), vec![((0, 6), vec![2])]);
        assert!(named(&words("What is this?")).is_empty());
    }

    #[test]
    fn hops_point_at_the_named_object_and_count_with_the_sink() {
        // sink, two tokens of a red cube, a background token, one token of a blue cone
        let ident = [None, Some((1, 2)), Some((1, 2)), None, Some((6, 4))];
        let t = Tokens::new(&ident);
        assert_eq!(t.firsts, vec![1, 4]);
        let d = t.dedupe();
        assert_eq!(
            d.iter().filter(|h| h.head == 0).map(|h| (h.query, h.targets.clone())).collect::<Vec<_>>(),
            vec![(1, vec![SINK]), (2, vec![1]), (4, vec![SINK])]
        );
        let q = words("Is there a red cube?");
        let (hops, slots) = question_hops(Kind::Exists, &q, 10, &[Word::Other, Word::Other], 16, &t);
        assert_eq!(slots, [1, 2, 0, 0, 0, 0], "no columns known: no places");
        let find: Vec<_> = hops.iter().filter(|h| h.kind == HopKind::Find).collect();
        assert_eq!(find.len(), 2);
        assert_eq!(find[0].targets, vec![1, 2]);
        let gather: Vec<_> = hops.iter().filter(|h| h.kind == HopKind::Words).collect();
        assert_eq!(gather[0].targets, vec![13, 14]);
        // absent: the sink
        let (hops, _) =
            question_hops(Kind::Exists, &words("Is there a red cone?"), 10, &[Word::Other, Word::Other], 16, &t);
        assert_eq!(hops.iter().find(|h| h.kind == HopKind::Find).unwrap().targets, vec![SINK]);
        // counting: uniform over the sink and each object's first token
        let (hops, _) =
            question_hops(Kind::Count, &words("How many objects are there?"), 10, &[Word::Other, Word::Other], 16, &t);
        let c = hops.iter().find(|h| h.kind == HopKind::Find).unwrap();
        assert!(c.uniform);
        assert_eq!(c.targets, vec![SINK, 1, 4]);
        // a list: each object while its words are written, then the sink
        let ans = [Word::Color(1), Word::Shape(2), Word::Color(6), Word::Shape(4), Word::Other];
        let (hops, _) = question_hops(Kind::Objects, &words("What objects are there?"), 10, &ans, 16, &t);
        let per: Vec<_> = hops.iter().filter(|h| h.head == 0).map(|h| (h.query, h.targets.clone())).collect();
        assert_eq!(per, vec![(16, vec![1, 2]), (17, vec![1, 2]), (18, vec![4]), (19, vec![4]), (20, vec![SINK])]);
    }

    #[test]
    fn places_are_the_named_objects_mean_column() {
        // the red cube in columns 5 and 6, the blue cone in column 1, a red sphere in column 3
        let ident = [None, Some((1, 2)), Some((1, 2)), None, Some((6, 4)), Some((1, 1))];
        let cols = vec![None, Some(5), Some(6), Some(0), Some(1), Some(3)];
        let t = Tokens::new(&ident).with_columns(cols);
        let q = words("Is the red cube left of the blue cone?");
        let (_, slots) = question_hops(Kind::LeftOf, &q, 10, &[Word::Other, Word::Other], 16, &t);
        // 1 + round(5.5) = 7 (half away from zero), 1 + 1 = 2
        assert_eq!(slots, [1, 2, 6, 4, 7, 2]);
        // "the red object" names two objects here, an absent one none: no place
        assert_eq!(t.place((1, 0)), 0);
        assert_eq!(t.place((2, 2)), 0);
        assert_eq!(t.place((0, 4)), 2, "the only cone");
    }
}
