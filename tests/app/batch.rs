//! `chatsplat batch` as a cluster runs it: two shards as two processes cover a manifest exactly
//! once, a rerun skips finished scenes, a worker killed mid-scene resumes it, and a bad manifest
//! or shard is refused naming the line; the `deploy/` manifests parse and call only commands and
//! options the binary has.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_chatsplat");

fn tmp(name: &str) -> chatsplat_tests::Scratch {
    chatsplat_tests::temp_dir(&format!("batch-{name}"))
}

fn show(o: &Output) -> String {
    format!("stdout:\n{}\nstderr:\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// Tiny synthetic tabletops `d<seed>` in `dir` (6 views of 48x48).
fn scenes(dir: &Path, seeds: &[u64]) {
    for s in seeds {
        let o = Command::new(BIN)
            .args(["synth", "--seed", &s.to_string(), "--views", "6", "--width", "48", "--height", "48", "--out"])
            .arg(dir.join(format!("d{s}")))
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", show(&o));
    }
}

fn batch(manifest: &Path, extra: &[&str]) -> Command {
    let mut c = Command::new(BIN);
    c.args(["batch", "--manifest"]).arg(manifest).args(extra);
    c
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))).unwrap()
}

fn summary(out: &Path, scene: &str) -> serde_json::Value {
    json(&out.join(scene).join("summary.json"))
}

#[test]
fn two_shards_cover_the_manifest_once_and_a_rerun_skips_what_is_done() {
    let dir = tmp("shards");
    std::fs::create_dir_all(&*dir).unwrap();
    scenes(&dir, &[30_201, 30_202, 30_203]);
    let manifest = dir.join("scenes.toml");
    let text = "geometry_iters = 20\nlanguage_iters = 3\n\n[[scene]]\nname = \"one\"\ndata = \"d30201\"\n\n\
                [[scene]]\nname = \"two\"\ndata = \"d30202\"\n\n[[scene]]\nname = \"three\"\ndata = \"d30203\"\n";
    std::fs::write(&manifest, text).unwrap();
    let workers: Vec<_> = ["0/2", "1/2"]
        .iter()
        .map(|s| batch(&manifest, &["--shard", s]).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap())
        .collect();
    for w in workers {
        let o = w.wait_with_output().unwrap();
        assert!(o.status.success(), "{}", show(&o));
    }
    let out = dir.join("scenes-out");
    // shard 0 took scenes 0 and 2, shard 1 scene 1: each exactly once
    let mut answered = 0;
    for (scene, shard, seed) in [("one", "0/2", 30_201), ("two", "1/2", 30_202), ("three", "0/2", 30_203)] {
        let s = summary(&out, scene);
        assert_eq!(s["shard"], shard, "{s}");
        assert_eq!(s["resumed_from"], serde_json::json!({}), "{s}");
        for stage in ["geometry", "teacher", "language"] {
            assert!(s["seconds"][stage].as_f64().is_some(), "{stage} missing in {s}");
        }
        // the teacher leaves the default number of the tower's last layers to chat
        let index = json(&out.join(scene).join("teacher/teacher.json"));
        assert_eq!(index["tower_tail"], train::teacher::DEFAULT_TOWER_TAIL, "{scene}");
        // VQA on every question of the scene's file (the find phrases scored apart), or none
        // when a 48 px capture has none
        let qf = json(&dir.join(format!("d{seed}/questions.json")));
        let all = qf["questions"].as_array().unwrap();
        let phrases = all.iter().filter(|q| q["level"] == "find").count() as u64;
        let asked = all.len() as u64 - phrases;
        if all.is_empty() {
            assert!(s["vqa"].is_null(), "{s}");
        } else {
            assert_eq!(s["vqa"]["overall"]["questions"].as_u64(), Some(asked), "{s}");
            assert!(phrases > 0, "a synthetic scene's file has find phrases: {qf}");
            assert_eq!(s["vqa"]["find"]["phrases"].as_u64(), Some(phrases), "{s}");
            answered += 1;
        }
    }
    assert!(answered > 0, "no scene had questions");
    let o = batch(&manifest, &["--report"]).output().unwrap();
    assert!(o.status.success(), "{}", show(&o));
    let report = json(&out.join("report.json"));
    assert_eq!(report["done"], 3, "{report}");
    let names: Vec<&str> = report["results"].as_array().unwrap().iter().map(|r| r["scene"].as_str().unwrap()).collect();
    assert_eq!(names, ["one", "two", "three"]);
    // a worker started again skips its finished scene and leaves it as it was
    let before = std::fs::read(out.join("two/summary.json")).unwrap();
    let o = batch(&manifest, &["--shard", "1/2"]).output().unwrap();
    assert!(o.status.success(), "{}", show(&o));
    assert!(String::from_utf8_lossy(&o.stderr).contains("done earlier"), "{}", show(&o));
    assert_eq!(std::fs::read(out.join("two/summary.json")).unwrap(), before);
    let left: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".tmp"))
        .collect();
    assert!(left.is_empty(), "temporary files left behind: {left:?}");
}

#[test]
fn a_worker_killed_mid_scene_resumes_it_from_its_checkpoint() {
    let dir = tmp("killed");
    std::fs::create_dir_all(&*dir).unwrap();
    scenes(&dir, &[30_204]);
    let manifest = dir.join("one.toml");
    // a tower tail other than the default, as a manifest asks for it
    let tail = train::teacher::DEFAULT_TOWER_TAIL + 1;
    let text = format!(
        "geometry_iters = 80\nlanguage_iters = 3\ntower_tail = {tail}\n[[scene]]\nname = \"a\"\ndata = \"d30204\"\n"
    );
    std::fs::write(&manifest, text).unwrap();
    let state = dir.join("one-out/a/run/state.json");
    let mut child = batch(&manifest, &[]).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
    // killed (SIGKILL) once the geometry has a checkpoint past its start
    let t0 = Instant::now();
    let at = loop {
        let iter = std::fs::read(&state)
            .ok()
            .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
            .and_then(|v| v["iter"].as_u64());
        if let Some(i) = iter.filter(|&i| i > 0) {
            child.kill().unwrap();
            child.wait().unwrap();
            break i;
        }
        assert!(child.try_wait().unwrap().is_none(), "the worker finished before it could be killed");
        assert!(t0.elapsed() < Duration::from_secs(300), "no checkpoint past the start");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(!dir.join("one-out/a/summary.json").exists());
    let o = batch(&manifest, &[]).output().unwrap();
    assert!(o.status.success(), "{}", show(&o));
    let s = summary(&dir.join("one-out"), "a");
    let resumed = s["resumed_from"]["geometry"].as_u64().expect("resumed");
    assert!(resumed >= at, "resumed from {resumed}, killed after {at}: {s}");
    let metrics = json(&dir.join("one-out/a/run/metrics.json"));
    let state = json(&state);
    assert_eq!(state["iter"], 80, "{metrics}");
    assert_eq!(json(&dir.join("one-out/a/teacher/teacher.json"))["tower_tail"], tail);
    assert_eq!(json(&dir.join("one-out/a/run/language/state.json"))["field"]["tower_tail"], tail);
}

/// A scene that fails is recorded and the shard goes on (exiting non-zero, naming it); a scene
/// pointed at other data runs again, its earlier results kept aside.
#[test]
fn a_failed_scene_is_recorded_and_a_scene_on_other_data_runs_again() {
    let dir = tmp("failed");
    std::fs::create_dir_all(&*dir).unwrap();
    scenes(&dir, &[30_205, 30_206]);
    std::fs::create_dir_all(dir.join("broken")).unwrap();
    std::fs::write(dir.join("broken/transforms.json"), "{\"frames\": [").unwrap();
    let manifest = dir.join("m.toml");
    let text = |good: &str| {
        format!(
            "geometry_iters = 10\nlanguage_iters = 2\n[[scene]]\nname = \"bad\"\ndata = \"broken\"\n\
             [[scene]]\nname = \"good\"\ndata = \"{good}\"\n"
        )
    };
    std::fs::write(&manifest, text("d30205")).unwrap();
    let o = batch(&manifest, &[]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && !err.contains("panicked"), "{}", show(&o));
    assert!(err.contains("1 of its 2 scenes failed: bad"), "{}", show(&o));
    let out = dir.join("m-out");
    let first = summary(&out, "good");
    let failed = json(&out.join("bad/failed.json"));
    assert!(failed["error"].as_str().unwrap().contains("transforms.json"), "{failed}");
    let report = json(&out.join("report.json"));
    let status: Vec<&str> =
        report["results"].as_array().unwrap().iter().map(|r| r["status"].as_str().unwrap()).collect();
    assert_eq!(status, ["failed", "done"], "{report}");
    // the same manifest again: "good" is done, "bad" fails again
    let o = batch(&manifest, &[]).output().unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("done earlier"), "{}", show(&o));
    assert_eq!(summary(&out, "good"), first);
    // "good" pointed at other data: it runs again, and its earlier folder is kept aside
    std::fs::write(&manifest, text("d30206")).unwrap();
    let o = batch(&manifest, &[]).output().unwrap();
    assert!(String::from_utf8_lossy(&o.stderr).contains("runs again"), "{}", show(&o));
    let second = summary(&out, "good");
    assert_ne!(second["job"], first["job"], "{second}");
    assert!(second["data"].as_str().unwrap().ends_with("d30206"), "{second}");
    let aside = out.join(format!("good.superseded-{}", first["job"].as_str().unwrap()));
    assert_eq!(json(&aside.join("summary.json")), first);
}

/// Issue 84's flow in a batch: a capture without masks and a segmenter's per-view masks beside it
/// -> geometry without masks -> matched masks -> identity -> teacher (object crops from the
/// matched masks) -> language field.
#[test]
fn a_scene_given_per_view_masks_gets_its_objects() {
    let dir = tmp("per-view");
    std::fs::create_dir_all(&*dir).unwrap();
    scenes(&dir, &[30_211]);
    let true_objects = chatsplat_tests::unlabelled::strip_to_per_view(&dir.join("d30211"), &dir.join("sam"));
    // a second scene with no masks at all: SAM (the tiny random checkpoint) makes them
    scenes(&dir, &[30_212]);
    chatsplat_tests::unlabelled::strip_to_per_view(&dir.join("d30212"), &dir.join("unused"));
    let tiny_sam = Path::new(env!("CARGO_MANIFEST_DIR")).join("checkpoints/tiny-sam");
    let manifest = dir.join("scenes.toml");
    let text = format!(
        "geometry_iters = 150\nlanguage_iters = 3\nsegmenter = {:?}\n\n[[scene]]\nname = \"one\"\n\
         data = \"d30211\"\nper_view_masks = \"sam\"\n\n[[scene]]\nname = \"two\"\ndata = \"d30212\"\n\
         geometry_iters = 40\n",
        tiny_sam.display().to_string()
    );
    std::fs::write(&manifest, text).unwrap();
    let o = batch(&manifest, &[]).output().unwrap();
    assert!(o.status.success(), "{}", show(&o));
    let out = dir.join("scenes-out/one");
    let s = summary(&dir.join("scenes-out"), "one");
    for stage in ["geometry", "objects", "teacher", "language"] {
        assert!(s["seconds"][stage].as_f64().is_some(), "{stage} missing in {s}");
    }
    let matched = json(&out.join("masks/masks.json"));
    let found = matched["objects"].as_array().unwrap().len();
    assert!(found >= 1 && found <= true_objects, "{found} of {true_objects} objects: {matched}");
    // the run chat reads has an identity field of the matched objects; the geometry without masks
    // beside it
    let state = json(&out.join("run/state.json"));
    assert!(!state["data"]["mask_dir"].is_null(), "the run names no masks: {state}");
    let bytes = std::fs::read(out.join("run/checkpoint.safetensors")).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let shape = st.tensor("classifier_w").unwrap().shape().to_vec();
    assert_eq!(shape, vec![16, found + 1], "one class per object and the background");
    assert!(out.join("geometry/checkpoint.safetensors").is_file());
    // the scene without masks: SAM's masks of every image kept, matched, and the stages run
    let two = dir.join("scenes-out/two");
    let images = std::fs::read_dir(dir.join("d30212/images")).unwrap().count();
    assert_eq!(std::fs::read_dir(two.join("per-view")).unwrap().count(), images, "a view without SAM's masks");
    assert!(two.join("masks/masks.json").is_file(), "SAM's masks were not matched");
    let s = summary(&dir.join("scenes-out"), "two");
    assert!(s["seconds"]["objects"].as_f64().is_some(), "no objects stage in {s}");
}

#[test]
fn bad_manifests_and_shards_are_refused_naming_the_line() {
    let dir = tmp("bad");
    std::fs::create_dir_all(dir.join("d")).unwrap();
    let cases: Vec<(&str, &str, Vec<&str>)> = vec![
        ("[[scene]]\nname = \"a\"\ndata = \"d\"\ncolour = \"red\"\n", "", vec![":4:", "unknown field `colour`"]),
        (
            "[[scene]]\nname = \"a\"\ndata = \"d\"\n\n[[scene]]\nname = \"b\"\ndata = \"missing\"\n",
            "",
            vec![":7:", "scene `b`", "missing is not a directory"],
        ),
        (
            "[[scene]]\nname = \"a\"\ndata = \"d\"\n[[scene]]\nname = \"a\"\ndata = \"d\"\n",
            "",
            vec![":5:", "listed twice"],
        ),
        ("[[scene]]\nname = \"../up\"\ndata = \"d\"\n", "", vec![":2:", "folder name"]),
        ("backend = \"cuda\"\n[[scene]]\nname = \"a\"\ndata = \"d\"\n", "", vec![":1:", "cuda"]),
        ("geometry_iters = 10\n", "", vec!["no [[scene]]"]),
        ("[[scene]]\nname = \"a\"\ndata = \"d\"\n", "2/2", vec!["--shard 2/2", "below the shard count"]),
        ("[[scene]]\nname = \"a\"\ndata = \"d\"\n", "x", vec!["--shard x", "I/N"]),
        // a global setting the model cannot meet: refused before the first scene
        ("tower_tail = 99\n[[scene]]\nname = \"a\"\ndata = \"d\"\n", "", vec!["tower_tail 99", "vision tower"]),
        (
            "segmenter = \"no/such/sam\"\n[[scene]]\nname = \"a\"\ndata = \"d\"\n",
            "",
            vec!["segmenter", "no/such/sam", "no SAM folder"],
        ),
        (
            "[[scene]]\nname = \"a\"\ndata = \"d\"\nper_view_masks = \"sam\"\n",
            "",
            vec![":4:", "scene `a`", "per_view_masks", "sam is not a directory"],
        ),
    ];
    for (k, (text, shard, want)) in cases.into_iter().enumerate() {
        let manifest = dir.join(format!("m{k}.toml"));
        std::fs::write(&manifest, text).unwrap();
        let extra: Vec<&str> = if shard.is_empty() { vec![] } else { vec!["--shard", shard] };
        let o = batch(&manifest, &extra).output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && !err.contains("panicked"), "case {k}: {}", show(&o));
        assert!(err.contains(&format!("m{k}.toml")) || !shard.is_empty(), "case {k} names no file: {err}");
        for w in want {
            assert!(err.contains(w), "case {k}: no `{w}` in: {err}");
        }
    }
    // the scheduler's index without its count
    let manifest = dir.join("m0.toml");
    std::fs::write(&manifest, "[[scene]]\nname = \"a\"\ndata = \"d\"\n").unwrap();
    let o = batch(&manifest, &[]).env("JOB_COMPLETION_INDEX", "1").output().unwrap();
    assert!(String::from_utf8_lossy(&o.stderr).contains("CHATSPLAT_SHARD_COUNT"), "{}", show(&o));
}

/// The options `chatsplat SUB --help` lists.
fn has_options(sub: &str, args: &[String]) {
    let o = Command::new(BIN).args([sub, "--help"]).output().unwrap();
    assert!(o.status.success(), "chatsplat has no subcommand `{sub}`");
    let help = String::from_utf8_lossy(&o.stdout);
    for a in args.iter().filter(|a| a.starts_with("--")) {
        assert!(help.contains(a.as_str()), "chatsplat {sub} has no {a}");
    }
}

/// The chatsplat command inside a list of words (after `mpirun ...` when there is one).
fn chatsplat_words(words: &[String]) -> Option<(String, Vec<String>)> {
    let at = words.iter().position(|w| w == "chatsplat")?;
    Some((words.get(at + 1)?.clone(), words[at + 2..].to_vec()))
}

fn yaml(path: &Path) -> serde_yaml::Value {
    serde_yaml::from_slice(&std::fs::read(path).unwrap()).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn strings(v: &serde_yaml::Value) -> Vec<String> {
    v.as_sequence().unwrap().iter().map(|w| w.as_str().unwrap().to_string()).collect()
}

#[test]
fn the_deploy_manifests_parse_and_call_commands_the_binary_has() {
    let deploy = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("deploy");
    let job = yaml(&deploy.join("k8s-batch-indexed-job.yaml"));
    assert_eq!(job["kind"], "Job");
    assert_eq!(job["spec"]["completionMode"], "Indexed");
    let container = &job["spec"]["template"]["spec"]["containers"][0];
    let env = container["env"].as_sequence().unwrap();
    let count = env.iter().find(|e| e["name"] == "CHATSPLAT_SHARD_COUNT").expect("CHATSPLAT_SHARD_COUNT");
    assert_eq!(count["value"].as_str().unwrap(), job["spec"]["completions"].as_u64().unwrap().to_string());
    let (sub, args) = chatsplat_words(&strings(&container["command"])).expect("a chatsplat command");
    assert_eq!(sub, "batch");
    has_options(&sub, &args);

    let mpi = yaml(&deploy.join("kubeflow-train-vlm-mpijob.yaml"));
    assert_eq!(mpi["kind"], "MPIJob");
    let spec = &mpi["spec"]["mpiReplicaSpecs"];
    let words = strings(&spec["Launcher"]["template"]["spec"]["containers"][0]["command"]);
    let np: u64 = words[words.iter().position(|w| w == "-np").unwrap() + 1].parse().unwrap();
    assert_eq!(np, spec["Worker"]["replicas"].as_u64().unwrap() * mpi["spec"]["slotsPerWorker"].as_u64().unwrap());
    let (sub, args) = chatsplat_words(&words).expect("a chatsplat command");
    assert_eq!(sub, "train-vlm");
    has_options(&sub, &args);

    for script in ["slurm-batch-array.sh", "slurm-train-vlm.sh"] {
        let path = deploy.join(script);
        let o = Command::new("bash").arg("-n").arg(&path).output().unwrap();
        assert!(o.status.success(), "{script}: {}", String::from_utf8_lossy(&o.stderr));
        let text = std::fs::read_to_string(&path).unwrap();
        let mut found = 0;
        for line in text.lines().filter(|l| !l.trim_start().starts_with('#')) {
            let words: Vec<String> = line.split_whitespace().map(|w| w.trim_matches('"').to_string()).collect();
            if let Some((sub, args)) = chatsplat_words(&words) {
                has_options(&sub, &args);
                found += 1;
            }
        }
        assert!(found > 0, "{script} runs no chatsplat command");
        assert!(text.contains("#SBATCH"), "{script}");
    }
}

#[test]
fn extract_shards_write_what_one_extract_writes_and_the_last_one_writes_the_index() {
    let dir = tmp("extract");
    std::fs::create_dir_all(&*dir).unwrap();
    scenes(&dir, &[30_205]);
    let data = dir.join("d30205");
    let extract = |out: &Path, shard: Option<&str>| {
        let mut c = Command::new(BIN);
        c.args(["extract", "--data"]).arg(&data).arg("--out").arg(out);
        if let Some(s) = shard {
            c.args(["--shard", s]);
        }
        let o = c.output().unwrap();
        assert!(o.status.success(), "{}", show(&o));
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let (sharded, whole) = (dir.join("sharded"), dir.join("whole"));
    let said = extract(&sharded, Some("1/2"));
    assert!(said.contains("3 of 6 views done: the index waits for the other shards"), "{said}");
    assert!(!sharded.join("teacher.json").exists());
    let said = extract(&sharded, Some("0/2"));
    assert!(said.contains("teacher.json"), "{said}");
    extract(&whole, None);
    let files = |d: &Path| {
        let mut v: Vec<String> =
            std::fs::read_dir(d).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        v.sort();
        v
    };
    assert_eq!(files(&sharded), files(&whole));
    assert_eq!(files(&whole).len(), 7, "{:?}", files(&whole));
    // the same header (its metadata map's order aside) and the same token bytes
    let split = |p: &Path| -> (serde_json::Value, Vec<u8>) {
        let b = std::fs::read(p).unwrap();
        let n = u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
        (serde_json::from_slice(&b[8..8 + n]).unwrap(), b[8 + n..].to_vec())
    };
    for f in files(&whole).iter().filter(|f| f.ends_with(".safetensors")) {
        let ((ha, da), (hb, db)) = (split(&sharded.join(f)), split(&whole.join(f)));
        assert_eq!(ha, hb, "{f}");
        assert!(da == db, "{f}: the tokens differ");
    }
    // the same index, but for each file's content hash (the header's metadata is written in a
    // random order), which is that of the file each run wrote
    let index = |d: &Path| {
        let mut views = json(&d.join("teacher.json"))["views"].clone();
        for v in views.as_array_mut().unwrap() {
            let file = d.join(v["file"].as_str().unwrap());
            let hash = v.as_object_mut().unwrap().remove("hash").expect("the index records each file's hash");
            assert_eq!(hash, train::teacher::content_hash(&std::fs::read(&file).unwrap()), "{}", file.display());
        }
        views
    };
    assert_eq!(index(&sharded), index(&whole));
}
