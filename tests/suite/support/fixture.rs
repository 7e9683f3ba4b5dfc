//! A trained ChatSplat scene with the built-in model, shared by the tests that need one (the
//! end-to-end accuracy test, the viewer's HTTP and browser tests): a held-out synthetic tabletop
//! -> geometry -> teacher tokens -> language field. Built once per machine and source tree into
//! `TMP/tabletop-<hash>` (`TMP` the tests' `CARGO_TARGET_TMPDIR`), where `<hash>` covers every
//! source file of the crates that train it, `Cargo.lock` and the built-in model's files: any change
//! to them trains it anew, and a clean clone (CI) always does.

use burn::tensor::Device;
use std::path::{Path, PathBuf};
use train::pipeline::{Quiet, Recipe, SceneDirs, TeacherModel, train_scene};

/// The scene's seed: none of the built-in model's training or evaluation seeds.
pub const SEED: u64 = 30_100;
pub const VIEWS: usize = 16;
pub const GEOMETRY_ITERS: usize = 300;
pub const LANGUAGE_ITERS: usize = 150;

/// A trained scene on disk.
#[derive(Clone, Debug)]
pub struct Tabletop {
    /// The dataset (`chatsplat synth` layout: scene.json, questions.json, masks).
    pub data: PathBuf,
    /// The geometry run, with its language run in `run/language`.
    pub run: PathBuf,
}

/// The built-in LLaVA-OneVision.
pub fn builtin_model() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tabletop-llava-ov")
}

/// The shared scene under `tmp`, trained on first use (a few minutes on 2 cores).
pub fn tabletop(tmp: &Path) -> Tabletop {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _one_at_a_time = LOCK.lock().unwrap_or_else(|e| e.into_inner());
    let root = tmp.join(format!("tabletop-{:016x}", source_hash()));
    let done = Tabletop { data: root.join("data"), run: root.join("run") };
    if root.join("complete").exists() {
        return done;
    }
    // trained beside the final place, then renamed: another process never sees half a scene
    let building = tmp.join(format!("tabletop-building-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&building);
    train_into(&building);
    std::fs::write(building.join("complete"), b"").unwrap();
    if std::fs::rename(&building, &root).is_err() {
        // another process finished first
        let _ = std::fs::remove_dir_all(&building);
    }
    done
}

fn train_into(root: &Path) {
    let dev = Device::ndarray();
    let vlm = model::vlm::LlavaOnevision::load(&builtin_model(), &dev).unwrap();
    let dirs = SceneDirs::beside(&root.join("data"), &root.join("run"));
    // views the size the model reads, as the demo's
    let side = vlm.cfg.vision.image_size as u32;
    let opts =
        model::data::synth::SynthOptions { seed: SEED, views: VIEWS, width: side, height: side, ..Default::default() };
    model::data::synth::write_dataset(&dirs.data, &opts, |_, _| {}).unwrap();
    let mut recipe = Recipe::short(GEOMETRY_ITERS, LANGUAGE_ITERS);
    recipe.language.checkpoint_every = 0;
    train_scene(TeacherModel::Loaded(&vlm), &dirs, &recipe, &dev, false, &mut Quiet).unwrap();
}

/// FNV-1a over the sources that train the scene and the built-in model's files.
fn source_hash() -> u64 {
    let top = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut files = Vec::new();
    for dir in ["splat_kernels/src", "model/data/src", "model/core/src", "train/src", "checkpoints/tabletop-llava-ov"] {
        collect(&top.join(dir), &mut files);
    }
    files.push(top.join("Cargo.lock"));
    files.sort();
    let mut h = model::data::Fnv::default();
    for f in files {
        let name = f.strip_prefix(&top).unwrap_or(&f).to_string_lossy().into_owned();
        h.eat(name.as_bytes());
        h.eat(&std::fs::read(&f).unwrap_or_default());
    }
    h.0
}

fn collect(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            collect(&p, out);
        } else {
            out.push(p);
        }
    }
}
