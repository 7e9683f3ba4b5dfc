//! `chatsplat ask`: one question, to plain LLaVA-OneVision on images (the paper's baseline) or to
//! a trained scene at view, object (click) or scene level.

use super::{SamplingArgs, SceneArgs, print_piece};
use anyhow::bail;
use model::Backend;
use model::chat::{ChatSession, DEFAULT_SCENE_VIEWS, Target};
use model::vlm::{GenerateOptions, LlavaOnevision};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// LLaVA-OneVision directory or Hugging Face repo id, e.g.
    /// llava-hf/llava-onevision-qwen2-{0.5b,7b}-ov-hf, fetched into the Hugging Face cache
    /// (default: the built-in model).
    #[arg(long)]
    pub vlm: Option<PathBuf>,
    /// PNG image to ask about; repeat for a multi-image prompt (one base view + newline per image,
    /// LLaVA-OneVision's multi-image layout). Either images or `--run`.
    #[arg(long)]
    pub image: Vec<PathBuf>,
    /// A trained ChatSplat scene (geometry run directory with a `language/` run): the question
    /// goes to the scene's tokens instead of an image.
    #[arg(long)]
    pub run: Option<PathBuf>,
    /// Language run directory (default: RUN/language).
    #[arg(long)]
    pub language: Option<PathBuf>,
    /// View to ask about (training views first, then held-out views).
    #[arg(long, default_value_t = 0)]
    pub view: usize,
    /// Object level: the object under pixel X Y of the view (its highlighted view is written as PNG).
    #[arg(long, num_args = 2, value_names = ["X", "Y"])]
    pub object: Option<Vec<usize>>,
    /// Scene level: tokens of `--views` views spread around the scene.
    #[arg(long)]
    pub scene: bool,
    /// Views for scene level.
    #[arg(long, default_value_t = DEFAULT_SCENE_VIEWS)]
    pub views: usize,
    /// The question.
    pub question: String,
    #[command(flatten)]
    pub sampling: SamplingArgs,
    #[arg(long, default_value_t = Backend::Ndarray)]
    pub backend: Backend,
    /// Hold the model's linear layers and embeddings in f16, as checkpoints store them (half the
    /// memory: the 7B model in about 15 GiB instead of 30); with `--image` on `--backend flex`, or
    /// on `wgpu` where the adapter's shaders take f16.
    #[arg(long)]
    pub half: bool,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    if a.question.trim().is_empty() {
        bail!("the question is empty: ask something, e.g. chatsplat ask --view 0 --run RUN \"What is on the table?\"");
    }
    if a.half && a.run.is_some() {
        bail!("--half applies to --image (plain LLaVA-OneVision); a scene's model loads in f32");
    }
    if a.half && !a.backend.holds_half() {
        bail!(
            "--half needs f16 matmuls: add --backend flex, or wgpu on an adapter with f16 shaders \
             ({} here holds only f32)",
            a.backend
        );
    }
    match (&a.run, a.image.is_empty()) {
        (Some(_), false) => bail!("--image and --run exclude each other: ask about images or about a trained scene"),
        (Some(run), true) => ask_scene(&a, run.clone()),
        (None, false) => ask_images(&a),
        (None, true) => bail!("give --image PNG (plain LLaVA-OneVision) or --run DIR (a trained ChatSplat scene)"),
    }
}

fn ask_images(a: &Args) -> anyhow::Result<()> {
    let imgs = a.image.iter().map(|p| model::images::read_rgb_image(p)).collect::<Result<Vec<_>, _>>()?;
    let opts = a.sampling.options()?;
    let device = a.backend.device()?;
    let vlm_dir = super::vlm_dir(a.vlm.as_ref())?;
    let t0 = std::time::Instant::now();
    let m = model::catch_backend("loading the model", || LlavaOnevision::load_with(&vlm_dir, &device, a.half))??;
    eprintln!("loaded {} in {:.1} s", vlm_dir.display(), t0.elapsed().as_secs_f64());
    let t1 = std::time::Instant::now();
    let out = model::catch_backend("generation", || -> model::Result<_> {
        let multi = imgs.len() > 1;
        let embeds: Vec<_> = imgs.iter().map(|i| m.image_embeds(&m.preprocess(i, multi))).collect();
        let prompt = m.prompt_embeds(&a.question, &embeds)?;
        Ok(m.generate(prompt, &opts, print_piece)?)
    })??;
    println!();
    eprintln!(
        "{} prompt tokens, {} new tokens{} in {:.2} s on {}",
        out.prompt_tokens,
        out.ids.len(),
        if out.stopped { " (stopped at <|im_end|>)" } else { "" },
        t1.elapsed().as_secs_f64(),
        a.backend
    );
    Ok(())
}

fn ask_scene(a: &Args, run: PathBuf) -> anyhow::Result<()> {
    let opts = a.sampling.options()?;
    let scene = SceneArgs { run, language: a.language.clone(), vlm: a.vlm.clone(), backend: a.backend };
    let s = scene.open()?;
    s.check_max_new_tokens("--max-new-tokens", opts.max_new_tokens)?;
    let camera = *s.camera(a.view)?;
    let target = match (&a.object, a.scene) {
        (Some(_), true) => bail!("--object and --scene exclude each other"),
        (Some(xy), false) => match s.click(&camera, xy[0], xy[1])? {
            Some(p) => Target::Object(p),
            None => bail!("pixel ({}, {}) of view {} shows no object", xy[0], xy[1], a.view),
        },
        (None, true) => s.scene_target(a.views)?,
        (None, false) => Target::View(camera),
    };
    answer(&s, a.view, &target, &a.question, &opts)
}

/// Asks `question` about `target` (seen from view `view`) of the opened scene `s`, streaming the
/// answer to stdout; an object's highlighted view is written to the language run.
pub fn answer(
    s: &ChatSession,
    view: usize,
    target: &Target,
    question: &str,
    opts: &GenerateOptions,
) -> anyhow::Result<()> {
    if let Some(note) = model::known::unknown_question_note(&s.vlm, target, question) {
        eprintln!("note: {note}");
    }
    let t1 = std::time::Instant::now();
    let out = model::catch_backend("generation", || s.ask(target, question, opts, print_piece))??;
    println!();
    if s.model_note.is_some() {
        eprintln!("(the built-in tabletop model's answer: see the warning above)");
    }
    eprintln!(
        "{} prompt tokens, {} new tokens in {:.2} s",
        out.prompt_tokens,
        out.ids.len(),
        t1.elapsed().as_secs_f64()
    );
    if let Target::Object(p) = target {
        let path = s.language.picked(view, p.id);
        s.show(s.camera(view)?, Some(p), &path)?;
        eprintln!("picked object {}; highlighted view -> {}", p.id, path.display());
    }
    Ok(())
}
