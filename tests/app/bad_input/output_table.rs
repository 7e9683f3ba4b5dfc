//! One table of cases for every command that writes: an output that is an input, lies inside one
//! or holds one, a folder of another kind, a finished output of its own kind without `--resume`,
//! a file of another kind. Each must be refused naming the option, with every input and the
//! other folder byte for byte as they were. A command whose `--help` shows `--out` but that is
//! missing here fails the test: a new command cannot skip the guard.

use super::{Case, Suite, chatsplat, copy_dir, snapshot};
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Command;

/// What the commands of the table read: a dataset, a trained run (with its language run), its
/// teacher, a model folder, a question file, a .ply, a train-vlm config.
pub struct Made<'a> {
    pub base: &'a Path,
    pub run: &'a Path,
    pub teacher: &'a Path,
    pub model: &'a Path,
    pub dir: &'a Path,
}

/// How a command is called with `--out OUT`, what it reads (folders the cases aim at, and
/// whether an output may lie inside them), and what its output is.
struct Writer {
    name: &'static str,
    args: Box<dyn Fn(&Path) -> Vec<OsString>>,
    /// (input, an output inside it is refused)
    inputs: Vec<(PathBuf, bool)>,
    output: Output,
}

enum Output {
    /// A folder; `Some(finished)`: a finished output of its own kind that a new run (no
    /// `--resume`) must not replace.
    Folder(Option<PathBuf>),
    File,
}

fn os(parts: &[&dyn AsRef<std::ffi::OsStr>]) -> Vec<OsString> {
    parts.iter().map(|p| p.as_ref().to_os_string()).collect()
}

fn writers(m: &Made) -> Vec<Writer> {
    let (base, run, teacher, model, dir) =
        (m.base.to_path_buf(), m.run.to_path_buf(), m.teacher.to_path_buf(), m.model.to_path_buf(), m.dir);
    let ply = dir.join("table.ply");
    std::fs::write(&ply, super::inria_ply(3)).unwrap();
    let questions = dir.join("table-questions.json");
    let q = r#"{"questions": [{"id": "a", "level": "view", "view": 0, "question": "How many objects are there?",
        "answer": "3"}]}"#;
    std::fs::write(&questions, q).unwrap();
    let cfg = dir.join("table-vlm.json");
    std::fs::write(&cfg, r#"{"steps": 1}"#).unwrap();
    let checkpoint = run.join("checkpoint.safetensors");
    let language = run.join("language");
    let (b, r, t, mo, c) = (base.clone(), run.clone(), teacher.clone(), model.clone(), cfg.clone());
    let (p, qs) = (ply.clone(), questions.clone());
    let (r2, r3, r4, r6) = (run.clone(), run.clone(), run.clone(), run.clone());
    let per_view = dir.join("table-per-view");
    std::fs::create_dir_all(&per_view).unwrap();
    let pv = per_view.clone();
    vec![
        Writer {
            name: "train",
            args: Box::new(move |o| os(&[&"train", &"--iters", &"1", &"--data", &b, &"--out", &o])),
            inputs: vec![(base.clone(), true)],
            output: Output::Folder(Some(run.clone())),
        },
        Writer {
            name: "extract",
            args: Box::new({
                let b = base.clone();
                move |o| os(&[&"extract", &"--vlm", &mo, &"--data", &b, &"--out", &o])
            }),
            // its default output is DATA/teacher
            inputs: vec![(base.clone(), false), (model.clone(), true)],
            output: Output::Folder(None),
        },
        Writer {
            name: "train-language",
            args: Box::new(move |o| {
                os(&[&"train-language", &"--iters", &"1", &"--run", &r, &"--teacher", &t, &"--out", &o])
            }),
            inputs: vec![(teacher.clone(), true), (checkpoint.clone(), true)],
            output: Output::Folder(Some(language.clone())),
        },
        Writer {
            name: "export-ply",
            args: Box::new(move |o| os(&[&"export-ply", &"--run", &r2, &"--out", &o])),
            inputs: vec![(checkpoint.clone(), true), (language.join("language.safetensors"), true)],
            output: Output::File,
        },
        Writer {
            name: "export-encoder",
            args: Box::new(move |o| os(&[&"export-encoder", &"--run", &r3, &"--out", &o])),
            inputs: vec![(checkpoint.clone(), true), (language.join("config.json"), true)],
            output: Output::File,
        },
        Writer {
            name: "render",
            args: Box::new(move |o| os(&[&"render", &"--ply", &p, &"--width", &"8", &"--height", &"8", &"--out", &o])),
            inputs: vec![(ply.clone(), true)],
            output: Output::File,
        },
        Writer {
            name: "vqa",
            args: Box::new({
                let mo = model.clone();
                move |o| os(&[&"vqa", &"--vlm", &mo, &"--run", &r4, &"--questions", &qs, &"--out", &o])
            }),
            inputs: vec![(questions.clone(), true), (checkpoint.clone(), true)],
            output: Output::File,
        },
        Writer {
            name: "masks",
            args: Box::new({
                let b = base.clone();
                move |o| os(&[&"masks", &"--data", &b, &"--run", &r6, &"--per-view", &pv, &"--out", &o])
            }),
            inputs: vec![(base.clone(), true), (per_view.clone(), true), (checkpoint.clone(), true)],
            output: Output::Folder(None),
        },
        Writer {
            name: "identity",
            args: Box::new({
                let (b, r, pv) = (base.clone(), run.clone(), per_view.clone());
                move |o| os(&[&"identity", &"--data", &b, &"--run", &r, &"--masks", &pv, &"--out", &o])
            }),
            inputs: vec![(base.clone(), true), (per_view.clone(), true), (run.clone(), true)],
            output: Output::Folder(Some(run.clone())),
        },
        Writer {
            name: "train-vlm",
            args: Box::new(move |o| os(&[&"train-vlm", &"--config", &c, &"--out", &o])),
            inputs: vec![(cfg.clone(), true)],
            output: Output::Folder(None),
        },
        Writer {
            name: "synth",
            args: Box::new(|o| os(&[&"synth", &"--views", &"2", &"--width", &"8", &"--height", &"8", &"--out", &o])),
            inputs: vec![],
            output: Output::Folder(None),
        },
        Writer {
            name: "demo",
            args: Box::new(move |o| os(&[&"demo", &"--vlm", &model, &"--iters", &"1", &"--out", &o])),
            inputs: vec![(m.model.to_path_buf(), true)],
            output: Output::Folder(None),
        },
    ]
}

/// The subcommands whose `--help` shows an `--out` option.
fn commands_with_out() -> Vec<String> {
    let help = chatsplat().arg("--help").output().unwrap();
    let help = String::from_utf8_lossy(&help.stdout).into_owned();
    let names: Vec<String> = help
        .lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .filter(|n| n != "help")
        .collect();
    assert!(names.len() > 10, "chatsplat --help lists {names:?}");
    names
        .into_iter()
        .filter(|n| {
            let h = chatsplat().args([n.as_str(), "--help"]).output().unwrap();
            String::from_utf8_lossy(&h.stdout).contains("--out <")
        })
        .collect()
}

fn refused(s: &mut Suite, name: String, c: &mut Command, keep: &[&Path], other: Option<&Path>) {
    let keep: Vec<&Path> = keep.iter().copied().chain(other).collect();
    let before: Vec<_> = keep.iter().map(|k| snapshot(k)).collect();
    s.fails(Case { name: name.clone(), out: c.output().unwrap(), expect: vec!["--out".into()] });
    let after: Vec<_> = keep.iter().map(|k| snapshot(k)).collect();
    s.check(&format!("{name}: nothing changed"), before == after, "an input or the folder there was changed");
}

/// Runs the table over every writer.
pub fn every_command_keeps_the_guard(s: &mut Suite, m: &Made) {
    let table = writers(m);
    let missing: Vec<String> =
        commands_with_out().into_iter().filter(|c| !table.iter().any(|w| w.name == c.as_str())).collect();
    s.check("every command with --out is in the output table", missing.is_empty(), &format!("missing: {missing:?}"));
    // a folder of another kind: a second model folder; a file of another kind: notes
    let other = m.dir.join("table-other-model");
    copy_dir(m.model, &other);
    let notes = m.dir.join("table-notes.txt");
    std::fs::write(&notes, "the user's notes").unwrap();
    for w in &table {
        let call = |out: &Path| {
            let mut c = chatsplat();
            c.env("CHATSPLAT_VLM", m.model).args((w.args)(out));
            c
        };
        let inputs: Vec<&Path> = w.inputs.iter().map(|(p, _)| p.as_path()).collect();
        for (input, inside_refused) in &w.inputs {
            let n = super::name_of(input);
            refused(s, format!("{}: --out is {n}", w.name), &mut call(input), &inputs, None);
            if *inside_refused && input.is_dir() {
                refused(s, format!("{}: --out inside {n}", w.name), &mut call(&input.join("new")), &inputs, None);
            }
        }
        // a folder that holds the inputs (they all lie in the test's folder)
        if !w.inputs.is_empty() {
            refused(s, format!("{}: --out holds its inputs", w.name), &mut call(m.dir), &inputs, None);
        }
        match &w.output {
            Output::Folder(finished) => {
                let name = format!("{}: --out is a folder of another kind", w.name);
                refused(s, name, &mut call(&other), &inputs, Some(&other));
                if let Some(f) = finished {
                    let name = format!("{}: --out a finished one without --resume", w.name);
                    refused(s, name, &mut call(f), &inputs, Some(f));
                }
            }
            Output::File => {
                let name = format!("{}: --out a file of another kind", w.name);
                refused(s, name, &mut call(&notes), &inputs, Some(&notes));
            }
        }
    }
}
