//! Per-view instance masks from any segmenter, made into one id per object over all views through
//! the scene's own Gaussians (issue 84).
//!
//! A segmenter's ids are arbitrary per view, its masks split objects, merge neighbours, miss
//! views and add fragments. What a geometry run adds is, for every pixel, the blend weight of
//! each Gaussian that makes it ([`splat_kernels::blend::BlendWeights`]). So:
//!
//! 1. [`ownership`]: in each view, each Gaussian belongs to the mask (or the unmasked rest) that
//!    holds most of its blend weight there, when one holds more than half of it.
//! 2. [`group`]: two masks of different views are the same object when each owns most of the
//!    other's Gaussians that its view sees (a mutual overlap, which a part of an object or two
//!    objects merged into one mask never has with a whole one); such pairs joined give the
//!    objects. Each Gaussian then takes the object its views vote for most (background
//!    included), so a split, a merge or a missing mask in a few views is outvoted, not copied.
//! 3. The per-view masks out are the objects rendered: each pixel the label whose Gaussians hold
//!    most of its weight.
//!
//! Nothing depends on the order of the views (edges are joined by union-find and labels
//! renumbered by size), and ids are 16-bit.

pub mod corrupt;
pub mod files;
pub mod greedy;
pub mod group;
pub mod identity;
pub mod identity_run;
pub mod ownership;
pub mod score;

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
        Some(Self { width, height, ids: ids.iter().map(|&i| i as u16).collect() })
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
    /// this many pixels' worth of it is seen).
    pub min_weight: f32,
    /// Each of two masks must own at least this share of the other's Gaussians its view sees for
    /// the two to be one object.
    pub mutual: f32,
    /// An object is kept when it was seen as one mask in at least this many views.
    pub min_views: usize,
    /// ... and holds at least this many Gaussians.
    pub min_gaussians: usize,
}

impl Default for MatchOptions {
    fn default() -> Self {
        Self { min_weight: 0.5, mutual: 0.6, min_views: 2, min_gaussians: 8 }
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

/// The result: an object id per Gaussian (0 = background), the objects, and every view's mask.
#[derive(Clone, Debug)]
pub struct Matched {
    pub gaussian_labels: Vec<u16>,
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
    let grouping = group::group(&owners, gaussians, opts);
    let views: Vec<LabelMap> = weights.iter().map(|w| render_labels(w, &grouping.labels)).collect();
    let objects = grouping
        .objects
        .iter()
        .map(|o| Object {
            id: o.id,
            gaussians: o.gaussians,
            views: (0..views.len()).filter(|&v| views[v].ids.contains(&o.id)).collect(),
            confidence: o.confidence,
        })
        .collect();
    Matched { gaussian_labels: grouping.labels, objects, views }
}

/// Each pixel of the view of `w` labelled with the label whose Gaussians hold most of its weight
/// (the final transmittance counting for the background, 0).
pub fn render_labels(w: &BlendWeights, labels: &[u16]) -> LabelMap {
    let mut ids = vec![0u16; w.width * w.height];
    let mut acc: Vec<(u16, f32)> = Vec::new();
    for (p, id) in ids.iter_mut().enumerate() {
        acc.clear();
        acc.push((0, w.final_t[p]));
        for e in w.offsets[p]..w.offsets[p + 1] {
            let l = labels[w.gids[e] as usize];
            match acc.iter_mut().find(|(k, _)| *k == l) {
                Some((_, s)) => *s += w.weights[e],
                None => acc.push((l, w.weights[e])),
            }
        }
        // the largest weight; ties to the smaller label
        *id =
            acc.iter().fold((0u16, f32::MIN), |b, &(l, s)| if s > b.1 || (s == b.1 && l < b.0) { (l, s) } else { b }).0;
    }
    LabelMap { width: w.width, height: w.height, ids }
}
