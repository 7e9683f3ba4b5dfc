//! Consistent instance mIoU: each true object matched to one predicted id over all views (by
//! their total overlap, one to one), then its IoU in every view where either shows, averaged.

use super::LabelMap;
use std::collections::HashMap;

/// How predicted masks compare with the truth over the views of a scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Consistency {
    /// Mean over the true objects of their mean IoU over the views.
    pub miou: f64,
    pub true_objects: usize,
    pub predicted_objects: usize,
}

/// Scores `pred` against `truth` (one per view, the same sizes; ids consistent across views in
/// both; 0 = none).
pub fn consistency(truth: &[LabelMap], pred: &[LabelMap]) -> Consistency {
    assert_eq!(truth.len(), pred.len(), "one prediction per view");
    let mut inter: HashMap<(u16, u16), u64> = HashMap::new();
    let (mut true_ids, mut pred_ids) = (Vec::new(), Vec::new());
    for (t, p) in truth.iter().zip(pred) {
        assert_eq!(t.ids.len(), p.ids.len(), "view sizes");
        for (&a, &b) in t.ids.iter().zip(&p.ids) {
            if a != 0 && b != 0 {
                *inter.entry((a, b)).or_default() += 1;
            }
        }
        true_ids.extend(t.labels());
        pred_ids.extend(p.labels());
    }
    for ids in [&mut true_ids, &mut pred_ids] {
        ids.sort_unstable();
        ids.dedup();
    }
    // one to one, largest overlap first (ties by ids: deterministic)
    let mut pairs: Vec<((u16, u16), u64)> = inter.into_iter().collect();
    pairs.sort_unstable_by_key(|&((a, b), n)| (std::cmp::Reverse(n), a, b));
    let mut matched: HashMap<u16, u16> = HashMap::new();
    let mut taken = std::collections::HashSet::new();
    for ((a, b), _) in pairs {
        if !matched.contains_key(&a) && !taken.contains(&b) {
            matched.insert(a, b);
            taken.insert(b);
        }
    }
    let mut sum = 0f64;
    for &a in &true_ids {
        let b = matched.get(&a).copied();
        let (mut ious, mut views) = (0f64, 0usize);
        for (t, p) in truth.iter().zip(pred) {
            let (mut i, mut u) = (0u64, 0u64);
            for (&x, &y) in t.ids.iter().zip(&p.ids) {
                let (inx, iny) = (x == a, Some(y) == b);
                i += (inx && iny) as u64;
                u += (inx || iny) as u64;
            }
            if u > 0 {
                ious += i as f64 / u as f64;
                views += 1;
            }
        }
        sum += if views > 0 { ious / views as f64 } else { 0.0 };
    }
    let miou = if true_ids.is_empty() { 1.0 } else { sum / true_ids.len() as f64 };
    Consistency { miou, true_objects: true_ids.len(), predicted_objects: pred_ids.len() }
}

/// For each predicted id: the true id it overlaps most over all views (not one to one: two
/// pieces of one object both name it); ids that overlap nothing are left out.
pub fn truth_of(truth: &[LabelMap], pred: &[LabelMap]) -> HashMap<u16, u16> {
    let mut inter: HashMap<(u16, u16), u64> = HashMap::new();
    for (t, p) in truth.iter().zip(pred) {
        for (&a, &b) in t.ids.iter().zip(&p.ids) {
            if a != 0 && b != 0 {
                *inter.entry((b, a)).or_default() += 1;
            }
        }
    }
    let mut best: HashMap<u16, (u64, u16)> = HashMap::new();
    for ((b, a), n) in inter {
        let e = best.entry(b).or_insert((n, a));
        // largest overlap, then the smaller true id: deterministic
        if (n, std::cmp::Reverse(a)) > (e.0, std::cmp::Reverse(e.1)) {
            *e = (n, a);
        }
    }
    best.into_iter().map(|(b, (_, a))| (b, a)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(ids: &[u16]) -> LabelMap {
        LabelMap { width: ids.len(), height: 1, ids: ids.to_vec() }
    }

    #[test]
    fn renamed_ids_score_one_and_a_swap_between_views_does_not() {
        let truth = [map(&[0, 1, 1, 2, 2]), map(&[1, 1, 0, 2, 2])];
        let same = [map(&[0, 7, 7, 9, 9]), map(&[7, 7, 0, 9, 9])];
        assert_eq!(consistency(&truth, &same).miou, 1.0);
        // the second view's ids swapped: each object gets one id over all views, so half is wrong
        let swapped = [map(&[0, 7, 7, 9, 9]), map(&[9, 9, 0, 7, 7])];
        let c = consistency(&truth, &swapped);
        assert!((c.miou - 0.5).abs() < 1e-9, "{c:?}");
        assert_eq!((c.true_objects, c.predicted_objects), (2, 2));
        // each predicted id names the true object it overlaps most
        let split = [map(&[0, 7, 8, 9, 9]), map(&[7, 8, 0, 9, 9])];
        let named = truth_of(&truth, &split);
        assert_eq!((named[&7], named[&8], named[&9]), (1, 1, 2));
    }
}
