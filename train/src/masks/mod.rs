//! Per-view instance masks from any segmenter, made into one id per object over all views through
//! the scene's own Gaussians (issue 84).
//!
//! A segmenter's ids are arbitrary per view, its masks split objects, merge neighbours, miss
//! views, add fragments and move edges. What a geometry run adds is, for every pixel, the blend
//! weight of each Gaussian that makes it ([`splat_kernels::blend::BlendWeights`]). So:
//!
//! 1. [`ownership`]: in each view, each Gaussian belongs to the mask (or the unmasked rest) that
//!    holds more than half of its blend weight there, and counts by how much of it is seen (a
//!    glimpse little, so a scene of many small Gaussians keeps its evidence and a moved edge does
//!    not decide).
//! 2. [`group::join`]: two masks of different views are one candidate object when each owns most
//!    of the other's Gaussians that its view sees (a mutual overlap, which a part of an object or
//!    two objects merged into one mask never has with a whole one).
//! 3. [`soft`]: every pixel gives its candidate (or the background, at a lower weight: a
//!    segmenter's silence is weaker than its mask) to its Gaussians in proportion to their blend
//!    weights; masks no other view matched say nothing yet.
//! 4. [`consolidate`]: candidates whose Gaussians share a mask in most views where both are seen
//!    are one object (moved edges break the strict join of step 2 into pieces).
//! 5. Masks that matched no candidate take the object most of their Gaussians carry, when it is
//!    most of them (parts, shrunk or grown masks); the rest (merges) give each pixel the object
//!    rendered there. The shares are gathered again.
//! 6. The per-view masks out are the shares rendered: each pixel the object holding most of its
//!    weight, so a merge, a missing mask or a moved edge in one view is outvoted by the others.
//! 7. [`surface`]: objects that are flat and carry others (a table, the ground) are marked, and
//!    search leaves them out as a labelled scene leaves its table out.
//!
//! Nothing depends on the order of the views (masks joined by union-find, candidates keyed by
//! their first Gaussian, objects numbered by size), and ids are 16-bit.

pub mod consolidate;
pub mod corrupt;
pub mod files;
pub mod greedy;
pub mod group;
pub mod identity;
pub mod identity_run;
pub mod ownership;
pub mod score;
pub mod soft;
pub mod surface;

use splat_kernels::blend::BlendWeights;

/// One view's instance ids, row-major (`0` = no object).
#[derive(Clone, Debug, PartialEq)]
pub struct LabelMap {
    pub width: usize,
    pub height: usize,
    pub ids: Vec<u16>,
}

impl LabelMap {
    /// The instance mask of `view` (`None` when it has none).
    pub fn of_view(view: &model::data::View) -> Option<Self> {
        let ids = view.instance_ids.as_ref()?;
        let (width, height) = (view.camera.width as usize, view.camera.height as usize);
        Some(Self { width, height, ids: ids.clone() })
    }

    /// The same size, every id `f(id)`.
    pub fn map(&self, f: impl Fn(u16) -> u16) -> Self {
        Self { width: self.width, height: self.height, ids: self.ids.iter().map(|&i| f(i)).collect() }
    }

    /// The distinct non-zero ids, ascending.
    pub fn labels(&self) -> Vec<u16> {
        let mut l: Vec<u16> = self.ids.iter().copied().filter(|&i| i != 0).collect();
        l.sort_unstable();
        l.dedup();
        l
    }
}

/// How masks are matched.
#[derive(Clone, Debug, PartialEq)]
pub struct MatchOptions {
    /// A Gaussian takes part in a view when its blend weights there sum to at least this (about
    /// this many pixels' worth of it is seen); it counts there by the square of that sum, at most 1
    /// ([`ownership::ViewOwners::seen`]).
    pub min_weight: f32,
    /// Each of two masks must own at least this share of the other's Gaussians its view sees for
    /// the two to be one object.
    pub mutual: f32,
    /// An object is kept when it was seen as one mask in at least this many views.
    pub min_views: usize,
    /// ... and holds at least this many Gaussians.
    pub min_gaussians: usize,
    /// Two candidates are one object when their Gaussians share a mask in at least this share of
    /// the views that see both.
    pub together: f64,
    /// The weight of an unmasked pixel's vote for the background, against 1 for a mask's.
    pub unmasked: f32,
}

impl Default for MatchOptions {
    fn default() -> Self {
        Self { min_weight: 0.1, mutual: 0.6, min_views: 2, min_gaussians: 8, together: 0.4, unmasked: 0.35 }
    }
}

/// One matched object.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Object {
    /// Its id in every view (1..).
    pub id: u16,
    pub gaussians: usize,
    /// The views whose rendered mask shows it.
    pub views: Vec<usize>,
    /// The share of its Gaussians' view votes that went to it (1 = every view agreed).
    pub confidence: f32,
}

/// The result: each Gaussian's shares of the objects and its largest (0 = background), the
/// objects, and every view's mask.
#[derive(Clone, Debug)]
pub struct Matched {
    pub gaussian_labels: Vec<u16>,
    pub shares: soft::Shares,
    pub objects: Vec<Object>,
    pub views: Vec<LabelMap>,
}

/// Matches `masks` (one per view) across views through the Gaussians whose blend weights in each
/// view `weights` holds (same order, same sizes).
///
/// # Panics
/// When the two lists differ in length or a mask's size differs from its view's.
pub fn match_masks(weights: &[BlendWeights], masks: &[LabelMap], opts: &MatchOptions) -> Matched {
    assert_eq!(weights.len(), masks.len(), "one mask per view");
    for (w, m) in weights.iter().zip(masks) {
        assert_eq!((w.width, w.height, m.ids.len()), (m.width, m.height, m.width * m.height), "mask size");
    }
    let gaussians = weights.first().map_or(0, |w| w.gaussians);
    let owners: Vec<ownership::ViewOwners> =
        weights.iter().zip(masks).map(|(w, m)| ownership::ViewOwners::of(w, m, opts.min_weight)).collect();
    let joined = group::join(&owners, gaussians, opts);
    // every pixel: 0 unmasked, 1 + its mask's candidate, or SKIP (its mask joined none)
    let first: Vec<LabelMap> = masks
        .iter()
        .zip(&owners)
        .zip(&joined.object)
        .map(|((m, o), object)| {
            m.map(|id| match id {
                0 => 0,
                id => object[o.index(id)].map_or(soft::SKIP, |c| c as u16 + 1),
            })
        })
        .collect();
    let shares = soft::Shares::from_maps(weights, &first, opts.unmasked);
    let into = consolidate::consolidate(&owners, &shares.argmax(), joined.candidates, opts.together);
    let maps: Vec<LabelMap> =
        first.iter().map(|m| m.map(|l| if l == soft::SKIP { l } else { into[l as usize] })).collect();
    let shares = soft::Shares::from_maps(weights, &maps, opts.unmasked);
    let labels = shares.argmax();
    let filled: Vec<LabelMap> = (0..masks.len())
        .map(|v| {
            let o = &owners[v];
            let whole = whole_objects(o, &labels);
            let rendered = shares.render(&weights[v]);
            let ids = maps[v].ids.iter().zip(&rendered.ids).zip(&masks[v].ids).map(|((&l, &r), &id)| match l {
                soft::SKIP => whole[o.index(id)].or((r != 0).then_some(r)).unwrap_or(soft::SKIP),
                l => l,
            });
            LabelMap { ids: ids.collect(), ..maps[v].clone() }
        })
        .collect();
    let mut shares = soft::Shares::from_maps(weights, &filled, opts.unmasked);
    // objects: candidates that won enough Gaussians, numbered by size (then candidate)
    let mut won = vec![(0usize, 0f32); joined.candidates + 1];
    for (g, list) in shares.of.iter().enumerate() {
        let l = shares.best_of(g);
        if l != 0 {
            won[l as usize].0 += 1;
            won[l as usize].1 += list.iter().find(|x| x.0 == l).map_or(0.0, |x| x.1);
        }
    }
    let mut order: Vec<usize> = (1..won.len()).filter(|&c| won[c].0 >= opts.min_gaussians).collect();
    order.sort_unstable_by_key(|&c| (std::cmp::Reverse(won[c].0), c));
    let mut id_of = vec![0u16; won.len()];
    for (i, &c) in order.iter().enumerate() {
        id_of[c] = i as u16 + 1;
    }
    shares.relabel(|l| id_of[l as usize]);
    let views: Vec<LabelMap> = weights.iter().map(|w| shares.render(w)).collect();
    let objects = order
        .iter()
        .enumerate()
        .map(|(i, &c)| {
            let id = i as u16 + 1;
            Object {
                id,
                gaussians: won[c].0,
                views: (0..views.len()).filter(|&v| views[v].ids.contains(&id)).collect(),
                confidence: won[c].1 / won[c].0 as f32,
            }
        })
        .collect();
    Matched { gaussian_labels: shares.argmax(), shares, objects, views }
}

/// For each mask of a view (owners `o`): the object most of the Gaussians it owns carry
/// (`labels`), when they are at least half of them.
fn whole_objects(o: &ownership::ViewOwners, labels: &[u16]) -> Vec<Option<u16>> {
    // (label, how much of its Gaussians the view sees) per mask
    let mut count: Vec<Vec<(u16, f32)>> = vec![Vec::new(); o.labels.len()];
    for (g, own) in o.owner.iter().enumerate() {
        if let ownership::Owner::Mask(k) = own {
            let c = &mut count[*k as usize];
            match c.iter_mut().find(|(l, _)| *l == labels[g]) {
                Some((_, n)) => *n += o.seen[g],
                None => c.push((labels[g], o.seen[g])),
            }
        }
    }
    count
        .iter()
        .map(|c| {
            let n: f32 = c.iter().map(|x| x.1).sum();
            let best = c.iter().filter(|x| x.0 != 0).max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)))?;
            (2.0 * best.1 >= n).then_some(best.0)
        })
        .collect()
}

/// Each pixel of the view of `w` labelled with the label whose Gaussians hold most of its weight
/// (the final transmittance counting for the background, 0): hard labels, as the greedy baseline
/// gives them.
pub fn render_labels(w: &BlendWeights, labels: &[u16]) -> LabelMap {
    let shares = soft::Shares { of: labels.iter().map(|&l| vec![(l, 1.0)]).collect() };
    shares.render(w)
}
