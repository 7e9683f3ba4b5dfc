//! True masks corrupted the way segmenters err, for the tests and the benchmark: edges moved,
//! masks missing, merged with a touching neighbour, split in two, spurious fragments, and ids
//! shuffled per view (issue 84's recipe).

use super::LabelMap;
use model::rng::Rng;
use std::path::{Path, PathBuf};

/// How often each error happens (per mask, per view).
#[derive(Clone, Debug, PartialEq)]
pub struct Errors {
    /// Edges moved by up to this many pixels (each mask grown or shrunk).
    pub edge_px: usize,
    pub missing: f32,
    pub merged: f32,
    pub split: f32,
    /// Spurious fragments per view (0..=this, each a small square with an id of its own).
    pub fragments: usize,
}

impl Default for Errors {
    fn default() -> Self {
        Self { edge_px: 2, missing: 0.10, merged: 0.10, split: 0.20, fragments: 2 }
    }
}

/// `truth` corrupted by `errors`, seeded by `seed` and the view's index; every view's ids are
/// arbitrary (a fresh random numbering per view).
pub fn corrupt(truth: &[LabelMap], errors: &Errors, seed: u64) -> Vec<LabelMap> {
    truth.iter().enumerate().map(|(v, m)| corrupt_view(m, errors, seed ^ ((v as u64 + 1) * 0x9e37_79b9))).collect()
}

fn corrupt_view(m: &LabelMap, e: &Errors, seed: u64) -> LabelMap {
    let mut rng = Rng::new(seed);
    let (w, h) = (m.width, m.height);
    let mut ids = m.ids.clone();
    let mut next = m.labels().last().copied().unwrap_or(0) + 1;
    // edges: each mask grown into the unmasked pixels or shrunk from its border
    for id in m.labels() {
        let r = 1 + (rng.next_u64() % e.edge_px.max(1) as u64) as usize;
        let grow = rng.f() < 0.5;
        let before = ids.clone();
        for y in 0..h {
            for x in 0..w {
                let near = |want: &dyn Fn(u16) -> bool| {
                    (y.saturating_sub(r)..(y + r + 1).min(h))
                        .any(|yy| (x.saturating_sub(r)..(x + r + 1).min(w)).any(|xx| want(before[yy * w + xx])))
                };
                let p = y * w + x;
                if grow && before[p] == 0 && near(&|q| q == id) {
                    ids[p] = id;
                } else if !grow && before[p] == id && near(&|q| q != id) {
                    ids[p] = 0;
                }
            }
        }
    }
    for id in m.labels() {
        let roll = rng.f();
        if roll < e.missing {
            ids.iter_mut().filter(|i| **i == id).for_each(|i| *i = 0);
        } else if roll < e.missing + e.merged {
            // into a touching neighbour, if it has one
            let touching = (0..w * h).find_map(|p| {
                let (x, y) = (p % w, p / w);
                let n = [(x + 1 < w).then(|| p + 1), (y + 1 < h).then(|| p + w)];
                n.into_iter().flatten().find_map(|q| match (ids[p], ids[q]) {
                    (a, b) if a == id && b != 0 && b != id => Some(b),
                    (a, b) if b == id && a != 0 && a != id => Some(a),
                    _ => None,
                })
            });
            if let Some(other) = touching {
                ids.iter_mut().filter(|i| **i == id).for_each(|i| *i = other);
            }
        } else if roll < e.missing + e.merged + e.split {
            // in two by a line through its centre
            let pix: Vec<usize> = (0..w * h).filter(|&p| ids[p] == id).collect();
            if pix.len() >= 2 {
                let n = pix.len() as f32;
                let cx = pix.iter().map(|&p| (p % w) as f32).sum::<f32>() / n;
                let cy = pix.iter().map(|&p| (p / w) as f32).sum::<f32>() / n;
                let a = rng.range(0.0, std::f32::consts::PI);
                for &p in &pix {
                    if ((p % w) as f32 - cx) * a.cos() + ((p / w) as f32 - cy) * a.sin() > 0.0 {
                        ids[p] = next;
                    }
                }
                next += 1;
            }
        }
    }
    // fragments: small squares anywhere
    let count = rng.next_u64() % (e.fragments as u64 + 1);
    for _ in 0..count {
        let s = 2 + (rng.next_u64() % 3) as usize;
        let (x0, y0) = ((rng.next_u64() as usize) % w.max(1), (rng.next_u64() as usize) % h.max(1));
        for y in y0..(y0 + s).min(h) {
            for x in x0..(x0 + s).min(w) {
                ids[y * w + x] = next;
            }
        }
        next += 1;
    }
    // ids renumbered at random
    let mut labels: Vec<u16> = ids.iter().copied().filter(|&i| i != 0).collect();
    labels.sort_unstable();
    labels.dedup();
    let mut fresh: Vec<u16> = (1..=labels.len() as u16 + 40).collect();
    rng.shuffle(&mut fresh);
    for i in ids.iter_mut().filter(|i| **i != 0) {
        *i = fresh[labels.binary_search(i).unwrap()];
    }
    LabelMap { width: w, height: h, ids }
}

/// Makes the synthetic capture in `data` (written by `chatsplat synth`) one without labels, its
/// true masks handed to `per_view` corrupted by `errors` (one label PNG per image, ids arbitrary
/// per view): the masks folder, `scene.json`, `questions.json` and the frames' mask paths go.
/// Returns the number of true objects. The benchmarks' and the tests' stand-in for a segmenter.
pub fn strip_capture(data: &Path, per_view: &Path, errors: &Errors, seed: u64) -> model::Result<usize> {
    let masks = data.join("masks");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&masks)
        .map_err(|e| model::Error::io(&masks, "reading", e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "png"))
        .collect();
    files.sort();
    let mut truth = Vec::new();
    for p in &files {
        let (w, h, ids) = model::data::read_ids16_any(p)?;
        truth.push(LabelMap { width: w as usize, height: h as usize, ids });
    }
    model::io::create_dir(per_view)?;
    for (m, p) in corrupt(&truth, errors, seed).iter().zip(&files) {
        let name = p.file_name().expect("a file read from the folder");
        model::images::write_ids(&per_view.join(name), m.width as u32, m.height as u32, &m.ids)?;
    }
    std::fs::remove_dir_all(&masks).map_err(|e| model::Error::io(&masks, "removing", e))?;
    for f in ["scene.json", "questions.json"] {
        let p = data.join(f);
        if p.is_file() {
            std::fs::remove_file(&p).map_err(|e| model::Error::io(&p, "removing", e))?;
        }
    }
    let transforms = data.join("transforms.json");
    let mut t: serde_json::Value = model::io::read_json(&transforms)?;
    if let Some(frames) = t.get_mut("frames").and_then(|f| f.as_array_mut()) {
        frames.iter_mut().filter_map(|f| f.as_object_mut()).for_each(|f| {
            f.remove("instance_mask_path");
        });
    }
    model::io::write_json(&transforms, &t)?;
    Ok(truth.iter().flat_map(|m| m.labels()).collect::<std::collections::BTreeSet<_>>().len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corruption_is_seeded_and_changes_ids_and_edges() {
        let mut ids = vec![0u16; 24 * 24];
        for y in 4..12 {
            for x in 4..20 {
                ids[y * 24 + x] = if x < 12 { 1 } else { 2 };
            }
        }
        let m = LabelMap { width: 24, height: 24, ids };
        let a = corrupt(std::slice::from_ref(&m), &Errors::default(), 3);
        assert_eq!(a, corrupt(std::slice::from_ref(&m), &Errors::default(), 3), "seeded");
        assert_ne!(a[0], m, "changed");
        assert!(a[0].labels().iter().all(|&l| l <= 44));
    }
}
