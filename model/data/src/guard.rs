//! The output guard every command that writes goes through before any work: what it writes may
//! not be, lie inside or hold anything it reads, and a folder already there is written only when
//! it holds this command's own kind of output and the command may go on with it (`--resume`, or a
//! command that always goes on: extract, demo, batch). A refused command has changed nothing.
//!
//! What a folder holds is told by the files each command writes into its own ([`Kind::of`]).

use crate::error::{Error, Result};
use crate::io::resolved;
use std::path::{Path, PathBuf};

/// What a folder holds, by the files the command that made it writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// `chatsplat synth`'s tabletop: scene.json beside its views.
    Tabletop,
    /// A capture (transforms.json, sparse/, poses_bounds.npy, traj_w_c.txt).
    Dataset,
    /// `chatsplat train`: checkpoint.safetensors, cameras.json, state.json.
    GeometryRun,
    /// `chatsplat train-language`: language.safetensors, state.json.
    LanguageRun,
    /// `chatsplat extract`: teacher.json, or its token files (view_NNNN.safetensors) before it.
    Teacher,
    /// A LLaVA-OneVision folder (config.json and its weights) that no train-vlm run wrote.
    Model,
    /// `chatsplat train-vlm`: train_config.json beside the model it trains.
    VlmRun,
    /// `chatsplat demo`: geometry_config.json and language_config.json beside data/ and run/.
    Demo,
    /// `chatsplat batch`'s results: report.json.
    Batch,
    /// `chatsplat masks`: masks.json beside a label PNG per image.
    Masks,
}

impl Kind {
    /// What a user would call it, with its article.
    pub fn name(self) -> &'static str {
        match self {
            Kind::Tabletop => "a synthetic tabletop (chatsplat synth)",
            Kind::Dataset => "a dataset (a capture)",
            Kind::GeometryRun => "a geometry run",
            Kind::LanguageRun => "a language run",
            Kind::Teacher => "a teacher (extract's tokens)",
            Kind::Model => "a model (config.json, weights)",
            Kind::VlmRun => "a train-vlm run",
            Kind::Demo => "a demo's folder",
            Kind::Batch => "a batch's results",
            Kind::Masks => "a masks folder",
        }
    }

    /// The kind of output folder `dir` holds, from its marker files (`None`: missing, empty, or
    /// files no command of chatsplat writes).
    pub fn of(dir: &Path) -> Option<Kind> {
        let has = |name: &str| dir.join(name).exists();
        let checks: [(Kind, bool); 10] = [
            (Kind::Demo, has("geometry_config.json") && has("language_config.json")),
            (Kind::Batch, has("report.json")),
            (Kind::VlmRun, has("train_config.json")),
            (Kind::GeometryRun, has("cameras.json") && (has("checkpoint.safetensors") || has("state.json"))),
            (Kind::LanguageRun, has("language.safetensors") || (has("state.json") && has("compact.json"))),
            // a sharded or interrupted extract has token files before its index
            (Kind::Teacher, has("teacher.json") || has_token_files(dir)),
            (Kind::Model, has("config.json") && (has("model.safetensors") || has("tokenizer.json"))),
            (Kind::Masks, has("masks.json")),
            (Kind::Tabletop, has("scene.json")),
            (
                Kind::Dataset,
                ["transforms.json", "transforms_train.json", "sparse", "poses_bounds.npy", "traj_w_c.txt"]
                    .iter()
                    .any(|m| has(m)),
            ),
        ];
        checks.into_iter().find(|(_, yes)| *yes).map(|(k, _)| k)
    }
}

/// Whether `dir` holds one of extract's token files (`view_0003.safetensors`).
fn has_token_files(dir: &Path) -> bool {
    let Ok(read) = std::fs::read_dir(dir) else { return false };
    read.flatten().any(|e| {
        let name = e.file_name();
        let name = name.to_string_lossy();
        name.strip_prefix("view_")
            .and_then(|n| n.strip_suffix(".safetensors"))
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
    })
}

/// What a command reads: what each input is (as the user named it) and where.
pub type Inputs<'a> = [(&'a str, PathBuf)];

/// `a` is `b` or lies inside it (both compared where they lead).
fn within(a: &Path, b: &Path) -> bool {
    resolved(a).starts_with(resolved(b))
}

/// The output `option` at `out` is none of `inputs`, lies inside none of them, and holds none.
pub fn refuse_overlap(option: &str, out: &Path, inputs: &Inputs) -> Result<()> {
    overlap(option, out, inputs, false)
}

/// As [`refuse_overlap`], but the output may lie inside an input folder: a command's default
/// output inside what it reads (extract's DATA/teacher).
pub fn refuse_onto_or_around(option: &str, out: &Path, inputs: &Inputs) -> Result<()> {
    overlap(option, out, inputs, true)
}

fn overlap(option: &str, out: &Path, inputs: &Inputs, inside_ok: bool) -> Result<()> {
    for (what, p) in inputs {
        let problem = if resolved(out) == resolved(p) {
            "is"
        } else if !inside_ok && within(out, p) {
            "lies inside"
        } else if within(p, out) {
            "holds"
        } else {
            continue;
        };
        return Err(Error::invalid(
            out,
            format!(
                "{option} {problem} {what} ({}), which this command reads: writing there would change its input; \
                 choose another {option}",
                p.display()
            ),
        ));
    }
    Ok(())
}

/// Whether a command may write into a folder of its own kind that is already there.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Existing {
    /// It goes on with it (`--resume` given, or a command that always does).
    GoOn,
    /// It would start anew: refused, `instead` telling the user what to do.
    Refuse { instead: &'static str },
}

/// The output folder `option` at `out`, where the command writes `own`: not onto, inside or
/// around an input ([`refuse_overlap`]), not a file, and when it holds anything, only `own`'s
/// kind with `existing` saying the command goes on with it. Everything else there (another
/// kind's folder by name, files of the user's by their names) is refused before any work.
pub fn output_folder(option: &str, out: &Path, own: Kind, existing: Existing, inputs: &Inputs) -> Result<()> {
    refuse_overlap(option, out, inputs)?;
    if out.exists() && !out.is_dir() {
        return Err(Error::invalid(out, format!("{option} is a file; it should name a folder for {}", own.name())));
    }
    let Some(names) = entries(out) else { return Ok(()) };
    match (Kind::of(out), existing) {
        (Some(k), Existing::GoOn) if k == own => Ok(()),
        (Some(k), Existing::Refuse { instead }) if k == own => Err(Error::invalid(
            out,
            format!("{option} already holds {}, which a new one would replace: {instead}", own.name()),
        )),
        (Some(k), _) => Err(Error::invalid(
            out,
            format!("{option} holds {}, not {}: choose a new or empty {option}", k.name(), own.name()),
        )),
        (None, _) => Err(Error::invalid(
            out,
            format!(
                "{option} already holds files of yours ({}), which {} would mix with: choose a new or empty {option}",
                names.join(", "),
                own.name()
            ),
        )),
    }
}

/// The output file `option` at `out`: not onto, inside or around an input, not a folder, and an
/// existing file replaced only when `is_own` says from its first bytes (up to 64) that it is what
/// the command writes (`kind`, e.g. "a .ply or .spz file").
pub fn output_file(
    option: &str,
    out: &Path,
    kind: &str,
    is_own: impl Fn(&[u8]) -> bool,
    inputs: &Inputs,
) -> Result<()> {
    refuse_overlap(option, out, inputs)?;
    refuse_replacing_other(option, out, kind, is_own)
}

/// An existing file at `out` is replaced only when it is one the command writes: `is_own` says so
/// from its first bytes (up to 64), `kind` names what the command writes ("a .ply or .spz file").
/// Anything else there (a run's checkpoint, a config, a folder) is refused by name, before any
/// work; a missing file is fine.
fn refuse_replacing_other(option: &str, out: &Path, kind: &str, is_own: impl Fn(&[u8]) -> bool) -> Result<()> {
    let Ok(meta) = std::fs::metadata(out) else { return Ok(()) };
    if meta.is_dir() {
        return Err(Error::invalid(out, format!("{option} is a folder; it should name {kind} to write")));
    }
    use std::io::Read as _;
    let mut head = Vec::new();
    // only a regular file is opened (a FIFO would block the open)
    let read = meta.is_file() && std::fs::File::open(out).and_then(|f| f.take(64).read_to_end(&mut head)).is_ok();
    if !read || !is_own(&head) {
        return Err(Error::invalid(
            out,
            format!(
                "{option} exists and is not {kind}: this command replaces only such a file (choose another {option})"
            ),
        ));
    }
    Ok(())
}

/// Up to three entry names of folder `dir`; `None` when it is missing, not a folder, or empty.
fn entries(dir: &Path) -> Option<Vec<String>> {
    let mut names: Vec<String> =
        std::fs::read_dir(dir).ok()?.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    if names.is_empty() {
        return None;
    }
    names.sort();
    names.truncate(3);
    Some(names)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folders_are_told_by_their_markers_and_overlaps_refused_both_ways() {
        let dir = std::env::temp_dir().join(format!("chatsplat-guard-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let data = dir.join("data");
        std::fs::create_dir_all(&data).unwrap();
        std::fs::write(data.join("transforms.json"), "{}").unwrap();
        assert_eq!(Kind::of(&data), Some(Kind::Dataset));
        let inputs = [("the --data directory", data.clone())];
        for (out, word) in [(data.clone(), " is "), (data.join("run"), "lies inside"), (dir.clone(), "holds")] {
            let e = refuse_overlap("--out", &out, &inputs).unwrap_err().to_string();
            assert!(e.contains(word) && e.contains("--data"), "{e}");
        }
        let run = dir.join("run");
        std::fs::create_dir_all(&run).unwrap();
        let go = Existing::GoOn;
        assert!(output_folder("--out", &run, Kind::GeometryRun, go, &inputs).is_ok(), "empty folder");
        std::fs::write(run.join("cameras.json"), "{}").unwrap();
        std::fs::write(run.join("state.json"), "{}").unwrap();
        assert_eq!(Kind::of(&run), Some(Kind::GeometryRun));
        assert!(output_folder("--out", &run, Kind::GeometryRun, go, &inputs).is_ok());
        let again = Existing::Refuse { instead: "--resume goes on with it" };
        let e = output_folder("--out", &run, Kind::GeometryRun, again, &inputs).unwrap_err().to_string();
        assert!(e.contains("already holds a geometry run") && e.contains("--resume"), "{e}");
        let e = output_folder("--out", &run, Kind::Teacher, go, &inputs).unwrap_err().to_string();
        assert!(e.contains("holds a geometry run, not a teacher"), "{e}");
        let mine = dir.join("mine");
        std::fs::create_dir_all(&mine).unwrap();
        std::fs::write(mine.join("notes.txt"), "x").unwrap();
        let e = output_folder("--out", &mine, Kind::Teacher, go, &inputs).unwrap_err().to_string();
        assert!(e.contains("notes.txt"), "{e}");
        let e = output_folder("--out", &mine.join("notes.txt"), Kind::Teacher, go, &inputs).unwrap_err();
        assert!(e.to_string().contains("is a file"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
