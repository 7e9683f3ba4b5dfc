//! `chatsplat serve` as a user meets it, on the shared trained tabletop with the built-in model:
//! the HTTP API against the library (the camera contract, picks, answers), every bad request
//! refused by name, 20 clients at once, a client that goes away, a clean stop; and the page in a
//! real headless Chromium (WebGL2 on SwiftShader): the scene drawn, a click that tints the object
//! red, answers at object, view (from a camera no training view had) and scene level, and the
//! server-rendered fallback picking the same object.

#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

use chatsplat_tests::browser::{self, Browser};
use chatsplat_tests::fixture::{self, Tabletop};
use chatsplat_tests::http::{self, Reply, Server};
use glam::Vec3;
use model::chat::{ChatSession, Conversation, Target};
use model::data::synth::questions::{Kind, ViewFacts, view_questions};
use model::data::synth::scene::SynthScene;
use model::run::GeometryRun;
use serde_json::{Value, json};
use splat_kernels::Camera;
use std::io::Read;
use std::path::Path;
use std::sync::Mutex;
use std::time::{Duration, Instant};
use viewer::camera::ViewCamera;

/// The tests share two cores: one server at a time.
static SERIAL: Mutex<()> = Mutex::new(());

fn scene() -> Tabletop {
    fixture::tabletop(Path::new(env!("CARGO_TARGET_TMPDIR")))
}

fn scene_json(data: &Path) -> SynthScene {
    model::io::read_json(&data.join("scene.json")).unwrap()
}

fn ask(s: &Server, body: Value) -> Reply {
    let sent = http::send(&s.addr, "POST", "/api/ask", &[], Some(body.to_string().as_bytes()));
    sent.unwrap_or_else(|e| panic!("/api/ask {body}: {e}; the server's log:\n{}", s.log()))
}

/// The answer text of an ask's event stream, after checking the stream's shape and that it timed
/// a first token.
fn answer_of(r: &Reply) -> String {
    let (streamed, done) = http::streamed_answer(r);
    assert!(done["first_token_ms"].as_f64().unwrap() > 0.0 && done["tokens"].as_u64().unwrap() > 0);
    streamed
}

fn rle_covers(mask: &Value, p: usize) -> bool {
    let runs: Vec<usize> = mask["runs"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap() as usize).collect();
    runs.chunks(2).any(|r| p >= r[0] && p < r[0] + r[1])
}

fn rle_pixels(mask: &Value) -> Vec<usize> {
    let runs: Vec<usize> = mask["runs"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap() as usize).collect();
    runs.chunks(2).flat_map(|r| r[0]..r[0] + r[1]).collect()
}

#[test]
fn serve_answers_like_the_library_and_refuses_bad_requests_by_name() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let t = scene();
    let server = Server::start(env!("CARGO_BIN_EXE_chatsplat"), &t.run, &[]);
    let a = server.addr.clone();
    let dev = burn::tensor::Device::ndarray();
    let session = ChatSession::open(&GeometryRun::new(&t.run), None, &fixture::builtin_model(), &dev).unwrap();
    let truth = scene_json(&t.data);

    // --- the page and its files come from the binary; nothing else does
    let page = http::get(&a, "/");
    assert_eq!(page.status, 200);
    assert!(page.text().contains("<script type=\"module\" src=\"/app.js\">"));
    let spark = http::get(&a, "/vendor/spark.module.min.js");
    assert_eq!((spark.status, spark.header("content-type")), (200, Some("text/javascript; charset=utf-8")));
    assert!(spark.body.len() > 1_000_000);
    for path in ["/../Cargo.toml", "/%2e%2e/Cargo.toml", "/vendor/../../Cargo.toml", "/api/nothing", "/app.js.map"] {
        let r = http::get(&a, path);
        assert_eq!(r.status, 404, "{path}: {}", r.text());
        assert!(r.json()["error"].is_string());
    }

    // --- the scene as the page learns it
    let info = http::get(&a, "/api/scene").json();
    let views = info["views"].as_array().unwrap();
    assert_eq!(views.len(), session.cameras.len());
    // every Gaussian is drawn (a compacted run keeps fewer for the language maps only)
    let shown = session.scene.shown().len();
    assert_eq!(info["gaussians"].as_u64().unwrap() as usize, shown);
    for o in &truth.objects {
        let listed = info["objects"].as_array().unwrap().iter().find(|x| x["id"] == o.id);
        assert_eq!(listed.map(|x| x["name"].as_str().unwrap()), Some(o.name().as_str()), "object {}", o.id);
    }
    // the table is ground, not an object: the page's count is the scene's objects
    assert_eq!(info["objects"].as_array().unwrap().len(), truth.objects.len(), "{}", info["objects"]);
    // the built-in model offers the question forms it was trained on, about this scene's objects
    let forms = info["question_forms"].as_array().expect("the built-in model's question forms");
    for level in ["view", "object", "scene"] {
        assert!(forms.iter().any(|f| f["level"] == level), "no {level} form: {forms:?}");
    }
    let first = truth.objects[0].name();
    assert!(forms.iter().any(|f| f["question"] == format!("Is there a {first}?")), "{forms:?}");
    let ply = http::get(&a, "/api/splats.ply");
    assert_eq!(model::ply::parse(&ply.body, "splats.ply").unwrap().len(), shown);
    // one object's Gaussians to download (by each Gaussian's identity class, as export-ply
    // --object), and the scene without them: the page's "download" and "hide"
    let classes = session.scene.shown().gaussian_classes();
    let o = &truth.objects[0];
    let own = classes.iter().filter(|&&c| c == o.id).count();
    assert!(own > 10, "{} owns {own} Gaussians", o.name());
    let r = http::get(&a, &format!("/api/objects/{}.ply", o.id));
    assert_eq!(r.status, 200, "{}", r.text());
    let name = format!("{}-{}.ply", o.id, o.name().replace(' ', "-"));
    assert_eq!(r.header("content-disposition"), Some(format!("attachment; filename=\"{name}\"").as_str()));
    assert_eq!(model::ply::parse(&r.body, &name).unwrap().len(), own);
    let r = http::get(&a, &format!("/api/objects/{}.spz", o.id));
    assert_eq!(model::spz::parse(&r.body, "object.spz").unwrap().len(), own, "{}", r.text());
    // the whole scene as .spz too, far smaller (the page loads the smaller)
    let spz = http::get(&a, "/api/splats.spz");
    assert_eq!(model::spz::parse(&spz.body, "splats.spz").unwrap().len(), shown);
    let sizes = &info["splat_bytes"];
    assert_eq!(
        (sizes["ply"].as_u64(), sizes["spz"].as_u64()),
        (Some(ply.body.len() as u64), Some(spz.body.len() as u64))
    );
    assert!(spz.body.len() * 5 < ply.body.len(), "{sizes}");
    let other = truth.objects[1].id;
    let r = http::get(&a, &format!("/api/splats.ply?without={},{other}", o.id));
    let rest = classes.iter().filter(|&&c| c != o.id && c != other).count();
    assert_eq!(model::ply::parse(&r.body, "without.ply").unwrap().len(), rest);
    for (path, status, says) in [
        ("/api/objects/99.ply", 404, "no object 99"),
        ("/api/objects/0.ply", 404, "no object 0"),
        ("/api/objects/red.ply", 404, "no such file"),
        ("/api/objects/1.txt", 404, "no such file"),
        ("/api/splats.ply?without=abc", 400, "not an object id"),
        ("/api/splats.ply?without=99", 400, "no object 99"),
        ("/api/splats.ply?hide=1", 400, "without=ID"),
    ] {
        let r = http::get(&a, path);
        let e = r.json();
        assert_eq!(r.status, status, "{path}: {e}");
        assert!(e["error"].as_str().unwrap().contains(says), "{path}: {e}");
    }

    // --- the camera contract: a training (and a held-out) camera sent back renders the same
    // pixels as the library renders from the stored camera, with exact intrinsics or the page's
    // fov-only form
    let last = views.len() - 1;
    for v in [0, 5, last] {
        let cam = session.cameras[v];
        let own: Vec<u8> = session.view_image(&cam, None).unwrap().iter().map(|x| (x * 255.0 + 0.5) as u8).collect();
        let mut page_form = views[v]["camera"].clone();
        for k in ["fx", "fy", "cx", "cy"] {
            page_form.as_object_mut().unwrap().remove(k);
        }
        for camera in [views[v]["camera"].clone(), page_form] {
            let r = http::post(&a, "/api/render", &json!({ "camera": camera }));
            assert_eq!((r.status, r.header("content-type")), (200, Some("image/png")), "{}", r.text());
            let (w, h, rgb) = http::decode_png(&r.body);
            assert_eq!((w as u32, h as u32), (cam.width, cam.height));
            let diff: Vec<i32> = rgb.iter().zip(&own).map(|(x, y)| (*x as i32 - *y as i32).abs()).collect();
            let off = diff.iter().filter(|&&d| d > 1).count();
            assert!(off * 1000 <= diff.len(), "view {v}: {off} of {} values differ by more than 1", diff.len());
        }
    }

    // --- a pick at a training camera: the object under the pixel, named, its mask covering it
    let cam0 = views[0]["camera"].clone();
    let c0 = session.cameras[0];
    let ids = session.scene.splats.render_ids(&c0).unwrap();
    let w0 = c0.width as usize;
    // a server frame without a hidden object: its pixels change, the rest of the view hardly
    let frame = |hidden: Value| {
        let r = http::post(&a, "/api/render", &json!({"camera": cam0, "hidden": hidden}));
        assert_eq!(r.status, 200, "{}", r.text());
        http::decode_png(&r.body).2
    };
    let big = truth.objects.iter().max_by_key(|x| ids.iter().filter(|&&i| i == x.id).count()).unwrap();
    let (all, without) = (frame(json!([])), frame(json!([big.id])));
    let d = |p: usize| (0..3).map(|c| (all[3 * p + c] as f64 - without[3 * p + c] as f64).abs()).sum::<f64>() / 3.0;
    let of_big: Vec<usize> = (0..ids.len()).filter(|&p| ids[p] == big.id).collect();
    let changed = of_big.iter().map(|&p| d(p)).sum::<f64>() / of_big.len().max(1) as f64;
    let elsewhere = (0..ids.len()).filter(|&p| ids[p] != big.id && d(p) > 8.0).count();
    eprintln!("hidden {}: its {} px changed by {changed:.1} on average, {elsewhere} others", big.name(), of_big.len());
    assert!(of_big.len() > 30 && changed > 10.0, "hidden {}: {} px changed by {changed:.1}", big.name(), of_big.len());
    assert!(elsewhere * 20 < ids.len(), "hiding {} changed {elsewhere} other pixels", big.name());
    let r = http::post(&a, "/api/render", &json!({"camera": cam0, "hidden": [99]}));
    assert_eq!((r.status, r.json()["field"].as_str()), (400, Some("hidden")), "{}", r.text());
    let p = (0..ids.len()).find(|&p| ids[p] >= model::data::synth::FIRST_OBJECT_ID).expect("view 0 shows an object");
    let r = http::post(&a, "/api/pick", &json!({"camera": cam0, "x": p % w0, "y": p / w0}));
    assert_eq!(r.status, 200, "{}", r.text());
    let picked = r.json();
    let o = &picked["object"];
    assert_eq!(o["id"].as_u64(), Some(ids[p] as u64));
    assert_eq!(o["name"].as_str().unwrap(), truth.object(ids[p]).unwrap().name());
    assert!(rle_covers(&o["mask"], p) && o["pixels"].as_u64().unwrap() as usize == rle_pixels(&o["mask"]).len());
    let bg = http::post(&a, "/api/pick", &json!({"camera": cam0, "x": 0, "y": 0})).json();
    assert!(bg["object"].is_null(), "{bg}");
    let moved = http::post(&a, "/api/select", &json!({"camera": views[1]["camera"], "id": ids[p]})).json();
    assert!(moved["object"].is_null() || moved["object"]["id"].as_u64() == Some(ids[p] as u64), "{moved}");

    // --- answers stream, and they are the library's answers
    let opts = model::vlm::GenerateOptions { max_new_tokens: 256, ..Default::default() };
    let lib = |t: &Target, q: &str| session.ask(t, q, &opts, |_| {}).unwrap().text;
    let q = "What objects are there?";
    let served = answer_of(&ask(&server, json!({"scope": "view", "camera": cam0, "question": q})));
    assert_eq!(served, lib(&Target::View(c0), q));
    let object = session.click(&c0, p % w0, p / w0).unwrap().unwrap();
    let served =
        answer_of(&ask(&server, json!({"scope": "object", "camera": cam0, "id": ids[p], "question": "What is this?"})));
    assert_eq!(served, lib(&Target::Object(object), "What is this?"));
    let q = "How many objects are in the scene?";
    let served = answer_of(&ask(&server, json!({"scope": "scene", "views": 3, "question": q})));
    assert_eq!(served, lib(&session.scene_target(3).unwrap(), q));

    // --- a conversation: the follow-up names the id the first answer's start event gave, is
    // asked after the first turn (the library's conversation answers the same), and prefills
    // only its own tokens
    let (q1, q2) = ("What colors are there?", "What objects are there?");
    let first = ask(&server, json!({"scope": "view", "camera": cam0, "question": q1}));
    let start = |r: &Reply| r.events().into_iter().find(|(n, _)| n == "start").expect("a start event").1;
    let (s1, id) = (start(&first), start(&first)["conversation"].clone());
    assert_eq!((s1["turn"].as_u64(), s1["cached_tokens"].as_u64()), (Some(1), Some(0)), "{s1}");
    let second = ask(&server, json!({"scope": "view", "camera": cam0, "question": q2, "conversation": id}));
    let s2 = start(&second);
    assert_eq!((s2["conversation"].clone(), s2["turn"].as_u64()), (id.clone(), Some(2)), "{s2}");
    let (prompt1, cached2) = (s1["prompt_tokens"].as_u64().unwrap(), s2["cached_tokens"].as_u64().unwrap());
    assert!(cached2 > prompt1 && cached2 < s2["prompt_tokens"].as_u64().unwrap(), "{s1} {s2}");
    let mut conversation = Conversation::new(Target::View(c0));
    let mut said = |q: &str| {
        let r = session.converse_until(&mut conversation, q, &opts, |_| std::ops::ControlFlow::Continue(())).unwrap();
        r.generation
    };
    assert_eq!(answer_of(&first), said(q1).text);
    let g2 = said(q2);
    assert_eq!((answer_of(&second), g2.cached_tokens as u64), (g2.text, cached2));
    let fresh = ask(&server, json!({"scope": "view", "camera": cam0, "question": q2}));
    assert_ne!(start(&fresh)["conversation"], id, "a question without an id starts a new conversation");
    // a conversation that would pass the model's context drops its oldest exchanges, never the
    // images, and says so: here the answer's room leaves space for the new question alone
    let room = session.vlm.cfg.text.max_positions - session.check_question(q2, 1).unwrap() - 1;
    let tight = model::vlm::GenerateOptions { max_new_tokens: room, ..opts.clone() };
    let r = session.converse_until(&mut conversation, q2, &tight, |_| std::ops::ControlFlow::Continue(())).unwrap();
    assert_eq!((r.dropped, conversation.dropped(), conversation.exchanges().len()), (2, 2, 1));
    assert!(r.dropped_note().unwrap().contains("dropped"));
    assert_eq!(r.generation.text, lib(&Target::View(c0), q2), "the images kept: the question alone's answer");

    // --- find: an object's name finds the objects of that name, a colour those of that colour,
    // a shape those of that shape, each with its mask where view 0 shows it; a name no object
    // has finds nothing; the table (never named by the questions) is not searched; the command
    // line finds the same
    use model::data::synth::scene::{Color, Shape};
    let find = |phrase: &str| {
        let r = http::post(&a, "/api/find", &json!({"phrase": phrase, "camera": cam0}));
        assert_eq!(r.status, 200, "{phrase}: {}", r.text());
        r.json()
    };
    let ids_of = |v: &Value| -> Vec<u64> {
        let mut ids: Vec<u64> = v.as_array().unwrap().iter().map(|m| m["id"].as_u64().unwrap()).collect();
        ids.sort();
        ids
    };
    let having = |keep: &dyn Fn(&model::data::synth::scene::Object) -> bool| -> Vec<u64> {
        truth.objects.iter().filter(|o| keep(o)).map(|o| o.id as u64).collect()
    };
    for o in &truth.objects {
        let r = find(&o.name());
        assert_eq!(ids_of(&r["matches"]), having(&|x| x.name() == o.name()), "{}: {r}", o.name());
        assert_eq!(r["ranked"].as_array().unwrap().len(), truth.objects.len(), "{r}");
        assert_eq!(r["matches"][0]["name"], json!(o.name()), "{r}");
        let shown = ids.contains(&o.id);
        let m = r["matches"].as_array().unwrap().iter().find(|m| m["id"] == json!(o.id)).unwrap();
        assert_eq!(m["mask"].is_object(), shown, "{}: {m}", o.name());
        if shown {
            let (got, want) = (rle_pixels(&m["mask"]).len(), ids.iter().filter(|&&i| i == o.id).count());
            assert!(got.abs_diff(want) * 50 <= want, "{}: mask of {got} pixels, the library's {want}", o.name());
        }
        let (color, shape) = (o.color, o.shape);
        assert_eq!(ids_of(&find(color.word())["matches"]), having(&|x| x.color == color), "{}", color.word());
        assert_eq!(ids_of(&find(shape.word())["matches"]), having(&|x| x.shape == shape), "{}", shape.word());
    }
    let absent = Color::ALL
        .iter()
        .flat_map(|c| Shape::ALL.iter().map(move |s| (*c, *s)))
        .find(|(c, s)| !truth.objects.iter().any(|o| o.color == *c || o.shape == *s))
        .expect("a colour and a shape the scene does not have");
    let none = find(&format!("{} {}", absent.0.word(), absent.1.word()));
    assert_eq!(none["matches"], json!([]), "{none}");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_chatsplat"))
        .args(["find", "--json", "--run"])
        .arg(&t.run)
        .arg(truth.objects[0].name())
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let cli: Value = serde_json::from_slice(&out.stdout).unwrap();
    let api = find(&truth.objects[0].name());
    assert_eq!((&cli["query"], &cli["threshold"]), (&json!(truth.objects[0].name()), &json!(0.5)), "{cli}");
    assert_eq!(ids_of(&cli["matches"]), ids_of(&api["matches"]), "{cli} {api}");
    assert!(
        cli["matches"].as_array().unwrap().iter().all(|m| m["name"].is_string() && m["score"].as_f64() >= Some(0.5))
    );

    // --- every malformed request: a 4xx JSON error naming the field, never a panic
    let cam_with = |k: &str, v: Value| {
        let mut c = cam0.clone();
        c[k] = v;
        c
    };
    // the built-in model reads 4,096 tokens; its word-level tokenizer makes a word one token
    let long_words = "why ".repeat(5000);
    let cases: Vec<(&str, &str, String, u16, &str)> = vec![
        ("bad JSON", "/api/pick", "{\"camera\": ".into(), 400, "invalid JSON"),
        ("trailing bytes", "/api/pick", format!("{} x", json!({"camera": cam0, "x": 1, "y": 1})), 400, "invalid JSON"),
        (
            "unknown field",
            "/api/pick",
            json!({"camera": cam0, "x": 1, "y": 1, "z": 2}).to_string(),
            400,
            "unknown field",
        ),
        ("missing field", "/api/pick", json!({"camera": cam0, "x": 1}).to_string(), 400, "missing field `y`"),
        (
            "wrong type",
            "/api/pick",
            json!({"camera": cam_with("fov", json!("wide")), "x": 1, "y": 1}).to_string(),
            400,
            "camera.fov",
        ),
        (
            "infinite position",
            "/api/render",
            format!(
                "{{\"camera\": {}}}",
                cam_with("position", json!([0, 0, 0])).to_string().replace("[0,0,0]", "[1e39,0,0]")
            ),
            400,
            "camera.position",
        ),
        ("zero fov", "/api/render", json!({"camera": cam_with("fov", json!(0))}).to_string(), 400, "camera.fov"),
        ("huge fov", "/api/render", json!({"camera": cam_with("fov", json!(179.9))}).to_string(), 400, "camera.fov"),
        ("zero width", "/api/render", json!({"camera": cam_with("width", json!(0))}).to_string(), 400, "camera.width"),
        (
            "huge height",
            "/api/render",
            json!({"camera": cam_with("height", json!(100_000))}).to_string(),
            400,
            "camera.height",
        ),
        (
            "negative size",
            "/api/render",
            json!({"camera": cam_with("width", json!(-5))}).to_string(),
            400,
            "camera.width",
        ),
        (
            "zero quaternion",
            "/api/render",
            json!({"camera": cam_with("quaternion", json!([0, 0, 0, 0]))}).to_string(),
            400,
            "camera.quaternion",
        ),
        ("click outside", "/api/pick", json!({"camera": cam0, "x": cam0["width"], "y": 3}).to_string(), 400, "x"),
        ("negative click", "/api/pick", json!({"camera": cam0, "x": 3, "y": -1}).to_string(), 400, "y"),
        ("object id 0", "/api/select", json!({"camera": cam0, "id": 0}).to_string(), 400, "id"),
        ("object id 70000", "/api/select", json!({"camera": cam0, "id": 70000}).to_string(), 400, "id"),
        (
            "unknown object",
            "/api/ask",
            json!({"scope": "object", "camera": cam0, "id": 200, "question": "What is this?"}).to_string(),
            400,
            "has no object 200",
        ),
        (
            "object without id",
            "/api/ask",
            json!({"scope": "object", "camera": cam0, "question": "What is this?"}).to_string(),
            400,
            "id",
        ),
        ("view without camera", "/api/ask", json!({"scope": "view", "question": "What?"}).to_string(), 400, "camera"),
        ("unknown scope", "/api/ask", json!({"scope": "room", "question": "What?"}).to_string(), 400, "scope"),
        (
            "scene of 0 views",
            "/api/ask",
            json!({"scope": "scene", "views": 0, "question": "What?"}).to_string(),
            400,
            "views",
        ),
        (
            "id on a view",
            "/api/ask",
            json!({"scope": "view", "camera": cam0, "id": 3, "question": "What?"}).to_string(),
            400,
            "id",
        ),
        (
            "empty question",
            "/api/ask",
            json!({"scope": "view", "camera": cam0, "question": "  "}).to_string(),
            400,
            "question",
        ),
        (
            "question over the context",
            "/api/ask",
            json!({"scope": "view", "camera": cam0, "question": long_words}).to_string(),
            400,
            "at most 4096",
        ),
        (
            "zero new tokens",
            "/api/ask",
            json!({"scope": "view", "camera": cam0, "question": "What?", "max_new_tokens": 0}).to_string(),
            400,
            "max_new_tokens",
        ),
        (
            "unknown conversation",
            "/api/ask",
            json!({"scope": "view", "camera": cam0, "question": "What?", "conversation": 999_999}).to_string(),
            404,
            "conversation",
        ),
        (
            "conversation of another target",
            "/api/ask",
            json!({"scope": "scene", "views": 3, "question": "What?", "conversation": id}).to_string(),
            409,
            "is about the view",
        ),
        (
            "conversation at another camera",
            "/api/ask",
            json!({"scope": "view", "camera": views[1]["camera"], "question": "What?", "conversation": id}).to_string(),
            409,
            "another camera",
        ),
        (
            "conversation id not a number",
            "/api/ask",
            json!({"scope": "view", "camera": cam0, "question": "What?", "conversation": "one"}).to_string(),
            400,
            "conversation",
        ),
        ("empty phrase", "/api/find", json!({"phrase": " ", "camera": cam0}).to_string(), 400, "phrase"),
        (
            "phrase over 200 characters",
            "/api/find",
            json!({"phrase": "red ".repeat(60), "camera": cam0}).to_string(),
            400,
            "phrase",
        ),
        (
            "threshold over 1",
            "/api/find",
            json!({"phrase": "cone", "camera": cam0, "threshold": 1.5}).to_string(),
            400,
            "threshold",
        ),
        (
            "negative threshold",
            "/api/find",
            json!({"phrase": "cone", "camera": cam0, "threshold": -0.1}).to_string(),
            400,
            "threshold",
        ),
        ("find without camera", "/api/find", json!({"phrase": "cone"}).to_string(), 400, "camera"),
        ("body over the limit", "/api/pick", format!("{{\"pad\": \"{}\"}}", "x".repeat(100_000)), 413, "bytes"),
    ];
    for (name, path, body, status, says) in &cases {
        let r = http::send(&a, "POST", path, &[], Some(body.as_bytes())).unwrap();
        assert_eq!(r.status, *status, "{name}: {}", r.text());
        let e = r.json();
        let text = format!("{} {}", e["field"].as_str().unwrap_or(""), e["error"].as_str().unwrap_or(""));
        assert!(text.contains(says), "{name}: {text}");
    }
    let r = http::send(&a, "GET", "/api/pick", &[], None).unwrap();
    assert_eq!(r.status, 405, "{}", r.text());
    assert!(r.json()["error"].is_string());
    // another site's page may not call the API
    let body = json!({"camera": cam0, "x": 1, "y": 1}).to_string();
    let r = http::send(&a, "POST", "/api/pick", &[("Origin", "http://evil.example")], Some(body.as_bytes())).unwrap();
    assert_eq!(r.status, 403, "{}", r.text());
    assert!(r.header("access-control-allow-origin").is_none());
    // after all of that the server still answers
    assert_eq!(http::post(&a, "/api/pick", &json!({"camera": cam0, "x": p % w0, "y": p / w0})).status, 200);
    let log = server.stop();
    assert!(!log.contains("panicked"), "{log}");
    assert!(log.contains("stopped"), "{log}");
}

#[test]
fn twenty_clients_at_once_are_answered_in_order_or_refused_and_a_gone_client_frees_the_model() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let t = scene();
    let server = Server::start(
        env!("CARGO_BIN_EXE_chatsplat"),
        &t.run,
        &["--queue", "8", "--allow-origin", "http://localhost:3000"],
    );
    let info = http::get(&server.addr, "/api/scene").json();
    let cam0 = info["views"][0]["camera"].clone();
    // an origin let in: its preflight and its request are answered, with the header browsers need
    let origin = [("Origin", "http://localhost:3000")];
    let pre = http::send(&server.addr, "OPTIONS", "/api/pick", &origin, None).unwrap();
    assert_eq!((pre.status, pre.header("access-control-allow-origin")), (204, Some("http://localhost:3000")));
    let body = json!({"camera": cam0, "x": 1, "y": 1}).to_string();
    let r = http::send(&server.addr, "POST", "/api/pick", &origin, Some(body.as_bytes())).unwrap();
    assert_eq!((r.status, r.header("access-control-allow-origin")), (200, Some("http://localhost:3000")));
    let other = [("Origin", "http://localhost:3001")];
    assert_eq!(http::send(&server.addr, "POST", "/api/pick", &other, Some(body.as_bytes())).unwrap().status, 403);
    let questions = ["What objects are there?", "How many objects are there?", "What colors are there?"];
    let t0 = Instant::now();
    let barrier = std::sync::Arc::new(std::sync::Barrier::new(20));
    let clients: Vec<_> = (0..20)
        .map(|i| {
            let (addr, b, cam) = (server.addr.clone(), barrier.clone(), cam0.clone());
            let q = questions[i % questions.len()];
            std::thread::spawn(move || {
                b.wait();
                let sent = Instant::now();
                let r = ask_raw(&addr, json!({"scope": "view", "camera": cam, "question": q}));
                (r, sent.elapsed(), Instant::now())
            })
        })
        .collect();
    let results: Vec<(Reply, Duration, Instant)> = clients.into_iter().map(|c| c.join().unwrap()).collect();
    let wall = t0.elapsed();
    let (mut answered, mut refused) = (vec![], 0);
    for (r, latency, at) in &results {
        match r.status {
            200 => {
                let ev = r.events();
                assert_eq!(ev.last().map(|e| e.0.as_str()), Some("done"), "{}", r.text());
                let ticket = ev.iter().find(|e| e.0 == "start").unwrap().1["ticket"].as_u64().unwrap();
                answered.push((*at, ticket, *latency));
            }
            503 => {
                assert!(r.json()["error"].as_str().unwrap().contains("waiting"), "{}", r.text());
                refused += 1;
            }
            s => panic!("status {s}: {}", r.text()),
        }
    }
    assert_eq!(answered.len() + refused, 20, "none lost");
    // the 8 the queue holds at least, and the one in progress when the model took it off the queue
    // before the last arrived (under load the model may not have started yet: then 8)
    assert!(answered.len() >= 8, "the 8 queued at least: {} answered", answered.len());
    // in order: answers finish in the order their questions were queued
    answered.sort_by_key(|a| a.0);
    let tickets: Vec<u64> = answered.iter().map(|a| a.1).collect();
    assert!(tickets.windows(2).all(|w| w[0] < w[1]), "answered out of order: {tickets:?}");
    let mut lat: Vec<f64> = answered.iter().map(|a| a.2.as_secs_f64() * 1e3).collect();
    lat.sort_by(f64::total_cmp);
    let pct = |q: f64| lat[((lat.len() - 1) as f64 * q).round() as usize];
    eprintln!(
        "20 clients at once: {} answered, {refused} refused (503) in {:.1} s; latency p50 {:.0} ms, p99 {:.0} ms",
        answered.len(),
        wall.as_secs_f64(),
        pct(0.5),
        pct(0.99)
    );

    // a client that goes away mid-answer frees the model at its next token: a long answer
    // (1024 tokens, the end token ignored) is dropped after two tokens, and the next question
    // starts long before those 1024 tokens could have been generated
    let long = json!({"scope": "view", "camera": cam0, "question": "What objects are there?",
        "max_new_tokens": 1024, "ignore_stop": true});
    let mut s = http::open(&server.addr, "POST", "/api/ask", &[], Some(long.to_string().as_bytes())).unwrap();
    let (mut seen, mut buf) = (String::new(), [0u8; 4096]);
    let started = Instant::now();
    let mut first_token = None;
    while seen.matches("event: token").count() < 8 {
        let n = s.read(&mut buf).unwrap();
        assert!(n > 0, "the stream ended early: {seen}");
        seen.push_str(&String::from_utf8_lossy(&buf[..n]));
        if first_token.is_none() && seen.contains("event: token") {
            first_token = Some(Instant::now());
        }
    }
    // seconds per token of this model here, from the 7 tokens after the first
    let per_token = (Instant::now() - first_token.unwrap()).as_secs_f64() / 7.0;
    drop(s);
    let gone = Instant::now();
    let next = ask_raw(&server.addr, json!({"scope": "view", "camera": cam0, "question": "What colors are there?"}));
    let ev = next.events();
    let start = ev.iter().find(|e| e.0 == "start").unwrap_or_else(|| panic!("{}", next.text()));
    let waited = start.1["queue_ms"].as_f64().unwrap() / 1e3;
    let would_take = 1016.0 * per_token;
    eprintln!(
        "a client gone after 8 of 1024 tokens ({:.1} ms/token, {:.1} s in): the next question waited {waited:.2} s \
         (the rest of the answer would have taken {would_take:.1} s); freed {:.2} s after the disconnect",
        per_token * 1e3,
        started.elapsed().as_secs_f64(),
        gone.elapsed().as_secs_f64() - waited.min(gone.elapsed().as_secs_f64()),
    );
    assert!(waited < 0.25 * would_take, "waited {waited:.2} s; the whole answer takes {would_take:.1} s");
    let rss = std::fs::read_to_string(format!("/proc/{}/status", server.child.id()))
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmHWM:")).map(|l| l.to_string()));
    eprintln!("server peak memory: {}", rss.as_deref().unwrap_or("unknown"));
    if let Some(kb) = rss.and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<u64>().ok())) {
        assert!(kb < 3 << 20, "the server's memory peaked at {kb} kB");
    }
    server.stop();
}

fn ask_raw(addr: &str, body: Value) -> Reply {
    http::post(addr, "/api/ask", &body)
}

/// The page's canvas rectangle `[left, top, width, height]` in page pixels.
fn canvas_rect(b: &mut Browser) -> [f64; 4] {
    let r = b.eval("window.chatsplat.canvasRect()").unwrap();
    std::array::from_fn(|i| r[i].as_f64().unwrap())
}

fn page_camera(b: &mut Browser) -> (Value, Camera) {
    let v = b.eval("window.chatsplat.camera()").unwrap();
    let c: ViewCamera = serde_json::from_value(v.clone()).unwrap();
    (v, c.to_camera("camera").unwrap())
}

/// Asks `question` through the chat box (typed, then Enter) and waits for the streamed answer.
fn ask_in_page(b: &mut Browser, question: &str) -> Value {
    // the last answer's stream has closed (its turn reads "done" as soon as its last event
    // came; a question typed before the stream ends would be refused)
    b.wait_for("!window.chatsplat.busy", Duration::from_secs(60)).unwrap();
    let before = b.eval("window.chatsplat.turns().length").unwrap().as_u64().unwrap();
    b.eval("document.getElementById('question').focus()").unwrap();
    b.type_text(question).unwrap();
    b.key("Enter").unwrap();
    let expr = format!(
        "(() => {{ const t = window.chatsplat.turns(), last = t[t.length - 1]; \
         return t.length > {before} && last.state !== 'asking' && last; }})()"
    );
    b.wait_for(&expr, Duration::from_secs(120)).unwrap()
}

/// Where world point `p` lands in the canvas of `cam` (pixels), if in front of it.
fn project(cam: &Camera, p: Vec3) -> Option<(f32, f32)> {
    let q = cam.world_to_cam.transform_point3(p);
    (q.z > 0.0).then(|| (cam.fx * q.x / q.z + cam.cx, cam.fy * q.y / q.z + cam.cy))
}

/// Mean RGB of `rgb` (`w` wide) over pixel indices `ps`.
fn mean_rgb(rgb: &[u8], ps: &[usize]) -> [f64; 3] {
    let mut m = [0.0; 3];
    for &p in ps {
        for c in 0..3 {
            m[c] += rgb[3 * p + c] as f64 / ps.len() as f64;
        }
    }
    m
}

/// The canvas part of a screenshot, as RGB bytes of the canvas's size.
fn crop(shot: &(usize, usize, Vec<u8>), r: [f64; 4]) -> Vec<u8> {
    let (sw, _, rgb) = shot;
    let (x0, y0, w, h) = (r[0] as usize, r[1] as usize, r[2] as usize, r[3] as usize);
    (0..h).flat_map(|y| (0..w).flat_map(move |x| (0..3).map(move |c| rgb[3 * ((y0 + y) * sw + x0 + x) + c]))).collect()
}

#[test]
fn the_page_draws_the_scene_picks_in_red_and_answers_at_every_level() {
    let Some(exe) = browser::find() else {
        assert!(
            std::env::var_os("CHATSPLAT_REQUIRE_BROWSER").is_none(),
            "CHATSPLAT_REQUIRE_BROWSER is set but no chromium-headless-shell was found"
        );
        eprintln!("SKIPPED: no /usr/lib/chromium/chromium-headless-shell (apt-get install chromium-headless-shell)");
        return;
    };
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let t = scene();
    let truth = scene_json(&t.data);
    // whether the built-in model was trained on second turns (a two-turn stage)
    let converses = model::vlm::LlavaOnevision::load(&fixture::builtin_model(), &burn::tensor::Device::ndarray())
        .unwrap()
        .converses();
    let server = Server::start(env!("CARGO_BIN_EXE_chatsplat"), &t.run, &[]);
    let mut b = Browser::launch(&exe, 1100, 700).unwrap();
    let t0 = Instant::now();
    b.goto(
        // ?converse=1 holds conversations whatever the model was trained on
        &server.url("/?converse=1"),
        "window.chatsplat && window.chatsplat.ready && window.chatsplat.frames > 2",
        Duration::from_secs(180),
    )
    .unwrap();
    let load_s = t0.elapsed().as_secs_f64();
    assert_eq!(b.eval("window.chatsplat.mode").unwrap(), "webgl", "WebGL2 on SwiftShader: {:?}", b.page_errors);
    // the page draws the smaller file, Niantic's .spz (Spark reads what model::spz writes)
    assert_eq!(b.eval("window.chatsplat.splatsUrl").unwrap(), "/api/splats.spz");
    b.wait_for("window.chatsplat.idle", Duration::from_secs(60)).unwrap();

    // --- the scene is drawn: not blank, and every object the server sees in this view shows its
    // own colour where the server's identity puts it
    let rect = canvas_rect(&mut b);
    let (cam_v, cam) = page_camera(&mut b);
    let (_, shot) = b.screenshot().unwrap();
    let canvas = crop(&shot, rect);
    let frame = http::decode_png(&http::post(&server.addr, "/api/render", &json!({"camera": cam_v})).body);
    assert_eq!((frame.0, frame.1), (cam.width as usize, cam.height as usize));
    let spread = |rgb: &[u8]| {
        let m = rgb.iter().map(|&v| v as f64).sum::<f64>() / rgb.len() as f64;
        (rgb.iter().map(|&v| (v as f64 - m).powi(2)).sum::<f64>() / rgb.len() as f64).sqrt()
    };
    assert!(spread(&canvas) > 10.0, "the canvas is blank (spread {:.1})", spread(&canvas));
    let mut shown = vec![];
    for o in &truth.objects {
        let r = http::post(&server.addr, "/api/select", &json!({"camera": cam_v, "id": o.id})).json();
        if r["object"].is_null() || r["object"]["pixels"].as_u64().unwrap() < 30 {
            continue;
        }
        let ps = rle_pixels(&r["object"]["mask"]);
        let (browser_rgb, server_rgb) = (mean_rgb(&canvas, &ps), mean_rgb(&frame.2, &ps));
        let d = (0..3).map(|c| (browser_rgb[c] - server_rgb[c]).abs()).fold(0.0, f64::max);
        eprintln!("{}: {} px, browser {browser_rgb:.0?} vs server {server_rgb:.0?}", o.name(), ps.len());
        assert!(d < 40.0, "{} looks different in the browser: {browser_rgb:.0?} vs {server_rgb:.0?}", o.name());
        shown.push((o.clone(), ps));
    }
    assert!(shown.len() >= 2, "the first view shows objects ({} shown)", shown.len());

    // --- a click on the projected centre of an object picks it, tints it red and names it
    let (o, ps) = shown
        .iter()
        .filter_map(|(o, ps)| {
            let (x, y) = project(&cam, o.center)?;
            let p = y as usize * cam.width as usize + x as usize;
            ps.contains(&p).then_some((o, ps))
        })
        .max_by_key(|(_, ps)| ps.len())
        .expect("an object whose centre lies on itself");
    let (x, y) = project(&cam, o.center).unwrap();
    let t_click = Instant::now();
    b.click(rect[0] + x as f64 + 0.5, rect[1] + y as f64 + 0.5).unwrap();
    let sel = b.wait_for("window.chatsplat.selection", Duration::from_secs(30)).unwrap();
    let click_ms = t_click.elapsed().as_secs_f64() * 1e3;
    assert_eq!(sel["id"].as_u64(), Some(o.id as u64), "picked {sel}");
    assert_eq!(sel["name"].as_str(), Some(o.name().as_str()));
    assert_eq!(b.eval("document.getElementById('label').textContent").unwrap(), o.name());
    // the object is tinted red and the rest of the view dimmed (a red object stands out too)
    b.wait_for("window.chatsplat.idle", Duration::from_secs(60)).unwrap();
    let (_, shot) = b.screenshot().unwrap();
    let tinted = crop(&shot, rect);
    let red = |rgb: &[u8], p: usize| rgb[3 * p] as f64 - 0.5 * (rgb[3 * p + 1] as f64 + rgb[3 * p + 2] as f64);
    let luma = |rgb: &[u8], p: usize| (rgb[3 * p] as f64 + rgb[3 * p + 1] as f64 + rgb[3 * p + 2] as f64) / 3.0;
    let mean = |ps: &[usize], f: &dyn Fn(usize) -> f64| ps.iter().map(|&p| f(p)).sum::<f64>() / ps.len() as f64;
    let gain = mean(ps, &|p| red(&tinted, p) - red(&canvas, p));
    assert!(gain > 5.0, "the picked object is not tinted red (red gain {gain:.1})");
    let mut inside = vec![false; canvas.len() / 3];
    for &p in ps {
        inside[p] = true;
    }
    let outside: Vec<usize> = (0..inside.len()).filter(|&p| !inside[p]).step_by(7).collect();
    let (before, after) = (mean(&outside, &|p| luma(&canvas, p)), mean(&outside, &|p| luma(&tinted, p)));
    assert!(after < 0.7 * before, "the rest of the view is not dimmed ({before:.0} -> {after:.0})");
    // the menu still names the camera of the capture the view is at
    assert_eq!(b.eval("document.getElementById('views').value").unwrap(), "0");

    // --- the object question streams the right name; the page offers the model's question forms
    assert_eq!(b.eval("window.chatsplat.scope").unwrap(), "object");
    let known = b.eval("window.chatsplat.known()").unwrap();
    assert!(known.as_array().unwrap().iter().any(|q| q == "What is this?"), "{known}");
    let turn = ask_in_page(&mut b, "What is this?");
    eprintln!("object: {turn}");
    assert_eq!(turn["state"], "done", "{turn}");
    assert_eq!(turn["answer"].as_str(), Some(o.name().as_str()), "{turn}");
    let object_timing = turn["timing"].as_str().unwrap_or("").to_string();
    // a follow-up about the same object: the same conversation, its second turn, the first turn
    // kept in the model's cache; "New conversation" starts over
    let follow = ask_in_page(&mut b, "What color is it?");
    assert_eq!(
        (&follow["state"], &follow["conversation"], follow["turn"].as_u64()),
        (&json!("done"), &turn["conversation"], Some(2))
    );
    assert!(follow["cached"].as_u64().unwrap() > 0 && follow["timing"].as_str().unwrap().contains("follow-up 2"));
    // "it" is the object the first turn named, where the built-in model learnt second turns
    if converses {
        assert_eq!(follow["answer"].as_str(), Some(o.color.word()), "{follow}");
    }
    b.eval("document.getElementById('new-conversation').click()").unwrap();
    let again = ask_in_page(&mut b, "What is this?");
    assert_eq!((again["turn"].as_u64(), again["cached"].as_u64()), (Some(1), Some(0)), "{again}");
    assert_ne!(again["conversation"], turn["conversation"]);
    assert_eq!(again["answer"], turn["answer"], "a new conversation answers as the first did");
    let notes = b.eval("window.chatsplat.notes()").unwrap();
    assert!(notes.as_array().unwrap().iter().any(|n| n == "new conversation"), "{notes}");
    // README's picture: the picked object and its answer (CHATSPLAT_SCREENSHOT=path)
    if let Some(p) = std::env::var_os("CHATSPLAT_SCREENSHOT") {
        std::fs::write(p, b.screenshot().unwrap().0).unwrap();
    }

    // --- a view question from a camera no training view had: orbit by dragging, then ask
    b.eval("document.querySelector('[data-scope=view]').click()").unwrap();
    let mid = (rect[0] + rect[2] * 0.5, rect[1] + rect[3] * 0.5);
    b.drag(mid, (mid.0 + 60.0, mid.1 + 25.0), 6).unwrap();
    b.wait_for("window.chatsplat.idle", Duration::from_secs(60)).unwrap();
    let (_, novel) = page_camera(&mut b);
    // moved off the capture's cameras, the menu names none of them
    assert_eq!(b.eval("document.getElementById('views').value").unwrap(), "");
    let eye = |c: &Camera| c.world_to_cam.inverse().w_axis.truncate();
    let session_cams = GeometryRun::new(&t.run).read_cameras().unwrap().all();
    let nearest = session_cams.iter().map(|c| eye(c).distance(eye(&novel))).fold(f32::MAX, f32::min);
    assert!(nearest > 0.1, "the page camera is {nearest} from a training camera: not a new view");
    let gt = model::data::synth::raycast::render_view(&novel, &truth);
    let facts = ViewFacts::of(&truth, &gt.ids, &gt.depth, novel.width as usize, novel.height as usize);
    let qs = view_questions(&truth, &facts, &mut model::rng::Rng::new(7));
    let pick_q = |k: Kind, answer: Option<&str>| {
        qs.iter()
            .find(|q| q.kind == k && answer.is_none_or(|a| q.answer == a))
            .unwrap_or_else(|| panic!("no {k:?} question"))
    };
    let mut view_timing = String::new();
    for q in [pick_q(Kind::Exists, Some("yes")), pick_q(Kind::Exists, Some("no")), pick_q(Kind::Colors, None)] {
        // each on its own: the built-in model answers independent follow-ups worse
        b.eval("document.getElementById('new-conversation').click()").unwrap();
        let turn = ask_in_page(&mut b, &q.question);
        assert_eq!(turn["turn"].as_u64(), Some(1), "{turn}");
        eprintln!("view (novel camera): {} -> {} (truth {})", q.question, turn["answer"], q.answer);
        assert_eq!(turn["answer"].as_str(), Some(q.answer.as_str()), "{turn}");
        assert!(turn["unknown_form"].is_null(), "a question of the model's forms: {turn}");
        // a list answer shows its items apart ("red, blue")
        if q.kind == Kind::Colors && q.answer.contains(' ') {
            assert_eq!(turn["shown"].as_str(), Some(q.answer.replace(' ', ", ").as_str()), "{turn}");
        }
        view_timing = turn["timing"].as_str().unwrap_or("").to_string();
    }
    // a question far from every form the model knows is marked as a guess, beside its answer
    b.eval("document.getElementById('new-conversation').click()").unwrap();
    let guess = ask_in_page(&mut b, "What is on the table?");
    assert!(guess["unknown_form"].as_str().is_some_and(|n| n.contains("not a question this model")), "{guess}");
    assert!(guess["timing"].as_str().unwrap().contains("not a question this model"), "{guess}");

    // --- a search at this moved camera: the objects of the picked one's shape tinted red
    // (those the camera shows), listed with their scores; a click on one selects it for object
    // chat
    b.eval("document.activeElement.blur()").unwrap();
    b.key("Escape").unwrap();
    b.wait_for("!window.chatsplat.selection && window.chatsplat.idle", Duration::from_secs(60)).unwrap();
    let plain = crop(&b.screenshot().unwrap().1, rect);
    let word = o.shape.word();
    let submit =
        format!("document.getElementById('phrase').value = '{word}'; document.getElementById('find').requestSubmit()");
    b.eval(&submit).unwrap();
    let found =
        format!("window.chatsplat.found && window.chatsplat.found.query === '{word}' && window.chatsplat.found");
    let found = b.wait_for(&found, Duration::from_secs(60)).unwrap();
    let matched: Vec<u64> = found["matches"].as_array().unwrap().iter().map(|m| m["id"].as_u64().unwrap()).collect();
    let mut sorted = matched.clone();
    sorted.sort();
    let want: Vec<u64> = truth.objects.iter().filter(|x| x.shape == o.shape).map(|x| x.id as u64).collect();
    assert_eq!(sorted, want, "{found}");
    let (_, shot) = b.screenshot().unwrap();
    let searched = crop(&shot, rect);
    for m in found["matches"].as_array().unwrap() {
        let id = m["id"].as_u64().unwrap() as model::ObjectId;
        let ps: Vec<usize> = (0..gt.ids.len()).filter(|&p| gt.ids[p] == id).collect();
        if ps.len() > 30 {
            assert_eq!(m["shown"], true, "match {id} shows {} pixels here: {m}", ps.len());
            let gain = mean(&ps, &|p| red(&searched, p) - red(&plain, p));
            assert!(gain > 5.0, "match {id} is not tinted red at the moved camera (red gain {gain:.1})");
        }
    }
    b.eval("document.querySelector('#found button').click()").unwrap();
    let sel = b.wait_for("window.chatsplat.selection", Duration::from_secs(30)).unwrap();
    assert_eq!(sel["id"].as_u64(), Some(matched[0]), "{sel}");
    assert_eq!(b.eval("window.chatsplat.scope").unwrap(), "object");

    // --- a scene question answers
    b.eval("document.querySelector('[data-scope=scene]').click()").unwrap();
    let turn = ask_in_page(&mut b, "How many objects are in the scene?");
    eprintln!("scene: {turn} (truth {})", truth.objects.len());
    assert_eq!(turn["state"], "done", "{turn}");
    assert_eq!(turn["answer"].as_str(), Some(truth.objects.len().to_string().as_str()), "{turn}");
    assert!(b.page_errors.is_empty(), "{:?}", b.page_errors);

    // --- the selected object offers its Gaussians to download, and hides: the scene is drawn
    // again without it (its pixels change, as the server's frame without it says), and comes back
    let id = matched[0];
    let href = b.eval("document.getElementById('download').getAttribute('href')").unwrap();
    assert_eq!(href.as_str(), Some(format!("/api/objects/{id}.ply").as_str()));
    b.eval("document.getElementById('hide').click()").unwrap();
    let url = format!("/api/splats.spz?without={id}");
    b.wait_for(&format!("window.chatsplat.splatsUrl === '{url}' && window.chatsplat.idle"), Duration::from_secs(90))
        .unwrap();
    assert_eq!(b.eval("window.chatsplat.hidden()").unwrap(), json!([id]));
    assert!(b.eval("window.chatsplat.selection").unwrap().is_null(), "hiding clears the selection");
    let of_id: Vec<usize> = (0..gt.ids.len()).filter(|&p| gt.ids[p] as u64 == id).collect();
    let moved = |rgb: &[u8]| {
        mean(&of_id, &|p| (0..3).map(|c| (rgb[3 * p + c] as f64 - plain[3 * p + c] as f64).abs()).sum::<f64>() / 3.0)
    };
    // Spark sorts the new scene in a worker: look until it is drawn (at most 30 s)
    let settle = |b: &mut Browser, done: &dyn Fn(f64) -> bool| {
        let t = Instant::now();
        loop {
            let d = moved(&crop(&b.screenshot().unwrap().1, rect));
            if done(d) || t.elapsed() > Duration::from_secs(30) {
                return d;
            }
            std::thread::sleep(Duration::from_millis(500));
        }
    };
    let gone = settle(&mut b, &|d| d > 10.0);
    assert!(of_id.len() > 30 && gone > 10.0, "object {id} hidden: its {} px changed by {gone:.1}", of_id.len());
    b.eval("document.getElementById('show-hidden').click()").unwrap();
    b.wait_for("window.chatsplat.splatsUrl === '/api/splats.spz' && window.chatsplat.idle", Duration::from_secs(90))
        .unwrap();
    let back = settle(&mut b, &|d| d < gone / 3.0);
    assert!(
        back < gone / 3.0,
        "object {id} shown again: its pixels differ by {back:.1} from before (hidden {gone:.1})"
    );
    assert!(b.page_errors.is_empty(), "{:?}", b.page_errors);

    // --- a new window size keeps the pick: its tint and label stay (drawn again at the new
    // size). Last on this page: in headless Chromium a page resized by emulation has been seen to
    // stop drawing a later frame (CI, 2026-12-07), which nothing here should hang on.
    b.eval("window.chatsplat.jump(0)").unwrap();
    b.wait_for("window.chatsplat.idle", Duration::from_secs(60)).unwrap();
    b.click(rect[0] + x as f64 + 0.5, rect[1] + y as f64 + 0.5).unwrap();
    let again = format!("window.chatsplat.selection && window.chatsplat.selection.id === {}", o.id);
    b.wait_for(&again, Duration::from_secs(30)).unwrap();
    let metrics = |w: u32, h: u32| json!({"width": w, "height": h, "deviceScaleFactor": 1, "mobile": false});
    b.call("Emulation.setDeviceMetricsOverride", metrics(900, 600)).unwrap();
    b.wait_for("window.chatsplat.idle", Duration::from_secs(60)).unwrap();
    let label = "!document.getElementById('label').hidden && document.getElementById('label').textContent";
    assert_eq!(b.eval(label).unwrap(), o.name(), "the label after a resize");
    assert_eq!(b.eval("window.chatsplat.selection && window.chatsplat.selection.id").unwrap(), json!(o.id));
    // back to the window's own size (the override cleared, as a user's window would be)
    b.call("Emulation.clearDeviceMetricsOverride", json!({})).unwrap();
    b.wait_for("window.chatsplat.idle", Duration::from_secs(60)).unwrap();
    assert_eq!(b.eval(label).unwrap(), o.name(), "the label after the size came back");
    // the page lays out again once the frame has its size (idle may already be true): wait for
    // the canvas to take its first place again, then check it
    let settled = format!(
        "(() => {{ const r = window.chatsplat.canvasRect(), w = {rect:?}; \
         return r.every((v, i) => Math.abs(v - w[i]) < 1); }})()"
    );
    let _ = b.wait_for(&settled, Duration::from_secs(30));
    let back = canvas_rect(&mut b);
    assert!(back.iter().zip(rect).all(|(a, b)| (a - b).abs() < 1.0), "the canvas moved: {back:?} {rect:?}");

    // --- the server-rendered fallback picks the same object at the same pixel, in a fresh browser:
    // navigating away from the WebGL page leaves SwiftShader tearing it down for 30 s and more
    // before the next page's first request (measured: app.css asked for 27 s after the HTML came)
    drop(b);
    let mut b = Browser::launch(&exe, 1100, 700).unwrap();
    let t_server = Instant::now();
    if let Err(e) = b.goto(
        &server.url("/?render=server"),
        "window.chatsplat && window.chatsplat.ready && window.chatsplat.serverFrameKind() === 'full'",
        Duration::from_secs(60),
    ) {
        let page = b
            .eval(concat!(
                "location.href + ' ' + document.readyState + ' ready=' + (window.chatsplat && window.chatsplat.ready)",
                " + ' frame=' + (window.chatsplat && window.chatsplat.serverFrameKind())",
                " + ' status=' + document.getElementById('status').textContent",
                " + ' now=' + performance.now().toFixed(0) + ' requests=' + JSON.stringify(performance",
                ".getEntriesByType('resource').filter((r) => r.name.includes('/api/'))",
                ".map((r) => [r.name.replace(location.origin, ''), r.startTime.toFixed(0), r.duration.toFixed(0)]))"
            ))
            .unwrap_or_default();
        panic!("{e}; the page: {page}; the server's log:\n{}", server.log());
    }
    let server_s = t_server.elapsed().as_secs_f64();
    // without ?converse=1 the page holds conversations where the built-in model does (a two-turn
    // stage trained it), and else says that it takes each question on its own
    let notes = b.eval("window.chatsplat.notes()").unwrap();
    let said = notes.as_array().unwrap().iter().any(|n| n.as_str().unwrap().contains("single questions"));
    assert_eq!(said, !converses, "{notes}");
    assert_eq!(b.eval("document.getElementById('new-conversation').hidden").unwrap(), !converses);
    assert_eq!(b.eval("window.chatsplat.mode").unwrap(), "server");
    let rect = canvas_rect(&mut b);
    let (_, shot) = b.screenshot().unwrap();
    assert!(spread(&crop(&shot, rect)) > 10.0, "the server frame is blank");
    b.click(rect[0] + x as f64 + 0.5, rect[1] + y as f64 + 0.5).unwrap();
    let sel = b.wait_for("window.chatsplat.selection", Duration::from_secs(30)).unwrap();
    assert_eq!(sel["id"].as_u64(), Some(o.id as u64), "server mode picked {sel}");
    // hidden, the server draws the view without it, and a click there picks nothing
    let frames = b.eval("window.chatsplat.frames").unwrap().as_u64().unwrap();
    b.eval("document.getElementById('hide').click()").unwrap();
    let done = format!("window.chatsplat.frames > {frames} && window.chatsplat.idle && !window.chatsplat.selection");
    b.wait_for(&done, Duration::from_secs(60)).unwrap();
    let without = crop(&b.screenshot().unwrap().1, rect);
    let before = crop(&shot, rect);
    let gone =
        mean(ps, &|p| (0..3).map(|c| (without[3 * p + c] as f64 - before[3 * p + c] as f64).abs()).sum::<f64>() / 3.0);
    assert!(gone > 10.0, "server frames: the hidden {} changed by {gone:.1}", o.name());
    b.click(rect[0] + x as f64 + 0.5, rect[1] + y as f64 + 0.5).unwrap();
    b.wait_for("document.getElementById('status').textContent.includes('is hidden')", Duration::from_secs(30)).unwrap();
    assert!(b.eval("window.chatsplat.selection").unwrap().is_null());
    assert!(b.page_errors.is_empty(), "{:?}", b.page_errors);
    eprintln!(
        "page load {load_s:.1} s (server frames {server_s:.1} s); click -> highlight {click_ms:.0} ms; object answer \
         [{object_timing}]; view answer [{view_timing}]"
    );
    drop(b);
    server.stop();
}
