//! Candidate objects merged by how often their Gaussians share a mask.
//!
//! A mask that moved its edges, lost a part or missed a view matches no whole mask of another view
//! strictly, so one object can come out of the pairwise join as several candidates. Their
//! Gaussians, though, keep sharing a mask in almost every view (a split or a missing mask takes
//! a few views, not most), while two objects share one only where a segmenter merged them. So
//! candidates are merged, closest pair first, while the Gaussians of the two share a mask (or both
//! lie in the unmasked rest of a view) in at least `together` of the pairs seen together: for each
//! view, the product of how many Gaussians of each the view sees, summed over the views.

use super::ownership::{Owner, ViewOwners};
use std::collections::HashMap;

/// Per view: for each of its slots (0 = the unmasked rest, `1 + k` = mask `k`), how many
/// Gaussians of each label it owns, as `(label, count)` sorted by label.
type Counts = Vec<Vec<Vec<(u32, f64)>>>;

fn counts(views: &[ViewOwners], labels: &[u32]) -> Counts {
    views
        .iter()
        .map(|o| {
            let mut slots: Vec<HashMap<u32, f64>> = vec![HashMap::new(); o.labels.len() + 1];
            for (g, owner) in o.owner.iter().enumerate() {
                let s = match owner {
                    Owner::Background => 0,
                    Owner::Mask(k) => *k as usize + 1,
                    _ => continue,
                };
                *slots[s].entry(labels[g]).or_default() += o.seen[g] as f64;
            }
            slots
                .into_iter()
                .map(|m| {
                    let mut l: Vec<(u32, f64)> = m.into_iter().collect();
                    l.sort_unstable_by_key(|&(k, _)| k);
                    l
                })
                .collect()
        })
        .collect()
}

/// `(together, both seen)` pair counts of every two labels that ever share a slot.
fn rates(c: &Counts) -> HashMap<(u32, u32), (f64, f64)> {
    let mut out: HashMap<(u32, u32), (f64, f64)> = HashMap::new();
    for view in c {
        for slot in view {
            for (i, &(a, na)) in slot.iter().enumerate() {
                for &(b, nb) in &slot[i + 1..] {
                    out.entry((a, b)).or_default().0 += na * nb;
                }
            }
        }
    }
    for view in c {
        let mut seen: HashMap<u32, f64> = HashMap::new();
        for slot in view {
            for &(l, n) in slot {
                *seen.entry(l).or_default() += n;
            }
        }
        for (&(a, b), v) in out.iter_mut() {
            if let (Some(na), Some(nb)) = (seen.get(&a), seen.get(&b)) {
                v.1 += na * nb;
            }
        }
    }
    out
}

/// Each label of `labels` (one per Gaussian: 0 = the background, `1..=candidates`) mapped to the
/// label it merges into; the smaller label of a merged pair names the merge. The background merges
/// with nothing (its Gaussians are every object's that the votes left unclaimed).
pub fn consolidate(views: &[ViewOwners], labels: &[u16], candidates: usize, together: f64) -> Vec<u16> {
    let mut into: Vec<u32> = (0..=candidates as u32).collect();
    let current: Vec<u32> = labels.iter().map(|&l| l as u32).collect();
    let mut c = counts(views, &current);
    loop {
        // the closest pair, ties to the smaller labels
        let best = rates(&c)
            .into_iter()
            .filter(|((a, _), (t, s))| *a != 0 && *s > 0.0 && t / s >= together)
            .map(|(k, (t, s))| (k, t / s))
            .max_by(|x, y| x.1.total_cmp(&y.1).then(y.0.cmp(&x.0)));
        let Some(((a, b), _)) = best else { break };
        for l in into.iter_mut() {
            if *l == b {
                *l = a;
            }
        }
        for slot in c.iter_mut().flatten() {
            if let Some(i) = slot.iter().position(|&(l, _)| l == b) {
                let (_, n) = slot.remove(i);
                match slot.iter_mut().find(|(l, _)| *l == a) {
                    Some((_, m)) => *m += n,
                    None => {
                        slot.push((a, n));
                        slot.sort_unstable_by_key(|&(k, _)| k);
                    }
                }
            }
        }
    }
    into.into_iter().map(|l| l as u16).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A view whose masks own Gaussians as `owner` says (`None`: unmasked).
    fn view(masks: usize, owner: &[Option<u32>]) -> ViewOwners {
        ViewOwners {
            labels: (1..=masks as u16).collect(),
            owner: owner.iter().map(|o| o.map_or(Owner::Background, Owner::Mask)).collect(),
            seen: vec![1.0; owner.len()],
        }
    }

    #[test]
    fn pieces_of_one_object_merge_and_neighbours_merged_once_do_not() {
        // Gaussians 0-3: object A in two candidates (1: 0-1, 2: 2-3); 4-5: object B (3); 6-7: background
        let labels = [1, 1, 2, 2, 3, 3, 0, 0];
        let (a, b) = (Some(0), Some(1));
        let views = [
            view(2, &[a, a, a, a, b, b, None, None]),
            view(2, &[a, a, a, a, b, b, None, None]),
            // a segmenter merged A and B here, and split A there
            view(1, &[a, a, a, a, a, a, None, None]),
            view(2, &[a, a, b, b, None, None, None, None]),
        ];
        let into = consolidate(&views, &labels, 3, 0.4);
        assert_eq!(into, vec![0, 1, 1, 3], "A's pieces one object, B apart, the background alone");
        // the same views in another order: the same merges
        let rev: Vec<ViewOwners> = views.iter().rev().cloned().collect();
        assert_eq!(consolidate(&rev, &labels, 3, 0.4), into);
    }
}
