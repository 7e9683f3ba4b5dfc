//! `chatsplat batch`: many scenes as the jobs of a cluster scheduler. A manifest (TOML) lists the
//! scenes; a worker takes its shard (`--shard I/N`, or the index a Kubernetes Indexed Job or a
//! Slurm array gives it) and runs the pipeline for each of its scenes: geometry -> (per-view masks
//! matched and the identity fitted, when the scene gives `per_view_masks`) -> teacher tokens ->
//! language field -> VQA (when the scene has questions). Idempotent: a scene whose summary
//! carries the fingerprint of its inputs and settings is skipped (other data or settings train it
//! again, the earlier results kept aside), an interrupted one resumes from its checkpoints, and a
//! scene that fails is recorded (`OUT/<scene>/failed.json`) while the shard goes on. Writes
//! `OUT/<scene>/summary.json` per scene and `OUT/report.json`, every scene of the manifest merged
//! (done, failed or pending).

use super::SceneArgs;
use super::bars::Bars;
use super::vqa::Scoring;
use anyhow::{Context, bail};
use model::run::{GeometryRun, LanguageRun, TeacherDir};
use scoring::score::LevelSummary;
use std::path::{Path, PathBuf};
use train::manifest::{Job, Plan};
use train::pipeline::{Recipe, TeacherModel, train_scene};

#[derive(clap::Args)]
pub struct Args {
    /// The manifest (TOML): optional `out`, `vlm`, `segmenter`, `backend`, `geometry_iters`,
    /// `language_iters`, `tower_tail`, then one `[[scene]]` table per scene (`name`, `data`, optional
    /// `questions`, `per_view_masks` and per-scene iterations). Paths are relative to the manifest's folder;
    /// `vlm` and `segmenter` may be Hugging Face repo ids. With `segmenter`, a scene with no masks and no
    /// `per_view_masks` gets SAM's automatic masks of each image (kept in its `per-view/`), matched.
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
    fn failed(&self) -> PathBuf {
        self.dir.join("failed.json")
    }
}

/// The fingerprint of what makes a scene's results (16 hex digits): every file of its data folder
/// (name, size and first 64 KiB), its question file, the model folder and the settings.
fn job_fingerprint(plan: &Plan, s: &Job, vlm: &Path) -> anyhow::Result<String> {
    // only folders and regular files (links followed): a named pipe, socket or device would block
    // the read or never end, and is refused by name
    fn files(dir: &Path, out: &mut Vec<PathBuf>) -> anyhow::Result<()> {
        for e in std::fs::read_dir(dir).with_context(|| format!("{}: cannot list", dir.display()))? {
            let p = e.with_context(|| format!("{}: cannot list", dir.display()))?.path();
            let kind = std::fs::metadata(&p).with_context(|| format!("{}: cannot read", p.display()))?.file_type();
            if kind.is_dir() {
                files(&p, out)?
            } else if kind.is_file() {
                out.push(p)
            } else {
                bail!("{}: is not a regular file (a pipe, socket or device): a dataset holds files", p.display());
            }
        }
        Ok(())
    }
    let mut all = Vec::new();
    files(&s.data, &mut all)?;
    if let Some(p) = &s.per_view_masks {
        files(p, &mut all)?;
    }
    all.sort();
    all.extend(s.questions.clone());
    let mut h = model::data::Fnv::default();
    for f in &all {
        use std::io::Read;
        h.eat(f.strip_prefix(&s.data).unwrap_or(f).to_string_lossy().as_bytes());
        let file = std::fs::File::open(f).with_context(|| format!("{}: cannot read", f.display()))?;
        h.eat(&file.metadata().map(|m| m.len()).unwrap_or(0).to_le_bytes());
        let mut head = Vec::new();
        file.take(64 << 10).read_to_end(&mut head).with_context(|| format!("{}: cannot read", f.display()))?;
        h.eat(&head);
    }
    let mut settings = format!(
        "{}|{}|{}|{}|{}",
        s.geometry_iters,
        s.language_iters,
        plan.tower_tail,
        plan.backend,
        model::io::resolved(vlm).display()
    );
    if let Some(seg) = &plan.segmenter {
        settings += &format!("|{}", seg.display());
    }
    h.eat(settings.as_bytes());
    Ok(h.hex())
}

/// The manifest's global settings, checked before the first scene starts: the model folder is a
/// LLaVA-OneVision whose tower is deep enough for the tower tail.
fn check_globals(plan: &Plan, manifest: &Path) -> anyhow::Result<PathBuf> {
    let vlm = super::vlm_dir(plan.vlm.as_ref())?;
    let cfg = model::vlm::config::read_llava_config(&vlm).with_context(|| format!("{}: vlm", manifest.display()))?;
    if let Some(seg) = &plan.segmenter
        && !seg.join("config.json").is_file()
        && !seg.to_str().is_some_and(hub::is_repo_id)
    {
        bail!(
            "{}: segmenter {}: no SAM folder (config.json) there, nor a Hugging Face repo id",
            manifest.display(),
            seg.display()
        );
    }
    let layers = cfg.vision_layers_needed();
    if plan.tower_tail > layers {
        bail!(
            "{}: tower_tail {}: the vision tower of {} runs {layers} layers (the tail is at most that many)",
            manifest.display(),
            plan.tower_tail,
            vlm.display()
        );
    }
    Ok(vlm)
}

/// Per-view masks of a scene with no masks of its own from the segmenter `seg` (a folder or repo
/// id) in `out` (`<image stem>.png` per image; those an earlier attempt wrote are kept); `None`
/// when the capture has masks.
fn segment_scene(plan: &Plan, seg: &Path, data: &Path, out: &Path) -> anyhow::Result<Option<PathBuf>> {
    let (ds, _) = train::pipeline::load_for_geometry(data, &model::data::LoadOptions::default())?;
    let views: Vec<&model::data::View> = ds.train.iter().chain(&ds.test).collect();
    if views.iter().any(|v| v.instance_ids.is_some()) {
        return Ok(None);
    }
    let dir = hub::resolve(seg, &hub::wanted::SAM)?;
    let todo: Vec<&PathBuf> = views
        .iter()
        .map(|v| &v.image_path)
        .filter(|p| !out.join(format!("{}.png", p.file_stem().unwrap_or_default().to_string_lossy())).is_file())
        .collect();
    if !todo.is_empty() {
        let sam =
            super::masks::Segmenter::load(&dir, plan.backend, sam::automatic::AutoOptions::default().points_per_side)?;
        let bar = scoring::progress::Progress::new("SAM", "views");
        for (i, image) in todo.iter().enumerate() {
            let (w, h, ids, _) = sam.label_map(image)?;
            super::masks::write_label_map(out, image, (w, h, &ids))?;
            bar.update(i + 1, todo.len());
        }
    }
    Ok(Some(out.to_path_buf()))
}

/// Runs the pipeline on one scene, resuming whatever an earlier attempt left; returns its summary.
fn run_scene(plan: &Plan, s: &Job, d: &JobDirs, shard: &str, job: &str) -> anyhow::Result<serde_json::Value> {
    model::io::create_dir(&d.dir)?;
    model::io::write_json(&d.dir.join("job.json"), &serde_json::json!({"fingerprint": job}))?;
    let lang: LanguageRun = d.run.language();
    let mut seconds = serde_json::Map::new();
    let mut resumed = serde_json::Map::new();
    // a checkpoint every tenth of each stage: a killed worker loses at most that
    let mut recipe = Recipe::short(s.geometry_iters, s.language_iters);
    recipe.geometry.checkpoint_every = (s.geometry_iters / 10).max(1);
    recipe.language.checkpoint_every = (s.language_iters / 10).max(1);
    recipe.teacher.tower_tail = plan.tower_tail;
    let vlm = super::vlm_dir(plan.vlm.as_ref())?;
    let per_view = match (&s.per_view_masks, &plan.segmenter) {
        (Some(p), _) => Some(p.clone()),
        (None, Some(seg)) => segment_scene(plan, seg, &s.data, &d.dir.join("per-view"))?,
        (None, None) => None,
    };
    let dirs = train::pipeline::SceneDirs {
        data: s.data.clone(),
        run: d.run.clone(),
        teacher: d.teacher.clone(),
        language: lang.clone(),
        // per-view masks: the geometry without them in `geometry`, the matched masks in `masks`,
        // and `run` the same Gaussians with their identity
        objects: per_view.as_ref().map(|p| train::pipeline::PerViewMasks {
            per_view: p.clone(),
            bare: GeometryRun::new(d.dir.join("geometry")),
            matched: d.dir.join("masks"),
        }),
    };
    let mut bars = Bars::new(plan.backend);
    // resumable: finished stages are skipped, views already extracted kept
    let trained = train_scene(TeacherModel::Dir(&vlm), &dirs, &recipe, &plan.backend.device()?, true, &mut bars)?;
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
            let scoring = Scoring {
                views: model::chat::DEFAULT_SCENE_VIEWS,
                max_new_tokens: 16,
                show: false,
                keep_going: true,
                find_threshold: model::find::DEFAULT_THRESHOLD,
            };
            let grader = scoring::score::Grader::from_env()?;
            let qf = model::vqa::load_questions(q)?;
            model::question_file::check_scene(&qf, q, &s.data)?;
            let names = model::find::ObjectNames::of_run(&d.run, &mut Vec::new());
            let out = d.dir.join("vqa.json");
            let s = super::vqa::score(&scene.open()?, (q, &qf), &out, &scoring, names, grader.as_ref())?;
            seconds.insert("vqa".into(), serde_json::json!((t0.elapsed().as_secs_f64() * 10.0).round() / 10.0));
            // exact match (%) and the keyword score (0-100) of each level
            let level = |e: LevelSummary, k: LevelSummary| {
                let (exact, keyword, questions) = (e.mean, k.mean, e.count);
                serde_json::json!({"exact": exact, "keyword": keyword, "questions": questions})
            };
            serde_json::json!({
                "view": level(s.exact.view, s.keyword.view), "object": level(s.exact.object, s.keyword.object),
                "scene": level(s.exact.scene, s.keyword.scene), "overall": level(s.exact.overall, s.keyword.overall),
                "find": (s.find.phrases > 0).then(|| serde_json::json!({
                    "phrases": s.find.phrases, "precision": s.find.precision(), "recall": s.find.recall(),
                    "f1": s.find.f1(), "absent": s.find.absent, "absent_empty": s.find.absent_empty,
                })),
                "follow_ups": (s.follow.asked > 0).then(|| serde_json::json!({
                    "asked": s.follow.asked, "right": s.follow.right, "paired": s.follow.paired,
                    "paired_right": s.follow.paired_right, "twins_right": s.follow.twins_right,
                })),
            })
        }
        None => serde_json::Value::Null,
    };
    Ok(serde_json::json!({
        "scene": s.name,
        "job": job,
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
        let failed = JobDirs::new(&plan.out, &s.name).failed();
        if path.is_file() {
            done += 1;
            let summary: serde_json::Value = model::io::read_json(&path)?;
            rows.push(serde_json::json!({"scene": s.name, "status": "done", "summary": summary}));
        } else if failed.is_file() {
            let error = model::io::read_json::<serde_json::Value>(&failed)?["error"].clone();
            rows.push(serde_json::json!({"scene": s.name, "status": "failed", "error": error}));
        } else {
            rows.push(serde_json::json!({"scene": s.name, "status": "pending"}));
        }
    }
    let report = serde_json::json!({"scenes": plan.scenes.len(), "done": done, "results": rows});
    let path = plan.out.join(train::manifest::REPORT);
    let tmp = plan.out.join(format!("{}.{}.tmp", train::manifest::REPORT, std::process::id()));
    std::fs::write(&tmp, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("{}: cannot write", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("{}: cannot rename into place", path.display()))?;
    Ok((done, path))
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let plan = train::manifest::read(&a.manifest)?;
    let (i, n) = shard(a.shard.as_deref())?;
    model::io::create_dir(&plan.out)?;
    if a.report {
        let (done, path) = write_report(&plan)?;
        println!("{done} of {} scenes done -> {}", plan.scenes.len(), path.display());
        return Ok(());
    }
    let vlm = check_globals(&plan, &a.manifest)?;
    let mine: Vec<&Job> = plan.scenes.iter().skip(i).step_by(n).collect();
    let label = format!("{i}/{n}");
    let names: Vec<&str> = mine.iter().map(|s| s.name.as_str()).collect();
    eprintln!("batch: shard {label}: {} of {} scenes: {}", mine.len(), plan.scenes.len(), names.join(", "));
    let mut failed = Vec::new();
    for (k, s) in mine.iter().enumerate() {
        let d = JobDirs::new(&plan.out, &s.name);
        let job = job_fingerprint(&plan, s, &vlm)?;
        match earlier_job(&d)? {
            Some(was) if was != job => set_aside(&plan.out, &s.name, &was)?,
            // done with these inputs (or before fingerprints were recorded: kept as done)
            _ if d.summary().is_file() => {
                let at = d.summary();
                eprintln!("\n== scene {} ({} of {}): done earlier ({})", s.name, k + 1, mine.len(), at.display());
                continue;
            }
            _ => {}
        }
        eprintln!("\n== scene {} ({} of {})", s.name, k + 1, mine.len());
        match run_scene(&plan, s, &d, &label, &job) {
            Ok(summary) => {
                model::io::write_json(&d.summary(), &summary)?;
                let _ = std::fs::remove_file(d.failed());
            }
            Err(e) => {
                let error = format!("{e:#}");
                eprintln!("error: scene `{}`: {error} (the shard goes on)", s.name);
                model::io::create_dir(&d.dir)?;
                model::io::write_json(&d.failed(), &serde_json::json!({"job": job, "error": error}))?;
                failed.push(s.name.as_str());
            }
        }
    }
    let (done, path) = write_report(&plan)?;
    println!(
        "shard {label} finished; {done} of {} scenes of the manifest done -> {}",
        plan.scenes.len(),
        path.display()
    );
    if !failed.is_empty() {
        bail!(
            "shard {label}: {} of its {} scenes failed: {} (each error in OUT/<scene>/failed.json and {})",
            failed.len(),
            mine.len(),
            failed.join(", "),
            path.display()
        );
    }
    Ok(())
}

/// The job fingerprint a scene's folder was made for: its summary's, else the one an interrupted
/// or failed attempt recorded; `None` for a new scene, or a summary from before fingerprints.
fn earlier_job(d: &JobDirs) -> anyhow::Result<Option<String>> {
    let read = |p: &Path, key: &str| -> anyhow::Result<Option<String>> {
        if !p.is_file() {
            return Ok(None);
        }
        let v: serde_json::Value = model::io::read_json(p)?;
        Ok(v[key].as_str().map(str::to_string))
    };
    if d.summary().is_file() {
        return read(&d.summary(), "job");
    }
    read(&d.dir.join("job.json"), "fingerprint")
}

/// Moves a scene's folder made from other inputs or settings (`was`) aside, so the scene trains
/// again from scratch and nothing it had is lost.
fn set_aside(out: &Path, name: &str, was: &str) -> anyhow::Result<()> {
    let from = out.join(name);
    let to = (0..)
        .map(|k| {
            let aside = format!("{name}{}{was}", train::manifest::SET_ASIDE);
            out.join(if k == 0 { aside } else { format!("{aside}.{k}") })
        })
        .find(|p| !p.exists())
        .expect("a free name");
    std::fs::rename(&from, &to).with_context(|| format!("{}: cannot move aside", from.display()))?;
    eprintln!(
        "scene `{name}`: its data, questions or settings changed since it ran (job {was}): it runs again; the \
         earlier results are in {}",
        to.display()
    );
    Ok(())
}
