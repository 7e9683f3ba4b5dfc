//! The subcommands, one file each, in the order of the pipeline, and the arguments they share.

mod ask;
mod bars;
mod batch;
mod chat;
mod demo;
mod export_encoder;
mod export_ply;
mod extract;
mod find;
mod identity;
mod masks;
mod render;
mod resume;
mod serve;
mod synth;
mod train;
mod train_language;
mod train_vlm;
mod vqa;

use anyhow::Context;
use clap::{Parser, Subcommand};
use model::Backend;
use model::chat::ChatSession;
use model::run::{GeometryRun, LanguageRun};
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "chatsplat", version, about = "3D conversational Gaussian splatting in Rust on burn")]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The whole pipeline on the built-in synthetic tabletop with the built-in LLaVA-OneVision
    /// (no downloads): synth -> geometry -> teacher tokens -> language field -> chat at view,
    /// object and scene level -> VQA scoring -> encoder export.
    #[command(allow_negative_numbers = true)]
    Demo(demo::Args),
    /// Write the built-in synthetic tabletop as a dataset: ray-cast RGB views, instance masks,
    /// depth, transforms.json, scene.json and questions.json.
    #[command(allow_negative_numbers = true)]
    Synth(synth::Args),
    /// Render a Gaussian scene (an Inria-layout .ply, a Niantic .spz, or the built-in synthetic tabletop) to PNG.
    #[command(allow_negative_numbers = true)]
    Render(render::Args),
    /// Geometry stage: fit 3D Gaussians with a 16-channel identity field to a posed dataset.
    #[command(allow_negative_numbers = true)]
    Train(train::Args),
    /// Export a run's Gaussians (or one object's) as an Inria-layout .ply (with identity features as extra
    /// properties) or a compressed Niantic .spz.
    #[command(allow_negative_numbers = true)]
    ExportPly(export_ply::Args),
    /// Teacher tokens for the language field: SigLIP patch features of every training view and of
    /// every masked object, as f16 safetensors (resumable).
    #[command(allow_negative_numbers = true)]
    Extract(extract::Args),
    /// Per-view instance masks from any segmenter (ids arbitrary per view) matched across views
    /// through a geometry run's Gaussians: one id per object in every view, for `train --masks`.
    #[command(allow_negative_numbers = true)]
    Masks(masks::Args),
    /// Identity field for a run trained without masks, from masks whose ids agree across views
    /// (`chatsplat masks --out`): a new run with the same Gaussians, objects to click and chat about.
    #[command(allow_negative_numbers = true)]
    Identity(identity::Args),
    /// Language stage: train the per-Gaussian language features, the encoder and the scaling
    /// adjustment against the teacher tokens (geometry frozen).
    #[command(allow_negative_numbers = true)]
    TrainLanguage(train_language::Args),
    /// Write the encoder and scaling adjustment as safetensors (PyTorch Conv2d layout) with a JSON header.
    #[command(allow_negative_numbers = true)]
    ExportEncoder(export_encoder::Args),
    /// Train the tabletop LLaVA-OneVision from scratch on synthetic scenes (the built-in model).
    #[command(allow_negative_numbers = true)]
    TrainVlm(train_vlm::Args),
    /// Ask one question: plain LLaVA-OneVision on images (the paper's baseline), or a trained
    /// scene at view, object (click) or scene level.
    #[command(allow_negative_numbers = true)]
    Ask(ask::Args),
    /// Interactive chat with a trained scene: view, object (click) and scene level.
    #[command(allow_negative_numbers = true)]
    Chat(chat::Args),
    /// Find the objects of a trained scene that match a phrase ("red cone"), scored through the
    /// scene's own object tokens, best first.
    #[command(allow_negative_numbers = true)]
    Find(find::Args),
    /// Chat with a trained scene in the browser: look around, click an object (highlighted in
    /// red), ask about the view, the object or the whole scene; answers stream as they come.
    #[command(allow_negative_numbers = true)]
    Serve(serve::Args),
    /// Answer an annotated question file about a trained scene and score the answers (offline
    /// exact-match/keyword scorer; plus an OpenAI-compatible grader when CHATSPLAT_GRADER_URL is set).
    #[command(allow_negative_numbers = true)]
    Vqa(vqa::Args),
    /// Many scenes as cluster jobs: the pipeline (geometry, teacher, language, VQA) for each scene
    /// of a manifest in this worker's shard, resuming what an earlier attempt left; a summary per
    /// scene and a merged report.
    Batch(batch::Args),
}

/// `I/N` of a `--shard` option: worker I (from 0) of N.
pub fn parse_shard(s: &str) -> anyhow::Result<(usize, usize)> {
    let num = |x: &str| x.trim().parse::<usize>().ok();
    match s.split_once('/').and_then(|(i, n)| Some((num(i)?, num(n)?))) {
        Some((i, n)) if i < n => Ok((i, n)),
        Some((i, n)) => anyhow::bail!("--shard {i}/{n}: the shard index must be below the shard count (0 <= I < N)"),
        None => anyhow::bail!("--shard {s}: expected I/N, e.g. 0/4"),
    }
}

/// A config's range check, naming the config file when the settings came from one.
pub fn check_config(path: Option<&std::path::Path>, r: model::error::Result<()>) -> anyhow::Result<()> {
    match (r, path) {
        (Err(e), Some(p)) => Err(anyhow::anyhow!("{}: {e}", p.display())),
        (r, _) => Ok(r?),
    }
}

impl Cli {
    /// The subcommand's name, and whether it runs data-parallel on several ranks.
    pub fn name(&self) -> (&'static str, bool) {
        match self.command {
            Command::Demo(_) => ("demo", false),
            Command::Synth(_) => ("synth", false),
            Command::Render(_) => ("render", false),
            Command::Train(_) => ("train", false),
            Command::ExportPly(_) => ("export-ply", false),
            Command::Extract(_) => ("extract", false),
            Command::Masks(_) => ("masks", false),
            Command::Identity(_) => ("identity", false),
            Command::TrainLanguage(_) => ("train-language", true),
            Command::ExportEncoder(_) => ("export-encoder", false),
            Command::TrainVlm(_) => ("train-vlm", true),
            Command::Ask(_) => ("ask", false),
            Command::Chat(_) => ("chat", false),
            Command::Find(_) => ("find", false),
            Command::Serve(_) => ("serve", false),
            Command::Vqa(_) => ("vqa", false),
            Command::Batch(_) => ("batch", false),
        }
    }
}

/// Runs one command (`ranks`: this process's place in a data-parallel job, if any).
pub fn run(cli: Cli, ranks: &crate::ranks::Ranks) -> anyhow::Result<()> {
    match cli.command {
        Command::Demo(a) => demo::run(a),
        Command::Synth(a) => synth::run(a),
        Command::Render(a) => render::run(a),
        Command::Train(a) => train::run(a),
        Command::ExportPly(a) => export_ply::run(a),
        Command::Extract(a) => extract::run(a),
        Command::Masks(a) => masks::run(a),
        Command::Identity(a) => identity::run(a),
        Command::TrainLanguage(a) => train_language::run(a, ranks),
        Command::ExportEncoder(a) => export_encoder::run(a),
        Command::TrainVlm(a) => train_vlm::run(a, ranks),
        Command::Ask(a) => ask::run(a),
        Command::Chat(a) => chat::run(a),
        Command::Find(a) => find::run(a),
        Command::Serve(a) => serve::run(a),
        Command::Vqa(a) => vqa::run(a),
        Command::Batch(a) => batch::run(a),
    }
}

/// A trained scene: the geometry run, its language run and the LLaVA-OneVision to chat with.
#[derive(clap::Args, Clone)]
pub struct SceneArgs {
    /// Geometry run directory (`chatsplat train --out`) with a trained language run.
    #[arg(long)]
    pub run: PathBuf,
    /// Language run directory (default: RUN/language).
    #[arg(long)]
    pub language: Option<PathBuf>,
    /// LLaVA-OneVision directory or Hugging Face repo id, the one the teacher tokens came from
    /// (default: the model the language run was taught by, as `extract --vlm` named it; else the
    /// built-in model, see `--vlm` of `chatsplat demo`).
    #[arg(long)]
    pub vlm: Option<PathBuf>,
    /// Compute backend.
    #[arg(long, default_value_t = Backend::Ndarray)]
    pub backend: Backend,
}

impl SceneArgs {
    pub fn geometry(&self) -> GeometryRun {
        GeometryRun::new(&self.run)
    }

    pub fn language(&self) -> LanguageRun {
        self.language.as_ref().map(LanguageRun::new).unwrap_or_else(|| self.geometry().language())
    }

    /// The files of both runs that no output may overwrite.
    pub fn own_files(&self) -> Vec<(&'static str, PathBuf)> {
        self.language().own_files().into_iter().chain(self.geometry().own_files()).collect()
    }

    /// The VLM to chat with: `--vlm`, else the model the language run was taught by when it is
    /// still there (a warning when it is not), else the built-in model.
    pub fn vlm_dir(&self) -> anyhow::Result<PathBuf> {
        if self.vlm.is_some() {
            return vlm_dir(self.vlm.as_ref());
        }
        // an unreadable language run is reported by whatever opens it next
        if let Ok(state) = self.language().read_state() {
            let taught = PathBuf::from(&state.teacher_model);
            if taught.join("config.json").is_file() {
                return Ok(taught);
            }
            eprintln!(
                "warning: the language run was taught by {}, which is not there any more; trying the built-in \
                    model (give --vlm DIR, the same model, if it is elsewhere)",
                taught.display()
            );
        }
        vlm_dir(None)
    }

    /// Loads the scene and the VLM, reporting the time taken.
    pub fn open(&self) -> anyhow::Result<ChatSession> {
        let vlm = self.vlm_dir()?;
        let t0 = std::time::Instant::now();
        let device = self.backend.device()?;
        let s = model::catch_backend("loading", || {
            ChatSession::open(&self.geometry(), self.language.as_deref(), &vlm, &device)
        })??;
        eprintln!(
            "loaded {} ({} Gaussians, {} views) and {} in {:.1} s",
            self.run.display(),
            s.scene.field.len(),
            s.cameras.len(),
            vlm.display(),
            t0.elapsed().as_secs_f64()
        );
        if let Some(note) = &s.model_note {
            model::error::warn(note);
        }
        Ok(s)
    }
}

/// The VLM directory: the one given (a repo id fetched into the Hugging Face cache, `hub`), or the
/// built-in model.
pub fn vlm_dir(given: Option<&PathBuf>) -> anyhow::Result<PathBuf> {
    match given {
        Some(p) => Ok(hub::resolve(p, &hub::wanted::VLM)?),
        None => model::vlm::default_model_dir().context("no --vlm given"),
    }
}

/// How to pick tokens: `--max-new-tokens`, `--temperature`, `--top-p`, `--seed`.
#[derive(clap::Args, Clone)]
pub struct SamplingArgs {
    #[arg(long, default_value_t = 256)]
    pub max_new_tokens: usize,
    /// 0 = greedy.
    #[arg(long, default_value_t = 0.0)]
    pub temperature: f32,
    #[arg(long, default_value_t = 1.0)]
    pub top_p: f32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl SamplingArgs {
    pub fn options(&self) -> anyhow::Result<model::vlm::GenerateOptions> {
        let top_p_ok = self.top_p > 0.0 && self.top_p <= 1.0;
        let temperature_ok = self.temperature >= 0.0 && self.temperature.is_finite();
        if !(top_p_ok && temperature_ok) {
            anyhow::bail!("--top-p must be in (0, 1] and --temperature >= 0");
        }
        Ok(model::vlm::GenerateOptions {
            max_new_tokens: self.max_new_tokens,
            temperature: self.temperature,
            top_p: self.top_p,
            seed: self.seed,
            ignore_stop: false,
        })
    }
}

/// Streams a generation to stdout.
pub fn print_piece(piece: &str) {
    use std::io::Write;
    print!("{piece}");
    let _ = std::io::stdout().flush();
}
