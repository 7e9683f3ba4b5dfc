//! A synthetic capture made into one without labels, with a segmenter's per-view masks beside it
//! (issue 84's flow: `tests/app/cli.rs`, `tests/app/batch.rs`).

use std::path::Path;
use train::masks::{LabelMap, corrupt};

/// Takes the capture in `data` (written by `chatsplat synth`) its masks, `scene.json` and
/// questions, and writes its true masks into `per_view` with their ids shuffled per view and
/// edges moved by a pixel, the first view without a file. Returns the number of true objects.
pub fn strip_to_per_view(data: &Path, per_view: &Path) -> usize {
    let mut truth = Vec::new();
    let mut stems = Vec::new();
    let mut files: Vec<_> = std::fs::read_dir(data.join("masks")).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort();
    for p in files {
        let (w, h, ids) = model::data::read_ids16_any(&p).unwrap();
        truth.push(LabelMap { width: w as usize, height: h as usize, ids });
        stems.push(p.file_name().unwrap().to_owned());
    }
    let errors = corrupt::Errors { edge_px: 1, missing: 0.0, merged: 0.0, split: 0.0, fragments: 0 };
    std::fs::create_dir_all(per_view).unwrap();
    for (m, name) in corrupt::corrupt(&truth, &errors, 3).iter().zip(&stems).skip(1) {
        model::images::write_ids(&per_view.join(name), m.width as u32, m.height as u32, &m.ids).unwrap();
    }
    // a capture without labels: no masks, no scene.json naming objects, no questions
    std::fs::remove_dir_all(data.join("masks")).unwrap();
    for f in ["scene.json", "questions.json"] {
        let _ = std::fs::remove_file(data.join(f));
    }
    let transforms = data.join("transforms.json");
    let mut t: serde_json::Value = serde_json::from_slice(&std::fs::read(&transforms).unwrap()).unwrap();
    t["frames"].as_array_mut().unwrap().iter_mut().for_each(|f| {
        f.as_object_mut().unwrap().remove("instance_mask_path");
    });
    std::fs::write(&transforms, serde_json::to_vec_pretty(&t).unwrap()).unwrap();
    truth.iter().flat_map(|m| m.labels()).collect::<std::collections::BTreeSet<_>>().len()
}
