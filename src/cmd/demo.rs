//! `chatsplat demo`: the whole pipeline on the built-in scene, each step what the subcommand a
//! user would run does (synth -> train -> extract -> train-language -> ask at view, object and
//! scene level -> vqa -> export-encoder), called with typed settings; the scene and the model
//! are loaded once for the questions and the question file. Before the export, the paper's
//! comparison in miniature: the question file's single questions answered from the held-out
//! photos, from the geometry's renders through the vision tower, and from ChatSplat's tokens
//! (`scoring::compare`), exact match per level and views/s of each path, also in
//! `OUT/summary.json`.

use super::SceneArgs;
use super::bars::Bars;
use super::vqa::Scoring;
use model::Backend;
use model::chat::Target;
use model::data::synth::SynthOptions;
use model::run::GeometryRun;
use model::vlm::GenerateOptions;
use model::vqa::{Level, load_questions};
use scoring::compare;
use std::path::PathBuf;
use train::pipeline::{Recipe, SceneDirs, Stage, TeacherModel, train_scene};

#[derive(clap::Args)]
pub struct Args {
    /// Output directory (data/, run/, run/language/).
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// LLaVA-OneVision directory (default: the built-in model; give a real
    /// llava-onevision-qwen2-0.5b-ov-hf directory for a real one).
    #[arg(long)]
    vlm: Option<PathBuf>,
    /// Geometry iterations.
    #[arg(long, default_value_t = 600)]
    iters: usize,
    /// Language-field iterations.
    #[arg(long, default_value_t = 100)]
    language_iters: usize,
    /// The compute backend: flex by default (burn-flex, the faster CPU backend here: the demo ran
    /// in 361 s on flex against 413 s on ndarray, 2026-12-06, BENCHMARKS.md).
    #[arg(long, default_value_t = Backend::Flex)]
    backend: Backend,
}

/// The largest side the views take from the model's input size (a real 384-px model's would make
/// the geometry stage 16 times slower than 96-px views).
const MAX_SIDE: usize = 128;

fn step(n: usize, what: &str) {
    eprintln!("\n== {n}/8 {what}");
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let vlm = super::vlm_dir(a.vlm.as_ref())?;
    let (data, run) = (a.out.join("data"), GeometryRun::new(a.out.join("run")));
    let lang = run.language();
    // an earlier demo goes on (what it finished is kept); anything else there is refused
    let inputs = [("the model directory", vlm.clone())];
    model::guard::output_folder("--out", &a.out, model::guard::Kind::Demo, model::guard::Existing::GoOn, &inputs)?;
    model::io::create_dir(&a.out)?;
    // views the size the model reads (the built-in: no resampling between render and tower)
    let side = model::vlm::config::read_llava_config(&vlm)?.vision.image_size.min(MAX_SIDE) as u32;
    let recipe = Recipe::short(a.iters, a.language_iters);
    // the demo's settings, as files a user can give to `--config` (first: they mark the folder
    // as a demo's)
    model::io::write_json(&a.out.join("geometry_config.json"), &recipe.geometry)?;
    model::io::write_json(&a.out.join("language_config.json"), &recipe.language)?;
    step(1, &format!("synthetic tabletop (32 views, {side}x{side})"));
    let scene = SynthOptions { views: 32, width: side, height: side, ..Default::default() };
    super::synth::write(&data, &scene)?;

    let mut bars = Bars::with_heading(a.backend, |stage| match stage {
        Stage::Geometry => step(2, "geometry stage: 3DGS + identity field"),
        // the demo's capture has masks: no per-view masks to match
        Stage::Objects => {}
        Stage::Teacher => step(3, "teacher tokens (SigLIP features of every training view and masked object)"),
        Stage::Language => step(4, "language field, encoder and scaling adjustment"),
    });
    let dirs = SceneDirs::beside(&data, &run.dir);
    train_scene(TeacherModel::Dir(&vlm), &dirs, &recipe, &a.backend.device()?, false, &mut bars)?;

    step(5, "chat: view, object (click) and scene level");
    let scene = SceneArgs { run: run.dir.clone(), language: None, vlm: Some(vlm), backend: a.backend };
    let s = scene.open()?;
    let opts = GenerateOptions { max_new_tokens: 16, ..Default::default() };
    // the questions the built-in model knows, on the first view the question file asks about
    // and at the first object it clicks (a held-out view: what the user sees from a new angle)
    let questions = data.join("questions.json");
    let qf = load_questions(&questions)?;
    let images = run.read_cameras()?.image_names();
    let in_run = |v: Option<usize>| model::vqa::scene_view(&qf, &images, v.unwrap_or(0));
    let view = in_run(qf.questions.iter().find(|q| q.level == Level::View).and_then(|q| q.view))?;
    let click = match qf.questions.iter().find(|q| q.level == Level::Object) {
        Some(q) => q.object.map(|xy| in_run(q.view).map(|v| (v, xy))).transpose()?,
        None => None,
    };
    eprintln!("[view {view}] What objects are there?");
    super::ask::answer(&s, view, &Target::View(*s.camera(view)?), "What objects are there?", &opts)?;
    if let Some((v, [x, y])) = click {
        eprintln!("[view {v}, click ({x}, {y})] What is this?");
        match s.click(s.camera(v)?, x as usize, y as usize)? {
            Some(p) => super::ask::answer(&s, v, &Target::Object(p), "What is this?", &opts)?,
            None => eprintln!("pixel ({x}, {y}) of view {v} shows no object in the reconstruction"),
        }
    }
    eprintln!("[scene, 3 views] What objects are in the scene?");
    super::ask::answer(&s, 0, &s.scene_target(3)?, "What objects are in the scene?", &opts)?;

    step(6, "VQA on the generated question file (offline scorer)");
    // a click the reconstruction misses is scored 0 and listed, not fatal
    let scoring = Scoring {
        views: 3,
        max_new_tokens: 16,
        show: true,
        keep_going: true,
        find_threshold: model::find::DEFAULT_THRESHOLD,
    };
    let grader = scoring::score::Grader::from_env()?;
    let names = model::find::ObjectNames::of_run(&run, &mut Vec::new());
    super::vqa::score(&s, (&questions, &qf), &lang.vqa(), &scoring, names, grader.as_ref())?;

    step(7, "the paper's comparison on the held-out views: images, rendered RGB, ChatSplat's tokens");
    let ds = model::data::load_any(&data, &model::data::LoadOptions::default())?;
    let compared = model::catch_backend("the comparison", || compare::three_ways(&s, &qf, &ds))??;
    println!("{}", compare::table(&compared));
    let summary = a.out.join("summary.json");
    model::io::write_json(&summary, &compare::summary_json(&compared, (&questions, &qf)))?;
    println!("(one answer per question from each source; as JSON in {})", summary.display());

    step(8, "encoder export");
    super::export_encoder::export(&lang, &lang.dir.join("encoder.safetensors"))?;
    println!(
        "\ndemo done: renders in {}, language run in {}, highlighted pick in {}",
        run.renders().display(),
        lang.dir.display(),
        lang.dir.display()
    );
    let vlm_arg = a.vlm.as_ref().map(|v| format!(" --vlm {}", v.display())).unwrap_or_default();
    println!(
        "\nLook at the scene, click objects and chat with it in the browser:\n  chatsplat serve --run {}{vlm_arg}\n\
         (in a checkout: cargo run --release -- serve --run {}{vlm_arg}), then open http://127.0.0.1:7860/",
        run.dir.display(),
        run.dir.display()
    );
    Ok(())
}
