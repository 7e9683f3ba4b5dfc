//! The real-size path as a user meets it, on every push: a LLaVA-OneVision of the published 0.5B
//! widths and token shapes (SigLIP 1152 wide at 384 px with 14-px patches, 27 x 27 = 729 tokens
//! a view; the projector to 896; Qwen2 896 wide with 14 heads and 2 key/value heads), one layer in
//! the tower and one in the LLM, random weights drawn here (nothing downloaded or committed), run
//! through every stage of the README with the `chatsplat` binary: `synth`, `train`, `extract`
//! (views and objects), `train-language` (its token L1 falls), `ask` at view, object and scene
//! level, `chat`, `vqa`, `export-encoder` and one `serve` answer over HTTP. The front ends must
//! agree: the same question about the same view gets the same answer from each.

#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

use burn::tensor::Device;
use chatsplat_tests::http::{self, Server};
use model::chat::{ChatSession, Target};
use model::run::{GeometryRun, TeacherDir};
use serde_json::json;
use std::io::Write;
use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::Instant;

const BIN: &str = env!("CARGO_BIN_EXE_chatsplat");
/// The synthetic scene: views of this side (the teacher squashes them to 384 px), the number of
/// views, the geometry and language iterations. The language maps are rendered at about the views'
/// own resolution (`field.patch` 0: a 5 x 5 patch a token here; the default 14 renders 378-px maps,
/// 40x the work a step). In the first iterations of the warm-up the view L1 may rise a little
/// (0.1895 -> 0.1929 at 12 where this was written); at 30 it is well below its start (0.150).
const SIDE: &str = "128";
const VIEWS: &str = "6";
const GEOMETRY_ITERS: &str = "150";
const LANGUAGE_ITERS: &str = "30";
/// Tokens generated per answer: the prefill of 729 image tokens a view is what this test runs.
const NEW_TOKENS: usize = 3;
const VIEW_Q: &str = "What objects are there?";
const OBJECT_Q: &str = "What is this?";
const SCENE_Q: &str = "How many objects are in the scene?";

/// `chatsplat ARGS` (with `stdin` typed on its standard input), timed; fails the test with its
/// standard error unless it succeeds without a panic.
fn chatsplat(args: &[&str], stdin: Option<&str>) -> Output {
    let t0 = Instant::now();
    let mut child = Command::new(BIN)
        .args(args)
        .stdin(if stdin.is_some() { Stdio::piped() } else { Stdio::null() })
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    if let Some(text) = stdin {
        child.stdin.take().unwrap().write_all(text.as_bytes()).unwrap();
    }
    let out = child.wait_with_output().unwrap();
    eprintln!("real size: chatsplat {} in {:.1} s", args[0], t0.elapsed().as_secs_f64());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "chatsplat {} failed ({}):\n{err}", args[0], out.status);
    assert!(!err.contains("panicked"), "{err}");
    out
}

fn text(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn path(p: &Path) -> &str {
    p.to_str().expect("the scratch paths are UTF-8")
}

/// The four figures of train-language's "token L1 on training views: view A -> B, object C -> D".
fn token_l1(out: &str) -> [f64; 4] {
    let line = out.lines().find(|l| l.starts_with("token L1 on training views")).unwrap_or_else(|| panic!("{out}"));
    let nums: Vec<f64> = line
        .split(|c: char| !(c.is_ascii_digit() || c == '.'))
        .filter(|w| w.contains('.'))
        .filter_map(|w| w.parse().ok())
        .take(4)
        .collect();
    nums.try_into().unwrap_or_else(|_| panic!("four figures expected in {line}"))
}

/// The pixel nearest the centre of the largest object seen by `cam`.
fn object_pixel(s: &ChatSession, cam: &splat_kernels::Camera) -> (usize, usize) {
    let ids = s.scene.splats.render_ids(cam).unwrap();
    let w = cam.width as usize;
    let (id, _) = model::language::pixel_counts(&ids)
        .into_iter()
        .filter(|&(id, _)| id >= model::data::synth::FIRST_OBJECT_ID)
        .max_by_key(|&(id, n)| (n, std::cmp::Reverse(id)))
        .unwrap();
    let at: Vec<usize> = (0..ids.len()).filter(|&p| ids[p] == id).collect();
    assert!(!at.is_empty(), "view 0 shows an object");
    let (cx, cy) = at.iter().fold((0.0, 0.0), |(x, y), &p| (x + (p % w) as f64, y + (p / w) as f64));
    let (cx, cy) = (cx / at.len() as f64, cy / at.len() as f64);
    let d = |p: usize| ((p % w) as f64 - cx).powi(2) + ((p / w) as f64 - cy).powi(2);
    let p = *at.iter().min_by(|&&a, &&b| d(a).total_cmp(&d(b))).unwrap();
    (p % w, p / w)
}

#[test]
fn a_real_shape_llava_onevision_runs_through_every_stage_and_its_front_ends_agree() {
    let dir = chatsplat_tests::temp_dir("real-size");
    let (vlm, data, run, teacher) = (dir.join("vlm"), dir.join("data"), dir.join("run"), dir.join("teacher"));
    let t0 = Instant::now();
    let mut cfg = model::vlm::LlavaConfig::onevision_0_5b();
    (cfg.vision.num_layers, cfg.text.num_layers, cfg.text.vocab_size) = (1, 1, 0);
    let m = train::vlm::random_published(cfg, 7, &Device::flex(), false).unwrap();
    train::vlm::save_model_as(&m, &vlm, true).unwrap();
    drop(m);
    let mb = std::fs::metadata(vlm.join("model.safetensors")).unwrap().len() as f64 / 1e6;
    eprintln!("real size: the model ({mb:.0} MB in bf16) in {:.1} s", t0.elapsed().as_secs_f64());

    let scene = ["--views", VIEWS, "--width", SIDE, "--height", SIDE, "--seed", "41"];
    chatsplat(&[&["synth", "--out", path(&data)][..], &scene].concat(), None);
    chatsplat(&["train", "--data", path(&data), "--iters", GEOMETRY_ITERS, "--out", path(&run)], None);

    // --- extract: 27 x 27 tokens of 1152 for every training view and its objects
    chatsplat(&["extract", "--vlm", path(&vlm), "--data", path(&data), "--out", path(&teacher)], None);
    let ix = TeacherDir::new(&teacher).read_index().unwrap();
    assert_eq!((ix.grid, ix.dim, ix.image_size, ix.patch_size), (27, 1152, 384, 14));
    assert!(!ix.views.is_empty() && ix.views.iter().all(|v| !v.objects.is_empty()), "{:?}", ix.views);

    // --- the language stage learns at this width: the training views' token L1 falls
    let lang_cfg = dir.join("language.json");
    std::fs::write(&lang_cfg, r#"{"field": {"patch": 0}}"#).unwrap();
    let (r, t) = (path(&run), path(&teacher));
    let out = chatsplat(
        &["train-language", "--run", r, "--teacher", t, "--config", path(&lang_cfg), "--iters", LANGUAGE_ITERS],
        None,
    );
    let [view0, view1, obj0, obj1] = token_l1(&text(&out));
    assert!(view1 < view0 && obj1 < obj0, "token L1 view {view0} -> {view1}, object {obj0} -> {obj1}");

    // --- the library's answers at view 0, at the object in its middle and at scene level
    let t1 = Instant::now();
    let session = ChatSession::open(&GeometryRun::new(&run), None, &vlm, &Device::ndarray()).unwrap();
    let cam0 = session.cameras[0];
    let (x, y) = object_pixel(&session, &cam0);
    let opts = model::vlm::GenerateOptions { max_new_tokens: NEW_TOKENS, ..Default::default() };
    let lib = |t: &Target, q: &str| session.ask(t, q, &opts, |_| {}).unwrap().text.trim().to_string();
    let object = session.click(&cam0, x, y).unwrap().expect("the pixel shows an object");
    let (lib_view, lib_object) = (lib(&Target::View(cam0), VIEW_Q), lib(&Target::Object(object), OBJECT_Q));
    let lib_scene = lib(&session.scene_target(3).unwrap(), SCENE_Q);
    drop(session);
    eprintln!("real size: the library's three answers in {:.1} s", t1.elapsed().as_secs_f64());

    // --- ask at each level: 729 image tokens a view or object, the library's answers
    let n = NEW_TOKENS.to_string();
    let ask = |extra: &[&str], q: &str| {
        let o = chatsplat(&[&["ask", "--run", path(&run), "--max-new-tokens", &n][..], extra, &[q]].concat(), None);
        (chatsplat_tests::prompt_tokens(&String::from_utf8_lossy(&o.stderr)), text(&o).trim().to_string())
    };
    let (xs, ys) = (x.to_string(), y.to_string());
    let (vt, view_answer) = ask(&["--view", "0"], VIEW_Q);
    assert!((729..729 + 64).contains(&vt), "a view is 729 image tokens and a short question, got {vt}");
    assert_eq!(view_answer, lib_view);
    let (ot, object_answer) = ask(&["--view", "0", "--object", &xs, &ys], OBJECT_Q);
    assert!((729..729 + 64).contains(&ot), "an object is 729 image tokens and a short question, got {ot}");
    assert_eq!(object_answer, lib_object);
    let (st, scene_answer) = ask(&["--scene", "--views", "3"], SCENE_Q);
    assert!((3 * 729..3 * 729 + 64).contains(&st), "three views are 3 x 729 image tokens, got {st}");
    assert_eq!(scene_answer, lib_scene);

    // --- chat: the same questions typed, the same answers
    let typed = format!(":view 0\n{VIEW_Q}\n:click {x} {y}\n{OBJECT_Q}\n:quit\n");
    let chat = text(&chatsplat(&["chat", "--run", path(&run), "--max-new-tokens", &n], Some(&typed)));
    assert!(chat.contains(&lib_view) && chat.contains(&lib_object), "chat said {chat:?}");

    // --- vqa on one question of each level (the scene's at 3 views): no error, the library's answers
    let few = dir.join("questions.json");
    let q =
        |id: &str, level: &str, question: &str| json!({"id": id, "level": level, "question": question, "answer": "x"});
    let mut questions = vec![q("v", "view", VIEW_Q), q("o", "object", OBJECT_Q), q("s", "scene", SCENE_Q)];
    questions[0]["view"] = json!(0);
    (questions[1]["view"], questions[1]["object"]) = (json!(0), json!([x as f32 + 0.5, y as f32 + 0.5]));
    std::fs::write(&few, serde_json::to_vec(&json!({"questions": questions})).unwrap()).unwrap();
    let answers = dir.join("answers.json");
    let vqa = ["vqa", "--run", path(&run), "--questions", path(&few), "--out", path(&answers), "--views", "3"];
    chatsplat(&[&vqa[..], &["--max-new-tokens", &n]].concat(), None);
    let got: serde_json::Value = serde_json::from_slice(&std::fs::read(&answers).unwrap()).unwrap();
    let rows = got["answers"].as_array().unwrap();
    assert_eq!(rows.len(), 3, "{got}");
    assert!(rows.iter().all(|r| r["error"].is_null()), "{got}");
    let said: Vec<&str> = rows.iter().map(|r| r["answer"].as_str().unwrap().trim()).collect();
    assert_eq!(said, [lib_view.as_str(), lib_object.as_str(), lib_scene.as_str()], "{got}");

    // --- export-encoder: the encoder's weights at the teacher's width and token count
    let enc = dir.join("encoder.safetensors");
    chatsplat(&["export-encoder", "--run", path(&run), "--out", path(&enc)], None);
    let bytes = std::fs::read(&enc).unwrap();
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let dims: Vec<usize> = st.tensors().iter().flat_map(|(_, t)| t.shape().to_vec()).collect();
    assert!(dims.contains(&1152) && dims.contains(&729), "tensor shapes {:?}", st.tensors());

    // --- serve: one answer over HTTP, the library's
    let t2 = Instant::now();
    let server = Server::start(BIN, &run, &["--max-new-tokens", &n]);
    let views = http::get(&server.addr, "/api/scene").json()["views"].clone();
    let body = json!({"scope": "view", "camera": views[0]["camera"], "question": VIEW_Q});
    let (served, _) = http::streamed_answer(&http::post(&server.addr, "/api/ask", &body));
    assert_eq!(served.trim(), lib_view);
    server.stop();
    eprintln!("real size: serve and its answer in {:.1} s", t2.elapsed().as_secs_f64());
    eprintln!("real size: every stage in {:.1} s", t0.elapsed().as_secs_f64());
}
