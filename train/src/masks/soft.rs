//! Every Gaussian's share of each object, from the blend weights it gives the pixels each view
//! labels with that object, and the views rendered from those shares.
//!
//! A Gaussian on an object's border gives part of its weight to the object's pixels and part to
//! its neighbour's; over many views, each with its own edge errors, its shares settle where its
//! weight falls. Rendered with the same weights, each pixel takes the object holding most of its
//! weight: the borders come from the geometry and every view's masks at once, not from one.

use super::LabelMap;
use splat_kernels::blend::BlendWeights;

/// A pixel that says nothing of its Gaussians (its mask matched no object: a part, a merge, a
/// fragment).
pub const SKIP: u16 = u16::MAX;

/// `[N]` per Gaussian: `(object, share)` pairs, shares summing to 1, objects ascending (0 = the
/// background). A Gaussian no view labelled holds none.
#[derive(Clone, Debug, PartialEq)]
pub struct Shares {
    pub of: Vec<Vec<(u16, f32)>>,
}

impl Shares {
    /// The shares from `maps` (one per view, ids consistent over the views, [`SKIP`] where a pixel
    /// says nothing), each pixel's label given to its Gaussians in proportion to their weights,
    /// the background's (0) times `background`.
    pub fn from_maps(weights: &[BlendWeights], maps: &[LabelMap], background: f32) -> Self {
        let n = weights.first().map_or(0, |w| w.gaussians);
        let mut of: Vec<Vec<(u16, f32)>> = vec![Vec::new(); n];
        for (w, m) in weights.iter().zip(maps) {
            for p in 0..w.width * w.height {
                let l = m.ids[p];
                if l == SKIP {
                    continue;
                }
                let f = if l == 0 { background } else { 1.0 };
                for e in w.offsets[p]..w.offsets[p + 1] {
                    let list = &mut of[w.gids[e] as usize];
                    match list.iter_mut().find(|(k, _)| *k == l) {
                        Some((_, s)) => *s += f * w.weights[e],
                        None => list.push((l, f * w.weights[e])),
                    }
                }
            }
        }
        for list in &mut of {
            list.sort_unstable_by_key(|&(k, _)| k);
            let total: f32 = list.iter().map(|&(_, s)| s).sum();
            if total > 0.0 {
                list.iter_mut().for_each(|(_, s)| *s /= total);
            } else {
                list.clear();
            }
        }
        Self { of }
    }

    /// Every label renamed by `f` (shares of labels renamed alike summed).
    pub fn relabel(&mut self, f: impl Fn(u16) -> u16) {
        for list in &mut self.of {
            let mut out: Vec<(u16, f32)> = Vec::with_capacity(list.len());
            for &(l, s) in list.iter() {
                let l = f(l);
                match out.iter_mut().find(|(k, _)| *k == l) {
                    Some((_, a)) => *a += s,
                    None => out.push((l, s)),
                }
            }
            out.sort_unstable_by_key(|&(k, _)| k);
            *list = out;
        }
    }

    /// Each Gaussian's largest share (ties to the smaller id; 0 when it holds none).
    pub fn argmax(&self) -> Vec<u16> {
        (0..self.of.len()).map(|g| self.best_of(g)).collect()
    }

    /// Gaussian `g`'s largest share, as [`argmax`](Self::argmax).
    pub fn best_of(&self, g: usize) -> u16 {
        best(self.of[g].iter().copied())
    }

    /// The view of `w` labelled: each pixel the object with most of its weight times the shares
    /// (the final transmittance and Gaussians with no shares counting for the background).
    pub fn render(&self, w: &BlendWeights) -> LabelMap {
        let mut ids = vec![0u16; w.width * w.height];
        let mut acc: Vec<(u16, f32)> = Vec::new();
        for (p, id) in ids.iter_mut().enumerate() {
            acc.clear();
            acc.push((0, w.final_t[p]));
            for e in w.offsets[p]..w.offsets[p + 1] {
                let list = &self.of[w.gids[e] as usize];
                if list.is_empty() {
                    acc[0].1 += w.weights[e];
                }
                for &(l, s) in list {
                    match acc.iter_mut().find(|(k, _)| *k == l) {
                        Some((_, a)) => *a += w.weights[e] * s,
                        None => acc.push((l, w.weights[e] * s)),
                    }
                }
            }
            *id = best(acc.iter().copied());
        }
        LabelMap { width: w.width, height: w.height, ids }
    }
}

/// The label with the largest value; ties to the smaller label; 0 for none.
fn best(it: impl Iterator<Item = (u16, f32)>) -> u16 {
    it.fold((0u16, f32::MIN), |b, (l, s)| if s > b.1 || (s == b.1 && l < b.0) { (l, s) } else { b }).0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Four pixels in a row; Gaussian 0 makes pixels 0 and 1, Gaussian 1 pixels 1, 2 and 3.
    fn row() -> BlendWeights {
        BlendWeights {
            width: 4,
            height: 1,
            gaussians: 2,
            offsets: vec![0, 1, 3, 4, 5],
            gids: vec![0, 0, 1, 1, 1],
            weights: vec![0.9, 0.3, 0.6, 0.9, 0.9],
            final_t: vec![0.1, 0.1, 0.1, 0.1],
        }
    }

    #[test]
    fn shares_follow_the_weights_and_render_back() {
        let w = row();
        let m = LabelMap { width: 4, height: 1, ids: vec![1, 1, 2, 2] };
        let s = Shares::from_maps(std::slice::from_ref(&w), std::slice::from_ref(&m), 1.0);
        assert_eq!(s.of[0], vec![(1, 1.0)]);
        let (a, b) = (s.of[1][0], s.of[1][1]);
        assert_eq!((a.0, b.0), (1, 2));
        assert!((a.1 - 0.6 / 2.4).abs() < 1e-6 && (b.1 - 1.8 / 2.4).abs() < 1e-6, "{:?}", s.of[1]);
        assert_eq!(s.argmax(), vec![1, 2]);
        // pixel 1: 0.3 of label 1 from Gaussian 0 and 0.6 * 0.25 from Gaussian 1, against 0.45 of 2
        assert_eq!(s.render(&w).ids, vec![1, 1, 2, 2]);
        // a skipped pixel says nothing, the background counts at its weight
        let skip = LabelMap { width: 4, height: 1, ids: vec![SKIP, SKIP, 0, 2] };
        let s = Shares::from_maps(std::slice::from_ref(&w), std::slice::from_ref(&skip), 0.5);
        assert!(s.of[0].is_empty());
        assert_eq!(s.of[1].iter().map(|x| x.0).collect::<Vec<_>>(), vec![0, 2]);
        assert!((s.of[1][0].1 - 0.45 / 1.35).abs() < 1e-6, "{:?}", s.of[1]);
        // relabelled: shares of labels renamed alike are summed
        let mut s = s;
        s.relabel(|l| if l == 2 { 0 } else { l });
        assert_eq!(s.of[1].len(), 1);
        assert!((s.of[1][0].1 - 1.0).abs() < 1e-6);
    }
}
