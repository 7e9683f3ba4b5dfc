//! `chatsplat batch`'s manifest (TOML): its scenes and settings read and checked before any
//! work starts, each error naming the file and the line.

use model::Backend;
use model::error::{Error, Result};
use serde::Deserialize;
use std::path::{Path, PathBuf};
use toml::Spanned;

/// The manifest file.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    /// Output folder (default: `<manifest stem>-out` beside the manifest).
    out: Option<PathBuf>,
    /// LLaVA-OneVision directory or Hugging Face repo id (default: the built-in model).
    vlm: Option<PathBuf>,
    /// Segment Anything directory or Hugging Face repo id: scenes with no masks of their own and no
    /// `per_view_masks` get per-view masks from its automatic masks, matched across views.
    segmenter: Option<PathBuf>,
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
    crate::teacher::DEFAULT_TOWER_TAIL
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
    /// Per-view masks of any segmenter (`<image stem>.png`, ids arbitrary per view) for a capture
    /// without consistent masks: matched after the geometry stage (`chatsplat masks`), then the
    /// identity fitted (`chatsplat identity`).
    per_view_masks: Option<Spanned<PathBuf>>,
    geometry_iters: Option<usize>,
    language_iters: Option<usize>,
}

/// A scene ready to run: a job of the batch.
#[derive(Clone, Debug)]
pub struct Job {
    pub name: String,
    /// The dataset (a directory).
    pub data: PathBuf,
    /// Its question file, when it has questions.
    pub questions: Option<PathBuf>,
    /// Its per-view masks (a directory), when its objects come from them.
    pub per_view_masks: Option<PathBuf>,
    pub geometry_iters: usize,
    pub language_iters: usize,
}

/// A checked manifest.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The output folder.
    pub out: PathBuf,
    /// The LLaVA-OneVision directory or repo id (`None`: the built-in model).
    pub vlm: Option<PathBuf>,
    /// The Segment Anything directory or repo id for scenes without masks.
    pub segmenter: Option<PathBuf>,
    pub backend: Backend,
    pub tower_tail: usize,
    pub scenes: Vec<Job>,
}

/// The manifest's size limit: a list of scenes, never more than a few megabytes.
const MAX_BYTES: u64 = 16 << 20;

/// `path:line: message` for the byte offset `at` of `text`.
fn at_line(path: &Path, text: &str, at: usize, message: impl std::fmt::Display) -> Error {
    let line = text.get(..at.min(text.len())).unwrap_or(text).matches('\n').count() + 1;
    Error::input(format!("{}:{line}: {message}", path.display()))
}

/// The batch's report in its output folder (`OUT/report.json`).
pub const REPORT: &str = "report.json";

/// What a scene's results folder set aside is named after (`OUT/<scene>.superseded-<job>`).
pub const SET_ASIDE: &str = ".superseded-";

/// Whether `a` is `b` or lies inside it, where both lead.
fn within(a: &Path, b: &Path) -> bool {
    model::io::resolved(a).starts_with(model::io::resolved(b))
}

/// A scene's data may not be, or lie inside, any scene's results folder (`OUT/<name>`, which a
/// later run with other inputs sets aside: the data would move), and `out` may not be, or lie
/// inside, a scene's data (every run would change that data, so each later run would train it
/// again): refused before any scene runs.
fn refuse_data_in_results(manifest: &Path, out: &Path, scenes: &[Job]) -> Result<()> {
    // out holds results of this kind or things batch never touches (it writes only report.json
    // and a folder per scene); a dataset, a run, a model as out is refused by name
    if let Some(k) = model::guard::Kind::of(out).filter(|&k| k != model::guard::Kind::Batch) {
        return Err(Error::invalid(
            manifest,
            format!("out {} holds {}, not a batch's results: choose another out", out.display(), k.name()),
        ));
    }
    for s in scenes {
        if within(out, &s.data) {
            return Err(Error::invalid(
                manifest,
                format!(
                    "out {} is, or lies inside, the data of scene `{}` ({}): its results would change its data; \
                     choose an out outside every scene's data",
                    out.display(),
                    s.name,
                    s.data.display()
                ),
            ));
        }
        if let Some(o) = scenes.iter().find(|o| within(&s.data, &out.join(&o.name))) {
            return Err(Error::invalid(
                manifest,
                format!(
                    "scene `{}`: its data {} lies inside {}, the results folder of scene `{}`, which a later run \
                     may set aside: choose another out or another name",
                    s.name,
                    s.data.display(),
                    out.join(&o.name).display(),
                    o.name
                ),
            ));
        }
    }
    Ok(())
}

/// Reads and checks the manifest at `path`: every error names the file (and the line where it
/// has one).
pub fn read(path: &Path) -> Result<Plan> {
    let size = std::fs::metadata(path).map_err(|e| Error::invalid(path, format!("cannot read: {e}")))?.len();
    if size > MAX_BYTES {
        return Err(Error::invalid(path, format!("is {size} bytes; a manifest is at most {MAX_BYTES}")));
    }
    let bytes = std::fs::read(path).map_err(|e| Error::invalid(path, format!("cannot read: {e}")))?;
    let text = String::from_utf8(bytes).map_err(|e| Error::invalid(path, format!("is not UTF-8 text: {e}")))?;
    let m: Manifest = toml::from_str(&text).map_err(|e| match e.span() {
        Some(s) => at_line(path, &text, s.start, e.message()),
        None => Error::invalid(path, e.message().to_string()),
    })?;
    let base = path.parent().unwrap_or(Path::new("."));
    let backend = match &m.backend {
        Some(b) => b.get_ref().parse::<Backend>().map_err(|e| at_line(path, &text, b.span().start, e))?,
        None => Backend::Ndarray,
    };
    if m.scene.is_empty() {
        return Err(Error::invalid(path, "no [[scene]] tables: the manifest lists no scene"));
    }
    if m.geometry_iters == 0 || m.language_iters == 0 {
        return Err(Error::invalid(path, "geometry_iters and language_iters must be at least 1"));
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
        if name == REPORT || name.contains(SET_ASIDE) {
            return Err(bad(s.name.span().start, format!("names the batch's own `{REPORT}` or `*{SET_ASIDE}*` files")));
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
        let per_view_masks = match &s.per_view_masks {
            Some(m) => {
                let p = base.join(m.get_ref());
                if !p.is_dir() {
                    return Err(bad(m.span().start, format!("per_view_masks {} is not a directory", p.display())));
                }
                Some(p)
            }
            None => None,
        };
        scenes.push(Job { name: name.clone(), data, questions, per_view_masks, geometry_iters, language_iters });
    }
    let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "batch".into());
    let out = m.out.as_ref().map(|o| base.join(o)).unwrap_or_else(|| base.join(format!("{stem}-out")));
    refuse_data_in_results(path, &out, &scenes)?;
    // a folder beside the manifest, else a repo id as written
    let model = |v: &PathBuf| match v.to_str() {
        Some(id) if !base.join(v).exists() && hub::is_repo_id(id) => v.clone(),
        _ => base.join(v),
    };
    let (vlm, segmenter) = (m.vlm.as_ref().map(model), m.segmenter.as_ref().map(model));
    Ok(Plan { out, vlm, segmenter, backend, tower_tail: m.tower_tail, scenes })
}
