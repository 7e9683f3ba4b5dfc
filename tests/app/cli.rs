//! The `chatsplat` binary as a user runs it: a render that writes real PNGs, and clear errors with
//! a non-zero exit for bad input.

use chatsplat_tests::fake_hub::{COMMIT, FakeHub, Served};
use std::process::Command;

fn chatsplat() -> Command {
    Command::new(env!("CARGO_BIN_EXE_chatsplat"))
}

/// A scratch path (file or directory), removed when the test passes.
fn tmp(name: &str) -> chatsplat_tests::Scratch {
    chatsplat_tests::temp_dir(&format!("cli-{name}"))
}

#[test]
fn render_writes_png_files_of_the_requested_size() {
    let out = tmp("r.png");
    let depth = tmp("d.png");
    let st = chatsplat()
        .args(["render", "--density", "16", "--width", "97", "--height", "61", "--out"])
        .arg(&out)
        .arg("--depth")
        .arg(&depth)
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    for p in [&out, &depth] {
        let bytes = std::fs::read(p).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
        // IHDR width and height, big endian.
        assert_eq!(u32::from_be_bytes(bytes[16..20].try_into().unwrap()), 97);
        assert_eq!(u32::from_be_bytes(bytes[20..24].try_into().unwrap()), 61);
    }
    let stdout = String::from_utf8_lossy(&st.stdout);
    assert!(stdout.contains("rendered"), "{stdout}");
}

/// On a machine whose only wgpu adapter the op cannot run on (here: the Vulkan loader shown no
/// driver, so wgpu falls back to OpenGL, on Mesa's llvmpipe where it is installed), `--backend
/// wgpu` is refused with the adapter and its graphics API named, or with "no wgpu adapter" where
/// there is no OpenGL either; never a panic, a kernel that fails to compile, or a PNG.
#[test]
fn wgpu_without_a_usable_adapter_is_refused_by_name() {
    let out = tmp("gl.png");
    let st = chatsplat()
        .args(["render", "--density", "4", "--width", "32", "--height", "32", "--backend", "wgpu", "--out"])
        .arg(&out)
        .env("VK_ICD_FILENAMES", "/nonexistent.json")
        .env("VK_DRIVER_FILES", "/nonexistent.json")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&st.stderr);
    assert_eq!(st.status.code(), Some(1), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    let gl = err.contains("through OpenGL, a software rasterizer") && err.contains("mesa-vulkan-drivers");
    assert!(gl || err.contains("no wgpu adapter"), "{err}");
    if !gl {
        eprintln!("(no OpenGL on this machine either: {err})");
    }
    assert!(!out.exists(), "nothing written");
}

#[test]
fn bad_input_gives_a_clear_error_and_a_non_zero_exit() {
    let missing = tmp("does-not-exist.ply");
    let st = chatsplat().args(["render", "--ply"]).arg(&missing).output().unwrap();
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("does-not-exist.ply") && err.contains("cannot read"), "{err}");
    assert!(!err.contains("panicked"), "{err}");

    let bad = tmp("bad.ply");
    let props: String = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2"]
        .iter()
        .chain(&["rot_0", "rot_1", "rot_2", "rot_3"])
        .map(|p| format!("property float {p}\n"))
        .collect();
    let header = format!("ply\nformat binary_little_endian 1.0\nelement vertex 10\n{props}end_header\n");
    std::fs::write(&bad, [header.as_bytes(), b"\0\0\0\0"].concat()).unwrap();
    let st = chatsplat().args(["render", "--ply"]).arg(&bad).output().unwrap();
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("bad.ply") && err.contains("truncated"), "{err}");

    let st = chatsplat().args(["render", "--eye", "1,2"]).output().unwrap();
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("--eye expects three"));
}

#[test]
fn synth_writes_a_dataset_and_rejects_zero_views() {
    let dir = tmp("synth");
    let st = chatsplat()
        .args(["synth", "--views", "2", "--width", "16", "--height", "12", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    for rel in
        ["transforms.json", "scene.json", "images/frame_0001.png", "masks/frame_0001.png", "depth/frame_0001.png"]
    {
        assert!(dir.join(rel).is_file(), "{rel} missing");
    }
    let st = chatsplat().args(["synth", "--views", "0", "--out"]).arg(&dir).output().unwrap();
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("views, width and height must be positive"));
}

fn fixture() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("checkpoints/tiny-llava-ov")
}

#[test]
fn ask_streams_an_answer_from_the_tiny_vlm_and_rejects_bad_paths() {
    let st = chatsplat()
        .args(["ask", "--max-new-tokens", "6", "--vlm"])
        .arg(fixture())
        .arg("--image")
        .arg(fixture().join("image_a.png"))
        .arg("What is on the table?")
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("prompt tokens") && err.contains("new tokens"), "{err}");
    assert!(!st.stdout.is_empty());

    // Two images: the multi-image layout (730 placeholder tokens each in the fixture).
    let st = chatsplat()
        .args(["ask", "--max-new-tokens", "2", "--vlm"])
        .arg(fixture())
        .arg("--image")
        .arg(fixture().join("image_a.png"))
        .arg("--image")
        .arg(fixture().join("image_b.png"))
        .arg("Which is brighter?")
        .output()
        .unwrap();
    assert!(st.status.success(), "{}", String::from_utf8_lossy(&st.stderr));
    let err = String::from_utf8_lossy(&st.stderr);
    let n = chatsplat_tests::prompt_tokens(&err);
    assert!(n > 2 * 730 && n < 2 * 730 + 40, "two base views + newline = 1460 image tokens plus the text, got {n}");

    let st = chatsplat()
        .args(["ask", "--vlm", "/nonexistent/vlm", "--image"])
        .arg(fixture().join("image_a.png"))
        .arg("q")
        .output()
        .unwrap();
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("/nonexistent/vlm") && !err.contains("panicked"), "{err}");

    let st = chatsplat()
        .args(["ask", "--vlm"])
        .arg(fixture())
        .args(["--image", "/nonexistent/x.png", "q"])
        .output()
        .unwrap();
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("/nonexistent/x.png"));

    let st =
        chatsplat().args(["extract", "--vlm"]).arg(fixture()).args(["--data", "/nonexistent/scene"]).output().unwrap();
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("/nonexistent/scene") && !err.contains("panicked"), "{err}");
}

#[test]
fn language_commands_reject_bad_input_by_name() {
    let missing = tmp("no-such-run");
    let teacher = tmp("no-such-teacher");
    let cases: Vec<(Vec<String>, String)> = vec![
        (
            vec![
                "train-language".into(),
                "--run".into(),
                missing.display().to_string(),
                "--teacher".into(),
                teacher.display().to_string(),
            ],
            teacher.join("teacher.json").display().to_string(),
        ),
        (
            vec![
                "export-encoder".into(),
                "--run".into(),
                missing.display().to_string(),
                "--out".into(),
                tmp("e.safetensors").display().to_string(),
            ],
            "no-such-run".into(),
        ),
        (vec!["ask".into(), "--vlm".into(), missing.display().to_string(), "q".into()], "--run".into()),
    ];
    for (args, want) in cases {
        let st = chatsplat().args(&args).output().unwrap();
        let err = String::from_utf8_lossy(&st.stderr);
        assert!(!st.status.success(), "{args:?} succeeded");
        assert!(err.contains(&want), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
    // a malformed question file is named with the JSON position
    let q = tmp("questions.json");
    std::fs::write(&q, "{\"questions\": [ {\"id\": 1,,] }").unwrap();
    let st = chatsplat()
        .args(["vqa", "--run"])
        .arg(&missing)
        .args(["--vlm"])
        .arg(&missing)
        .arg("--questions")
        .arg(&q)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(!st.status.success() && err.contains(&q.display().to_string()) && err.contains("line"), "{err}");
}

/// Issue 84's flow on a capture without masks: `train` -> `masks` (per-view masks whose ids are
/// arbitrary per view) -> `identity` -> `extract` -> `train-language` -> object chat and `find`.
#[test]
fn a_capture_without_masks_gets_objects_through_masks_and_identity() {
    let root = tmp("flow");
    let (data, per_view, masks) = (root.join("capture"), root.join("per-view"), root.join("masks"));
    let (run, objects, teacher) = (root.join("run"), root.join("run-objects"), root.join("teacher"));
    let ok = |c: &mut Command| {
        let o = c.output().unwrap();
        let (out, err) = (String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
        assert!(o.status.success(), "{c:?}\n{out}\n{err}");
        format!("{out}{err}")
    };
    ok(chatsplat()
        .args(["synth", "--seed", "11", "--views", "10", "--width", "64", "--height", "56", "--out"])
        .arg(&data));
    // the segmenter's masks: the true ones with their ids shuffled per view, one view without a
    // file; then the capture loses its own masks
    let true_objects = chatsplat_tests::unlabelled::strip_to_per_view(&data, &per_view);

    let config = root.join("geometry.json");
    std::fs::write(
        &config,
        r#"{"iters": 300, "init_per_view": 400, "densify_from": 50, "densify_every": 50, "densify_until": 1000,
            "opacity_reset_every": 0, "checkpoint_every": 0, "max_gaussians": 6000}"#,
    )
    .unwrap();
    ok(chatsplat().arg("train").arg("--data").arg(&data).arg("--out").arg(&run).arg("--config").arg(&config));
    let said = ok(chatsplat()
        .arg("masks")
        .args(["--data".as_ref(), data.as_os_str(), "--run".as_ref(), run.as_os_str()])
        .arg("--per-view")
        .arg(&per_view)
        .arg("--out")
        .arg(&masks));
    let summary: serde_json::Value = serde_json::from_slice(&std::fs::read(masks.join("masks.json")).unwrap()).unwrap();
    let found = summary["objects"].as_array().unwrap().len();
    assert!(found >= true_objects.min(2) && found <= true_objects, "{found} of {true_objects} objects: {said}");
    assert_eq!(summary["views_without_masks"].as_array().unwrap().len(), 1, "{summary}");
    // the table the objects stand on is the one surface (kept out of find, as scene.json keeps it)
    let surfaces: Vec<u64> = summary["objects"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|o| o["surface"].as_bool().unwrap())
        .map(|o| o["id"].as_u64().unwrap())
        .collect();
    assert_eq!(surfaces.len(), 1, "{summary}");

    // the same matching from masks SAM makes here, in process (the tiny random checkpoint: its
    // masks mean nothing, but every view is segmented and the masks folder is whole)
    // masks, named by its repo id and fetched from a loopback hub into HF_HOME
    let tiny_sam = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("checkpoints/tiny-sam");
    let hub = FakeHub::start("acme/tiny-sam", Served::files(&tiny_sam, &["config.json", "model.safetensors"]));
    let hf_home = root.join("hf-home");
    let sam_masks = root.join("sam-masks");
    let masks_cmd = || {
        let mut c = chatsplat();
        c.env("HF_HOME", &hf_home).env("HF_ENDPOINT", &hub.endpoint).env_remove("HF_HUB_OFFLINE");
        c.arg("masks").args(["--data".as_ref(), data.as_os_str(), "--run".as_ref(), run.as_os_str()]);
        c.args(["--segmenter", "acme/tiny-sam", "--points-per-side", "4", "--keep-per-view"])
            .arg("--out")
            .arg(&sam_masks);
        c
    };
    let both = masks_cmd().arg("--per-view").arg(&per_view).output().unwrap();
    assert!(!both.status.success() && !sam_masks.exists(), "--per-view and --segmenter together were not refused");
    let mut missing = chatsplat();
    missing.arg("masks").args(["--data".as_ref(), data.as_os_str(), "--run".as_ref(), run.as_os_str()]);
    let o = missing.arg("--segmenter").arg(root.join("no-such-sam")).arg("--out").arg(&sam_masks).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("no-such-sam") && !sam_masks.exists(), "{err}");
    // offline with nothing cached: refused, naming the repo, nothing written
    let o = masks_cmd().env("HF_HUB_OFFLINE", "1").output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("acme/tiny-sam") && !sam_masks.exists(), "{err}");
    let said = ok(&mut masks_cmd());
    assert!(said.contains("SAM:") && said.contains("s per view"), "{said}");
    let fetched = hf_home.join("hub/models--acme--tiny-sam/snapshots").join(COMMIT).join("model.safetensors");
    assert_eq!(std::fs::read(fetched).unwrap(), std::fs::read(tiny_sam.join("model.safetensors")).unwrap());
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(sam_masks.join("masks.json")).unwrap()).unwrap();
    assert_eq!(summary["views_without_masks"].as_array().unwrap().len(), 0, "{summary}");
    for image in std::fs::read_dir(data.join("images")).unwrap() {
        let stem = image.unwrap().path().file_stem().unwrap().to_string_lossy().into_owned();
        assert!(sam_masks.join(format!("{stem}.png")).is_file(), "no SAM-matched mask for {stem}");
        assert!(sam_masks.join(format!("per-view/{stem}.png")).is_file(), "SAM's own mask of {stem} not kept");
    }

    // identity on the frozen geometry: a new run, the old one untouched, the same Gaussians
    let before = std::fs::read(run.join("checkpoint.safetensors")).unwrap();
    let identity = || {
        let mut c = chatsplat();
        c.arg("identity").arg("--data").arg(&data).arg("--run").arg(&run);
        c.arg("--masks").arg(&masks).arg("--out").arg(&objects);
        c
    };
    let said = ok(identity().args(["--iters", "40"]));
    assert_eq!(std::fs::read(run.join("checkpoint.safetensors")).unwrap(), before, "the old run changed");
    let tensor = |dir: &std::path::Path, name: &str| {
        let bytes = std::fs::read(dir.join("checkpoint.safetensors")).unwrap();
        let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
        (st.tensor(name).unwrap().data().to_vec(), st.tensor(name).unwrap().shape().to_vec())
    };
    for name in ["means", "log_scales", "opacity_logits", "sh_dc"] {
        assert!(tensor(&run, name) == tensor(&objects, name), "{name} changed");
    }
    assert_eq!(tensor(&objects, "classifier_w").1, vec![16, found + 1], "one class per object and the background");
    let miou: f32 = said
        .split("identity mIoU ")
        .nth(1)
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or_else(|| panic!("no mIoU in {said}"));
    assert!(miou > 0.5, "{said}");
    // a second identity onto the same --out is refused, and changes nothing
    let st = identity().output().unwrap();
    assert!(!st.status.success() && String::from_utf8_lossy(&st.stderr).contains("--out"));

    // the language stage on the run with objects (the built-in model): object chat at a click
    // on a matched object, and find, name matched objects
    ok(chatsplat()
        .arg("extract")
        .arg("--data")
        .arg(&data)
        .arg("--masks")
        .arg(&masks)
        .arg("--run")
        .arg(&objects)
        .args(["--novel-views", "0", "--out"])
        .arg(&teacher));
    ok(chatsplat().arg("train-language").arg("--run").arg(&objects).arg("--teacher").arg(&teacher).args([
        "--iters",
        "3",
        "--no-compact",
    ]));
    // view 0 is the run's first camera; a pixel well inside one of its matched masks
    let cams: serde_json::Value =
        serde_json::from_slice(&std::fs::read(objects.join("cameras.json")).unwrap()).unwrap();
    let first = std::path::Path::new(cams["train"][0]["image"].as_str().unwrap()).file_stem().unwrap().to_owned();
    let (w, h, ids) = model::data::read_ids16_any(&masks.join(first).with_extension("png")).unwrap();
    let (w, h) = (w as usize, h as usize);
    let inside = |p: usize| {
        let (x, y) = (p % w, p / w);
        let around = |k: usize| ids[(y + k / 5 - 2) * w + x + k % 5 - 2];
        ids[p] != 0 && x > 1 && y > 1 && x + 2 < w && y + 2 < h && (0..25).all(|k| around(k) == ids[p])
    };
    let p = (0..w * h).find(|&p| inside(p)).expect("an object well inside view 0");
    let (x, y) = ((p % w).to_string(), (p / w).to_string());
    let said = ok(chatsplat()
        .arg("ask")
        .arg("--run")
        .arg(&objects)
        .args(["--view", "0", "--object", &x, &y])
        .arg("What is this?"));
    assert!(said.contains(&format!("picked object {}", ids[p])), "{said}");
    let said = ok(chatsplat().arg("find").arg("--run").arg(&objects).args(["--json", "--threshold", "0", "cone"]));
    let listed: serde_json::Value = serde_json::from_str(said.lines().find(|l| l.starts_with('{')).unwrap()).unwrap();
    let ids: Vec<u64> = listed["matches"].as_array().unwrap().iter().map(|m| m["id"].as_u64().unwrap()).collect();
    assert!(!ids.is_empty() && ids.iter().all(|&i| i >= 1 && i <= found as u64), "{said}");
    assert!(!ids.contains(&surfaces[0]), "the table was searched: {said}");
    // a question file whose find entry names the surface is refused, naming it
    let q = root.join("find-surface.json");
    std::fs::write(
        &q,
        format!(
            r#"{{"questions": [{{"id": "f", "level": "find", "question": "red", "answer": "-", "objects": [{}]}}]}}"#,
            surfaces[0]
        ),
    )
    .unwrap();
    let o = chatsplat().arg("vqa").arg("--run").arg(&objects).arg("--questions").arg(&q).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("find-surface.json") && err.contains("a surface"), "{err}");
}
