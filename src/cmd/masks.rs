//! `chatsplat masks`: per-view instance masks from any segmenter (ids arbitrary per view; a
//! folder of them, or SAM's automatic masks made here) made into one id per object over all
//! views through a geometry run's Gaussians (`train::masks`), written as a masks folder `train
//! --masks` and `extract --masks` read.

use model::Backend;
use model::guard::{Existing, Kind};
use model::run::GeometryRun;
use sam::automatic::AutoOptions;
use scoring::progress::Progress;
use std::path::{Path, PathBuf};
use train::masks::{MatchOptions, files};

#[derive(clap::Args)]
#[command(group = clap::ArgGroup::new("source").required(true).args(["per_view", "segmenter"]))]
pub struct Args {
    /// The capture the run was trained on (its images give the masks' sizes).
    #[arg(long)]
    pub data: PathBuf,
    /// A geometry run of the capture (`chatsplat train --out`), trained with or without masks.
    #[arg(long)]
    pub run: PathBuf,
    /// The per-view masks: `<image stem>.png` per image (8- or 16-bit grayscale or palette, 0 =
    /// none, ids arbitrary per view); a view without a file is matched as showing no object.
    #[arg(long)]
    pub per_view: Option<PathBuf>,
    /// Instead of --per-view: a Segment Anything model folder (transformers' layout) or Hugging
    /// Face repo id (e.g. facebook/sam-vit-base, fetched into the Hugging Face cache) whose
    /// automatic masks of each image are matched.
    #[arg(long)]
    pub segmenter: Option<PathBuf>,
    /// With --segmenter: points per side of the prompt grid (SAM's default 32).
    #[arg(long, default_value_t = AutoOptions::default().points_per_side, requires = "segmenter")]
    pub points_per_side: usize,
    /// With --segmenter: the backend SAM runs on.
    #[arg(long, default_value_t = Backend::Flex, requires = "segmenter")]
    pub backend: Backend,
    /// With --segmenter: also keep SAM's own masks of each view, before matching, in
    /// OUT/per-view/<image stem>.png (ids arbitrary per view), to look at or to match again with
    /// --per-view without running SAM again.
    #[arg(long, requires = "segmenter")]
    pub keep_per_view: bool,
    /// The masks folder to write: `<image stem>.png` per image and masks.json.
    #[arg(long)]
    pub out: PathBuf,
    /// Each of two masks must own this share of the other's Gaussians its view sees to be one object.
    #[arg(long, default_value_t = MatchOptions::default().mutual)]
    pub mutual: f32,
    /// An object is kept when it was seen as one mask in at least this many views.
    #[arg(long, default_value_t = MatchOptions::default().min_views)]
    pub min_views: usize,
    /// Two objects whose Gaussians share one mask in at least this share of the views that see
    /// both are one object (the pieces of an object a segmenter split); higher keeps objects
    /// apart that a segmenter often merges.
    #[arg(long, default_value_t = MatchOptions::default().together)]
    pub together: f64,
    /// A Gaussian takes part in a view's overlaps when its blend weights there sum to at least
    /// this (pixels' worth); it counts by the square of that sum (at most 1), so a glimpse counts
    /// little. Lower keeps objects that lie on many small Gaussians apart.
    #[arg(long, default_value_t = MatchOptions::default().min_weight)]
    pub min_weight: f32,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    if !(0.5..=1.0).contains(&a.mutual) || a.min_views == 0 || !(0.0..=1.0).contains(&a.together) {
        anyhow::bail!("--mutual must be within 0.5..=1, --together within 0..=1 and --min-views at least 1");
    }
    if !(a.min_weight.is_finite() && a.min_weight >= 0.0) {
        anyhow::bail!("--min-weight must be a number at least 0, not {}", a.min_weight);
    }
    let run = GeometryRun::new(&a.run);
    let mut inputs = run.own_files();
    inputs.push(("the --data directory", a.data.clone()));
    if let Some(p) = &a.per_view {
        inputs.push(("the --per-view directory", p.clone()));
    }
    if a.points_per_side == 0 {
        anyhow::bail!("--points-per-side must be at least 1");
    }
    // a repo id is fetched into the Hugging Face cache (or found there)
    let segmenter = a.segmenter.as_ref().map(|p| hub::resolve(p, &hub::wanted::SAM)).transpose()?;
    if let Some(p) = &segmenter {
        inputs.push(("the --segmenter directory", p.clone()));
    }
    model::guard::output_folder("--out", &a.out, Kind::Masks, Existing::GoOn, &inputs)?;
    check_trained_on(&run, &a.data)?;
    let opts = MatchOptions {
        mutual: a.mutual,
        min_views: a.min_views,
        together: a.together,
        min_weight: a.min_weight,
        ..Default::default()
    };
    let s = match (&a.per_view, &segmenter) {
        (Some(dir), _) => files::match_capture(&a.data, &run, files::PerView::Dir(dir), &a.out, &opts)?,
        (None, Some(dir)) => {
            let sam = Segmenter::load(dir, a.backend, a.points_per_side)?;
            let total = run.read_cameras()?.image_names().len();
            let bar = Progress::new("SAM", "views");
            let (mut done, mut seconds) = (0, 0.0);
            let mut segment = |image: &Path| -> model::error::Result<(u32, u32, Vec<u16>)> {
                let t = std::time::Instant::now();
                let (w, h, ids, n) = sam.label_map(image)?;
                seconds += t.elapsed().as_secs_f64();
                if a.keep_per_view {
                    write_label_map(&a.out.join("per-view"), image, (w, h, &ids))?;
                }
                done += 1;
                bar.update_with(done, total, &format!("{n} masks in the last view"));
                Ok((w, h, ids))
            };
            let s = files::match_capture(&a.data, &run, files::PerView::Made(&mut segment), &a.out, &opts)?;
            eprintln!("SAM: {:.1} s per view", seconds / done.max(1) as f64);
            s
        }
        (None, None) => unreachable!("clap requires --per-view or --segmenter"),
    };
    for o in &s.objects {
        eprintln!(
            "object {}: {} Gaussians, {} views, confidence {:.2}",
            o.id,
            o.gaussians,
            o.views.len(),
            o.confidence
        );
    }
    if !s.views_without_masks.is_empty() {
        eprintln!("{} views had no per-view mask file (matched as showing no object)", s.views_without_masks.len());
    }
    println!(
        "{} objects over {} views ({:.0} ms per view) -> {}",
        s.objects.len(),
        s.views,
        s.per_view_ms,
        a.out.display()
    );
    Ok(())
}

/// Refuses a `--data` that is not the capture `run` was trained on; returns the run's state.
pub fn check_trained_on(run: &GeometryRun, data: &std::path::Path) -> anyhow::Result<model::run::GeometryState> {
    let state = run.read_state()?;
    let trained_on = state.data.dir.resolve(&run.dir);
    if model::io::resolved(&trained_on) != model::io::resolved(data) {
        anyhow::bail!(
            "{}: the run was trained on {}, not on --data {}",
            run.state().display(),
            trained_on.display(),
            data.display()
        );
    }
    Ok(state)
}

/// Segment Anything's automatic masks of an image as one label map (larger masks painted first).
pub struct Segmenter {
    sam: sam::Sam,
    device: burn::tensor::Device,
    auto: AutoOptions,
}

impl Segmenter {
    /// The SAM folder `dir` on `backend`, `points_per_side` prompts a side.
    pub fn load(dir: &Path, backend: Backend, points_per_side: usize) -> anyhow::Result<Self> {
        let device = backend.device()?;
        let sam = model::catch_backend("loading SAM", || sam::Sam::load(dir, &device))??;
        Ok(Self { sam, device, auto: AutoOptions { points_per_side, ..Default::default() } })
    }

    /// `(width, height, ids, masks)` of the image at `path`.
    pub fn label_map(&self, path: &Path) -> model::error::Result<(u32, u32, Vec<u16>, usize)> {
        let img = model::data::read_rgb_any(path)?;
        let masks = model::catch_backend("SAM", || self.sam.automatic_masks(&img, &self.auto, &self.device))
            .map_err(|e| model::error::Error::invalid(path, format!("SAM failed on it: {e}")))?;
        let ids = sam::automatic::label_map(&masks, img.width * img.height);
        Ok((img.width as u32, img.height as u32, ids, masks.len()))
    }
}

/// Writes `dir/<image stem>.png`, the label map of `image`.
pub fn write_label_map(dir: &Path, image: &Path, (w, h, ids): (u32, u32, &[u16])) -> model::error::Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| model::error::Error::io(dir, "cannot create", e))?;
    let stem = image.file_stem().unwrap_or_default().to_string_lossy();
    model::images::write_ids(&dir.join(format!("{stem}.png")), w, h, ids)
}
