//! One scene through the training stages, in order: [`geometry`](crate::geometry) (3DGS and the
//! identity field), [`teacher`](crate::teacher) tokens, the [`language`](crate::language) field.
//! The demo, `chatsplat batch`, `vqa-bench` and the tests' trained scene all run it; the short
//! settings they share are [`Recipe::short`]. What a caller shows while it runs (progress bars,
//! summary lines) goes through an [`Observer`]; each stage runs inside
//! [`model::catch_backend`], so a backend panic is an error naming the stage.

use crate::geometry::{self, GeometryConfig, RunSummary};
use crate::language::{LangProgress, LangSummary, LanguageTrainConfig};
use crate::masks::identity_run::{IdentityOptions, IdentitySummary, identity_run};
use crate::masks::{MatchOptions, files};
use crate::teacher::{self, ExtractOptions, ExtractSummary, Plan};
use burn::tensor::Device;
use model::data::colmap::{self, SparsePoints};
use model::data::{Dataset, LoadOptions, load_any};
use model::error::Result;
use model::run::{GeometryRun, LanguageRun, TeacherDir};
use model::vlm::LlavaOnevision;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The settings of every stage.
#[derive(Clone, Debug)]
pub struct Recipe {
    pub geometry: GeometryConfig,
    pub teacher: ExtractOptions,
    pub language: LanguageTrainConfig,
    /// How a scene given per-view masks ([`SceneDirs::objects`]) gets its identity field.
    pub identity: IdentityOptions,
}

impl Recipe {
    /// The short recipe of the demo, `batch`, `vqa-bench` and the tests' scene:
    /// [`GeometryConfig::short`], the default extraction and [`LanguageTrainConfig::short`].
    pub fn short(geometry_iters: usize, language_iters: usize) -> Self {
        Self {
            geometry: GeometryConfig::short(geometry_iters),
            teacher: ExtractOptions::default(),
            language: LanguageTrainConfig::short(language_iters),
            identity: IdentityOptions::default(),
        }
    }
}

/// Where a scene's stages read and write.
#[derive(Clone, Debug)]
pub struct SceneDirs {
    /// The posed photos (any supported format).
    pub data: PathBuf,
    pub run: GeometryRun,
    pub teacher: TeacherDir,
    pub language: LanguageRun,
    /// Per-view masks of any segmenter, for a capture without masks whose ids agree across views:
    /// the geometry is trained without them, they are matched, and `run` is the geometry with an
    /// identity field fitted from the matched masks (issue 84's flow).
    pub objects: Option<PerViewMasks>,
}

/// Where a scene's per-view masks come from and what is made of them.
#[derive(Clone, Debug)]
pub struct PerViewMasks {
    /// `<image stem>.png` per view, ids arbitrary per view (`chatsplat masks --per-view`).
    pub per_view: PathBuf,
    /// The geometry run trained without masks.
    pub bare: GeometryRun,
    /// The matched masks (`chatsplat masks --out`), read by the identity and teacher stages.
    pub matched: PathBuf,
}

impl SceneDirs {
    /// The layout of `chatsplat demo`: teacher tokens in `data/teacher`, the language run in
    /// `run/language`.
    pub fn beside(data: &Path, run: &Path) -> Self {
        let run = GeometryRun::new(run);
        let teacher = TeacherDir::new(data.join("teacher"));
        Self { data: data.to_path_buf(), teacher, language: run.language(), run, objects: None }
    }
}

/// The model the teacher tokens come from: one already loaded, or a directory loaded only if the
/// teacher stage runs.
#[derive(Clone, Copy)]
pub enum TeacherModel<'a> {
    Loaded(&'a LlavaOnevision),
    Dir(&'a Path),
}

/// A stage of [`train_scene`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    Geometry,
    /// Per-view masks matched and the identity fitted ([`SceneDirs::objects`]).
    Objects,
    Teacher,
    Language,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Stage::Geometry => "geometry",
            Stage::Objects => "objects",
            Stage::Teacher => "teacher",
            Stage::Language => "language",
        }
    }
}

/// What a caller sees of [`train_scene`]; every method does nothing by default.
pub trait Observer {
    /// A stage starts (`resumed_from`: the iteration its checkpoint holds, when resuming).
    fn start(&mut self, _stage: Stage, _resumed_from: Option<usize>) {}
    /// The dataset the geometry stage trains on, loaded.
    fn dataset(&mut self, _data: &Path, _ds: &Dataset) {}
    fn geometry(&mut self, _p: &geometry::Progress) {}
    fn geometry_done(&mut self, _s: &RunSummary, _out: &GeometryRun) {}
    /// An identity step of the objects stage (`iter` of `iters`, its cross-entropy).
    fn identity(&mut self, _iter: usize, _iters: usize, _loss: f32) {}
    fn objects_done(&mut self, _m: &files::Summary, _i: &IdentitySummary, _out: &GeometryRun) {}
    /// The extraction's plan, before any image is encoded.
    fn teacher_plan(&mut self, _plan: &Plan, _opts: &ExtractOptions, _out: &TeacherDir) {}
    fn teacher(&mut self, _done: usize, _total: usize) {}
    fn teacher_done(&mut self, _s: &ExtractSummary, _seconds: f64, _out: &TeacherDir) {}
    fn language(&mut self, _p: &LangProgress) {}
    fn language_done(&mut self, _s: &LangSummary, _cfg: &LanguageTrainConfig, _out: &LanguageRun) {}
}

/// An [`Observer`] that shows nothing.
pub struct Quiet;
impl Observer for Quiet {}

/// What [`train_scene`] did.
#[derive(Debug, Default)]
pub struct Trained {
    /// `None` for a stage that was already complete and skipped.
    pub geometry: Option<RunSummary>,
    pub objects: Option<(files::Summary, IdentitySummary)>,
    pub teacher: Option<ExtractSummary>,
    pub language: Option<LangSummary>,
    /// Wall-clock seconds of each stage that ran (or was found complete).
    pub seconds: Vec<(Stage, f64)>,
}

/// The dataset in `data` as the geometry stage reads it: COLMAP projects with their sparse points.
pub fn load_for_geometry(data: &Path, load: &LoadOptions) -> Result<(Dataset, Option<SparsePoints>)> {
    if data.join("sparse").is_dir() && !data.join("poses_bounds.npy").is_file() {
        let (ds, p) = colmap::load(data, load)?;
        Ok((ds, Some(p)))
    } else {
        Ok((load_any(data, load)?, None))
    }
}

/// Trains one scene through every stage into `dirs`. With `resume`, a stage whose metrics are
/// written is skipped (the teacher with the language stage it feeds), and one with a checkpoint
/// goes on from it; without, every stage starts afresh.
pub fn train_scene(
    vlm: TeacherModel<'_>,
    dirs: &SceneDirs,
    recipe: &Recipe,
    device: &Device,
    resume: bool,
    obs: &mut dyn Observer,
) -> Result<Trained> {
    recipe.geometry.validate()?;
    recipe.language.validate()?;
    let mut out = Trained::default();
    let t0 = Instant::now();
    // with per-view masks, the geometry without them is a run of its own
    let geometry_run = dirs.objects.as_ref().map_or(&dirs.run, |o| &o.bare);
    if !(resume && geometry_run.metrics().is_file()) {
        let again = resume && geometry_run.checkpoint().is_file() && geometry_run.state().is_file();
        obs.start(Stage::Geometry, if again { Some(geometry_run.read_state()?.iter) } else { None });
        let load = LoadOptions::default();
        let (ds, points) = load_for_geometry(&dirs.data, &load)?;
        obs.dataset(&dirs.data, &ds);
        let cfg = recipe.geometry.clone();
        let s = model::catch_backend("training", || {
            geometry::fit(&ds, points.as_ref(), &dirs.data, &load, geometry_run, cfg, device, again, |p| {
                obs.geometry(&p)
            })
        })??;
        obs.geometry_done(&s, geometry_run);
        out.geometry = Some(s);
    }
    out.seconds.push((Stage::Geometry, t0.elapsed().as_secs_f64()));
    if let Some(o) = dirs.objects.as_ref().filter(|_| !(resume && dirs.run.metrics().is_file())) {
        let t0 = Instant::now();
        obs.start(Stage::Objects, None);
        let matched = files::match_capture(
            &dirs.data,
            &o.bare,
            files::PerView::Dir(&o.per_view),
            &o.matched,
            &MatchOptions::default(),
        )?;
        let load = LoadOptions { masks: Some(o.matched.clone()), ..Default::default() };
        let (ds, _) = load_for_geometry(&dirs.data, &load)?;
        let s = model::catch_backend("the identity", || {
            let iters = recipe.identity.iters;
            identity_run(&o.bare, &ds, &dirs.data, &load, &dirs.run, &recipe.identity, device, |i, loss| {
                obs.identity(i, iters, loss)
            })
        })??;
        obs.objects_done(&matched, &s, &dirs.run);
        out.objects = Some((matched, s));
        out.seconds.push((Stage::Objects, t0.elapsed().as_secs_f64()));
    }
    if resume && dirs.language.metrics().is_file() {
        return Ok(out);
    }
    let t0 = Instant::now();
    obs.start(Stage::Teacher, None);
    let loaded;
    let m = match vlm {
        TeacherModel::Loaded(m) => m,
        TeacherModel::Dir(d) => {
            loaded = model::catch_backend("loading the model", || LlavaOnevision::load(d, device))??;
            &loaded
        }
    };
    // the teacher's object crops come from the matched masks where the capture has none
    let mut opts = recipe.teacher.clone();
    if let Some(o) = &dirs.objects {
        opts.load.masks = Some(o.matched.clone());
    }
    let opts = &opts;
    let t_encode = Instant::now();
    // the plan and the progress both report to the observer, one after the other
    let shared = std::cell::RefCell::new(&mut *obs);
    let s = model::catch_backend("extraction", || {
        teacher::extract(
            m,
            &dirs.data,
            &dirs.teacher,
            opts,
            |plan| shared.borrow_mut().teacher_plan(plan, opts, &dirs.teacher),
            |done, total| shared.borrow_mut().teacher(done, total),
        )
    })??;
    obs.teacher_done(&s, t_encode.elapsed().as_secs_f64(), &dirs.teacher);
    out.teacher = Some(s);
    out.seconds.push((Stage::Teacher, t0.elapsed().as_secs_f64()));

    let t0 = Instant::now();
    let lang = &dirs.language;
    let again = resume && lang.checkpoint().is_file() && lang.state().is_file();
    obs.start(Stage::Language, if again { Some(lang.read_state()?.iter) } else { None });
    let cfg = recipe.language.clone();
    let s = model::catch_backend("language training", || {
        crate::language::fit(&dirs.run, &dirs.teacher.dir, lang, cfg, device, again, &crate::dist::Solo, |p| {
            obs.language(&p)
        })
    })??;
    obs.language_done(&s, &recipe.language, lang);
    out.language = Some(s);
    out.seconds.push((Stage::Language, t0.elapsed().as_secs_f64()));
    Ok(out)
}
