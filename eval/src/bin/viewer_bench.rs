//! `viewer-bench`: the browser viewer's figures on a trained run (default: the demo's), as a
//! user feels them: click -> highlight (the pick request), object question -> first token, view
//! question at a new camera -> first token, server-rendered frames per second, page load and
//! browser frames per second (headless Chromium on SwiftShader, when installed).
//!
//! ```text
//! cargo build --release && cargo run --release -p eval --bin viewer-bench -- [--run out/demo/run]
//! ```

use eval::browser::{self, Browser};
use eval::http;
use serde_json::{Value, json};
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn arg(name: &str) -> Option<String> {
    let args: Vec<String> = std::env::args().collect();
    args.iter().position(|a| a == name).and_then(|i| args.get(i + 1).cloned())
}

fn pct(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// A camera of `w x h` pixels at the view camera `v`'s pose and vertical field of view.
fn sized(v: &Value, w: u32, h: u32) -> Value {
    let mut c = v.clone();
    let o = c.as_object_mut().expect("a camera");
    for k in ["fx", "fy", "cx", "cy"] {
        o.remove(k);
    }
    o.insert("width".into(), json!(w));
    o.insert("height".into(), json!(h));
    c
}

/// The server, stopped however the bench ends.
struct Server(std::process::Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn main() {
    let run = PathBuf::from(arg("--run").unwrap_or_else(|| "out/demo/run".into()));
    let exe = arg("--chatsplat")
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::current_exe().expect("own path").with_file_name("chatsplat"));
    let (w, h) = (640u32, 480u32);
    let t0 = Instant::now();
    let mut child = Server(
        Command::new(&exe)
            .args(["serve", "--addr", "127.0.0.1:0", "--run"])
            .arg(&run)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e} (cargo build --release first)", exe.display())),
    );
    let mut line = String::new();
    BufReader::new(child.0.stdout.take().expect("piped")).read_line(&mut line).expect("the server's URL");
    let addr = line.trim().trim_start_matches("chatsplat viewer: http://").trim_end_matches('/').to_string();
    assert!(!addr.is_empty(), "the server did not start");
    let start_s = t0.elapsed().as_secs_f64();
    let info = http::get(&addr, "/api/scene").json();
    let view0 = info["views"][0]["camera"].clone();
    let cam = sized(&view0, w, h);

    // the objects of view 0 and a pixel well inside each (the middle of its mask's longest run)
    let targets = |camera: &Value| {
        let width = camera["width"].as_u64().unwrap();
        let mut t = vec![];
        for o in info["objects"].as_array().expect("objects") {
            let r = http::post(&addr, "/api/select", &json!({"camera": camera, "id": o["id"]})).json();
            if let Some(runs) = r["object"]["mask"]["runs"].as_array().filter(|r| !r.is_empty()) {
                let runs: Vec<u64> = runs.iter().map(|v| v.as_u64().unwrap()).collect();
                let longest = runs.chunks(2).max_by_key(|r| r[1]).unwrap();
                let p = longest[0] + longest[1] / 2;
                t.push((o["id"].as_u64().unwrap(), p % width, p / width));
            }
        }
        assert!(!t.is_empty(), "view 0 shows no object");
        t
    };
    // clicks as the page makes them (at most 320 px on the longest side: app.js, PICK_SIDE), and
    // at the full size
    let picks = |camera: &Value| {
        let at = targets(camera);
        let mut ms = vec![];
        for i in 0..20 {
            let (id, x, y) = at[i % at.len()];
            let t = Instant::now();
            let r = http::post(&addr, "/api/pick", &json!({"camera": camera, "x": x, "y": y})).json();
            ms.push(t.elapsed().as_secs_f64() * 1e3);
            assert_eq!(r["object"]["id"].as_u64(), Some(id), "{r}");
        }
        ms
    };
    let mut pick_ms = picks(&sized(&view0, 320, 240));
    let mut full_pick_ms = picks(&cam);
    let first_token = |body: Value| -> (f64, String) {
        let r = http::post(&addr, "/api/ask", &body);
        let ev = r.events();
        let done = &ev.iter().find(|e| e.0 == "done").unwrap_or_else(|| panic!("{}", r.text())).1;
        (done["first_token_ms"].as_f64().unwrap(), done["text"].as_str().unwrap_or("").to_string())
    };
    let mut object_ms = vec![];
    for (id, _, _) in targets(&cam).into_iter().take(5) {
        let (ms, _) = first_token(json!({"scope": "object", "camera": cam, "id": id, "question": "What is this?"}));
        object_ms.push(ms);
    }
    // new cameras: view 0's pose turned about the scene's up axis through its centre
    let mut view_ms = vec![];
    let centre: [f64; 3] = std::array::from_fn(|i| info["center"][i].as_f64().unwrap());
    for k in 1..=5 {
        let a = 0.1 * k as f64;
        let mut c = cam.clone();
        let p: Vec<f64> = (0..3).map(|i| c["position"][i].as_f64().unwrap() - centre[i]).collect();
        // rotate about +y (the synthetic scenes' up) and turn the camera with it
        let (s, co) = (a.sin(), a.cos());
        c["position"] = json!([centre[0] + co * p[0] + s * p[2], centre[1] + p[1], centre[2] - s * p[0] + co * p[2]]);
        let q: Vec<f64> = (0..4).map(|i| c["quaternion"][i].as_f64().unwrap()).collect();
        let (hs, hc) = ((a / 2.0).sin(), (a / 2.0).cos());
        // (0, hs, 0, hc) * q
        c["quaternion"] =
            json!([hc * q[0] + hs * q[2], hc * q[1] + hs * q[3], hc * q[2] - hs * q[0], hc * q[3] - hs * q[1]]);
        let (ms, _) = first_token(json!({"scope": "view", "camera": c, "question": "What objects are there?"}));
        view_ms.push(ms);
    }
    let frames = |camera: &Value, seconds: f64| {
        let t = Instant::now();
        let mut n = 0;
        while t.elapsed().as_secs_f64() < seconds {
            let r = http::post(&addr, "/api/render", &json!({"camera": camera}));
            assert_eq!(r.status, 200);
            n += 1;
        }
        n as f64 / t.elapsed().as_secs_f64()
    };
    let full_fps = frames(&cam, 8.0);
    let preview_fps = frames(&sized(&view0, 160, 120), 4.0);

    let mut page = None;
    if let Some(exe) = browser::find() {
        let mut b = Browser::launch(&exe, 1100, 700).expect("the browser");
        let t = Instant::now();
        b.goto(
            &format!("http://{addr}/"),
            "window.chatsplat && window.chatsplat.ready && window.chatsplat.frames > 0",
            Duration::from_secs(300),
        )
        .expect("the page");
        let load_s = t.elapsed().as_secs_f64();
        b.wait_for("window.chatsplat.idle", Duration::from_secs(120)).expect("idle");
        let r = b.eval("window.chatsplat.canvasRect()").expect("rect");
        let canvas = format!("{}x{}", r[2], r[3]);
        // orbit a little every animation frame for 8 s, in the page (no input round trips)
        let orbit = "new Promise((done) => { const f0 = window.chatsplat.frames, t0 = performance.now(); \
            const step = () => { window.chatsplat.orbit(3, 0); \
              if (performance.now() - t0 < 8000) requestAnimationFrame(step); \
              else done((window.chatsplat.frames - f0) * 1000 / (performance.now() - t0)); }; \
            requestAnimationFrame(step); })";
        let fps = b.eval(orbit).expect("orbit").as_f64().unwrap();
        page = Some((load_s, fps, canvas));
    }
    drop(child);

    println!("\n## Viewer ({}, {} Gaussians, {w}x{h})\n", run.display(), info["gaussians"]);
    println!("| what | figure |\n|---|---|");
    println!("| server start (scene + model loaded) | {start_s:.1} s |");
    println!(
        "| click -> highlight (the page's pick at 320x240, 20 clicks) | p50 {:.0} ms, p90 {:.0} ms |",
        pct(&mut pick_ms, 0.5),
        pct(&mut pick_ms, 0.9)
    );
    println!(
        "| a pick at the full {w}x{h} (20 clicks) | p50 {:.0} ms, p90 {:.0} ms |",
        pct(&mut full_pick_ms, 0.5),
        pct(&mut full_pick_ms, 0.9)
    );
    println!(
        "| object question -> first token (5) | p50 {:.0} ms, max {:.0} ms |",
        pct(&mut object_ms, 0.5),
        pct(&mut object_ms, 1.0)
    );
    println!(
        "| view question at a new camera -> first token (5) | p50 {:.0} ms, max {:.0} ms |",
        pct(&mut view_ms, 0.5),
        pct(&mut view_ms, 1.0)
    );
    println!("| server-rendered frames, {w}x{h} | {full_fps:.1} /s |");
    println!("| server-rendered preview frames, 160x120 | {preview_fps:.1} /s |");
    match page {
        Some((load_s, fps, canvas)) => {
            println!("| page load -> first frame (headless Chromium, SwiftShader) | {load_s:.1} s |");
            println!("| browser frames while orbiting (Spark on SwiftShader, {canvas} canvas) | {fps:.2} /s |");
        }
        None => println!("| browser | not installed (apt-get install chromium-headless-shell) |"),
    }
}
