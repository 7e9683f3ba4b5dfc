//! `chatsplat masks`: per-view instance masks from any segmenter (ids arbitrary per view) made
//! into one id per object over all views through a geometry run's Gaussians
//! (`train::masks`), written as a masks folder `train --masks` and `extract --masks` read.

use model::guard::{Existing, Kind};
use model::run::GeometryRun;
use std::path::PathBuf;
use train::masks::{MatchOptions, files};

#[derive(clap::Args)]
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
    pub per_view: PathBuf,
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
}

pub fn run(a: Args) -> anyhow::Result<()> {
    if !(0.5..=1.0).contains(&a.mutual) || a.min_views == 0 || !(0.0..=1.0).contains(&a.together) {
        anyhow::bail!("--mutual must be within 0.5..=1, --together within 0..=1 and --min-views at least 1");
    }
    let run = GeometryRun::new(&a.run);
    let mut inputs = run.own_files();
    inputs.push(("the --data directory", a.data.clone()));
    inputs.push(("the --per-view directory", a.per_view.clone()));
    model::guard::output_folder("--out", &a.out, Kind::Masks, Existing::GoOn, &inputs)?;
    check_trained_on(&run, &a.data)?;
    let opts = MatchOptions { mutual: a.mutual, min_views: a.min_views, together: a.together, ..Default::default() };
    let s = files::match_capture(&a.data, &run, &a.per_view, &a.out, &opts)?;
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
