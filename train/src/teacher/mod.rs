//! Teacher targets for the language field: LLaVA-OneVision's SigLIP patch features of every
//! training view and of every masked object in it, stored as f16 safetensors (one file per view,
//! written atomically, so an interrupted extraction resumes where it stopped), indexed by
//! `teacher.json` ([`TeacherIndex`]).
//!
//! Views are the processor's base view: the whole image resized to the tower's input. Object
//! images follow the one crop rule of `model::language::crop`: the object's pixels, black
//! elsewhere, the box + margin padded to a square, resized to the tower's input.
//!
//! Novel views ([`NovelViews`]): the frozen geometry rendered at cameras between the training
//! cameras ([`novel_cameras`]), its RGB and rendered identity taught like a photo and its masks.
//! They supervise the field where the capture has no photo, which is where its tokens were
//! worst (held-out views: eval/journal/2026-11-27.md, "Where the field's tokens lose count and
//! colours").
mod extract;
mod novel;
mod read;

pub use extract::{ExtractSummary, extract};
pub use novel::{NOVEL_BETWEEN, NOVEL_NEIGHBOURS, NovelViews, gaussians_hash, novel_cameras};
pub use read::{TeacherObject, TeacherSet, TeacherViewInfo, content_hash, read_tokens};

use model::ObjectId;
use model::data::{LoadOptions, View};
use model::language::objects_in;
use std::path::PathBuf;

/// Extraction settings.
#[derive(Clone, Debug)]
pub struct ExtractOptions {
    /// Bounding-box margin as a fraction of the box size, per side.
    pub margin: f32,
    /// Objects with fewer mask pixels in a view are skipped there.
    pub min_object_pixels: usize,
    /// Instance ids that are not objects (0 = background).
    pub ignore_ids: Vec<ObjectId>,
    /// Dataset loader options (downscale etc.).
    pub load: LoadOptions,
    /// This worker's shard `(I, N)` of the views: those whose index is I modulo N (`(0, 1)`:
    /// every view). The index is written by the worker that finds every view's file complete.
    pub shard: (usize, usize),
    /// Novel views rendered from a geometry run, taught after the photos (`None`: photos only).
    pub novel: Option<NovelViews>,
    /// Keep the tower's state before its last this many layers (0: the selected hidden state, as
    /// the paper): a field trained on it leaves those layers to the tower at inference.
    pub tower_tail: usize,
}

/// The tower's layers a field leaves to the tower by default ([`ExtractOptions::tower_tail`]):
/// none, as the paper. One (`--tower-tail 1`) brings ten held-out scenes' count at new poses
/// within 1.2 points of the photos (0: 6.9 under) but reads shapes worse: on the demo scene it
/// answers 88.8 % against 94.2 % at 240 language iterations (BENCHMARKS.md, "Where the field's
/// tokens lose count and colours").
pub const DEFAULT_TOWER_TAIL: usize = 0;

impl Default for ExtractOptions {
    fn default() -> Self {
        Self {
            margin: model::language::CROP_MARGIN,
            min_object_pixels: 64,
            ignore_ids: vec![0],
            load: LoadOptions::default(),
            shard: (0, 1),
            novel: None,
            tower_tail: DEFAULT_TOWER_TAIL,
        }
    }
}

impl ExtractOptions {
    /// The objects of a view that get tokens.
    pub fn objects(&self, ids: &[ObjectId]) -> Vec<ObjectId> {
        objects_in(ids, self.min_object_pixels, &self.ignore_ids)
    }
}

/// What will be extracted for one view.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewPlan {
    pub index: usize,
    pub image: PathBuf,
    /// Object ids with enough pixels, ascending.
    pub objects: Vec<ObjectId>,
}

/// The whole job.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    pub views: Vec<ViewPlan>,
    /// Bytes of f16 tokens that will be written.
    pub bytes: u64,
    pub tokens_per_image: usize,
    pub dim: usize,
}

pub fn plan(views: &[View], grid: usize, dim: usize, opts: &ExtractOptions) -> Plan {
    let views: Vec<ViewPlan> = views
        .iter()
        .enumerate()
        .map(|(index, v)| ViewPlan {
            index,
            image: v.image_path.clone(),
            objects: v.instance_ids.as_deref().map(|m| opts.objects(m)).unwrap_or_default(),
        })
        .collect();
    let images: usize = views.iter().map(|v| 1 + v.objects.len()).sum();
    let tokens = grid * grid;
    Plan { bytes: (images * tokens * dim * 2) as u64, views, tokens_per_image: tokens, dim }
}
