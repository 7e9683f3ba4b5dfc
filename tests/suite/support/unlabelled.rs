//! A synthetic capture made into one without labels, with a segmenter's per-view masks beside it
//! (issue 84's flow: `tests/app/cli.rs`, `tests/app/batch.rs`).

use std::path::Path;
use train::masks::corrupt;

/// Takes the capture in `data` (written by `chatsplat synth`) its masks, `scene.json` and
/// questions, and writes its true masks into `per_view` with their ids shuffled per view and
/// edges moved by a pixel, the first view without a file. Returns the number of true objects.
pub fn strip_to_per_view(data: &Path, per_view: &Path) -> usize {
    let errors = corrupt::Errors { edge_px: 1, missing: 0.0, merged: 0.0, split: 0.0, fragments: 0 };
    let objects = corrupt::strip_capture(data, per_view, &errors, 3).unwrap();
    let mut files: Vec<_> = std::fs::read_dir(per_view).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort();
    std::fs::remove_file(&files[0]).unwrap();
    objects
}
