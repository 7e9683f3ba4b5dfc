//! `chatsplat demo`: the whole pipeline on the built-in scene, each step the subcommand a user
//! would run: synth -> train -> extract -> train-language -> ask (view, object, scene) -> vqa ->
//! export-encoder.

use super::{SamplingArgs, SceneArgs};
use model::Backend;
use model::run::GeometryRun;
use model::vqa::{Level, load_questions};
use std::path::PathBuf;
use train::geometry::GeometryConfig;
use train::language::LanguageTrainConfig;

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
    #[arg(long, default_value_t = Backend::Ndarray)]
    backend: Backend,
}

fn step(n: usize, what: &str) {
    eprintln!("\n== {n}/7 {what}");
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let vlm = super::vlm_dir(a.vlm.as_ref())?;
    let (data, run) = (a.out.join("data"), GeometryRun::new(a.out.join("run")));
    let lang = run.language();
    model::io::create_dir(&a.out)?;
    step(1, "synthetic tabletop (32 views, 96x96)");
    super::synth::run(super::synth::Args {
        seed: model::data::synth::DEFAULT_SEED,
        out: data.clone(),
        views: 32,
        width: 96,
        height: 96,
    })?;

    step(2, "geometry stage: 3DGS + identity field");
    let geometry = GeometryConfig::short(a.iters);
    let geometry_cfg = a.out.join("geometry_config.json");
    model::io::write_json(&geometry_cfg, &geometry)?;
    super::train::run(super::train::Args {
        data: data.clone(),
        out: run.dir.clone(),
        iters: None,
        backend: a.backend,
        downscale: 1,
        masks: None,
        resume: false,
        config: Some(geometry_cfg),
        background: "white".into(),
    })?;

    step(3, "teacher tokens (SigLIP features of every training view and masked object)");
    super::extract::run(super::extract::Args {
        vlm: Some(vlm.clone()),
        data: data.clone(),
        out: Some(data.join("teacher")),
        downscale: 1,
        masks: None,
        margin: model::language::CROP_MARGIN,
        shard: None,
        backend: a.backend,
    })?;

    step(4, "language field, encoder and scaling adjustment");
    let mut language = LanguageTrainConfig { warmup_iters: (a.language_iters / 10).max(1), ..Default::default() };
    language.field.patch = 0; // render maps at the views' own resolution
    let language_cfg = a.out.join("language_config.json");
    model::io::write_json(&language_cfg, &language)?;
    super::train_language::run(
        super::train_language::Args {
            run: run.dir.clone(),
            teacher: data.join("teacher"),
            out: None,
            iters: Some(a.language_iters),
            channels: None,
            backend: a.backend,
            resume: false,
            config: Some(language_cfg),
            no_compact: false,
        },
        &crate::ranks::Ranks::Solo,
    )?;

    step(5, "chat: view, object (click) and scene level");
    let ask = |view: usize, object: Option<Vec<usize>>, scene: bool, q: &str| super::ask::Args {
        vlm: Some(vlm.clone()),
        image: vec![],
        run: Some(run.dir.clone()),
        language: None,
        view,
        object,
        scene,
        views: 3,
        question: q.into(),
        sampling: SamplingArgs { max_new_tokens: 16, temperature: 0.0, top_p: 1.0, seed: 0 },
        backend: a.backend,
        half: false,
    };
    // the questions the built-in model knows, on the first view the question file asks about
    // and at the first object it clicks (a held-out view: what the user sees from a new angle)
    let qf = load_questions(&data.join("questions.json"))?;
    let images = run.read_cameras()?.image_names();
    let in_run = |v: Option<usize>| model::vqa::scene_view(&qf, &images, v.unwrap_or(0));
    let view = in_run(qf.questions.iter().find(|q| q.level == Level::View).and_then(|q| q.view))?;
    let click = match qf.questions.iter().find(|q| q.level == Level::Object) {
        Some(q) => q.object.map(|xy| in_run(q.view).map(|v| (v, xy))).transpose()?,
        None => None,
    };
    eprintln!("[view {view}] What objects are there?");
    super::ask::run(ask(view, None, false, "What objects are there?"))?;
    if let Some((v, [x, y])) = click {
        eprintln!("[view {v}, click ({x}, {y})] What is this?");
        super::ask::run(ask(v, Some(vec![x as usize, y as usize]), false, "What is this?"))?;
    }
    eprintln!("[scene, 3 views] What objects are in the scene?");
    super::ask::run(ask(0, None, true, "What objects are in the scene?"))?;

    step(6, "VQA on the generated question file (offline scorer)");
    let scene = SceneArgs { run: run.dir.clone(), language: None, vlm: Some(vlm.clone()), backend: a.backend };
    super::vqa::run(super::vqa::Args {
        scene,
        questions: data.join("questions.json"),
        out: None,
        views: 3,
        max_new_tokens: 16,
        show: true,
        keep_going: true, // a click the reconstruction misses is scored 0 and listed, not fatal
    })?;

    step(7, "encoder export");
    super::export_encoder::run(super::export_encoder::Args {
        run: run.dir.clone(),
        language: None,
        out: lang.dir.join("encoder.safetensors"),
    })?;
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
