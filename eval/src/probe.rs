//! What `token-probe` and `encoder-probe` share: where a token's patch lies relative to the
//! objects of a view (from the ground-truth instance mask), a view's true count and colour
//! answers, reading a count answer, and the L1 of one token.

use model::ObjectId;
use model::data::synth::FIRST_OBJECT_ID;
use model::data::synth::questions::{Kind, ViewFacts, view_questions};
use model::data::synth::scene::SynthScene;
use model::rng::Rng;

/// A patch's place relative to the objects.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Region {
    /// No object pixel in the patch.
    Background,
    /// One object fills the patch.
    Inside,
    /// One object and background.
    Edge,
    /// Two objects or more.
    Contact,
}

/// Every region, in order.
pub const REGIONS: [Region; 4] = [Region::Background, Region::Inside, Region::Edge, Region::Contact];

impl Region {
    /// Whether the patch holds an object boundary (an edge or a contact).
    pub fn is_boundary(self) -> bool {
        matches!(self, Region::Edge | Region::Contact)
    }
}

/// The region of every patch of a `w`x`h` instance mask `ids` cut in `p`-pixel patches, row-major.
pub fn regions(ids: &[ObjectId], w: usize, h: usize, p: usize) -> Vec<Region> {
    let mut out = Vec::with_capacity((w / p) * (h / p));
    for py in 0..h / p {
        for px in 0..w / p {
            let (mut objects, mut other) = (Vec::new(), false);
            for y in py * p..(py + 1) * p {
                for &i in &ids[y * w + px * p..y * w + (px + 1) * p] {
                    if i >= FIRST_OBJECT_ID {
                        if !objects.contains(&i) {
                            objects.push(i);
                        }
                    } else {
                        other = true;
                    }
                }
            }
            out.push(match (objects.len(), other) {
                (0, _) => Region::Background,
                (1, false) => Region::Inside,
                (1, true) => Region::Edge,
                _ => Region::Contact,
            });
        }
    }
    out
}

/// The true answers of "How many objects are there?" and "What colors are there?" for a `w`x`h`
/// view of `scene` with instance mask `ids`, by the question files' own rule
/// ([`view_questions`]); `None` for a view the question files leave out as ambiguous.
pub fn view_truth(scene: &SynthScene, ids: &[ObjectId], w: usize, h: usize) -> Option<(usize, String)> {
    let facts = ViewFacts::of(scene, ids, &vec![0.0; w * h], w, h);
    if facts.ambiguous {
        return None;
    }
    let qas = view_questions(scene, &facts, &mut Rng::new(0));
    let colors = qas.iter().find(|q| q.kind == Kind::Colors).map(|q| q.answer.clone()).unwrap_or_default();
    Some((facts.seen.len(), colors))
}

/// The number a count answer gives ("3" or "3."), if it is one.
pub fn count_answer(text: &str) -> Option<i64> {
    text.trim().trim_end_matches('.').parse().ok()
}

/// Mean absolute difference of token `t` of two `[T, d]` token grids.
pub fn token_l1(a: &[f32], b: &[f32], t: usize, d: usize) -> f64 {
    let (x, y) = (&a[t * d..(t + 1) * d], &b[t * d..(t + 1) * d]);
    x.iter().zip(y).map(|(x, y)| (x - y).abs() as f64).sum::<f64>() / d as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_patch_gets_its_region() {
        let (bg, a, b) = (0u16, FIRST_OBJECT_ID, FIRST_OBJECT_ID + 1);
        // an 8x2 mask in four 2x2 patches: table only, object a only, a beside table, a beside b
        #[rustfmt::skip]
        let ids = [
            bg, bg, a, a, a, bg, a, b,
            bg, 1, a, a, a, bg, a, b,
        ];
        let r = regions(&ids, 8, 2, 2);
        assert_eq!(r, [Region::Background, Region::Inside, Region::Edge, Region::Contact]);
        assert_eq!(r.iter().map(|r| r.is_boundary()).collect::<Vec<_>>(), [false, false, true, true]);
    }

    #[test]
    fn count_answers_and_token_l1() {
        assert_eq!(count_answer(" 3."), Some(3));
        assert_eq!(count_answer("three"), None);
        let (a, b) = ([0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 0.0]);
        assert_eq!(token_l1(&a, &b, 0, 2), 0.0);
        assert_eq!(token_l1(&a, &b, 1, 2), 1.5);
    }
}
