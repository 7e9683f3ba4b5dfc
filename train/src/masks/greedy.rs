//! The baseline matching is measured against: Gaga's greedy recipe, written from its paper and
//! notes (not its code). Views in their order; a memory bank of Gaussian sets seeded by the first
//! view's masks; each later mask joins the group with the best `|I| / (|mask| + |I|)` when that
//! passes 0.1 (a score that cannot pass 0.5), else starts a group; a Gaussian belongs to the last
//! group it joined. Here a mask's Gaussians are those it owns ([`super::ownership`]), not every
//! centre along its pixels' rays, so the baseline gets the same 3D evidence as the matching.

use super::ownership::{Owner, ViewOwners};
use std::collections::HashSet;

/// Every Gaussian's group (0 = none) after the greedy pass over `views` in their order.
pub fn greedy(views: &[ViewOwners], n: usize) -> Vec<u16> {
    let mut groups: Vec<HashSet<usize>> = Vec::new();
    let mut label = vec![0u16; n];
    for o in views {
        let mut members: Vec<Vec<usize>> = vec![Vec::new(); o.labels.len()];
        for (g, owner) in o.owner.iter().enumerate() {
            if let Owner::Mask(k) = owner {
                members[*k as usize].push(g);
            }
        }
        for m in members.into_iter().filter(|m| !m.is_empty()) {
            let best = groups
                .iter()
                .enumerate()
                .map(|(i, grp)| {
                    let inter = m.iter().filter(|g| grp.contains(g)).count() as f32;
                    (i, inter / (m.len() as f32 + inter))
                })
                .max_by(|a, b| a.1.total_cmp(&b.1).then(b.0.cmp(&a.0)));
            let i = match best {
                Some((i, s)) if s > 0.1 => i,
                _ => {
                    groups.push(HashSet::new());
                    groups.len() - 1
                }
            };
            for &g in &m {
                groups[i].insert(g);
                label[g] = (i + 1).min(u16::MAX as usize) as u16;
            }
        }
    }
    label
}
