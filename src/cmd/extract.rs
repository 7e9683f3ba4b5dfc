//! `chatsplat extract`: teacher tokens of every training view and masked object.

use super::bars::Bars;
use anyhow::bail;
use model::Backend;
use model::data::LoadOptions;
use model::guard::Existing;
use model::run::TeacherDir;
use std::path::{Path, PathBuf};
use train::pipeline::{Observer, Stage};
use train::teacher::{ExtractOptions, NovelViews, extract};

#[derive(clap::Args)]
pub struct Args {
    /// LLaVA-OneVision directory or Hugging Face repo id (fetched into the Hugging Face cache),
    /// the teacher (default: the built-in model).
    #[arg(long)]
    pub vlm: Option<PathBuf>,
    /// Scene dataset (any format `chatsplat train` reads, e.g. from `chatsplat synth`).
    #[arg(long)]
    pub data: PathBuf,
    /// Output directory (default: DATA/teacher).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Instance masks from another tool: DIR/<image stem>.png per image (8- or 16-bit
    /// ids, 0 = background, the image's size), instead of the dataset's own; use the same as for `train`.
    #[arg(long, value_name = "DIR")]
    pub masks: Option<PathBuf>,
    /// Integer image downscale before extraction.
    #[arg(long, default_value_t = 1)]
    pub downscale: u32,
    /// Object crop margin as a fraction of the object's box, per side.
    #[arg(long, default_value_t = model::language::CROP_MARGIN)]
    pub margin: f32,
    #[arg(long, default_value_t = Backend::Ndarray)]
    pub backend: Backend,
    /// Only this worker's views of a large capture, `I/N`: those whose index is I modulo N
    /// (workers on one shared OUT); the last to finish writes the index.
    #[arg(long)]
    pub shard: Option<String>,
    /// Also teach this many novel views: the geometry run `--run` rendered at cameras between
    /// the training cameras (its RGB and rendered identity taught like a photo and its masks), so
    /// the language field is supervised where the capture has no photo.
    #[arg(long, default_value_t = 0, requires = "run")]
    pub novel_views: usize,
    /// The geometry run (`chatsplat train --out`) that renders the novel views; train the language
    /// stage on this run.
    #[arg(long)]
    pub run: Option<PathBuf>,
    /// Seed of the novel views' cameras.
    #[arg(long, default_value_t = 0)]
    pub novel_seed: u64,
    /// Keep the vision tower's state before its last K layers instead of its output (0 is the
    /// paper's teacher): a field trained on these tokens leaves those K layers to the tower,
    /// which runs them on the field's tokens at inference (not in the paper; K = 1 counts
    /// objects at new poses nearly as the photos do, but reads shapes worse).
    #[arg(long, default_value_t = train::teacher::DEFAULT_TOWER_TAIL, value_name = "K")]
    pub tower_tail: usize,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    if a.downscale == 0 || !(0.0..=2.0).contains(&a.margin) {
        bail!("--downscale must be >= 1 and --margin in [0, 2]");
    }
    let out = TeacherDir::new(a.out.clone().unwrap_or_else(|| a.data.join("teacher")));
    let vlm_dir = super::vlm_dir(a.vlm.as_ref())?;
    let mut inputs = vec![("the model directory", vlm_dir.clone())];
    inputs.extend(a.masks.iter().map(|m| ("the --masks directory", m.clone())));
    inputs.extend(a.run.iter().map(|r| ("the geometry run (--run)", r.clone())));
    // the teacher goes inside the data by default (DATA/teacher); it may not be it or hold it
    model::guard::refuse_onto_or_around("--out", &out.dir, &[("the --data directory", a.data.clone())])?;
    model::guard::output_folder("--out", &out.dir, model::guard::Kind::Teacher, Existing::GoOn, &inputs)?;
    let shard = a.shard.as_deref().map(super::parse_shard).transpose()?.unwrap_or((0, 1));
    let opts = ExtractOptions {
        margin: a.margin,
        load: LoadOptions { downscale: a.downscale, masks: a.masks.clone(), ..Default::default() },
        shard,
        novel: a.run.as_ref().map(|run| NovelViews {
            run: model::run::GeometryRun::new(run),
            count: a.novel_views,
            seed: a.novel_seed,
        }),
        tower_tail: a.tower_tail,
        ..Default::default()
    };
    teacher(&vlm_dir, &a.data, &out, &opts, a.backend)
}

/// Writes the teacher tokens of the capture in `data` (the model in `vlm_dir` as teacher) to
/// `out`, keeping views already done, with a progress bar and a summary line.
pub fn teacher(
    vlm_dir: &Path,
    data: &Path,
    out: &TeacherDir,
    opts: &ExtractOptions,
    backend: Backend,
) -> anyhow::Result<()> {
    let device = backend.device()?;
    let m = model::catch_backend("loading the model", || model::vlm::LlavaOnevision::load(vlm_dir, &device))??;
    // the plan and the progress both report to the bars, one after the other
    let bars = std::cell::RefCell::new(Bars::new(backend));
    bars.borrow_mut().start(Stage::Teacher, None);
    let t0 = std::time::Instant::now();
    let summary = model::catch_backend("extraction", || {
        extract(
            &m,
            data,
            out,
            opts,
            |plan| bars.borrow_mut().teacher_plan(plan, opts, out),
            |done, total| bars.borrow_mut().teacher(done, total),
        )
    })??;
    bars.borrow_mut().teacher_done(&summary, t0.elapsed().as_secs_f64(), out);
    Ok(())
}
