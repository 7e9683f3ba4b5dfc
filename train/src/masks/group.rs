//! Masks of different views joined into objects by the Gaussians they share, then every Gaussian
//! labelled by its views' votes.

use super::MatchOptions;
use super::ownership::{Owner, ViewOwners};
use std::collections::HashMap;

/// An object of the grouping, before its views are rendered.
#[derive(Clone, Debug, PartialEq)]
pub struct Grouped {
    pub id: u16,
    pub gaussians: usize,
    pub confidence: f32,
}

/// Every Gaussian's object (0 = background) and the objects.
#[derive(Clone, Debug)]
pub struct Grouping {
    pub labels: Vec<u16>,
    pub objects: Vec<Grouped>,
}

fn find(parent: &mut [usize], mut a: usize) -> usize {
    while parent[a] != a {
        parent[a] = parent[parent[a]];
        a = parent[a];
    }
    a
}

/// Groups the masks of `views` (owners of `n` Gaussians each).
pub fn group(views: &[ViewOwners], n: usize, opts: &MatchOptions) -> Grouping {
    let nv = views.len();
    // masks numbered over all views: view v's mask k is base[v] + k
    let mut base = vec![0usize; nv + 1];
    for (v, o) in views.iter().enumerate() {
        base[v + 1] = base[v] + o.labels.len();
    }
    let masks = base[nv];
    let view_of: Vec<usize> = (0..nv).flat_map(|v| std::iter::repeat_n(v, views[v].labels.len())).collect();
    let owned = |g: usize| -> Vec<usize> {
        (0..nv)
            .filter_map(|v| match views[v].owner[g] {
                Owner::Mask(k) => Some(base[v] + k as usize),
                _ => None,
            })
            .collect()
    };
    // shared[(a, b)]: Gaussians both own; seen[a * nv + v]: a's Gaussians that view v sees;
    // first[a]: a's first Gaussian (an order-free key)
    let mut shared: HashMap<(usize, usize), u32> = HashMap::new();
    let mut seen = vec![0u32; masks * nv];
    let mut first = vec![usize::MAX; masks];
    for g in 0..n {
        let list = owned(g);
        for (i, &a) in list.iter().enumerate() {
            first[a] = first[a].min(g);
            for &b in &list[i + 1..] {
                *shared.entry((a, b)).or_default() += 1;
            }
            for (v, o) in views.iter().enumerate() {
                if o.sees(g) {
                    seen[a * nv + v] += 1;
                }
            }
        }
    }
    // a mutual overlap joins two masks
    let mut parent: Vec<usize> = (0..masks).collect();
    for (&(a, b), &both) in &shared {
        let (va, vb) = (view_of[a], view_of[b]);
        let (sa, sb) = (seen[a * nv + vb].max(1), seen[b * nv + va].max(1));
        if both >= 3 && both as f32 >= opts.mutual * sa as f32 && both as f32 >= opts.mutual * sb as f32 {
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
    let kept = |r: usize| {
        let mut vs = group_views[&r].clone();
        vs.sort_unstable();
        vs.dedup();
        vs.len() >= opts.min_views
    };
    let kept: HashMap<usize, bool> = group_views.keys().map(|&r| (r, kept(r))).collect();
    // the order-free key of a group: the first Gaussian any of its masks owns
    let mut key: HashMap<usize, usize> = HashMap::new();
    for a in 0..masks {
        let k = key.entry(root[a]).or_insert(usize::MAX);
        *k = (*k).min(first[a]);
    }
    // every Gaussian votes in each view that sees it: the background, or its mask's group
    // (a mask in no kept group, a part or a merge, does not vote)
    let mut label_key = vec![usize::MAX; n];
    let mut agree = vec![0f32; n];
    let mut votes: Vec<(usize, u32)> = Vec::new();
    for g in 0..n {
        votes.clear();
        for (v, o) in views.iter().enumerate() {
            let k = match o.owner[g] {
                Owner::Background => usize::MAX,
                Owner::Mask(m) if kept[&root[base[v] + m as usize]] => key[&root[base[v] + m as usize]],
                _ => continue,
            };
            match votes.iter_mut().find(|(x, _)| *x == k) {
                Some((_, c)) => *c += 1,
                None => votes.push((k, 1)),
            }
        }
        let total: u32 = votes.iter().map(|v| v.1).sum();
        // most votes; ties to the background, then to the smaller key
        if let Some(&(k, c)) = votes.iter().max_by_key(|&&(k, c)| (c, k == usize::MAX, std::cmp::Reverse(k))) {
            label_key[g] = k;
            agree[g] = c as f32 / total as f32;
        }
    }
    // objects: groups that won enough Gaussians, numbered by size (then key)
    let mut sizes: HashMap<usize, (usize, f32)> = HashMap::new();
    for g in 0..n {
        if label_key[g] != usize::MAX {
            let e = sizes.entry(label_key[g]).or_default();
            e.0 += 1;
            e.1 += agree[g];
        }
    }
    let mut order: Vec<(usize, usize, f32)> =
        sizes.into_iter().filter(|&(_, (c, _))| c >= opts.min_gaussians).map(|(k, (c, a))| (k, c, a)).collect();
    order.sort_unstable_by_key(|&(k, c, _)| (std::cmp::Reverse(c), k));
    order.truncate(u16::MAX as usize);
    let id_of: HashMap<usize, u16> = order.iter().enumerate().map(|(i, &(k, _, _))| (k, i as u16 + 1)).collect();
    let labels = label_key.iter().map(|k| id_of.get(k).copied().unwrap_or(0)).collect();
    let objects = order
        .iter()
        .enumerate()
        .map(|(i, &(_, c, a))| Grouped { id: i as u16 + 1, gaussians: c, confidence: a / c as f32 })
        .collect();
    Grouping { labels, objects }
}
