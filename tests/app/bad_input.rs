//! The bad-input suite: broken files, bad configs and bad command lines, generated here, each run
//! through the `chatsplat` binary as a user would. Every case must exit non-zero (or succeed where
//! a success is the documented behaviour), name the file or option and the problem, never panic,
//! and leave what the user had intact.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

#[path = "bad_input/output_table.rs"]
mod output_table;

fn chatsplat() -> Command {
    Command::new(env!("CARGO_BIN_EXE_chatsplat"))
}

fn root(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("chatsplat-bad-{tag}-{}", std::process::id()));
    std::fs::remove_dir_all(&d).ok();
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn run(args: &[&str], paths: &[&Path]) -> Output {
    let mut c = chatsplat();
    c.args(args);
    for p in paths {
        c.arg(p);
    }
    c.output().unwrap()
}

/// One case: what it ran, what the user must read in the error.
struct Case {
    name: String,
    out: Output,
    /// Every one of these must be in stderr (case-insensitive).
    expect: Vec<String>,
}

#[derive(Default)]
struct Suite {
    cases: usize,
    failures: Vec<String>,
}

impl Suite {
    /// Checks a case that must fail: non-zero exit, no panic, every expected word in stderr.
    fn fails(&mut self, c: Case) {
        self.cases += 1;
        let err = String::from_utf8_lossy(&c.out.stderr).to_lowercase();
        let mut why = Vec::new();
        if c.out.status.success() {
            why.push("exited 0".to_string());
        }
        if err.contains("panicked") || c.out.status.code().is_none() {
            why.push("panicked or was killed".to_string());
        }
        for e in &c.expect {
            if !err.contains(&e.to_lowercase()) {
                why.push(format!("no \"{e}\" in the message"));
            }
        }
        if !why.is_empty() {
            self.failures.push(format!("{}: {} -- stderr: {}", c.name, why.join(", "), err.trim()));
        }
    }

    /// Checks a case that must succeed (documented behaviour).
    fn succeeds(&mut self, name: &str, out: Output) {
        self.cases += 1;
        if !out.status.success() {
            self.failures.push(format!("{name}: failed: {}", String::from_utf8_lossy(&out.stderr).trim()));
        }
    }

    fn check(&mut self, name: &str, ok: bool, what: &str) {
        self.cases += 1;
        if !ok {
            self.failures.push(format!("{name}: {what}"));
        }
    }

    fn finish(self, at_least: usize) {
        eprintln!("{} cases, {} failures", self.cases, self.failures.len());
        assert!(
            self.failures.is_empty(),
            "{} of {} cases failed:\n{}",
            self.failures.len(),
            self.cases,
            self.failures.join("\n")
        );
        assert!(self.cases >= at_least, "only {} cases", self.cases);
    }
}

/// Starts `c`, waits (at most 120 s) until `file` exists, then kills it (SIGKILL) half a second later.
fn kill_after(mut c: Command, file: &Path) {
    let mut child = c.stdout(std::process::Stdio::null()).stderr(std::process::Stdio::null()).spawn().unwrap();
    let t0 = std::time::Instant::now();
    while !file.is_file() && t0.elapsed().as_secs() < 120 {
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
    std::thread::sleep(std::time::Duration::from_millis(500));
    child.kill().unwrap();
    child.wait().unwrap();
}

fn name_of(p: &Path) -> String {
    p.file_name().unwrap().to_string_lossy().into_owned()
}

/// A valid binary .ply in the Inria 3DGS layout with `n` Gaussians.
fn inria_ply(n: usize) -> Vec<u8> {
    let mut out = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n").into_bytes();
    for p in PLY_PROPS {
        out.extend(format!("property float {p}\n").bytes());
    }
    out.extend(b"end_header\n");
    for i in 0..n {
        let v = [i as f32 * 0.1, 0.0, 0.0, 0.5, 0.2, 0.1, 2.0, -3.0, -3.0, -3.0, 1.0, 0.0, 0.0, 0.0];
        for x in v {
            out.extend(x.to_le_bytes());
        }
    }
    out
}

fn ply_header(count: &str) -> Vec<u8> {
    let props: String = PLY_PROPS.iter().map(|p| format!("property float {p}\n")).collect();
    format!("ply\nformat binary_little_endian 1.0\nelement vertex {count}\n{props}end_header\n").into_bytes()
}

/// The Inria layout's properties (all required).
const PLY_PROPS: [&str; 14] = [
    "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2",
    "rot_3",
];

/// Broken .ply files through `chatsplat render --ply`; the existing output image is never
/// overwritten by a failed render.
#[test]
fn broken_ply_files_are_refused_with_the_file_and_the_problem() {
    let dir = root("ply");
    let mut s = Suite::default();
    let out_png = dir.join("keep.png");
    // a PNG of the user's (render replaces PNGs), kept because the .ply is refused first
    std::fs::write(&out_png, b"\x89PNG\r\n\x1a\n the user's picture").unwrap();
    let good = inria_ply(4);
    let header_len = good.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let mut files: Vec<(String, Vec<u8>, &str)> = vec![
        ("empty".into(), vec![], "ply"),
        ("magic".into(), b"plx\nformat binary_little_endian 1.0\nend_header\n".to_vec(), "ply"),
        ("no-end-header".into(), b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n".to_vec(), "header"),
        ("huge-count".into(), ply_header("10000000000000000000"), "vertices"),
        ("absurd-count".into(), ply_header("200000000000"), "vertices"),
        ("negative-count".into(), ply_header("-5"), "vertex"),
        ("text-count".into(), ply_header("many"), "vertex"),
        ("no-body".into(), ply_header("10"), "truncated"),
        (
            "big-endian".into(),
            b"ply\nformat binary_big_endian 1.0\nelement vertex 1\nend_header\n".to_vec(),
            "property",
        ),
        ("binary-junk".into(), (0..400u32).map(|i| (i * 7919 % 251) as u8).collect(), "ply"),
    ];
    // a valid file cut at many lengths: inside the header and inside the body
    for cut in [3, 20, header_len - 5, header_len + 1, header_len + 17, good.len() - 1] {
        files.push((format!("cut-{cut}"), good[..cut].to_vec(), "ply"));
    }
    // a body longer than the header says (a count edited down, or two files concatenated)
    let mut long = good.clone();
    long.extend_from_slice(&good[header_len..]);
    files.push(("body-longer".into(), long, "disagrees with the body"));
    let ascii = String::from_utf8_lossy(&ply_header("1")).replace("binary_little_endian", "ascii");
    let row = "0 0 0 0 0 0 1 -3 -3 -3 1 0 0 0\n";
    files.push(("ascii-longer".into(), format!("{ascii}{row}{row}").into_bytes(), "disagrees with the body"));
    // a point cloud (no Gaussian properties), and a 3DGS file without opacity: no defaults assumed
    let cloud = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n\
        end_header\n0 0 0\n";
    files.push(("point-cloud".into(), cloud.as_bytes().to_vec(), "point cloud"));
    let no_opacity = String::from_utf8_lossy(&good[..header_len]).replace("property float opacity\n", "");
    let mut no_opacity = no_opacity.into_bytes();
    no_opacity.extend(&good[header_len..good.len() - 4 * 4]);
    files.push(("no-opacity".into(), no_opacity, "lacks the `opacity` property"));
    // a NaN position
    let mut nan = good.clone();
    nan[header_len..header_len + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    files.push(("nan".into(), nan, "not finite"));
    // an unknown property type
    let mut odd = String::from_utf8_lossy(&good[..header_len]).replace("property float rot_3", "property quad rot_3");
    odd.push_str("\0\0\0\0");
    files.push(("unknown-type".into(), odd.into_bytes(), "quad"));
    // .spz (Niantic's compressed splats, read by name or gzip magic): not gzip, a .ply named .spz,
    // cut short, with bytes after its gzip stream
    let spz = model::spz::encode(&model::ply::parse(&good, "good.ply").unwrap()).unwrap();
    let mut spz_files: Vec<(String, Vec<u8>, &str)> = vec![
        ("spz-not-gzip".into(), b"NGSP not compressed".to_vec(), "not gzip-compressed"),
        ("spz-a-ply".into(), good.clone(), "it is a .ply file"),
        ("spz-cut".into(), spz[..spz.len() / 2].to_vec(), "gzip"),
    ];
    let mut trailing = spz.clone();
    trailing.extend(b"more");
    spz_files.push(("spz-trailing".into(), trailing, "follow the gzip stream"));
    for (tag, bytes, want) in spz_files {
        let p = dir.join(format!("{tag}.spz"));
        std::fs::write(&p, &bytes).unwrap();
        let out = run(&["render", "--width", "16", "--height", "16", "--ply"], &[&p]);
        s.fails(Case { name: format!("spz {tag}"), out, expect: vec![name_of(&p), want.into()] });
    }
    let p = dir.join("good.spz");
    std::fs::write(&p, &spz).unwrap();
    s.succeeds(
        "spz good",
        run(&["render", "--width", "16", "--height", "16", "--out"], &[&dir.join("g.png"), Path::new("--ply"), &p]),
    );
    for (tag, bytes, want) in files {
        let p = dir.join(format!("{tag}.ply"));
        std::fs::write(&p, &bytes).unwrap();
        let out = run(&["render", "--width", "16", "--height", "16", "--ply"], &[&p]);
        let out2 = run(&["render", "--width", "16", "--height", "16", "--out"], &[&out_png, Path::new("--ply"), &p]);
        s.fails(Case { name: format!("ply {tag}"), out, expect: vec![name_of(&p), want.into()] });
        s.fails(Case { name: format!("ply {tag} with --out"), out: out2, expect: vec![name_of(&p)] });
    }
    let kept = std::fs::read(&out_png).unwrap();
    s.check("ply: the user's picture", kept.ends_with(b" the user's picture"), "a failed render overwrote --out");
    // the valid file renders (the cases above fail for their defect, not for the layout)
    let p = dir.join("good.ply");
    std::fs::write(&p, &good).unwrap();
    s.succeeds(
        "ply good",
        run(&["render", "--width", "16", "--height", "16", "--out"], &[&dir.join("g.png"), Path::new("--ply"), &p]),
    );
    s.finish(44);
    std::fs::remove_dir_all(&dir).ok();
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let t = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &t);
        } else {
            std::fs::copy(e.path(), t).unwrap();
        }
    }
}

/// A 16-bit instance-mask PNG (24x24) holding id `id` in one pixel, 0 elsewhere.
fn mask16(path: &Path, id: u16) {
    let mut enc = png::Encoder::new(std::fs::File::create(path).unwrap(), 24, 24);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Sixteen);
    let mut data = vec![0u8; 24 * 24 * 2];
    data[2 * 30..2 * 30 + 2].copy_from_slice(&id.to_be_bytes());
    enc.write_header().unwrap().write_image_data(&data).unwrap();
}

/// A colour-coded RGB mask (24x24): red in one half, green in the other.
fn mask_rgb(path: &Path) {
    let data: Vec<u8> = (0..24 * 24).flat_map(|i| if i % 24 < 12 { [200, 0, 0] } else { [0, 200, 0] }).collect();
    model::images::write_rgb8(path, 24, 24, &data).unwrap();
}

fn synth(dir: &Path, seed: &str) {
    let out = run(&["synth", "--views", "4", "--width", "24", "--height", "24", "--seed", seed, "--out"], &[dir]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

fn edit_json(p: &Path, f: impl FnOnce(&mut serde_json::Value)) {
    let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap();
    f(&mut v);
    std::fs::write(p, serde_json::to_vec_pretty(&v).unwrap()).unwrap();
}

/// Broken datasets, configs and command lines through `chatsplat train`, `synth`, `extract` and
/// `render`; resuming checks what it resumes; a run killed with SIGKILL resumes.
#[test]
fn broken_datasets_configs_and_arguments_are_refused() {
    let dir = root("data");
    let mut s = Suite::default();
    let base = dir.join("base");
    synth(&base, "46");
    broken_datasets(&mut s, &dir, &base);
    broken_configs(&mut s, &dir, &base);
    bad_command_lines(&mut s, &dir, &base);
    let (r, other) = resumes(&mut s, &dir, &base);
    outputs_and_vlm_options(&mut s, &dir);
    teachers(&mut s, &dir, &base, &other, &r);
    let (bare_run, bare_teacher) = without_masks(&mut s, &dir, &base);
    outputs_onto_inputs(&mut s, &dir, &base, &bare_run);
    resumes_keep_the_command_line(&mut s, &dir, &r, &bare_run, &bare_teacher);
    counts_and_shapes(&mut s, &dir, &base, &r);
    teacher_files(&mut s, &dir, &r);
    builtin_model_on_another_scene(&mut s, &dir, &base);
    chat_repl(&mut s, &bare_run);
    vqa_files(&mut s, &dir, &bare_run);
    relative_paths(&mut s, &dir);
    killed_geometry(&mut s, &dir, &base);
    killed_language(&mut s, &dir, &bare_run, &bare_teacher);
    s.finish(100);
    std::fs::remove_dir_all(&dir).ok();
}

/// `chatsplat train --iters 2` (unless `extra` sets them) on `data` into `out`.
fn train(data: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec!["train"];
    if !extra.contains(&"--iters") {
        args.extend(["--iters", "2"]);
    }
    args.extend(extra);
    run(&args, &[Path::new("--data"), data, Path::new("--out"), out])
}

/// Datasets, each a copy of the base with one defect, and one that is missing: refused, the copy intact.
fn broken_datasets(s: &mut Suite, dir: &Path, base: &Path) {
    // datasets: each a copy of the base with one defect
    type Edit = Box<dyn Fn(&Path)>;
    let tj =
        |f: fn(&mut serde_json::Value)| -> Edit { Box::new(move |d: &Path| edit_json(&d.join("transforms.json"), f)) };
    let write = |rel: &'static str, bytes: &'static [u8]| -> Edit {
        Box::new(move |d: &Path| std::fs::write(d.join(rel), bytes).unwrap())
    };
    let cut = |rel: &'static str, keep: usize| -> Edit {
        Box::new(move |d: &Path| {
            let b = std::fs::read(d.join(rel)).unwrap();
            std::fs::write(d.join(rel), &b[..keep.min(b.len())]).unwrap()
        })
    };
    let datasets: Vec<(&str, Edit, &str)> = vec![
        ("transforms-cut", cut("transforms.json", 300), "transforms.json"),
        ("transforms-text", write("transforms.json", b"hello"), "transforms.json"),
        ("transforms-empty", write("transforms.json", b""), "transforms.json"),
        ("no-frames", tj(|v| drop(v.as_object_mut().unwrap().remove("frames"))), "transforms.json"),
        ("zero-frames", tj(|v| v["frames"] = serde_json::json!([])), "transforms.json"),
        (
            "matrix-3x3",
            tj(|v| v["frames"][0]["transform_matrix"] = serde_json::json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]])),
            "transforms.json",
        ),
        ("matrix-text", tj(|v| v["frames"][1]["transform_matrix"] = serde_json::json!("identity")), "transforms.json"),
        ("matrix-huge", tj(|v| v["frames"][0]["transform_matrix"][0][3] = serde_json::json!(1e300)), "transforms.json"),
        ("focal-zero", tj(|v| v["fl_x"] = serde_json::json!(0.0)), "transforms.json"),
        ("focal-negative", tj(|v| v["fl_y"] = serde_json::json!(-20.0)), "transforms.json"),
        ("width-zero", tj(|v| v["w"] = serde_json::json!(0)), "the transforms say 0x24"),
        ("width-absurd", tj(|v| v["w"] = serde_json::json!(4_000_000_000u64)), "the transforms say 4000000000x24"),
        ("path-missing", tj(|v| v["frames"][2]["file_path"] = serde_json::json!("images/nope.png")), "nope.png"),
        ("path-number", tj(|v| v["frames"][2]["file_path"] = serde_json::json!(7)), "transforms.json"),
        ("image-cut", cut("images/frame_0001.png", 60), "frame_0001.png"),
        ("image-junk", write("images/frame_0002.png", b"not a png at all"), "frame_0002.png"),
        ("image-empty", write("images/frame_0003.png", b""), "frame_0003.png"),
        ("mask-cut", cut("masks/frame_0000.png", 50), "frame_0000.png"),
        ("mask-junk", write("masks/frame_0001.png", b"\x89PNG junk"), "frame_0001.png"),
        ("depth-junk", write("depth/frame_0002.png", b"junk"), "frame_0002.png"),
        // silent wrong results before: now refused, naming the file and the problem
        ("mask-16bit-id", Box::new(|d: &Path| mask16(&d.join("masks/frame_0001.png"), 5000)), "instance id 5000"),
        ("mask-colour", Box::new(|d: &Path| mask_rgb(&d.join("masks/frame_0002.png"))), "colour-coded mask"),
        (
            "mask-partial",
            tj(|v| drop(v["frames"][2].as_object_mut().unwrap().remove("instance_mask_path"))),
            "every frame needs a mask",
        ),
        ("depth-scale-negative", tj(|v| v["depth_unit_scale_factor"] = serde_json::json!(-0.001)), "depth_unit_scale"),
        ("focal-in-mm", tj(|v| v["fl_x"] = serde_json::json!(0.035)), "field of view"),
        ("principal-point-far", tj(|v| v["cx"] = serde_json::json!(1000.0)), "far outside"),
        (
            "frames-listed-twice",
            tj(|v| {
                let f = v["frames"].as_array().unwrap().clone();
                v["frames"].as_array_mut().unwrap().extend(f);
            }),
            "both a training view and a held-out view",
        ),
        (
            "frames-identical",
            tj(|v| {
                let f = v["frames"][0].clone();
                v["frames"] = serde_json::json!([f.clone(), f.clone(), f.clone(), f]);
            }),
            "the same camera pose",
        ),
    ];
    for (tag, edit, want) in &datasets {
        let d = dir.join(tag);
        copy_dir(base, &d);
        edit(&d);
        let before = std::fs::read(d.join("transforms.json")).unwrap();
        let out = train(&d, &dir.join(format!("run-{tag}")), &[]);
        s.fails(Case { name: format!("dataset {tag}"), out, expect: vec![want.to_string()] });
        s.check(
            &format!("dataset {tag} intact"),
            std::fs::read(d.join("transforms.json")).unwrap() == before,
            "changed",
        );
    }
    let missing = dir.join("no-such-dataset");
    s.fails(Case {
        name: "dataset missing".into(),
        out: train(&missing, &dir.join("run-missing"), &[]),
        expect: vec!["no-such-dataset".into()],
    });
}

/// Training configs that are not JSON, hold unknown keys, wrong types or values out of range.
fn broken_configs(s: &mut Suite, dir: &Path, base: &Path) {
    // configs
    let configs: Vec<(&str, &str, &str)> = vec![
        ("unknown-key", r#"{"lr_means": 0.001, "frobnicate": 1}"#, "frobnicate"),
        ("not-json", "iters = 5", "invalid json"),
        ("wrong-type", r#"{"iters": "many"}"#, "\"many\""),
        ("negative-iters", r#"{"iters": -3}"#, "iters"),
        ("zero-densify", r#"{"densify_every": 0, "densify_until": 100}"#, "densify_every"),
        ("negative-lr", r#"{"lr_means": -0.1}"#, "lr"),
        ("nan-ish", r#"{"lambda_dssim": 7.0}"#, "lambda_dssim"),
        ("array", "[1, 2, 3]", "json object"),
        ("empty", "", "invalid json"),
        (
            "nothing-learns",
            r#"{"lr_means": 0, "lr_log_scales": 0, "lr_quats": 0, "lr_opacity": 0, "lr_sh_dc": 0, "lr_sh_rest": 0,
                "lr_identity": 0, "lr_classifier": 0}"#,
            "nothing would learn",
        ),
    ];
    for (tag, text, want) in configs {
        let c = dir.join(format!("{tag}.json"));
        std::fs::write(&c, text).unwrap();
        let out = run(
            &["train", "--iters", "2", "--config"],
            &[&c, Path::new("--data"), base, Path::new("--out"), &dir.join(format!("run-cfg-{tag}"))],
        );
        s.fails(Case { name: format!("config {tag}"), out, expect: vec![format!("{tag}.json"), want.into()] });
    }
}

/// Options out of range, a port another program holds, one-process commands under an MPI launcher,
/// and a question longer than the model's context.
fn bad_command_lines(s: &mut Suite, dir: &Path, base: &Path) {
    // command lines
    let out_dir = dir.join("cli");
    let o = out_dir.to_string_lossy().to_string();
    let b = base.to_string_lossy().to_string();
    let no_masks = format!("{o}-masks");
    let lines: Vec<(Vec<&str>, &str)> = vec![
        (vec!["synth", "--width", "100000", "--height", "100000", "--out", &o], "width"),
        (vec!["synth", "--views", "0", "--out", &o], "views"),
        (vec!["synth", "--views", "100000000", "--out", &o], "views"),
        (vec!["synth", "--width", "-5", "--out", &o], "width"),
        (vec!["synth", "--seed", "x", "--out", &o], "seed"),
        (vec!["render", "--width", "0", "--out", &o], "width"),
        (vec!["render", "--width", "200000", "--height", "200000", "--out", &o], "width"),
        (vec!["render", "--fov", "0", "--out", &o], "fov"),
        (vec!["render", "--fov", "180", "--out", &o], "fov"),
        (vec!["render", "--eye", "1,2", "--out", &o], "eye"),
        (vec!["render", "--eye", "0,0,0", "--target", "0,0,0", "--out", &o], "eye"),
        (vec!["render", "--background", "2,0,0", "--out", &o], "background"),
        (vec!["train", "--data", &b, "--out", &o, "--downscale", "0"], "downscale"),
        (vec!["train", "--data", &b, "--out", &o, "--iters", "0"], "iters must be at least 1"),
        (vec!["train", "--data", &b, "--out", &o, "--iters", "-1"], "iters"),
        (vec!["train", "--data", &b, "--out", &o, "--backend", "cuda"], "backend"),
        (vec!["train", "--data", &b, "--out", &o, "--background", "grey"], "background"),
        (vec!["extract", "--data", &b, "--out", &o, "--margin", "-1"], "margin"),
        (vec!["extract", "--data", &b, "--out", &o, "--downscale", "0"], "downscale"),
        (vec!["train", "--data", &b, "--out", &o, "--masks", "/no/such/masks"], "/no/such/masks"),
        (vec!["extract", "--data", &b, "--out", &o, "--masks", &no_masks], "is not a directory"),
        (vec!["extract", "--data", &b, "--out", &o, "--masks", &o], "is the --masks directory"),
        (vec!["train", "--data", &b, "--out", &o, "--masks", &b], "is missing: every image needs a mask"),
        (vec!["ask", "--image", "x.png", "--run", &o, "What?"], "--image"),
        (vec!["ask", "--image", "x.png", "--half", "What?"], "--backend flex"),
        (vec!["export-ply", "--run", &o, "--out", &o], "run"),
        (vec!["serve", "--run", "/no/such/run", "--addr", "127.0.0.1:0"], "/no/such/run"),
        (vec!["serve", "--run", &o, "--addr", "nowhere"], "--addr"),
        (vec!["serve", "--run", &o, "--queue", "0"], "--queue"),
    ];
    for (args, want) in lines {
        let out = run(&args, &[]);
        s.fails(Case { name: format!("cli {}", args.join(" ")), out, expect: vec![want.into()] });
    }
    // a port another program holds
    let held = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = held.local_addr().unwrap().to_string();
    let out = run(&["serve", "--addr", &addr, "--run", &b], &[]);
    s.fails(Case { name: "serve on a port in use".into(), out, expect: vec!["cannot listen".into(), addr] });
    // under an MPI launcher with several ranks: a command that runs on one process, and (in a
    // build without the `mpi` feature) train-vlm, whose ranks would each train alone
    let ranks = |args: &[&str]| chatsplat().args(args).env("OMPI_COMM_WORLD_SIZE", "2").output().unwrap();
    let out = ranks(&["render", "--out", &o]);
    s.fails(Case {
        name: "render on 2 ranks".into(),
        out,
        expect: vec!["`chatsplat render`".into(), "2 ranks".into()],
    });
    if !cfg!(feature = "mpi") {
        let out = ranks(&["train-vlm", "--steps", "1", "--out", &o]);
        s.fails(Case { name: "train-vlm on 2 ranks without MPI".into(), out, expect: vec!["--features mpi".into()] });
    }
    // a 100 KB question is longer than the model's context
    let photo = base.join("images/frame_0000.png");
    let long = "what is on the table ".repeat(5000);
    let out = run(&["ask", "--image"], &[&photo, Path::new(&long)]);
    s.fails(Case { name: "ask with a 100 KB question".into(), out, expect: vec!["at most 4096".into()] });
}

/// Resuming without a checkpoint, on another dataset, downscale or masks, or at an absurd iteration;
/// a moved copy of the dataset resumes. Returns the trained run and the other dataset.
fn resumes(s: &mut Suite, dir: &Path, base: &Path) -> (PathBuf, PathBuf) {
    // resume: no checkpoint; another dataset; a moved copy of the same dataset resumes
    let empty_run = dir.join("empty-run");
    std::fs::create_dir_all(&empty_run).unwrap();
    s.fails(Case {
        name: "resume without checkpoint".into(),
        out: train(base, &empty_run, &["--resume"]),
        expect: vec!["checkpoint".into()],
    });
    let r = dir.join("run-a");
    s.succeeds("train a", train(base, &r, &[]));
    let other = dir.join("other");
    synth(&other, "7");
    s.fails(Case {
        name: "resume on another dataset".into(),
        out: train(&other, &r, &["--resume"]),
        expect: vec!["base".into(), "other".into(), "fingerprint".into()],
    });
    s.fails(Case {
        name: "resume at another downscale".into(),
        out: train(base, &r, &["--resume", "--downscale", "2"]),
        expect: vec!["downscale".into()],
    });
    let moved = dir.join("moved");
    copy_dir(base, &moved);
    s.succeeds("resume on a moved copy", train(&moved, &r, &["--resume", "--iters", "4"]));
    // resuming with other masks (one mask edited, or --masks from elsewhere) is another run
    let remasked = dir.join("remasked");
    copy_dir(base, &remasked);
    mask16(&remasked.join("masks/frame_0000.png"), 9);
    s.fails(Case {
        name: "resume with other masks".into(),
        out: train(&remasked, &r, &["--resume", "--iters", "5"]),
        expect: vec!["fingerprint".into(), "masks".into()],
    });
    // a state.json edited to an absurd iteration: refused, not "resumed" into training nothing
    let state = r.join("state.json");
    let kept_state = std::fs::read(&state).unwrap();
    edit_json(&state, |v| v["iter"] = serde_json::json!(1_000_000_000u64));
    s.fails(Case {
        name: "resume an absurd iteration count".into(),
        out: train(base, &r, &["--resume", "--iters", "5"]),
        expect: vec!["state.json".into(), "iteration 1000000000".into()],
    });
    std::fs::write(&state, kept_state).unwrap();
    (r, other)
}

/// `--out` naming a folder, and `train-vlm --evaluate` options that would report nothing true.
fn outputs_and_vlm_options(s: &mut Suite, dir: &Path) {
    // --out naming a folder: refused before any work, nothing left beside it
    let folder_out = dir.join("a-folder.png");
    std::fs::create_dir_all(&folder_out).unwrap();
    s.fails(Case {
        name: "render --out a folder".into(),
        out: run(&["render", "--width", "8", "--height", "8", "--out"], &[&folder_out]),
        expect: vec!["a-folder.png".into(), "is a folder".into()],
    });
    s.check("render --out a folder: no temporary left", !dir.join("a-folder.png.tmp").exists(), "a .tmp was left");
    // train-vlm --evaluate on 0 seeds would report 0 %
    s.fails(Case {
        name: "train-vlm --eval-seeds 0".into(),
        out: run(&["train-vlm", "--eval-seeds", "0", "--evaluate"], &[dir]),
        expect: vec!["--eval-seeds".into()],
    });
    // held-out seeds that run into the training seeds are not held out
    s.fails(Case {
        name: "train-vlm --eval-from into the training seeds".into(),
        out: run(&["train-vlm", "--eval-from", "999990", "--evaluate"], &[dir]),
        expect: vec!["--eval-from 999990".into(), "training seeds".into()],
    });
    // a model whose train_config.json was edited out of range: named, not clamped to a default
    let edited = dir.join("vlm-edited");
    std::fs::create_dir_all(&edited).unwrap();
    std::fs::write(edited.join("train_config.json"), r#"{"supersample": 0}"#).unwrap();
    s.fails(Case {
        name: "train-vlm --evaluate a config out of range".into(),
        out: run(&["train-vlm", "--evaluate"], &[&edited]),
        expect: vec!["train_config.json".into(), "supersample".into()],
    });
}

/// Teacher tokens from another scene, or from a dataset that changed since; a language resume
/// without a checkpoint.
fn teachers(s: &mut Suite, dir: &Path, base: &Path, other: &Path, r: &Path) {
    // teacher tokens: from another scene, or from a dataset that changed since, are refused
    let (teacher_other, teacher_base) = (dir.join("teacher-other"), dir.join("teacher-base"));
    s.succeeds("extract other", run(&["extract", "--data"], &[other, Path::new("--out"), &teacher_other]));
    s.succeeds("extract base", run(&["extract", "--data"], &[base, Path::new("--out"), &teacher_base]));
    let language = |teacher: &Path, extra: &[&str]| {
        let mut args = vec!["train-language", "--iters", "1"];
        args.extend(extra);
        run(&args, &[Path::new("--run"), r, Path::new("--teacher"), teacher])
    };
    s.fails(Case {
        name: "teacher from another scene".into(),
        out: language(&teacher_other, &[]),
        expect: vec!["fingerprint".into(), "other".into(), "run-a".into()],
    });
    s.fails(Case {
        name: "language resume without checkpoint".into(),
        out: language(&teacher_base, &["--resume"]),
        expect: vec!["checkpoint".into()],
    });
    let img = base.join("images/frame_0001.png");
    let photo = std::fs::read(&img).unwrap();
    std::fs::write(&img, std::fs::read(other.join("images/frame_0001.png")).unwrap()).unwrap();
    s.fails(Case {
        name: "teacher of a changed dataset".into(),
        out: language(&teacher_base, &[]),
        expect: vec!["teacher.json".into(), "extract".into()],
    });
    std::fs::write(&img, photo).unwrap();
}

/// A capture without masks: view level works, object level says it needs masks; a language stage
/// at 1000x the rates diverges with a loadable checkpoint. Returns the run and its teacher.
fn without_masks(s: &mut Suite, dir: &Path, base: &Path) -> (PathBuf, PathBuf) {
    // a capture without masks: view level works, object level says it needs masks
    let bare = dir.join("no-masks");
    copy_dir(base, &bare);
    std::fs::remove_dir_all(bare.join("masks")).unwrap();
    edit_json(&bare.join("transforms.json"), |v| {
        for f in v["frames"].as_array_mut().unwrap() {
            f.as_object_mut().unwrap().remove("instance_mask_path");
        }
    });
    let (bare_run, bare_teacher) = (dir.join("run-no-masks"), dir.join("teacher-no-masks"));
    s.succeeds("train without masks", train(&bare, &bare_run, &[]));
    s.succeeds("extract without masks", run(&["extract", "--data"], &[&bare, Path::new("--out"), &bare_teacher]));
    let zero = run(&["train-language", "--iters", "0", "--run"], &[&bare_run, Path::new("--teacher"), &bare_teacher]);
    s.fails(Case {
        name: "train-language --iters 0".into(),
        out: zero,
        expect: vec!["iters must be at least 1".into()],
    });
    let lang = run(&["train-language", "--iters", "1", "--run"], &[&bare_run, Path::new("--teacher"), &bare_teacher]);
    s.succeeds("train-language without masks", lang);
    // learning rates 1000x the defaults: a divergence error, and the checkpoint left loads
    let (hot, hot_out) = (dir.join("hot.json"), dir.join("language-hot"));
    std::fs::write(&hot, r#"{"lr_features": 50.0, "lr_encoder": 20.0, "warmup_iters": 0, "checkpoint_every": 1}"#)
        .unwrap();
    s.fails(Case {
        name: "train-language at 1000x the learning rates".into(),
        out: run(
            &["train-language", "--iters", "30", "--run"],
            &[
                &bare_run,
                Path::new("--teacher"),
                &bare_teacher,
                Path::new("--config"),
                &hot,
                Path::new("--out"),
                &hot_out,
            ],
        ),
        expect: vec!["diverged".into(), "lower lr_features and lr_encoder".into()],
    });
    s.check(
        "diverged language run: its checkpoint loads",
        model::io::read_f32(&hot_out.join("language.safetensors")).is_ok(),
        "no loadable language.safetensors",
    );
    let ask = |extra: &[&str]| {
        let mut args = vec!["ask", "--view", "0", "--max-new-tokens", "2"];
        args.extend(extra);
        args.push("What is this?");
        run(&args, &[Path::new("--run"), &bare_run])
    };
    s.succeeds("view level without masks", ask(&[]));
    s.fails(Case {
        name: "an empty question".into(),
        out: run(&["ask", "--view", "0", "--run"], &[&bare_run, Path::new("  ")]),
        expect: vec!["the question is empty".into()],
    });
    s.fails(Case {
        name: "object level without masks".into(),
        out: ask(&["--object", "5", "5"]),
        expect: vec!["needs instance masks".into()],
    });
    (bare_run, bare_teacher)
}

/// The bytes of every file under `p` (a file or a folder), by path: what must be left intact.
fn snapshot(p: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    if p.is_file() {
        return vec![(p.to_path_buf(), std::fs::read(p).unwrap())];
    }
    let mut out = Vec::new();
    for e in std::fs::read_dir(p).unwrap().flatten() {
        out.extend(snapshot(&e.path()));
    }
    out.sort();
    out
}

/// A case that must fail and leave `keep` (files or folders) byte for byte as they were.
fn fails_intact<A: AsRef<str>>(
    s: &mut Suite,
    name: &str,
    keep: &[&Path],
    args: &[A],
    paths: &[&Path],
    expect: &[&str],
) {
    let before: Vec<_> = keep.iter().map(|k| snapshot(k)).collect();
    let args: Vec<&str> = args.iter().map(AsRef::as_ref).collect();
    s.fails(Case { name: name.into(), out: run(&args, paths), expect: expect.iter().map(|e| e.to_string()).collect() });
    let after: Vec<_> = keep.iter().map(|k| snapshot(k)).collect();
    s.check(&format!("{name}: inputs intact"), before == after, "an input was changed");
}

/// An output onto one of the command's inputs or a run's own files: refused before anything is
/// written, through a link too.
fn outputs_onto_inputs(s: &mut Suite, dir: &Path, base: &Path, bare_run: &Path) {
    let ply = dir.join("scene.ply");
    std::fs::write(&ply, inria_ply(3)).unwrap();
    let ply_s = ply.to_str().unwrap();
    let render = |extra: &[&str]| -> Vec<String> {
        ["render", "--ply", ply_s, "--width", "8", "--height", "8"].iter().chain(extra).map(|a| a.to_string()).collect()
    };
    fails_intact(s, "render --out onto --ply", &[&ply], &render(&["--out", ply_s]), &[], &["--out", "--ply"]);
    let png = dir.join("r.png");
    let png_s = png.to_str().unwrap();
    let same = render(&["--out", png_s, "--depth", png_s]);
    let same: Vec<&str> = same.iter().map(String::as_str).collect();
    s.fails(Case { name: "render --out = --depth".into(), out: run(&same, &[]), expect: vec!["same file".into()] });
    s.check("render --out = --depth: nothing written", !png.exists(), "r.png was written");
    let lang = bare_run.join("language");
    let ckpt = lang.join("language.safetensors");
    fails_intact(
        s,
        "export-encoder --out onto the language checkpoint",
        &[&lang],
        &["export-encoder", "--run", bare_run.to_str().unwrap(), "--out"],
        &[&ckpt],
        &["language.safetensors", "language run's checkpoint"],
    );
    // a link to the geometry checkpoint is followed
    let link = dir.join("link.ply");
    std::os::unix::fs::symlink(bare_run.join("checkpoint.safetensors"), &link).unwrap();
    fails_intact(
        s,
        "export-ply --out through a link onto the checkpoint",
        &[bare_run],
        &["export-ply", "--run", bare_run.to_str().unwrap(), "--out"],
        &[&link],
        &["geometry run's checkpoint"],
    );
    let q = dir.join("questions-one.json");
    std::fs::write(
        &q,
        r#"{"questions": [{"id": "v", "level": "view", "view": 0, "question": "How many objects are there?",
        "answer": "3"}]}"#,
    )
    .unwrap();
    fails_intact(
        s,
        "vqa --out onto the question file",
        &[&q],
        &["vqa", "--run", bare_run.to_str().unwrap(), "--questions", q.to_str().unwrap(), "--out"],
        &[&q],
        &["--questions file"],
    );
    fails_intact(
        s,
        "train --out onto --data",
        &[base],
        &["train", "--data"],
        &[base, Path::new("--out"), base],
        &["--data directory"],
    );
    // synth over a folder of the user's that is not a synthetic tabletop
    let photos = dir.join("user-photos");
    std::fs::create_dir_all(photos.join("images")).unwrap();
    std::fs::write(photos.join("transforms.json"), "{}").unwrap();
    std::fs::write(photos.join("images/frame_0000.png"), "a photo").unwrap();
    fails_intact(
        s,
        "synth --out over a capture",
        &[&photos],
        &["synth", "--views", "2", "--out"],
        &[&photos],
        &["user-photos", "not a synthetic tabletop"],
    );
    let teacher = dir.join("teacher-no-masks");
    fails_intact(
        s,
        "train-language --out onto the geometry run",
        &[bare_run],
        &["train-language", "--iters", "1", "--teacher", teacher.to_str().unwrap(), "--run"],
        &[bare_run, Path::new("--out"), bare_run],
        &["geometry run's checkpoint"],
    );
}

/// A resume refuses settings the command line asks for that the run does not have, naming each.
fn resumes_keep_the_command_line(s: &mut Suite, dir: &Path, r: &Path, bare_run: &Path, bare_teacher: &Path) {
    let cfg = dir.join("geometry-lr.json");
    std::fs::write(&cfg, r#"{"lr_means": 0.5, "iters": 6}"#).unwrap();
    fails_intact(
        s,
        "train --resume --config with another lr_means",
        &[r],
        &["train", "--resume", "--config"],
        &[&cfg, Path::new("--data"), &dir.join("base"), Path::new("--out"), r],
        &["geometry-lr.json", "lr_means", "--resume"],
    );
    fails_intact(
        s,
        "train --resume --background black",
        &[r],
        &["train", "--resume", "--background", "black", "--data"],
        &[&dir.join("base"), Path::new("--out"), r],
        &["--background black", "background"],
    );
    let lang = |extra: &[&str], teacher: &Path| -> Vec<String> {
        let tail = ["--run", bare_run.to_str().unwrap(), "--teacher", teacher.to_str().unwrap()];
        ["train-language", "--resume", "--iters", "2"].iter().chain(extra).chain(&tail).map(|a| a.to_string()).collect()
    };
    let language = bare_run.join("language");
    fails_intact(
        s,
        "train-language --resume --channels 8",
        &[&language],
        &lang(&["--channels", "8"], bare_teacher),
        &[],
        &["--channels 8", "field.view_channels"],
    );
    let other = dir.join("teacher-base");
    fails_intact(
        s,
        "train-language --resume --teacher another",
        &[&language],
        &lang(&[], &other),
        &[],
        &["--teacher", "teacher-no-masks"],
    );
    // what the stage sets itself (an automatic patch) is no change: the resume goes on
    let auto = dir.join("language-auto.json");
    std::fs::write(&auto, r#"{"field": {"patch": 0}}"#).unwrap();
    let args = lang(&["--config", auto.to_str().unwrap()], bare_teacher);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    s.succeeds("train-language --resume --config with an automatic patch", run(&args, &[]));
}

/// Counts and model shapes out of range: refused before any work, never a panic.
fn counts_and_shapes(s: &mut Suite, dir: &Path, base: &Path, r: &Path) {
    for n in ["18446744073709551615", "1000000"] {
        s.fails(Case {
            name: format!("extract --novel-views {n}"),
            out: run(
                &["extract", "--novel-views", n, "--data"],
                &[base, Path::new("--run"), r, Path::new("--out"), &dir.join("teacher-novel")],
            ),
            expect: vec![format!("--novel-views {n}"), "at most".into()],
        });
    }
    for (name, cfg, key) in [
        ("a text width of 0", r#"{"model": {"text_width": 0}}"#, "model.text_width"),
        ("0 tower layers", r#"{"model": {"vision_layers": 0}}"#, "model.vision_layers"),
        ("0 steps", r#"{"steps": 0}"#, "steps"),
        ("a negative weight decay", r#"{"weight_decay": -1}"#, "weight_decay"),
        ("a model too large", r#"{"model": {"text_width": 4096, "text_layers": 64, "text_mlp": 16384}}"#, "parameters"),
    ] {
        let p = dir.join("vlm-shape.json");
        std::fs::write(&p, cfg).unwrap();
        let out = dir.join("vlm-shape");
        s.fails(Case {
            name: format!("train-vlm with {name}"),
            out: run(&["train-vlm", "--config"], &[&p, Path::new("--out"), &out]),
            expect: vec![key.into()],
        });
        s.check(&format!("train-vlm with {name}: nothing written"), !out.exists(), "the output folder was made");
    }
    s.fails(Case {
        name: "serve --allow-origin '*'".into(),
        out: run(&["serve", "--allow-origin", "*", "--run"], &[r]),
        expect: vec!["wildcard".into()],
    });
    // find: a phrase that is empty or too long, a threshold outside 0-1 (refused before loading)
    let long = "red ".repeat(60);
    for (name, args, expect) in [
        ("find with an empty phrase", vec!["find", "  ", "--run"], vec!["phrase", "empty"]),
        ("find with a 239-character phrase", vec!["find", long.as_str(), "--run"], vec!["phrase", "at most 200"]),
        ("find --threshold 1.5", vec!["find", "cone", "--threshold", "1.5", "--run"], vec!["--threshold", "0-1"]),
        ("find --threshold -0.2", vec!["find", "cone", "--threshold", "-0.2", "--run"], vec!["--threshold", "0-1"]),
        (
            "vqa --find-threshold 1.5",
            vec!["vqa", "--questions", "q.json", "--find-threshold", "1.5", "--run"],
            vec!["--find-threshold", "0-1"],
        ),
    ] {
        s.fails(Case {
            name: name.into(),
            out: run(&args, &[r]),
            expect: expect.into_iter().map(String::from).collect(),
        });
    }
    // a finished run's state.json edited to an absurd iteration: export-ply refuses it too
    let state = r.join("state.json");
    let kept = std::fs::read(&state).unwrap();
    edit_json(&state, |v| v["iter"] = serde_json::json!(1_000_000_000u64));
    s.fails(Case {
        name: "export-ply of an absurd iteration count".into(),
        out: run(&["export-ply", "--run"], &[r, Path::new("--out"), &dir.join("absurd.ply")]),
        expect: vec!["state.json".into(), "iteration 1000000000".into()],
    });
    std::fs::write(&state, kept).unwrap();
    // an object the run does not hold, taken out or left out: refused, nothing written
    for flag in ["--object", "--without"] {
        let out = dir.join("no-object.ply");
        s.fails(Case {
            name: format!("export-ply {flag} of an object the run does not hold"),
            out: run(&["export-ply", flag, "200", "--run"], &[r, Path::new("--out"), &out]),
            expect: vec![format!("{flag} 200"), "holds no Gaussian of object 200".into()],
        });
        s.check(&format!("export-ply {flag}: nothing written"), !out.exists(), "the .ply was written");
    }
    // question files: a view question with an object pixel, a top level that is not an object
    let q = dir.join("questions-mixed.json");
    std::fs::write(
        &q,
        r#"{"questions": [{"id": "v", "level": "view", "view": 0, "object": [3, 4],
        "question": "What is this?", "answer": "red cube"}]}"#,
    )
    .unwrap();
    let vqa = |q: &Path| run(&["vqa", "--run"], &[r, Path::new("--questions"), q]);
    s.fails(Case {
        name: "vqa: a view question with an object pixel".into(),
        out: vqa(&q),
        expect: vec!["questions-mixed.json".into(), "\"object\" does not apply to view-level".into()],
    });
    // another scene's question file (the same frame names, another tabletop)
    let theirs = dir.join("questions-seed-7.json");
    std::fs::write(
        &theirs,
        r#"{"scene": "synthetic tabletop, seed 7", "questions": [{"id": "v", "level": "view",
        "view": 0, "question": "How many objects are there?", "answer": "3"}]}"#,
    )
    .unwrap();
    s.fails(Case {
        name: "vqa: another scene's question file".into(),
        out: vqa(&theirs),
        expect: vec!["seed 7".into(), "seed 46".into(), "give a question file of this scene".into()],
    });
    std::fs::write(&q, r#"[{"id": "v", "level": "view", "view": 0, "question": "Q?", "answer": "x"}]"#).unwrap();
    s.fails(Case {
        name: "vqa: a question file that is an array".into(),
        out: vqa(&q),
        expect: vec!["the top level is an array".into(), "\"questions\"".into()],
    });
}

/// Token files the index does not describe: swapped, or one file for two views.
fn teacher_files(s: &mut Suite, dir: &Path, r: &Path) {
    let teacher = dir.join("teacher-swapped");
    copy_dir(&dir.join("teacher-base"), &teacher);
    let (a, b) = (teacher.join("view_0000.safetensors"), teacher.join("view_0001.safetensors"));
    let (ba, bb) = (std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    std::fs::write(&a, &bb).unwrap();
    std::fs::write(&b, &ba).unwrap();
    let language = |teacher: &Path| {
        run(
            &["train-language", "--iters", "1", "--run"],
            &[r, Path::new("--teacher"), teacher, Path::new("--out"), &dir.join("language-swapped")],
        )
    };
    s.fails(Case {
        name: "teacher token files swapped".into(),
        out: language(&teacher),
        expect: vec!["view_0000.safetensors".into(), "changed or replaced".into()],
    });
    // an index without the files' hashes (written before they were recorded): the files' own
    // metadata still tells them apart
    let index = teacher.join("teacher.json");
    let with_hashes = std::fs::read(&index).unwrap();
    edit_json(&index, |v| {
        for view in v["views"].as_array_mut().unwrap() {
            view.as_object_mut().unwrap().remove("hash");
        }
    });
    s.fails(Case {
        name: "teacher token files swapped, an index without hashes".into(),
        out: language(&teacher),
        expect: vec!["view_0000.safetensors".into(), "moved or swapped".into()],
    });
    std::fs::write(&index, with_hashes).unwrap();
    std::fs::write(&b, &bb).unwrap();
    // one token changed inside a file (its last byte): only the hash sees it
    let mut edited = ba.clone();
    *edited.last_mut().unwrap() ^= 0x40;
    std::fs::write(&a, &edited).unwrap();
    s.fails(Case {
        name: "a teacher token file edited".into(),
        out: language(&teacher),
        expect: vec!["view_0000.safetensors".into(), "changed or replaced".into()],
    });
    std::fs::write(&a, &ba).unwrap();
    edit_json(&teacher.join("teacher.json"), |v| v["views"][1]["file"] = v["views"][0]["file"].clone());
    s.fails(Case {
        name: "two teacher views on one file".into(),
        out: language(&teacher),
        expect: vec!["teacher.json".into(), "both point at view_0000.safetensors".into()],
    });
}

/// The built-in tabletop model on a scene that is not a tabletop: said once on the terminal, and
/// beside the answer.
fn builtin_model_on_another_scene(s: &mut Suite, dir: &Path, base: &Path) {
    let data = dir.join("not-a-tabletop");
    copy_dir(base, &data);
    std::fs::remove_file(data.join("scene.json")).unwrap();
    let (run_dir, teacher) = (dir.join("run-not-a-tabletop"), dir.join("teacher-not-a-tabletop"));
    s.succeeds("train on a capture that is not a tabletop", train(&data, &run_dir, &[]));
    s.succeeds("extract it", run(&["extract", "--data"], &[&data, Path::new("--out"), &teacher]));
    let lang = run(&["train-language", "--iters", "1", "--run"], &[&run_dir, Path::new("--teacher"), &teacher]);
    s.succeeds("train-language on it", lang);
    let out = run(&["ask", "--view", "0", "--max-new-tokens", "2", "--run"], &[&run_dir, Path::new("What is this?")]);
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    s.succeeds("ask with the built-in model about it", out);
    s.check(
        "the built-in model on another scene: said once, and beside the answer",
        err.matches("knows only the synthetic tabletops").count() == 1
            && err.contains("--vlm")
            && err.contains("the built-in tabletop model's answer"),
        &err,
    );
    // a tabletop says nothing of it
    let tabletop = run(
        &["ask", "--view", "0", "--max-new-tokens", "2", "--run"],
        &[&dir.join("run-no-masks"), Path::new("What is this?")],
    );
    let err = String::from_utf8_lossy(&tabletop.stderr).into_owned();
    s.check("a tabletop: no note", !err.contains("knows only the synthetic tabletops"), &err);
}

/// The chat REPL: bad commands are reported and the session goes on.
fn chat_repl(s: &mut Suite, bare_run: &Path) {
    // the chat REPL: bad commands are reported and the session goes on (documented: an
    // interactive session is not ended by a typo); each line's message names the problem
    let mut child = chatsplat()
        .args(["chat", "--max-new-tokens", "1", "--run"])
        .arg(bare_run)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    {
        use std::io::Write;
        let lines = ":frobnicate\n:scene 0\n:view x\n:view 99999\n:click 1\n:click 99999 5\n:click 5 5\n:scene 99\n";
        let mut stdin = child.stdin.take().unwrap();
        stdin.write_all(lines.as_bytes()).unwrap();
        // a line in Latin-1 (not UTF-8) is refused and the session goes on to the next command
        stdin.write_all(b"what colour is the caf\xe9 table?\n:view 99998\n:quit\n").unwrap();
    }
    let out = child.wait_with_output().unwrap();
    s.succeeds("chat REPL with bad commands", out.clone());
    let err = String::from_utf8_lossy(&out.stderr).to_lowercase();
    for (what, want) in [
        (":frobnicate", "unknown command :frobnicate"),
        (":scene 0", "k >= 1"),
        (":view x", "usage: :view n"),
        (":view 99999", "99999"),
        (":click 1", "usage: :click x y"),
        (":click 99999 5", "outside"),
        (":click without masks", "needs instance masks"),
        (":scene 99", "scene level takes 1 to"),
        ("a line that is not UTF-8", "not utf-8"),
        ("the session goes on after it", "view 99998"),
    ] {
        s.check(&format!("chat REPL {what}"), err.contains(want), &format!("no \"{want}\" in: {err}"));
    }
    s.check("chat REPL: no panic", !err.contains("panicked"), &err);
}

/// VQA: an empty question file, and a question that cannot be asked.
fn vqa_files(s: &mut Suite, dir: &Path, bare_run: &Path) {
    // VQA: an empty question file is refused; a question that cannot be asked fails the run
    // unless --keep-going (documented: then it is scored 0 and the run exits 0)
    let empty_q = dir.join("questions-empty.json");
    std::fs::write(&empty_q, r#"{"questions": []}"#).unwrap();
    let vqa = |q: &Path, extra: &[&str]| {
        let mut c = chatsplat();
        c.args(["vqa", "--max-new-tokens", "1", "--run"]).arg(bare_run).arg("--questions").arg(q).args(extra);
        c.output().unwrap()
    };
    s.fails(Case {
        name: "vqa empty question file".into(),
        out: vqa(&empty_q, &[]),
        expect: vec!["questions-empty.json".into(), "holds no questions".into()],
    });
    let bad_q = dir.join("questions-bad-view.json");
    let q = r#"{"questions": [{"id": "v", "level": "view", "view": 999, "question": "How many objects are there?",
        "answer": "3"}]}"#;
    std::fs::write(&bad_q, q).unwrap();
    s.fails(Case {
        name: "vqa question about view 999".into(),
        out: vqa(&bad_q, &[]),
        expect: vec!["questions-bad-view.json".into(), "could not be asked".into()],
    });
    s.succeeds("vqa view 999 with --keep-going", vqa(&bad_q, &["--keep-going"]));
}

/// A run made with relative paths works from any directory.
fn relative_paths(s: &mut Suite, dir: &Path) {
    // a run made with relative paths works from any directory (paths resolve against the run)
    let vlm = Path::new(env!("CARGO_MANIFEST_DIR")).join("checkpoints/tiny-llava-ov");
    let rel = |args: &[&str]| chatsplat().current_dir(dir).env("CHATSPLAT_VLM", &vlm).args(args).output().unwrap();
    s.succeeds("relative: train", rel(&["train", "--iters", "2", "--data", "base", "--out", "rel-run"]));
    s.succeeds("relative: extract", rel(&["extract", "--data", "base", "--out", "rel-teacher"]));
    let lang = rel(&["train-language", "--iters", "1", "--run", "rel-run", "--teacher", "rel-teacher"]);
    s.succeeds("relative: train-language", lang);
    let elsewhere = chatsplat()
        .current_dir(std::env::temp_dir())
        .env("CHATSPLAT_VLM", &vlm)
        .args(["ask", "--view", "0", "--max-new-tokens", "1", "--run"])
        .arg(dir.join("rel-run"))
        .arg("How many objects are there?")
        .output()
        .unwrap();
    s.succeeds("relative: ask from another directory", elsewhere);
}

/// `kill -9` during geometry training, then `--resume`; a NaN written into its checkpoint.
fn killed_geometry(s: &mut Suite, dir: &Path, base: &Path) {
    // kill -9 during geometry training, then --resume
    let k = dir.join("run-killed");
    let mut c = chatsplat();
    c.args(["train", "--iters", "1000000", "--data"]).arg(base).arg("--out").arg(&k);
    kill_after(c, &k.join("checkpoint.safetensors"));
    s.check("kill -9: first checkpoint", k.join("checkpoint.safetensors").is_file(), "no checkpoint within 120 s");
    s.check("kill -9: config", k.join("config.json").is_file(), "no config.json");
    s.succeeds("kill -9 then resume", train(base, &k, &["--resume", "--iters", "3"]));
    // a NaN written into a checkpoint: export and resume refuse it, naming the file
    let ck = k.join("checkpoint.safetensors");
    let mut bytes = std::fs::read(&ck).unwrap();
    let header = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let meta: serde_json::Value = serde_json::from_slice(&bytes[8..8 + header]).unwrap();
    let (_, first) = meta
        .as_object()
        .unwrap()
        .iter()
        .find(|(n, t)| *n != "__metadata__" && t["dtype"] == "F32")
        .expect("an f32 tensor");
    let at = 8 + header + first["data_offsets"][0].as_u64().unwrap() as usize;
    bytes[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&ck, &bytes).unwrap();
    let kept = dir.join("kept.ply");
    // a splat file export-ply may replace, so the checkpoint is what is refused
    let user_ply = b"ply\nformat ascii 1.0\ncomment the user's\nend_header\n";
    std::fs::write(&kept, user_ply).unwrap();
    s.fails(Case {
        name: "export a checkpoint holding NaN".into(),
        out: run(&["export-ply", "--run"], &[&k, Path::new("--out"), &kept]),
        expect: vec!["checkpoint.safetensors".into(), "non-finite".into()],
    });
    s.check("NaN checkpoint: --out intact", std::fs::read(&kept).unwrap() == user_ply, "--out overwritten");
    s.fails(Case {
        name: "resume a checkpoint holding NaN".into(),
        out: train(base, &k, &["--resume", "--iters", "5"]),
        expect: vec!["checkpoint.safetensors".into(), "non-finite".into()],
    });
}

/// `kill -9` during language training, then `--resume`; resuming a finished run.
fn killed_language(s: &mut Suite, dir: &Path, bare_run: &Path, bare_teacher: &Path) {
    // the same during language training
    let lk = dir.join("language-killed");
    let lang_args = |c: &mut Command| {
        c.arg("--run").arg(bare_run).arg("--teacher").arg(bare_teacher).arg("--out").arg(&lk);
    };
    let mut c = chatsplat();
    c.args(["train-language", "--iters", "1000000"]);
    lang_args(&mut c);
    kill_after(c, &lk.join("language.safetensors"));
    s.check("language kill -9: first checkpoint", lk.join("language.safetensors").is_file(), "none within 120 s");
    s.check("language kill -9: config", lk.join("config.json").is_file(), "no config.json");
    let mut c = chatsplat();
    c.args(["train-language", "--resume", "--iters", "2"]);
    lang_args(&mut c);
    s.succeeds("language kill -9 then resume", c.output().unwrap());
    // resuming a finished run trains nothing and keeps its figures (before-L1, time per step)
    let metrics = std::fs::read(lk.join("metrics.json")).unwrap_or_default();
    let mut c = chatsplat();
    c.args(["train-language", "--resume", "--iters", "2"]);
    lang_args(&mut c);
    s.succeeds("language resume with nothing left", c.output().unwrap());
    let again = std::fs::read(lk.join("metrics.json")).unwrap_or_default();
    s.check("language resume with nothing left: metrics kept", !metrics.is_empty() && again == metrics, "rewritten");
}

/// Runs `c` for at most `secs` seconds (killed past them: a hang is a failure, not a stuck suite).
fn output_within(mut c: Command, secs: u64) -> Option<Output> {
    use std::process::Stdio;
    let mut child = c.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    let t0 = std::time::Instant::now();
    while t0.elapsed().as_secs() < secs {
        if child.try_wait().unwrap().is_some() {
            return Some(child.wait_with_output().unwrap());
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    None
}

/// Nothing a user has is replaced or moved: an output onto a run's language files, over a file of
/// another kind, a new run over a finished one, a model folder as `train-vlm --out`, a resume with
/// another configuration, a batch whose results would hold (and later move) a scene's data or lie
/// inside it; and fingerprinting a dataset never blocks on a pipe. Each refused with the path and
/// the problem, and every input left byte for byte.
#[test]
fn outputs_never_replace_or_move_what_the_user_had() {
    let dir = root("outputs");
    let mut s = Suite::default();
    let base = dir.join("base");
    synth(&base, "46");
    let vlm = Path::new(env!("CARGO_MANIFEST_DIR")).join("checkpoints/tiny-llava-ov");
    let r = dir.join("run");
    s.succeeds("train", train(&base, &r, &[]));
    let teacher = dir.join("teacher");
    let mut extract = chatsplat();
    extract.env("CHATSPLAT_VLM", &vlm).args(["extract", "--data"]).arg(&base).arg("--out").arg(&teacher);
    s.succeeds("extract", extract.output().unwrap());
    let mut lang = chatsplat();
    lang.env("CHATSPLAT_VLM", &vlm).args(["train-language", "--iters", "1", "--run"]).arg(&r);
    s.succeeds("train-language", lang.arg("--teacher").arg(&teacher).output().unwrap());
    let r_s = r.to_str().unwrap();

    // export-ply onto the language run's own files, or over a file that is no splat file
    let checkpoint = r.join("language/language.safetensors");
    let export = |extra: &[&str]| -> Vec<String> {
        ["export-ply", "--run", r_s].iter().chain(extra).map(|a| a.to_string()).collect()
    };
    let spz = export(&["--format", "spz", "--out", checkpoint.to_str().unwrap()]);
    fails_intact(&mut s, "export-ply onto the language checkpoint", &[&r], &spz, &[], &["language run's checkpoint"]);
    let compact = r.join("language/compact.json");
    let onto_compact = export(&["--out", compact.to_str().unwrap()]);
    fails_intact(&mut s, "export-ply onto compact.json", &[&r], &onto_compact, &[], &["compact.json"]);
    let notes = dir.join("notes.ply");
    std::fs::write(&notes, "my notes, not a splat file").unwrap();
    let over = export(&["--out", notes.to_str().unwrap()]);
    fails_intact(&mut s, "export-ply over a file of another kind", &[&notes], &over, &[], &["notes.ply", "not a .ply"]);
    let zero = export(&["--object", "0", "--out", dir.join("zero.ply").to_str().unwrap()]);
    fails_intact(&mut s, "export-ply --object 0", &[&r], &zero, &[], &["--object 0", "background"]);
    let again = export(&["--out", dir.join("scene.ply").to_str().unwrap()]);
    let again: Vec<&str> = again.iter().map(String::as_str).collect();
    s.succeeds("export-ply", run(&again, &[]));
    s.succeeds("export-ply over its own earlier output", run(&again, &[]));

    // an answer length past what the model's context leaves is refused, not a conversation that
    // drops every earlier turn
    let mut c = chatsplat();
    c.env("CHATSPLAT_VLM", &vlm).args(["chat", "--max-new-tokens", "100000", "--run", r_s]);
    let long = c.stdin(std::process::Stdio::null()).output().unwrap();
    s.fails(Case {
        name: "chat --max-new-tokens past the context".into(),
        out: long,
        expect: vec!["--max-new-tokens 100000".into(), "1..=1024".into()],
    });

    // references checked against what they name: find entries naming objects the scene lacks, a
    // follow-up's twin about another target (each refused before anything is asked)
    let questions = |name: &str, entries: &str| -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, format!(r#"{{"questions": [{entries}]}}"#)).unwrap();
        p
    };
    let view = r#"{"id": "v", "level": "view", "view": 0, "question": "How many objects are there?", "answer": "3"}"#;
    let find = |ids: &str| {
        format!(r#"{view}, {{"id": "f", "level": "find", "question": "red", "answer": "-", "objects": {ids}}}"#)
    };
    for (name, ids, expect) in [
        ("find-unknown.json", "[99]", "object 99, which the scene does not have"),
        ("find-table.json", "[1]", "the table"),
        ("find-zero.json", "[0]", "names 0, the background"),
        ("find-twice.json", "[2, 2]", "object 2 twice"),
    ] {
        let q = questions(name, &find(ids));
        let mut c = chatsplat();
        c.env("CHATSPLAT_VLM", &vlm)
            .args(["vqa", "--run", r_s, "--questions"])
            .arg(&q)
            .arg("--out")
            .arg(dir.join("v.json"));
        s.fails(Case {
            name: format!("vqa: find {ids}"),
            out: c.output().unwrap(),
            expect: vec![name.into(), expect.into()],
        });
    }
    let other = r#"{"id": "w", "level": "view", "view": 1, "question": "How many objects are there?", "answer": "3"}"#;
    let follow = r#"{"id": "x", "level": "view", "view": 0, "question": "Is it left of the red cube?", "answer": "no",
        "follows": "v", "spelled": "w"}"#;
    let q = questions("twin.json", &format!("{view}, {other}, {follow}"));
    let mut c = chatsplat();
    c.env("CHATSPLAT_VLM", &vlm).args(["vqa", "--run", r_s, "--questions"]).arg(&q);
    s.fails(Case {
        name: "vqa: a twin about another target".into(),
        out: c.output().unwrap(),
        expect: vec!["twin.json".into(), "another target".into()],
    });
    // a teacher index without its files' hashes: read, with one warning naming it
    let old_teacher = dir.join("teacher-unhashed");
    copy_dir(&teacher, &old_teacher);
    edit_json(&old_teacher.join("teacher.json"), |v| {
        for view in v["views"].as_array_mut().unwrap() {
            view.as_object_mut().unwrap().remove("hash");
        }
    });
    let mut c = chatsplat();
    c.env("CHATSPLAT_VLM", &vlm).args(["train-language", "--iters", "1", "--run", r_s, "--out"]);
    let out = c.arg(dir.join("lang-unhashed")).arg("--teacher").arg(&old_teacher).output().unwrap();
    let warned = String::from_utf8_lossy(&out.stderr).contains("record no hash of their token files");
    s.check("teacher index without hashes", out.status.success() && warned, "no warning naming the index");

    // a new geometry run over a finished one, or into a folder of other files
    let retrain = ["train", "--iters", "1", "--data", base.to_str().unwrap(), "--out", r_s];
    fails_intact(
        &mut s,
        "train over a finished run",
        &[&r],
        &retrain,
        &[],
        &["already holds a geometry run", "--resume"],
    );
    let stuff = dir.join("stuff");
    std::fs::create_dir_all(&stuff).unwrap();
    std::fs::write(stuff.join("keep.txt"), "mine").unwrap();
    let into_stuff = ["train", "--iters", "1", "--data", base.to_str().unwrap(), "--out", stuff.to_str().unwrap()];
    fails_intact(&mut s, "train into a folder of other files", &[&stuff], &into_stuff, &[], &["keep.txt"]);

    // train-vlm: a model folder as --out; a resume with another configuration; the base model
    // trained with this very configuration
    let model = dir.join("model");
    copy_dir(&vlm, &model);
    let vlm_out = ["train-vlm", "--steps", "1", "--out", model.to_str().unwrap()];
    fails_intact(
        &mut s,
        "train-vlm --out a model folder",
        &[&model],
        &vlm_out,
        &[],
        &["holds a model", "not a train-vlm run"],
    );
    let cfg = dir.join("vlm.json");
    std::fs::write(&cfg, r#"{"steps": 2}"#).unwrap();
    let stage = dir.join("stage");
    std::fs::create_dir_all(&stage).unwrap();
    std::fs::write(stage.join("train_config.json"), r#"{"steps": 5}"#).unwrap();
    let resume = ["train-vlm", "--resume", "--config", cfg.to_str().unwrap(), "--out", stage.to_str().unwrap()];
    fails_intact(
        &mut s,
        "train-vlm --resume with another configuration",
        &[&stage],
        &resume,
        &[],
        &["another configuration"],
    );
    // a value that does not fit is refused naming its key, nested ones too
    let bad_cfg = dir.join("vlm-bad.json");
    std::fs::write(&bad_cfg, "{\n  \"steps\": 2,\n  \"base\": {\"soup\": [1, \"x\"]}\n}\n").unwrap();
    let bad_out = dir.join("vlm-bad");
    let bad = ["train-vlm", "--config", bad_cfg.to_str().unwrap(), "--out", bad_out.to_str().unwrap()];
    fails_intact(
        &mut s,
        "train-vlm config: a soup seed not a number",
        &[&bad_cfg],
        &bad,
        &[],
        &["base.soup[1]", "line 3"],
    );
    s.check("bad config: nothing written", !dir.join("vlm-bad").exists(), "vlm-bad was made");
    let same = dir.join("same-base");
    copy_dir(&vlm, &same);
    std::fs::write(same.join("train_config.json"), r#"{"steps": 2}"#).unwrap();
    let vlm_new = dir.join("vlm-new");
    let from_same = [
        "train-vlm",
        "--config",
        cfg.to_str().unwrap(),
        "--base-model",
        same.to_str().unwrap(),
        "--out",
        vlm_new.to_str().unwrap(),
    ];
    fails_intact(
        &mut s,
        "train-vlm --base-model of this configuration",
        &[&same],
        &from_same,
        &[],
        &["this very configuration"],
    );

    // batch: out = "." with a scene whose data is its own results folder; out inside a scene's
    // data; a scene named like the report
    let b1 = dir.join("b1");
    copy_dir(&base, &b1.join("s1"));
    std::fs::write(b1.join("m.toml"), "out = \".\"\n[[scene]]\nname = \"s1\"\ndata = \"s1\"\n").unwrap();
    fails_intact(
        &mut s,
        "batch: data inside its results folder",
        &[&b1],
        &["batch", "--manifest"],
        &[&b1.join("m.toml")],
        &["m.toml", "results folder of scene `s1`"],
    );
    let b2 = dir.join("b2");
    copy_dir(&base, &b2.join("d"));
    std::fs::write(b2.join("m.toml"), "out = \"d/out\"\n[[scene]]\nname = \"a\"\ndata = \"d\"\n").unwrap();
    fails_intact(
        &mut s,
        "batch: out inside a scene's data",
        &[&b2],
        &["batch", "--manifest"],
        &[&b2.join("m.toml")],
        &["lies inside, the data of scene `a`"],
    );
    std::fs::write(b2.join("r.toml"), "[[scene]]\nname = \"report.json\"\ndata = \"d\"\n").unwrap();
    fails_intact(
        &mut s,
        "batch: a scene named report.json",
        &[&b2.join("d")],
        &["batch", "--manifest"],
        &[&b2.join("r.toml")],
        &["report.json"],
    );
    // a named pipe in a scene's data: refused by name, not read for ever
    let b3 = dir.join("b3");
    copy_dir(&base, &b3.join("d"));
    let fifo = b3.join("d/pipe");
    let made = Command::new("mkfifo").arg(&fifo).status().is_ok_and(|st| st.success());
    std::fs::write(b3.join("m.toml"), "[[scene]]\nname = \"a\"\ndata = \"d\"\n").unwrap();
    if made {
        let mut c = chatsplat();
        c.env("CHATSPLAT_VLM", &vlm).args(["batch", "--manifest"]).arg(b3.join("m.toml"));
        match output_within(c, 120) {
            Some(out) => s.fails(Case {
                name: "batch: a pipe in the data".into(),
                out,
                expect: vec!["pipe".into(), "not a regular file".into()],
            }),
            None => s.check("batch: a pipe in the data", false, "still running after 120 s"),
        }
    } else {
        eprintln!("SKIPPED the pipe case: no mkfifo on this machine");
    }

    // every command that writes, held to one table of cases
    let table_model = dir.join("table-model");
    copy_dir(&vlm, &table_model);
    let made = output_table::Made { base: &base, run: &r, teacher: &teacher, model: &table_model, dir: &dir };
    output_table::every_command_keeps_the_guard(&mut s, &made);
    s.finish(90);
    std::fs::remove_dir_all(&dir).ok();
}
