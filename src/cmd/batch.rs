//! `chatsplat batch`: many scenes as the jobs of a cluster scheduler. A manifest (TOML) lists the
//! scenes; a worker takes its shard (`--shard I/N`, or the index a Kubernetes Indexed Job or a
//! Slurm array gives it) and runs the pipeline for each of its scenes: geometry -> teacher tokens
//! -> language field -> VQA (when the scene has questions). Idempotent: a scene with a summary is
//! skipped, an interrupted one resumes from its checkpoints. Writes `OUT/<scene>/summary.json` per
//! scene and `OUT/report.json`, every scene of the manifest merged (done or pending).

use super::SceneArgs;
use super::bars::Bars;
use super::vqa::Scoring;
use anyhow::{Context, bail};
use model::Backend;
use model::run::{GeometryRun, LanguageRun, TeacherDir};
use serde::Deserialize;
use std::path::{Path, PathBuf};
use toml::Spanned;
use train::pipeline::{Recipe, TeacherModel, train_scene};

#[derive(clap::Args)]
pub struct Args {
    /// The manifest (TOML): optional `out`, `vlm`, `backend`, `geometry_iters`,
    /// `language_iters`, `tower_tail`, then one `[[scene]]` table per scene (`name`, `data`, optional
    /// `questions` and per-scene iterations). Paths are relative to the manifest's folder.
    #[arg(long)]
    pub manifest: PathBuf,
    /// This worker's shard `I/N` (0 <= I < N): the scenes at positions I, I + N, I + 2N ... of
    /// the manifest. Default: JOB_COMPLETION_INDEX and CHATSPLAT_SHARD_COUNT (a Kubernetes Indexed
    /// Job), SLURM_ARRAY_TASK_ID and SLURM_ARRAY_TASK_COUNT (a Slurm array), else 0/1.
    #[arg(long)]
    pub shard: Option<String>,
    /// Only merge the scenes' summaries into OUT/report.json (no training).
    #[arg(long)]
    pub report: bool,
}

/// The manifest file.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    /// Output folder (default: `<manifest stem>-out` beside the manifest).
    out: Option<PathBuf>,
    /// LLaVA-OneVision directory (default: the built-in model).
    vlm: Option<PathBuf>,
    backend: Option<Spanned<String>>,
    #[serde(default = "default_geometry_iters")]
    geometry_iters: usize,
    #[serde(default = "default_language_iters")]
    language_iters: usize,
    /// The vision tower's last layers left to run on the fields' tokens (`extract --tower-tail`).
    #[serde(default = "default_tower_tail")]
    tower_tail: usize,
    #[serde(default)]
    scene: Vec<SceneEntry>,
}

fn default_geometry_iters() -> usize {
    600
}

fn default_language_iters() -> usize {
    100
}

fn default_tower_tail() -> usize {
    train::teacher::DEFAULT_TOWER_TAIL
}

/// One `[[scene]]` table.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneEntry {
    name: Spanned<String>,
    /// The dataset (any format `chatsplat train` reads).
    data: Spanned<PathBuf>,
    /// A question file (default: DATA/questions.json when there is one).
    questions: Option<Spanned<PathBuf>>,
    geometry_iters: Option<usize>,
    language_iters: Option<usize>,
}

/// A scene ready to run: a job of the batch.
struct Job {
    name: String,
    data: PathBuf,
    questions: Option<PathBuf>,
    geometry_iters: usize,
    language_iters: usize,
}

/// A checked manifest.
struct Plan {
    out: PathBuf,
    vlm: Option<PathBuf>,
    backend: Backend,
    tower_tail: usize,
    scenes: Vec<Job>,
}

/// `path:line: message` for the byte offset `at` of `text`.
fn at_line(path: &Path, text: &str, at: usize, message: impl std::fmt::Display) -> anyhow::Error {
    let line = text[..at.min(text.len())].matches('\n').count() + 1;
    anyhow::anyhow!("{}:{line}: {message}", path.display())
}

/// Reads and checks the manifest: every error names the file and the line.
fn read_manifest(path: &Path) -> anyhow::Result<Plan> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let m: Manifest = toml::from_str(&text).map_err(|e| {
        let line = e.span().map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
        let msg = e.message().to_string();
        match line {
            Some(l) => anyhow::anyhow!("{}:{l}: {msg}", path.display()),
            None => anyhow::anyhow!("{}: {msg}", path.display()),
        }
    })?;
    let base = path.parent().unwrap_or(Path::new("."));
    let backend = match &m.backend {
        Some(b) => b.get_ref().parse::<Backend>().map_err(|e| at_line(path, &text, b.span().start, e))?,
        None => Backend::Ndarray,
    };
    if m.scene.is_empty() {
        bail!("{}: no [[scene]] tables: the manifest lists no scene", path.display());
    }
    if m.geometry_iters == 0 || m.language_iters == 0 {
        bail!("{}: geometry_iters and language_iters must be at least 1", path.display());
    }
    let mut scenes: Vec<Job> = Vec::new();
    for s in &m.scene {
        let name = s.name.get_ref();
        let bad = |at: usize, msg: String| at_line(path, &text, at, format!("scene `{name}`: {msg}"));
        let ok_name = !name.is_empty() && name.chars().all(|c| c.is_ascii_alphanumeric() || "._-".contains(c));
        if !ok_name || name.starts_with('.') {
            return Err(bad(s.name.span().start, "a name is letters, digits, `.`, `_` and `-` (a folder name)".into()));
        }
        if scenes.iter().any(|o| o.name == *name) {
            return Err(bad(s.name.span().start, "is listed twice".into()));
        }
        let data = base.join(s.data.get_ref());
        if !data.is_dir() {
            return Err(bad(s.data.span().start, format!("data {} is not a directory", data.display())));
        }
        // how many questions a file holds (a file that cannot be read or parsed is an error)
        let count = |p: &Path| model::io::read_json::<model::vqa::QuestionFile>(p).map(|f| f.questions.len());
        let questions = match &s.questions {
            Some(q) => {
                let p = base.join(q.get_ref());
                if !p.is_file() {
                    return Err(bad(q.span().start, format!("questions {} is not a file", p.display())));
                }
                if count(&p).map_err(|e| bad(q.span().start, e.to_string()))? == 0 {
                    return Err(bad(q.span().start, format!("questions {} holds no questions", p.display())));
                }
                Some(p)
            }
            // the dataset's own question file, when it has questions (a small capture may have none)
            None => match data.join("questions.json") {
                p if p.is_file() => (count(&p).map_err(|e| bad(s.data.span().start, e.to_string()))? > 0).then_some(p),
                _ => None,
            },
        };
        let (geometry_iters, language_iters) =
            (s.geometry_iters.unwrap_or(m.geometry_iters), s.language_iters.unwrap_or(m.language_iters));
        if geometry_iters == 0 || language_iters == 0 {
            return Err(bad(s.name.span().start, "geometry_iters and language_iters must be at least 1".into()));
        }
        scenes.push(Job { name: name.clone(), data, questions, geometry_iters, language_iters });
    }
    let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "batch".into());
    let out = m.out.as_ref().map(|o| base.join(o)).unwrap_or_else(|| base.join(format!("{stem}-out")));
    Ok(Plan { out, vlm: m.vlm.as_ref().map(|v| base.join(v)), backend, tower_tail: m.tower_tail, scenes })
}

/// `(I, N)` from `--shard I/N` or the scheduler's environment.
fn shard(arg: Option<&str>) -> anyhow::Result<(usize, usize)> {
    let env = |k: &str| std::env::var(k).ok();
    let num = |what: &str, s: &str| -> anyhow::Result<usize> {
        s.trim().parse().with_context(|| format!("{what}: `{s}` is not a whole number"))
    };
    let (i, n, from) = if let Some(s) = arg {
        return super::parse_shard(s);
    } else if let Some(i) = env("JOB_COMPLETION_INDEX") {
        let n = env("CHATSPLAT_SHARD_COUNT")
            .context("JOB_COMPLETION_INDEX is set but CHATSPLAT_SHARD_COUNT (the Job's completions) is not")?;
        (num("JOB_COMPLETION_INDEX", &i)?, num("CHATSPLAT_SHARD_COUNT", &n)?, "JOB_COMPLETION_INDEX")
    } else if let Some(i) = env("SLURM_ARRAY_TASK_ID") {
        let n =
            env("SLURM_ARRAY_TASK_COUNT").context("SLURM_ARRAY_TASK_ID is set but SLURM_ARRAY_TASK_COUNT is not")?;
        let min = env("SLURM_ARRAY_TASK_MIN").map(|m| num("SLURM_ARRAY_TASK_MIN", &m)).transpose()?.unwrap_or(0);
        let i = num("SLURM_ARRAY_TASK_ID", &i)?;
        let i = i.checked_sub(min).context("SLURM_ARRAY_TASK_ID is below SLURM_ARRAY_TASK_MIN")?;
        (i, num("SLURM_ARRAY_TASK_COUNT", &n)?, "SLURM_ARRAY_TASK_ID")
    } else {
        (0, 1, "")
    };
    if n == 0 || i >= n {
        bail!("{from} {i}/{n}: the shard index must be below the shard count (0 <= I < N)");
    }
    Ok((i, n))
}

/// Where a scene's files go.
struct JobDirs {
    dir: PathBuf,
    run: GeometryRun,
    teacher: TeacherDir,
}

impl JobDirs {
    fn new(out: &Path, name: &str) -> Self {
        let dir = out.join(name);
        Self { run: GeometryRun::new(dir.join("run")), teacher: TeacherDir::new(dir.join("teacher")), dir }
    }
    fn summary(&self) -> PathBuf {
        self.dir.join("summary.json")
    }
}

/// Runs the pipeline on one scene, resuming whatever an earlier attempt left; returns its summary.
fn run_scene(plan: &Plan, s: &Job, d: &JobDirs, shard: &str) -> anyhow::Result<serde_json::Value> {
    model::io::create_dir(&d.dir)?;
    let lang: LanguageRun = d.run.language();
    let mut seconds = serde_json::Map::new();
    let mut resumed = serde_json::Map::new();
    // a checkpoint every tenth of each stage: a killed worker loses at most that
    let mut recipe = Recipe::short(s.geometry_iters, s.language_iters);
    recipe.geometry.checkpoint_every = (s.geometry_iters / 10).max(1);
    recipe.language.checkpoint_every = (s.language_iters / 10).max(1);
    recipe.teacher.tower_tail = plan.tower_tail;
    let vlm = super::vlm_dir(plan.vlm.as_ref())?;
    let dirs = train::pipeline::SceneDirs {
        data: s.data.clone(),
        run: d.run.clone(),
        teacher: d.teacher.clone(),
        language: lang.clone(),
    };
    let mut bars = Bars::new(plan.backend);
    // resumable: finished stages are skipped, views already extracted kept
    let trained = train_scene(TeacherModel::Dir(&vlm), &dirs, &recipe, &plan.backend.device(), true, &mut bars)?;
    for (stage, secs) in &trained.seconds {
        seconds.insert(stage.name().into(), serde_json::json!((secs * 10.0).round() / 10.0));
    }
    let geometry_from = trained.geometry.as_ref().and_then(|g| g.resumed_from);
    let language_from = trained.language.as_ref().and_then(|l| l.resumed_from);
    for (stage, from) in [("geometry", geometry_from), ("language", language_from)] {
        if let Some(at) = from {
            resumed.insert(stage.into(), at.into());
        }
    }
    let t0 = std::time::Instant::now();
    let vqa = match &s.questions {
        Some(q) => {
            let scene =
                SceneArgs { run: d.run.dir.clone(), language: None, vlm: plan.vlm.clone(), backend: plan.backend };
            let scoring =
                Scoring { views: model::chat::DEFAULT_SCENE_VIEWS, max_new_tokens: 16, show: false, keep_going: true };
            let grader = eval::score::Grader::from_env()?;
            let qf = model::vqa::load_questions(q)?;
            let summary =
                super::vqa::score(&scene.open()?, (q, &qf), &d.dir.join("vqa.json"), &scoring, grader.as_ref())?;
            seconds.insert("vqa".into(), serde_json::json!((t0.elapsed().as_secs_f64() * 10.0).round() / 10.0));
            let level = |l: eval::score::LevelSummary| serde_json::json!({"mean": l.mean, "questions": l.count});
            serde_json::json!({
                "view": level(summary.view), "object": level(summary.object), "scene": level(summary.scene),
                "overall": level(summary.overall),
            })
        }
        None => serde_json::Value::Null,
    };
    Ok(serde_json::json!({
        "scene": s.name,
        "data": s.data.display().to_string(),
        "shard": shard,
        "resumed_from": resumed,
        "seconds": seconds,
        "vqa": vqa,
    }))
}

/// Merges every scene's summary (or "pending") into OUT/report.json, written through a temporary
/// file of this process (shards may finish at the same time) and a rename.
fn write_report(plan: &Plan) -> anyhow::Result<(usize, PathBuf)> {
    let mut rows = Vec::new();
    let mut done = 0;
    for s in &plan.scenes {
        let path = JobDirs::new(&plan.out, &s.name).summary();
        if path.is_file() {
            done += 1;
            let summary: serde_json::Value = model::io::read_json(&path)?;
            rows.push(serde_json::json!({"scene": s.name, "status": "done", "summary": summary}));
        } else {
            rows.push(serde_json::json!({"scene": s.name, "status": "pending"}));
        }
    }
    let report = serde_json::json!({"scenes": plan.scenes.len(), "done": done, "results": rows});
    let path = plan.out.join("report.json");
    let tmp = plan.out.join(format!("report.json.{}.tmp", std::process::id()));
    std::fs::write(&tmp, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("{}: cannot write", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("{}: cannot rename into place", path.display()))?;
    Ok((done, path))
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let plan = read_manifest(&a.manifest)?;
    let (i, n) = shard(a.shard.as_deref())?;
    model::io::create_dir(&plan.out)?;
    if a.report {
        let (done, path) = write_report(&plan)?;
        println!("{done} of {} scenes done -> {}", plan.scenes.len(), path.display());
        return Ok(());
    }
    let mine: Vec<&Job> = plan.scenes.iter().skip(i).step_by(n).collect();
    let label = format!("{i}/{n}");
    let names: Vec<&str> = mine.iter().map(|s| s.name.as_str()).collect();
    eprintln!("batch: shard {label}: {} of {} scenes: {}", mine.len(), plan.scenes.len(), names.join(", "));
    for (k, s) in mine.iter().enumerate() {
        let d = JobDirs::new(&plan.out, &s.name);
        if d.summary().is_file() {
            eprintln!("\n== scene {} ({} of {}): done earlier ({})", s.name, k + 1, mine.len(), d.summary().display());
            continue;
        }
        eprintln!("\n== scene {} ({} of {})", s.name, k + 1, mine.len());
        let summary = run_scene(&plan, s, &d, &label).with_context(|| format!("scene `{}`", s.name))?;
        model::io::write_json(&d.summary(), &summary)?;
    }
    let (done, path) = write_report(&plan)?;
    println!(
        "shard {label} finished; {done} of {} scenes of the manifest done -> {}",
        plan.scenes.len(),
        path.display()
    );
    Ok(())
}
