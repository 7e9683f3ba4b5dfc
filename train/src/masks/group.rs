//! Masks of different views joined into candidate objects by the Gaussians they share.

use super::MatchOptions;
use super::ownership::{Owner, ViewOwners};
use std::collections::HashMap;

fn find(parent: &mut [usize], mut a: usize) -> usize {
    while parent[a] != a {
        parent[a] = parent[parent[a]];
        a = parent[a];
    }
    a
}

/// Joins the masks of `views` (owners of `n` Gaussians each) that overlap mutually into candidate
/// objects.
pub fn join(views: &[ViewOwners], n: usize, opts: &MatchOptions) -> Joined {
    let nv = views.len();
    // masks numbered over all views: view v's mask k is base[v] + k
    let mut base = vec![0usize; nv + 1];
    for (v, o) in views.iter().enumerate() {
        base[v + 1] = base[v] + o.labels.len();
    }
    let masks = base[nv];
    let view_of: Vec<usize> = (0..nv).flat_map(|v| std::iter::repeat_n(v, views[v].labels.len())).collect();
    let owned = |g: usize| -> Vec<(usize, f32)> {
        (0..nv)
            .filter_map(|v| match views[v].owner[g] {
                Owner::Mask(k) => Some((base[v] + k as usize, views[v].seen[g])),
                _ => None,
            })
            .collect()
    };
    // each Gaussian counts as much as the less of the two views sees of it: shared[(a, b)]: the
    // Gaussians both own (their weight, their number); seen[a * nv + v]: a's Gaussians that view
    // v sees; first[a]: a's first Gaussian (an order-free key)
    let mut shared: HashMap<(usize, usize), (f32, u32)> = HashMap::new();
    let mut seen = vec![0f32; masks * nv];
    let mut first = vec![usize::MAX; masks];
    for g in 0..n {
        let list = owned(g);
        for (i, &(a, wa)) in list.iter().enumerate() {
            first[a] = first[a].min(g);
            for &(b, wb) in &list[i + 1..] {
                let s = shared.entry((a, b)).or_default();
                *s = (s.0 + wa.min(wb), s.1 + 1);
            }
            for (v, o) in views.iter().enumerate() {
                seen[a * nv + v] += wa.min(o.seen[g]);
            }
        }
    }
    // a mutual overlap joins two masks
    let mut parent: Vec<usize> = (0..masks).collect();
    for (&(a, b), &(both, count)) in &shared {
        let (va, vb) = (view_of[a], view_of[b]);
        let (sa, sb) = (seen[a * nv + vb].max(1e-6), seen[b * nv + va].max(1e-6));
        if count >= 3 && both >= opts.mutual * sa && both >= opts.mutual * sb {
            let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
            parent[ra.max(rb)] = ra.min(rb);
        }
    }
    // a group is an object candidate when it holds masks of enough views
    let root: Vec<usize> = (0..masks).map(|a| find(&mut parent, a)).collect();
    let mut group_views: HashMap<usize, Vec<usize>> = HashMap::new();
    for a in 0..masks {
        group_views.entry(root[a]).or_default().push(view_of[a]);
    }
    // the key of a group: the first Gaussian any of its masks owns (free of the views' order),
    // then its root (two groups whose masks own the same first Gaussian in different views)
    let mut key: HashMap<usize, (usize, usize)> = HashMap::new();
    for a in 0..masks {
        let k = key.entry(root[a]).or_insert((usize::MAX, root[a]));
        k.0 = k.0.min(first[a]);
    }
    let mut kept: Vec<(usize, usize)> = group_views
        .iter()
        .filter(|(_, vs)| {
            let mut vs = (*vs).clone();
            vs.sort_unstable();
            vs.dedup();
            vs.len() >= opts.min_views
        })
        .map(|(&r, _)| key[&r])
        .collect();
    kept.sort_unstable();
    kept.truncate(u16::MAX as usize - 1);
    let object = (0..nv)
        .map(|v| {
            (0..views[v].labels.len())
                .map(|k| kept.binary_search(&key[&root[base[v] + k]]).ok().map(|i| i as u32))
                .collect()
        })
        .collect();
    Joined { object, candidates: kept.len() }
}

/// Which candidate object each mask of each view joined.
#[derive(Clone, Debug, PartialEq)]
pub struct Joined {
    /// `object[v][k]`: view `v`'s mask `k` (an index into its labels) belongs to candidate
    /// `object[v][k]`, or to none (a part, a merge, a fragment: no mask of another view matched it).
    pub object: Vec<Vec<Option<u32>>>,
    /// Candidates, numbered by the first Gaussian any of their masks owns.
    pub candidates: usize,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A view owning Gaussians as `owner` says (`None`: the unmasked rest), each counting `seen`.
    fn view(masks: u16, owner: &[Option<u32>], seen: &[f32]) -> ViewOwners {
        ViewOwners {
            labels: (1..=masks).collect(),
            owner: owner.iter().map(|o| o.map_or(Owner::Background, Owner::Mask)).collect(),
            seen: seen.to_vec(),
        }
    }

    #[test]
    fn glimpsed_gaussians_count_little_in_an_overlap() {
        // Gaussians 0-9: one object, seen whole in both views; 10-29: the second view's mask
        // holds them too, but the first view only glimpses them (a tenth of a pixel each) outside
        // its mask, as the many small Gaussians behind an object's edge
        let n = 30;
        let first: Vec<Option<u32>> = (0..n).map(|g| (g < 10).then_some(0)).collect();
        let second = vec![Some(0); n];
        let glimpsed: Vec<f32> = (0..n).map(|g| if g < 10 { 1.0 } else { 0.1f32.powi(2) }).collect();
        let opts = MatchOptions::default();
        let views = [view(1, &first, &glimpsed), view(1, &second, &[1.0; 30])];
        let j = join(&views, n, &opts);
        assert_eq!(j.candidates, 1, "{j:?}");
        assert_eq!(j.object, vec![vec![Some(0)], vec![Some(0)]]);
        // every Gaussian counted alike: the glimpses outweigh the object and the masks stay apart
        let alike = [view(1, &first, &[1.0; 30]), view(1, &second, &[1.0; 30])];
        assert_eq!(join(&alike, n, &opts).candidates, 0);
    }
}
