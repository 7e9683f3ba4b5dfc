//! Which mask of a view each Gaussian belongs to: the one (or the unmasked rest) that holds more
//! than half of the Gaussian's blend weight in that view.

use super::LabelMap;
use splat_kernels::blend::BlendWeights;

/// What a view says of one Gaussian.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Owner {
    /// Too little of it is seen (its weights sum below `min_weight`).
    Unseen,
    /// Seen, but no mask (nor the unmasked rest) holds more than half of its weight.
    Ambiguous,
    /// Seen in no mask.
    Background,
    /// Seen in the view's mask `k` (an index into [`ViewOwners::labels`]).
    Mask(u32),
}

/// One view: its masks' labels and every Gaussian's owner.
#[derive(Clone, Debug)]
pub struct ViewOwners {
    /// The view's non-zero mask ids, ascending.
    pub labels: Vec<u16>,
    /// `[N]` per Gaussian.
    pub owner: Vec<Owner>,
    /// `[N]` how much each Gaussian counts in the view: the square of its blend weights' sum, at
    /// most 1, where a mask or the background owns it clearly (0 where unseen or ambiguous). A
    /// Gaussian glimpsed behind others or at an edge is seen in few pixels, so what owns it is said
    /// by few pixels (a mask's edge moved by one decides it): it counts for less than one seen
    /// whole, and less than in proportion.
    pub seen: Vec<f32>,
}

impl ViewOwners {
    /// The owners of the Gaussians of `w` under `mask` (the same size).
    pub fn of(w: &BlendWeights, mask: &LabelMap, min_weight: f32) -> Self {
        let labels = mask.labels();
        let index = |id: u16| labels.binary_search(&id).map_or(0, |k| k as u32 + 1);
        // (Gaussian, 0 = unmasked or 1 + mask index, weight) of every entry, summed per pair
        let mut entries: Vec<(u32, u32, f32)> = Vec::with_capacity(w.gids.len());
        for p in 0..w.width * w.height {
            let slot = index(mask.ids[p]);
            for e in w.offsets[p]..w.offsets[p + 1] {
                entries.push((w.gids[e], slot, w.weights[e]));
            }
        }
        entries.sort_unstable_by_key(|&(g, s, _)| (g, s));
        let mut owner = vec![Owner::Unseen; w.gaussians];
        let mut seen = vec![0f32; w.gaussians];
        let mut i = 0;
        while i < entries.len() {
            let g = entries[i].0;
            let (mut total, mut best, mut best_slot) = (0f32, 0f32, 0u32);
            while i < entries.len() && entries[i].0 == g {
                let s = entries[i].1;
                let mut sum = 0f32;
                while i < entries.len() && entries[i].0 == g && entries[i].1 == s {
                    sum += entries[i].2;
                    i += 1;
                }
                total += sum;
                if sum > best {
                    (best, best_slot) = (sum, s);
                }
            }
            owner[g as usize] = if total < min_weight {
                Owner::Unseen
            } else if best <= 0.5 * total {
                Owner::Ambiguous
            } else if best_slot == 0 {
                Owner::Background
            } else {
                Owner::Mask(best_slot - 1)
            };
            if matches!(owner[g as usize], Owner::Background | Owner::Mask(_)) {
                seen[g as usize] = total.min(1.0).powi(2);
            }
        }
        Self { labels, owner, seen }
    }

    /// The index of mask id `id` (non-zero, one of the view's).
    ///
    /// # Panics
    /// When the view has no mask `id`.
    pub fn index(&self, id: u16) -> usize {
        self.labels.binary_search(&id).expect("a mask id of the view")
    }
}
