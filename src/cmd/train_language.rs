//! `chatsplat train-language`: the language stage.

use super::bars::Bars;
use anyhow::bail;
use model::Backend;
use model::guard::{Existing, Kind};
use model::run::{GeometryRun, LanguageRun, TeacherDir};
use serde_json::json;
use std::path::{Path, PathBuf};
use train::language::{LanguageTrainConfig, fit as train_field};
use train::pipeline::{Observer, Stage};

#[derive(clap::Args)]
pub struct Args {
    /// Geometry run directory (`chatsplat train --out`).
    #[arg(long)]
    pub run: PathBuf,
    /// Teacher directory (`chatsplat extract --out`).
    #[arg(long)]
    pub teacher: PathBuf,
    /// Language run directory (default: RUN/language).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long)]
    pub iters: Option<usize>,
    /// Language feature channels per level (paper: 32).
    #[arg(long)]
    pub channels: Option<usize>,
    #[arg(long, default_value_t = Backend::Ndarray)]
    pub backend: Backend,
    /// Continue from the language run's last checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// A config.json with any LanguageTrainConfig fields (others keep their defaults).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Keep every Gaussian for the language maps. By default the run is compacted after training:
    /// the fewest Gaussians (by language contribution) whose training views' token L1 stays
    /// within `compact_tolerance` (3 %) of the whole field's are written to compact.json, and
    /// chat, ask, vqa and serve render language maps from those alone.
    #[arg(long)]
    pub no_compact: bool,
}

pub fn run(a: Args, ranks: &crate::ranks::Ranks) -> anyhow::Result<()> {
    let mut cfg = match &a.config {
        Some(p) => model::io::read_config::<LanguageTrainConfig>(p)?,
        None => LanguageTrainConfig::default(),
    };
    if let Some(n) = a.iters {
        cfg.iters = n;
    }
    if let Some(c) = a.channels {
        if c == 0 {
            bail!("--channels must be >= 1");
        }
        cfg.field.view_channels = c;
        cfg.field.object_channels = c;
    }
    super::check_config(a.config.as_deref(), cfg.validate())?;
    let geometry = GeometryRun::new(&a.run);
    let out = a.out.as_ref().map(LanguageRun::new).unwrap_or_else(|| geometry.language());
    let mut inputs = geometry.own_files();
    inputs.push(("the --teacher directory", a.teacher.clone()));
    let existing = if a.resume {
        Existing::GoOn
    } else {
        Existing::Refuse { instead: "--resume goes on with it; a new language run needs a new or empty --out" }
    };
    model::guard::output_folder("--out", &out.dir, Kind::LanguageRun, existing, &inputs)?;
    if a.resume && out.config().is_file() {
        let saved = model::io::read_json::<LanguageTrainConfig>(&out.config())?;
        let options: Vec<_> = a
            .channels
            .iter()
            .flat_map(|&c| {
                ["field.view_channels", "field.object_channels"].map(|k| (k, format!("--channels {c}"), json!(c)))
            })
            .collect();
        // what the stage takes from the teacher whatever was asked, an automatic patch, and the
        // channels of a field without lifting (the teacher's width)
        let resolved = |key: &str, asked: &serde_json::Value| {
            let from_teacher = ["grid", "dim", "teacher_image", "teacher_patch", "tower_tail"];
            let channels = ["field.view_channels", "field.object_channels"].contains(&key);
            key.strip_prefix("field.").is_some_and(|k| from_teacher.contains(&k))
                || (key == "field.patch" && asked.as_u64() == Some(0))
                || (channels && !saved.field.lifting)
        };
        super::resume::refuse_changes(&out.config(), &saved, a.config.as_deref(), &options, resolved)?;
        refuse_other_teacher(&out, &a.teacher)?;
        if a.iters.is_none() {
            // resuming without --iters: the run's own total
            cfg.iters = saved.iters;
        }
        cfg.compact_tolerance = saved.compact_tolerance;
    }
    if a.no_compact {
        cfg.compact_tolerance = 0.0;
    }
    fit(&geometry, &a.teacher, &out, cfg, a.backend, a.resume, ranks)
}

/// Refuses `--teacher` on a resume when it is not the teacher the run was trained on (the same
/// directory, or a copy of it: the same index).
fn refuse_other_teacher(out: &LanguageRun, teacher: &Path) -> anyhow::Result<()> {
    let state = out.read_state()?;
    let was = state.teacher.resolve(&out.dir);
    let same_dir = std::fs::canonicalize(&was).ok().is_some_and(|w| std::fs::canonicalize(teacher).ok() == Some(w));
    let index = |d: &Path| std::fs::read(TeacherDir::new(d).index()).ok();
    if same_dir || index(&was).is_some_and(|w| index(teacher) == Some(w)) {
        return Ok(());
    }
    bail!(
        "--teacher {}: the language run {} was trained on the teacher in {}; --resume goes on with that one. \
         Resume with --teacher {}, or train a new run into another --out",
        teacher.display(),
        out.dir.display(),
        was.display(),
        was.display()
    )
}

/// Trains the language field of the geometry run `geometry` against the teacher tokens in
/// `teacher` into `out` (data-parallel over `ranks`), with a progress bar and summary lines.
pub fn fit(
    geometry: &GeometryRun,
    teacher: &Path,
    out: &LanguageRun,
    cfg: LanguageTrainConfig,
    backend: Backend,
    resume: bool,
    ranks: &crate::ranks::Ranks,
) -> anyhow::Result<()> {
    cfg.validate()?;
    let device = backend.device()?;
    let c = ranks.collective();
    if c.size() > 1 && c.is_root() {
        eprintln!(
            "train-language: data-parallel on {} ranks ({} views per step, split between them)",
            c.size(),
            cfg.views_per_step
        );
    }
    let mut bars = Bars::new(backend);
    bars.start(Stage::Language, None);
    let shown = cfg.clone();
    let t0 = std::time::Instant::now();
    let s = model::catch_backend("language training", || {
        train_field(geometry, teacher, out, cfg, &device, resume, c, |p| bars.language(&p))
    })??;
    ranks.report(t0.elapsed().as_secs_f64());
    if c.is_root() {
        bars.language_done(&s, &shown, out);
    }
    Ok(())
}
