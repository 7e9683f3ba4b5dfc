//! Data-parallel `train-vlm` under a real `mpirun` (OpenMPI): two ranks with half the samples each
//! make the same updates as one process with all of them; ranks that disagree, one killed and
//! one that hangs all end the job with an error, never a hang. Built only with `--features mpi`;
//! skipped with a message when `mpirun` is missing, unless `CHATSPLAT_REQUIRE_MPI` is set (CI).

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_chatsplat");

fn tmp(name: &str) -> chatsplat_tests::Scratch {
    chatsplat_tests::temp_dir(&format!("mpi-{name}"))
}

/// `mpirun` when installed (else the test skips, or fails when MPI is required).
fn mpirun() -> Option<Command> {
    let found = Command::new("mpirun").arg("--version").stdout(Stdio::null()).stderr(Stdio::null()).status();
    if found.is_err() {
        assert!(
            std::env::var_os("CHATSPLAT_REQUIRE_MPI").is_none(),
            "CHATSPLAT_REQUIRE_MPI is set but mpirun is missing"
        );
        eprintln!("skipped: mpirun not found (apt install openmpi-bin libopenmpi-dev)");
        return None;
    }
    let mut c = Command::new("mpirun");
    // two ranks on whatever cores there are; as root (containers, CI) OpenMPI wants consent
    c.args(["--oversubscribe", "--bind-to", "none"])
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("OMPI_MCA_btl_vader_single_copy_mechanism", "none");
    Some(c)
}

/// A tiny model and a few steps that touch every part of a step: the tower's phase, label tokens,
/// feature noise, every supervised head, and the tower's own learning rate.
fn config(dir: &Path, name: &str, edit: impl FnOnce(&mut serde_json::Value)) -> std::path::PathBuf {
    let mut cfg = serde_json::json!({
        "seed": 5,
        "steps": 6,
        "model": {"image_size": 48, "patch_size": 12, "vision_width": 32, "vision_layers": 2, "vision_heads": 2,
                  "vision_mlp": 64, "text_width": 32, "text_layers": 3, "text_heads": 4, "text_kv_heads": 2,
                  "text_mlp": 64},
        "images_per_step": 8,
        "questions_per_sample": 3,
        "resolution": 48,
        "lr": 3e-3,
        "warmup": 1,
        "tower_steps": 2,
        "tower_images": 4,
        "tower_lr_scale": 0.5,
        "place_weight": 0.3,
        "label_tokens_until": 0.3,
        "label_tokens_end": 0.8,
        "eval_every": 0,
        "eval_seeds": 1
    });
    edit(&mut cfg);
    std::fs::create_dir_all(dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, serde_json::to_string_pretty(&cfg).unwrap()).unwrap();
    path
}

fn train_args(cfg: &Path, out: &Path) -> Vec<std::ffi::OsString> {
    ["train-vlm", "--config"].iter().map(Into::into).chain([cfg.into(), "--out".into(), out.into()]).collect()
}

fn show(o: &Output) -> String {
    format!("stdout:\n{}\nstderr:\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// Runs `c`, killing it past `limit` (a hang fails the test rather than the CI job).
fn run_within(mut c: Command, limit: Duration) -> (Output, Duration) {
    let t0 = Instant::now();
    let mut child = c.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    loop {
        if child.try_wait().unwrap().is_some() {
            return (child.wait_with_output().unwrap(), t0.elapsed());
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let o = child.wait_with_output().unwrap();
            panic!("still running after {limit:?} (a hang)\n{}", show(&o));
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn two_ranks_with_half_the_samples_each_make_the_same_updates_as_one_process() {
    let Some(mut mpi) = mpirun() else { return };
    let dir = tmp("equal");
    let cfg = config(&dir, "cfg.json", |_| {});
    let (one, two) = (dir.join("one"), dir.join("two"));
    let solo = Command::new(BIN).args(train_args(&cfg, &one)).output().unwrap();
    assert!(solo.status.success(), "{}", show(&solo));
    mpi.args(["-np", "2", BIN]).args(train_args(&cfg, &two));
    let (pair, _) = run_within(mpi, Duration::from_secs(300));
    assert!(pair.status.success(), "{}", show(&pair));
    let err = String::from_utf8_lossy(&pair.stderr);
    assert!(err.contains("data-parallel on 2 ranks"), "{err}");
    assert!(err.contains("rank 1 of 2:") && err.contains("in collectives"), "{err}");
    // rank 0 alone reports and writes: one summary line, one model
    assert_eq!(String::from_utf8_lossy(&pair.stdout).matches("trained 1 stage(s)").count(), 1, "{}", show(&pair));
    let (a, _) = model::io::read_f32(&one.join("model.safetensors")).unwrap();
    let (b, _) = model::io::read_f32(&two.join("model.safetensors")).unwrap();
    assert_eq!(a.len(), b.len());
    let mut worst = (0f32, String::new());
    let mut moved = 0f32;
    let init = dir.join("init");
    let cfg0 = config(&dir, "cfg0.json", |c| c["steps"] = 3.into());
    let st = Command::new(BIN).args(train_args(&cfg0, &init)).output().unwrap();
    assert!(st.status.success(), "{}", show(&st));
    let (c, _) = model::io::read_f32(&init.join("model.safetensors")).unwrap();
    for (name, (shape, x)) in &a {
        let (shape_b, y) = &b[name];
        assert_eq!(shape, shape_b, "{name}");
        let d = chatsplat_tests::max_abs_diff(x, y);
        if d > worst.0 {
            worst = (d, name.clone());
        }
        moved = moved.max(chatsplat_tests::max_abs_diff(x, &c[name].1));
    }
    eprintln!("2 ranks against 1: largest weight difference {:.2e} ({}); weights moved {moved:.3}", worst.0, worst.1);
    assert!(worst.0 <= 1e-5, "the 2-rank weights differ from the 1-rank ones by {} in {}", worst.0, worst.1);
    // and training did move them (from the weights after 3 steps), so equal is not trivially so
    assert!(moved > 1e-3, "weights moved by only {moved} in 3 steps");
    let log = |d: &Path| -> Vec<f64> {
        let v: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.join("training_log.json")).unwrap()).unwrap();
        v.as_array()
            .unwrap()
            .iter()
            .flat_map(|l| [l["answer_loss"].as_f64().unwrap(), l["aux_loss"].as_f64().unwrap()])
            .collect()
    };
    let (la, lb) = (log(&one), log(&two));
    assert_eq!(la.len(), lb.len());
    for (x, y) in la.iter().zip(&lb) {
        assert!((x - y).abs() <= 1e-4 * x.abs().max(1.0), "logged losses differ: {la:?} vs {lb:?}");
    }
}

#[test]
fn ranks_that_disagree_stop_with_an_error_naming_the_problem() {
    let Some(mpi) = mpirun() else { return };
    let dir = tmp("disagree");
    let good = config(&dir, "good.json", |_| {});
    let wider = config(&dir, "wider.json", |c| c["model"]["text_width"] = 64.into());
    let faster = config(&dir, "faster.json", |c| c["lr"] = 6e-3.into());
    for (other, says) in [(wider, "weights, rank 1 has"), (faster, "weights differ after step")] {
        let mut c = Command::new(mpi.get_program());
        c.args(mpi.get_args()).envs(mpi.get_envs().filter_map(|(k, v)| Some((k, v?))));
        c.args(["-np", "1", BIN]).args(train_args(&good, &dir.join("a"))).arg(":");
        c.args(["-np", "1", BIN]).args(train_args(&other, &dir.join("b")));
        let (o, _) = run_within(c, Duration::from_secs(120));
        assert!(!o.status.success(), "{}", show(&o));
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(says) && err.contains("stopping every rank"), "{}", show(&o));
    }
}

/// Rank 1 runs under a shell that stops (SIGSTOP) or kills (SIGKILL) it a few seconds in.
fn rank_one_then(signal: &str, timeout_s: u64) -> (Output, Duration) {
    let mpi = mpirun().expect("checked");
    let dir = tmp(&format!("signal-{signal}"));
    let cfg = config(&dir, "long.json", |c| {
        c["steps"] = 100_000.into();
        c["tower_steps"] = 0.into();
    });
    let out = dir.join("out");
    let script = format!(
        "\"{BIN}\" train-vlm --config \"{}\" --out \"{}\" & pid=$!; \
         if [ \"$OMPI_COMM_WORLD_RANK\" = 1 ]; then sleep 6; kill -{signal} $pid; fi; wait $pid",
        cfg.display(),
        out.display()
    );
    let mut c = Command::new(mpi.get_program());
    c.args(mpi.get_args()).envs(mpi.get_envs().filter_map(|(k, v)| Some((k, v?))));
    c.env("CHATSPLAT_MPI_TIMEOUT", timeout_s.to_string()).args(["-np", "2", "sh", "-c", &script]);
    let r = run_within(c, Duration::from_secs(120));
    // a stopped rank the launcher did not reap
    let _ = Command::new("pkill").args(["-KILL", "-f", &out.display().to_string()]).status();
    r
}

#[test]
fn a_rank_that_hangs_or_is_killed_stops_the_others_and_nothing_waits_forever() {
    if mpirun().is_none() {
        return;
    }
    let (o, took) = rank_one_then("STOP", 8);
    assert!(!o.status.success(), "{}", show(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("no answer from the other ranks in") && err.contains("stopping every rank"), "{}", show(&o));
    assert!(took < Duration::from_secs(60), "took {took:?}");
    let (o, took) = rank_one_then("KILL", 600);
    assert!(!o.status.success(), "{}", show(&o));
    assert!(took < Duration::from_secs(60), "took {took:?} after a rank was killed\n{}", show(&o));
}

#[test]
fn the_language_stage_on_two_ranks_makes_the_same_updates_as_one_process() {
    let Some(mut mpi) = mpirun() else { return };
    let scene = chatsplat_tests::fixture::tabletop(Path::new(env!("CARGO_TARGET_TMPDIR")));
    let dir = tmp("language");
    std::fs::create_dir_all(&dir).unwrap();
    let cfg = dir.join("language.json");
    let lang = serde_json::json!({
        "iters": 1, "views_per_step": 4, "warmup_iters": 0, "max_objects_per_step": 2, "checkpoint_every": 0,
        "field": {"patch": 0}
    });
    std::fs::write(&cfg, lang.to_string()).unwrap();
    let args = |out: &Path| -> Vec<std::ffi::OsString> {
        let teacher = scene.data.join("teacher");
        let mut v: Vec<std::ffi::OsString> = vec!["train-language".into(), "--run".into(), scene.run.clone().into()];
        v.extend([
            "--teacher".into(),
            teacher.into(),
            "--out".into(),
            out.into(),
            "--config".into(),
            cfg.clone().into(),
        ]);
        v
    };
    let (one, two) = (dir.join("one"), dir.join("two"));
    let solo = Command::new(BIN).args(args(&one)).output().unwrap();
    assert!(solo.status.success(), "{}", show(&solo));
    mpi.args(["-np", "2", BIN]).args(args(&two));
    let (pair, _) = run_within(mpi, Duration::from_secs(300));
    assert!(pair.status.success(), "{}", show(&pair));
    assert!(
        String::from_utf8_lossy(&pair.stderr).contains("data-parallel on 2 ranks (4 views per step"),
        "{}",
        show(&pair)
    );
    // One step: the gradients (Adam's first moment, 0.1 x the gradient) must agree; the weights
    // must agree wherever the gradient is above rounding level. (The language stage's Adam has an
    // epsilon of 1e-15, so a gradient that is rounding noise still moves a weight by a full
    // learning rate, in the direction the noise happens to have: summed in another order, it
    // can differ.)
    let (a, _) = model::io::read_f32(&one.join("language.safetensors")).unwrap();
    let (b, _) = model::io::read_f32(&two.join("language.safetensors")).unwrap();
    assert_eq!(a.len(), b.len());
    let (mut worst_grad, mut worst_weight, mut noise_only) = ((0f32, String::new()), (0f32, String::new()), 0);
    for (name, (shape, x)) in a.iter().filter(|(n, _)| !n.starts_with("adam.") && *n != "contribution") {
        let (m1a, m1b) = (&a[&format!("adam.{name}.m1")].1, &b[&format!("adam.{name}.m1")].1);
        let top = m1a.iter().fold(0f32, |m, v| m.max(v.abs()));
        assert!(top > 0.0, "{name} got no gradient");
        let d = chatsplat_tests::max_abs_diff(m1a, m1b) / top;
        if d > worst_grad.0 {
            worst_grad = (d, name.clone());
        }
        let (shape_b, y) = &b[name];
        assert_eq!(shape, shape_b, "{name}");
        for i in 0..x.len() {
            let d = (x[i] - y[i]).abs();
            if m1a[i].abs() > 1e-4 * top {
                if d > worst_weight.0 {
                    worst_weight = (d, name.clone());
                }
            } else if d > 1e-6 {
                noise_only += 1;
            }
        }
    }
    eprintln!(
        "language stage on 2 ranks against 1: gradients differ by at most {:.2e} of their largest ({}); weights \
         by {:.2e} ({}) where the gradient is above rounding level; {noise_only} weights moved differently by a \
         rounding-level gradient",
        worst_grad.0, worst_grad.1, worst_weight.0, worst_weight.1
    );
    assert!(worst_grad.0 <= 1e-5, "the 2-rank gradient differs by {} in {}", worst_grad.0, worst_grad.1);
    assert!(worst_weight.0 <= 1e-6, "the 2-rank weights differ by {} in {}", worst_weight.0, worst_weight.1);
}
