//! Property-based fuzzing of every parser a user feeds (proptest, a fixed seed so CI runs the
//! same cases every time): a valid file of each format is edited at random (bytes flipped, cut,
//! inserted, removed or repeated, numbers replaced by extreme ones, 4/8-byte words overwritten
//! with extreme counts and floats) and loaded through the public API. Every case must return
//! (no panic), allocate nothing larger than [`ALLOC_LIMIT`] at once (sizes are checked before
//! allocating, see `main.rs`'s allocator), and an error must name the file (its folder for the
//! loaders of a capture, whose errors may name any file in it). Covered: the capture formats, the
//! model files, question files, `.ply`, `chatsplat batch`'s manifest, and a teacher index with
//! its token files.

#![allow(deprecated)] // the teacher is extracted on burn-ndarray (deprecated in burn 0.22)

use crate::loaders_formats::{colmap_dir, llff_dir, replica_dir};
use crate::{largest_allocation, track_allocations};
use chatsplat_tests::temp_dir;
use model::data::{LoadOptions, colmap, llff, load_any, replica};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
use std::path::{Path, PathBuf};
use train::teacher::TeacherSet;

/// Cases per parser (each a fresh random edit of the valid file).
const CASES: u32 = 1000;
/// The largest single allocation a parser may make on a file of a few kilobytes.
const ALLOC_LIMIT: usize = 64 << 20;

/// Numbers a hand-edited or corrupt text file may hold.
const NUMBERS: [&str; 14] = [
    "0",
    "-1",
    "-0",
    "1e308",
    "-1e308",
    "1e-320",
    "nan",
    "inf",
    "4294967296",
    "18446744073709551616",
    "99999999999999999999999",
    "0.5",
    "\"x\"",
    "",
];

#[derive(Clone, Debug)]
enum Edit {
    Flip(usize, u8),
    Cut(usize),
    Insert(usize, Vec<u8>),
    Remove(usize, usize),
    Repeat(usize, usize),
    Number(usize, &'static str),
    Word(usize, u64, bool),
}

fn edits() -> impl Strategy<Value = Vec<Edit>> {
    let word = prop_oneof![
        Just(u64::MAX),
        Just(u32::MAX as u64),
        Just(i32::MAX as u64),
        Just(1u64 << 40),
        Just(0u64),
        Just(f32::NAN.to_bits() as u64),
        Just(f64::INFINITY.to_bits()),
        Just((-1e30f64).to_bits()),
        any::<u64>(),
    ];
    let edit = prop_oneof![
        (any::<usize>(), any::<u8>()).prop_map(|(p, b)| Edit::Flip(p, b)),
        any::<usize>().prop_map(Edit::Cut),
        (any::<usize>(), proptest::collection::vec(any::<u8>(), 1..12)).prop_map(|(p, v)| Edit::Insert(p, v)),
        (any::<usize>(), 1usize..48).prop_map(|(p, n)| Edit::Remove(p, n)),
        (any::<usize>(), 1usize..48).prop_map(|(p, n)| Edit::Repeat(p, n)),
        (any::<usize>(), proptest::sample::select(&NUMBERS[..])).prop_map(|(p, s)| Edit::Number(p, s)),
        (any::<usize>(), word, any::<bool>()).prop_map(|(p, w, wide)| Edit::Word(p, w, wide)),
    ];
    proptest::collection::vec(edit, 1..4)
}

fn apply(seed: &[u8], edits: &[Edit]) -> Vec<u8> {
    let mut b = seed.to_vec();
    for e in edits {
        let at = |p: usize, len: usize| if len == 0 { 0 } else { p % len };
        match e {
            Edit::Flip(p, x) if !b.is_empty() => {
                let i = at(*p, b.len());
                b[i] ^= x | 1;
            }
            Edit::Cut(p) => b.truncate(at(*p, b.len() + 1)),
            Edit::Insert(p, v) => {
                let i = at(*p, b.len() + 1);
                b.splice(i..i, v.iter().copied());
            }
            Edit::Remove(p, n) => {
                let i = at(*p, b.len() + 1);
                b.drain(i..(i + n).min(b.len()));
            }
            Edit::Repeat(p, n) => {
                let i = at(*p, b.len() + 1);
                let part: Vec<u8> = b[i..(i + n).min(b.len())].to_vec();
                b.splice(i..i, part);
            }
            Edit::Number(p, s) => {
                // the first run of digits at or after p (wrapping) becomes s
                let n = b.len();
                if let Some(start) = (0..n).map(|k| (at(*p, n) + k) % n).find(|&i| b[i].is_ascii_digit()) {
                    let end = (start..n).find(|&i| !(b[i].is_ascii_digit() || b[i] == b'.')).unwrap_or(n);
                    b.splice(start..end, s.bytes());
                }
            }
            Edit::Word(p, w, wide) => {
                let k = if *wide { 8 } else { 4 };
                if b.len() >= k {
                    let i = at(*p, b.len() - k + 1);
                    b[i..i + k].copy_from_slice(&w.to_le_bytes()[..k]);
                }
            }
            Edit::Flip(..) => {}
        }
    }
    b
}

/// Runs `CASES` edits of `target`'s current bytes through `load`; every error must contain
/// `names`. Returns (cases, errors).
fn fuzz(parser: &str, target: &Path, names: &str, load: impl Fn() -> Result<(), String>) -> (u32, u32) {
    fuzz_any(parser, target, &[names], load)
}

/// [`fuzz`] where an error may name any of `names` (a reader whose index names other files).
fn fuzz_any(parser: &str, target: &Path, names: &[&str], load: impl Fn() -> Result<(), String>) -> (u32, u32) {
    let seed = std::fs::read(target).unwrap();
    load().unwrap_or_else(|e| panic!("{parser}: the unedited file must load: {e}"));
    let config = Config { cases: CASES, failure_persistence: None, ..Config::default() };
    let mut runner = TestRunner::new_with_rng(config, TestRng::deterministic_rng(RngAlgorithm::ChaCha));
    let errors = std::cell::Cell::new(0);
    let result = runner.run(&edits(), |e| {
        std::fs::write(target, apply(&seed, &e)).unwrap();
        track_allocations(true);
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(&load));
        let largest = largest_allocation();
        track_allocations(false);
        let r = r.map_err(|_| TestCaseError::fail(format!("{parser}: panicked on {e:?}")))?;
        prop_assert!(largest <= ALLOC_LIMIT, "{parser}: allocated {largest} bytes at once on {e:?}");
        if let Err(msg) = r {
            errors.set(errors.get() + 1);
            prop_assert!(
                names.iter().any(|n| msg.contains(n)),
                "{parser}: the error names none of {names:?}: {msg} ({e:?})"
            );
        }
        Ok(())
    });
    std::fs::write(target, &seed).unwrap();
    if let Err(e) = result {
        panic!("{e}");
    }
    (CASES, errors.get())
}

fn ok<T, E: std::fmt::Display>(r: Result<T, E>) -> Result<(), String> {
    r.map(|_| ()).map_err(|e| e.to_string())
}

fn opts() -> LoadOptions {
    LoadOptions { holdout_every: 0, ..Default::default() }
}

fn report(parser: &str, (cases, errors): (u32, u32)) -> u32 {
    eprintln!("fuzz {parser}: {cases} cases, {errors} refused with an error naming the file, 0 panics");
    cases
}

#[test]
fn capture_parsers_survive_random_edits() {
    // the allocation guard sees a large allocation on this thread (so a parser's would be seen)
    track_allocations(true);
    let probe: Vec<u8> = Vec::with_capacity(ALLOC_LIMIT + 1);
    assert!(largest_allocation() > ALLOC_LIMIT, "the allocation tracker is not live");
    track_allocations(false);
    drop(probe);
    let mut total = 0;
    for bin in [true, false] {
        let (dir, _) = colmap_dir(if bin { "fuzz-colmap-bin" } else { "fuzz-colmap-txt" }, bin);
        let name = dir.file_name().unwrap().to_string_lossy().into_owned();
        let ext = if bin { "bin" } else { "txt" };
        for file in ["cameras", "images", "points3D"] {
            let target = dir.join(format!("sparse/0/{file}.{ext}"));
            let r = fuzz(&format!("colmap {file}.{ext}"), &target, &name, || ok(colmap::load(&dir, &opts())));
            total += report(&format!("colmap {file}.{ext}"), r);
        }
        if bin {
            let mask = dir.join("masks/img_a.png");
            total += report("mask png", fuzz("mask png", &mask, &name, || ok(colmap::load(&dir, &opts()))));
        }
    }
    let dir = llff_dir("fuzz-llff");
    let name = dir.file_name().unwrap().to_string_lossy().into_owned();
    let npy = dir.join("poses_bounds.npy");
    total += report("llff poses_bounds.npy", fuzz("llff", &npy, &name, || ok(llff::load(&dir, &opts()))));
    let dir = replica_dir("fuzz-replica", 3);
    let name = dir.file_name().unwrap().to_string_lossy().into_owned();
    let traj = dir.join("traj_w_c.txt");
    total += report("replica traj_w_c.txt", fuzz("replica", &traj, &name, || ok(replica::load(&dir, &opts()))));
    let dir = temp_dir("fuzz-nerfstudio");
    let o = model::data::synth::SynthOptions { seed: 3, views: 3, width: 16, height: 12, ..Default::default() };
    model::data::synth::write_dataset(&dir, &o, |_, _| {}).unwrap();
    let name = dir.file_name().unwrap().to_string_lossy().into_owned();
    let tf = nerfstudio_file(&dir);
    total += report("transforms.json", fuzz("nerfstudio", &tf, &name, || ok(load_any(&dir, &opts()))));
    eprintln!("fuzz captures: {total} cases");
    assert!(total >= 9 * CASES);
}

/// `chatsplat batch`'s manifest, and a teacher index with one of its token files, through their
/// readers: the manifest's scenes and settings (`train::manifest::read`), the index opened and
/// checked against its files and its dataset (`TeacherSet::open`, `cameras`, a view's tokens).
#[test]
fn batch_manifest_and_teacher_index_survive_random_edits() {
    let mut total = 0;
    let dir = temp_dir("fuzz-batch");
    std::fs::create_dir_all(dir.join("d")).unwrap();
    let manifest = dir.join("scenes.toml");
    let text = "out = \"o\"\nbackend = \"ndarray\"\ngeometry_iters = 600\nlanguage_iters = 100\ntower_tail = 1\n\n\
                [[scene]]\nname = \"a\"\ndata = \"d\"\ngeometry_iters = 10\n\n[[scene]]\nname = \"b\"\ndata = \"d\"\n";
    std::fs::write(&manifest, text).unwrap();
    let read = || ok(train::manifest::read(&manifest));
    total += report("batch manifest", fuzz("batch manifest", &manifest, "scenes.toml", read));

    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tiny-llava-ov");
    let vlm = model::vlm::LlavaOnevision::load(&fixture, &burn::tensor::Device::ndarray()).unwrap();
    let data = llff_dir("fuzz-teacher-data");
    let out = temp_dir("fuzz-teacher");
    let teacher = model::run::TeacherDir::new(&out);
    train::teacher::extract(&vlm, &data, &teacher, &Default::default(), |_| {}, |_, _| {}).unwrap();
    let open = || -> Result<(), String> {
        let set = TeacherSet::open(&out).map_err(|e| e.to_string())?;
        set.cameras().map_err(|e| e.to_string())?;
        ok(set.tokens(0, None))
    };
    let (out_name, data_name) =
        (out.file_name().unwrap().to_string_lossy(), data.file_name().unwrap().to_string_lossy());
    let names = [out_name.as_ref(), data_name.as_ref()];
    total += report("teacher.json", fuzz_any("teacher.json", &teacher.index(), &names, open));
    let set = TeacherSet::open(&out).unwrap();
    let file = set.views[0].file.clone();
    total += report("teacher token file", fuzz_any("teacher token file", &file, &names, open));
    eprintln!("fuzz manifests and teacher indexes: {total} cases");
    assert!(total >= 3 * CASES);
}

fn nerfstudio_file(dir: &Path) -> PathBuf {
    ["transforms.json", "transforms_train.json"].iter().map(|n| dir.join(n)).find(|p| p.is_file()).unwrap()
}

#[test]
fn model_and_question_parsers_survive_random_edits() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tiny-llava-ov");
    let dir = temp_dir("fuzz-model");
    std::fs::create_dir_all(&*dir).unwrap();
    for f in ["config.json", "tokenizer.json", "tokenizer_config.json", "processor_config.json"] {
        std::fs::copy(root.join(f), dir.join(f)).unwrap();
    }
    let mut total = 0;
    // config.json through the Hugging Face config reader
    let config = dir.join("config.json");
    let read_config = || {
        let v = model::vlm::config::read_json(&config).map_err(|e| e.to_string())?;
        ok(model::vlm::config::parse_llava_config(&config, &v))
    };
    total += report("config.json", fuzz("config.json", &config, "config.json", read_config));
    // tokenizer.json
    let tok = dir.join("tokenizer.json");
    let load_tok = || ok(model::vlm::tokenizer::ChatTokenizer::load(&dir, 3));
    let name = dir.file_name().unwrap().to_string_lossy().into_owned();
    total += report("tokenizer.json", fuzz("tokenizer.json", &tok, &name, load_tok));
    // safetensors (a small f32 file as runs store them)
    let st = dir.join("weights.safetensors");
    let named = vec![("a".to_string(), vec![2, 3], vec![1.0f32; 6]), ("b".to_string(), vec![4], vec![0.5; 4])];
    model::io::write_f32(&st, named, None).unwrap();
    total += report("safetensors", fuzz("safetensors", &st, "weights.safetensors", || ok(model::io::read_f32(&st))));
    // a question file
    let q = dir.join("questions.json");
    let questions = serde_json::json!({
        "views": ["view 0"],
        "questions": [
            {"id": "a", "level": "view", "view": 0, "question": "How many objects?", "answer": "3"},
            {"id": "b", "level": "scene", "question": "What colour is the cube?", "answer": "red"}
        ]
    });
    std::fs::write(&q, serde_json::to_string_pretty(&questions).unwrap()).unwrap();
    total += report("questions", fuzz("questions", &q, "questions.json", || ok(model::vqa::load_questions(&q))));
    // a question file of a synthetic scene, read and checked against the dataset a run was trained on
    // (whose own questions.json names the scene)
    let data = dir.join("scene-data");
    let o = model::data::synth::SynthOptions { seed: 5, views: 2, width: 16, height: 12, ..Default::default() };
    model::data::synth::write_dataset(&data, &o, |_, _| {}).unwrap();
    let theirs = dir.join("scene-questions.json");
    std::fs::copy(data.join("questions.json"), &theirs).unwrap();
    let against_scene = || -> Result<(), String> {
        let f = model::vqa::load_questions(&theirs).map_err(|e| e.to_string())?;
        ok(model::question_file::check_scene(&f, &theirs, &data))
    };
    total +=
        report("questions of a scene", fuzz("questions of a scene", &theirs, "scene-questions.json", against_scene));
    // a 3DGS .ply, binary and ASCII
    for ascii in [false, true] {
        let p = dir.join(if ascii { "ascii.ply" } else { "binary.ply" });
        std::fs::write(&p, ply_bytes(ascii)).unwrap();
        let parse = || ok(model::ply::read(&p));
        total += report(if ascii { "ply ascii" } else { "ply binary" }, fuzz("ply", &p, "ply", parse));
    }
    eprintln!("fuzz models and files: {total} cases");
    assert!(total >= 7 * CASES);
}

/// Three Gaussians in the Inria layout.
fn ply_bytes(ascii: bool) -> Vec<u8> {
    let props = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1",
        "rot_2", "rot_3", "f_rest_0",
    ];
    let format = if ascii { "ascii" } else { "binary_little_endian" };
    let mut out = format!("ply\nformat {format} 1.0\nelement vertex 3\n").into_bytes();
    for p in props {
        out.extend(format!("property float {p}\n").bytes());
    }
    out.extend(b"end_header\n");
    for i in 0..3 {
        let v = [i as f32 * 0.1, 0.2, 0.3, 0.5, 0.2, 0.1, 2.0, -3.0, -3.0, -3.0, 1.0, 0.0, 0.0, 0.0, 0.25];
        if ascii {
            let line: Vec<String> = v.iter().map(|x| x.to_string()).collect();
            out.extend(line.join(" ").bytes());
            out.push(b'\n');
        } else {
            for x in v {
                out.extend(x.to_le_bytes());
            }
        }
    }
    out
}

/// A scaled rope in any of the forms Hugging Face writes is refused, naming the key (this port
/// rotates by unscaled positions); the default forms read their theta.
#[test]
fn scaled_rope_configs_are_refused_in_every_spelling() {
    let file = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tiny-llava-ov/config.json");
    let base: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    let with = |place: &str, key: &str, v: serde_json::Value| {
        let mut c = base.clone();
        if place == "top" {
            c[key] = v;
        } else {
            c["text_config"][key] = v;
        }
        model::vlm::config::parse_llava_config(&file, &c).map(|m| m.text.rope_theta).map_err(|e| e.to_string())
    };
    use serde_json::json;
    let refused = [
        ("text", "rope_scaling", json!({"type": "linear", "factor": 2.0}), "text_config.rope_scaling.type"),
        ("text", "rope_scaling", json!({"rope_type": "dynamic", "factor": 2.0}), "text_config.rope_scaling.rope_type"),
        ("text", "rope_scaling", json!({"factor": 4.0}), "text_config.rope_scaling.factor"),
        ("top", "rope_scaling", json!({"type": "yarn", "factor": 4.0}), "rope_scaling.type"),
        (
            "text",
            "rope_parameters",
            json!({"rope_type": "llama3", "rope_theta": 5e5, "factor": 8.0}),
            "text_config.rope_parameters.rope_type",
        ),
        ("text", "rope_scaling", json!("linear"), "text_config.rope_scaling must be an object"),
    ];
    for (place, key, v, want) in refused {
        let e = with(place, key, v.clone()).expect_err(&format!("{v} must be refused"));
        assert!(e.contains(want) && e.contains("config.json"), "{v}: {e}");
    }
    // a rope_parameters with the default type, and a rope_scaling beside it, are both read
    let theta = with("text", "rope_parameters", json!({"rope_type": "default", "rope_theta": 5e5})).unwrap();
    assert_eq!(theta, 5e5);
    let mut c = base.clone();
    c["text_config"]["rope_parameters"] = json!({"rope_type": "default", "rope_theta": 5e5});
    c["text_config"]["rope_scaling"] = json!({"type": "linear", "factor": 2.0});
    assert!(model::vlm::config::parse_llava_config(&file, &c).is_err(), "rope_scaling beside rope_parameters");
    assert!(with("text", "rope_scaling", serde_json::Value::Null).is_ok(), "null is no scaling");
}
