//! `viewer-bench`: the browser viewer's figures on a trained run (default: the demo's), as a
//! user feels them: click -> highlight (the pick request), object question -> first token, view
//! question at a new camera -> first token, a follow-up against the same question afresh,
//! server-rendered frames per second, page load and
//! browser frames per second (headless Chromium on SwiftShader, when installed).
//!
//! ```text
//! cargo build --release && cargo run --release -p eval --bin viewer-bench -- [--run out/demo/run]
//! ```

use clap::Parser;
use eval::browser::{self, Browser};
use eval::http::{self, Reply, Server};
use model::{Error, Result};
use serde_json::{Value, json};
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[derive(Parser)]
#[command(about = "The browser viewer's figures on a trained run: clicks, first tokens, frames per second")]
struct Args {
    /// The run to serve (a `chatsplat demo`'s by default).
    #[arg(long, default_value = "out/demo/run")]
    run: PathBuf,
    /// The `chatsplat` binary (default: the one beside this bench; `cargo build --release` first).
    #[arg(long)]
    chatsplat: Option<PathBuf>,
    /// Instead of the figures: open the page (headless Chromium), click the object `--object`
    /// (default: the one covering most of the page's first view) and write the page as a PNG here.
    #[arg(long, value_name = "PNG")]
    screenshot: Option<PathBuf>,
    /// The object `--screenshot` clicks, by id (`/api/scene` lists them).
    #[arg(long, requires = "screenshot")]
    object: Option<u64>,
}

eval::bench_main!("viewer-bench", bench);

fn pct(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// A camera of `w x h` pixels at the view camera `v`'s pose and vertical field of view.
fn sized(v: &Value, w: u32, h: u32) -> Result<Value> {
    let mut c = v.clone();
    let o = c.as_object_mut().ok_or_else(|| Error::input(format!("/api/scene: a view's camera is {v}")))?;
    for k in ["fx", "fy", "cx", "cy"] {
        o.remove(k);
    }
    o.insert("width".into(), json!(w));
    o.insert("height".into(), json!(h));
    Ok(c)
}

/// `POST path` to the server: the reply, or the connection's error naming the route.
fn post(addr: &str, path: &str, body: &Value) -> Result<Reply> {
    http::send(addr, "POST", path, &[], Some(body.to_string().as_bytes()))
        .map_err(|e| Error::input(format!("{path}: {e}")))
}

/// `POST path` and its JSON reply (a failure status is an error naming the route).
fn post_json(addr: &str, path: &str, body: &Value) -> Result<Value> {
    post(addr, path, body)?.try_json().map_err(|e| Error::input(format!("{path}: {e}")))
}

/// A number of a reply, or an error naming the field.
fn num(v: &Value, what: &str) -> Result<f64> {
    v.as_f64().ok_or_else(|| Error::input(format!("the server's reply has no number for {what}")))
}

fn bench(a: &Args) -> Result<()> {
    let run = &a.run;
    let exe = match &a.chatsplat {
        Some(p) => p.clone(),
        None => {
            std::env::current_exe().map_err(|e| Error::input(format!("own path: {e}")))?.with_file_name("chatsplat")
        }
    };
    let (w, h) = (640u32, 480u32);
    let t0 = Instant::now();
    let server =
        Server::launch(&exe, run, &[]).map_err(|e| Error::input(format!("{e} (cargo build --release first)")))?;
    let addr = server.addr.clone();
    let start_s = t0.elapsed().as_secs_f64();
    let info = http::send(&addr, "GET", "/api/scene", &[], None)
        .map_err(|e| e.to_string())
        .and_then(|r| r.try_json())
        .map_err(|e| Error::input(format!("/api/scene: {e}")))?;
    let view0 = info["views"][0]["camera"].clone();
    let cam = sized(&view0, w, h)?;

    // the objects of view 0 and a pixel well inside each (the middle of its mask's longest run)
    let targets = |camera: &Value| -> Result<Vec<(u64, u64, u64)>> {
        let width = num(&camera["width"], "a camera's width")? as u64;
        let mut t = vec![];
        for o in info["objects"].as_array().ok_or_else(|| Error::input("/api/scene lists no objects"))? {
            let r = post_json(&addr, "/api/select", &json!({"camera": camera, "id": o["id"]}))?;
            if let Some(runs) = r["object"]["mask"]["runs"].as_array().filter(|r| !r.is_empty()) {
                let runs: Vec<u64> = runs.iter().filter_map(|v| v.as_u64()).collect();
                let Some(longest) = runs.chunks_exact(2).max_by_key(|r| r[1]) else { continue };
                let p = longest[0] + longest[1] / 2;
                t.push((num(&o["id"], "an object's id")? as u64, p % width, p / width));
            }
        }
        if t.is_empty() {
            return Err(Error::input(format!("{}: view 0 shows no object", run.display())));
        }
        Ok(t)
    };
    // clicks as the page makes them (at most 320 px on the longest side: app.js, PICK_SIDE), and
    // at the full size
    let picks = |camera: &Value| -> Result<Vec<f64>> {
        let at = targets(camera)?;
        let mut ms = vec![];
        for i in 0..20 {
            let (id, x, y) = at[i % at.len()];
            let t = Instant::now();
            let r = post_json(&addr, "/api/pick", &json!({"camera": camera, "x": x, "y": y}))?;
            ms.push(t.elapsed().as_secs_f64() * 1e3);
            if r["object"]["id"].as_u64() != Some(id) {
                return Err(Error::input(format!("a click inside object {id} picked {r}")));
            }
        }
        Ok(ms)
    };
    if let Some(path) = &a.screenshot {
        return screenshot(&addr, path, a.object, &targets);
    }
    let mut pick_ms = picks(&sized(&view0, 320, 240)?)?;
    let mut full_pick_ms = picks(&cam)?;
    let first_token = |body: Value| -> Result<f64> {
        let r = post(&addr, "/api/ask", &body)?;
        let ev = r.events();
        let done = &ev.iter().find(|e| e.0 == "done").ok_or_else(|| Error::input(format!("/api/ask: {}", r.text())))?.1;
        num(&done["first_token_ms"], "first_token_ms")
    };
    let mut object_ms = vec![];
    for (id, _, _) in targets(&cam)?.into_iter().take(5) {
        object_ms.push(first_token(json!({"scope": "object", "camera": cam, "id": id, "question": "What is this?"}))?);
    }
    // new cameras: view 0's pose turned about the scene's up axis through its centre
    let mut view_ms = vec![];
    let coords = |v: &Value, n: usize, what: &str| -> Result<Vec<f64>> { (0..n).map(|i| num(&v[i], what)).collect() };
    let centre = coords(&info["center"], 3, "the scene's centre")?;
    for k in 1..=5 {
        let a = 0.1 * k as f64;
        let mut c = cam.clone();
        let pos = coords(&c["position"], 3, "a camera's position")?;
        let p: Vec<f64> = (0..3).map(|i| pos[i] - centre[i]).collect();
        // rotate about +y (the synthetic scenes' up) and turn the camera with it
        let (s, co) = (a.sin(), a.cos());
        c["position"] = json!([centre[0] + co * p[0] + s * p[2], centre[1] + p[1], centre[2] - s * p[0] + co * p[2]]);
        let q = coords(&c["quaternion"], 4, "a camera's quaternion")?;
        let (hs, hc) = ((a / 2.0).sin(), (a / 2.0).cos());
        // (0, hs, 0, hc) * q
        c["quaternion"] =
            json!([hc * q[0] + hs * q[2], hc * q[1] + hs * q[3], hc * q[2] - hs * q[0], hc * q[3] - hs * q[1]]);
        view_ms.push(first_token(json!({"scope": "view", "camera": c, "question": "What objects are there?"}))?);
    }
    // a conversation's follow-up at view 0's camera (its first turn's tokens and keys and values
    // kept) against the same question asked afresh there
    let (mut follow_ms, mut fresh_ms) = (vec![], vec![]);
    let (q1, q2) = ("What colors are there?", "What objects are there?");
    for _ in 0..5 {
        let r = post(&addr, "/api/ask", &json!({"scope": "view", "camera": cam, "question": q1}))?;
        let ev = r.events();
        let start =
            ev.iter().find(|e| e.0 == "start").ok_or_else(|| Error::input(format!("/api/ask: {}", r.text())))?;
        let id = start.1["conversation"].clone();
        follow_ms.push(first_token(json!({"scope": "view", "camera": cam, "question": q2, "conversation": id}))?);
        fresh_ms.push(first_token(json!({"scope": "view", "camera": cam, "question": q2}))?);
    }
    let frames = |camera: &Value, seconds: f64| -> Result<f64> {
        let t = Instant::now();
        let mut n = 0;
        while t.elapsed().as_secs_f64() < seconds {
            let r = post(&addr, "/api/render", &json!({"camera": camera}))?;
            if r.status != 200 {
                return Err(Error::input(format!("/api/render: HTTP {}: {}", r.status, r.text())));
            }
            n += 1;
        }
        Ok(n as f64 / t.elapsed().as_secs_f64())
    };
    let full_fps = frames(&cam, 8.0)?;
    let preview_fps = frames(&sized(&view0, 160, 120)?, 4.0)?;

    let mut page = None;
    if let Some(exe) = browser::find() {
        let browser_err = |what: &str| {
            let what = what.to_string();
            move |e: String| Error::input(format!("the browser ({what}): {e}"))
        };
        let mut b = Browser::launch(&exe, 1100, 700).map_err(browser_err("start"))?;
        let t = Instant::now();
        b.goto(
            &format!("http://{addr}/"),
            "window.chatsplat && window.chatsplat.ready && window.chatsplat.frames > 0",
            Duration::from_secs(300),
        )
        .map_err(browser_err("the page"))?;
        let load_s = t.elapsed().as_secs_f64();
        b.wait_for("window.chatsplat.idle", Duration::from_secs(120)).map_err(browser_err("idle"))?;
        let r = b.eval("window.chatsplat.canvasRect()").map_err(browser_err("the canvas"))?;
        let canvas = format!("{}x{}", r[2], r[3]);
        // orbit a little every animation frame for 8 s, in the page (no input round trips)
        let orbit = "new Promise((done) => { const f0 = window.chatsplat.frames, t0 = performance.now(); \
            const step = () => { window.chatsplat.orbit(3, 0); \
              if (performance.now() - t0 < 8000) requestAnimationFrame(step); \
              else done((window.chatsplat.frames - f0) * 1000 / (performance.now() - t0)); }; \
            requestAnimationFrame(step); })";
        let fps = num(&b.eval(orbit).map_err(browser_err("orbit"))?, "the page's frames per second")?;
        page = Some((load_s, fps, canvas));
    }
    drop(server);

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
    let (follow, fresh) = (pct(&mut follow_ms, 0.5), pct(&mut fresh_ms, 0.5));
    println!(
        "| a follow-up in a view conversation -> first token (5), against the same question afresh | p50 {follow:.0} \
            ms against {fresh:.0} ms ({:.2}x) |",
        follow / fresh
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
    Ok(())
}

/// `--screenshot`: the page at its first view, `object` (or the largest object there) clicked,
/// its highlight drawn, written to `path`.
fn screenshot(
    addr: &str,
    path: &std::path::Path,
    object: Option<u64>,
    targets: &dyn Fn(&Value) -> Result<Vec<(u64, u64, u64)>>,
) -> Result<()> {
    let exe = browser::find().ok_or_else(|| Error::input("--screenshot needs chromium-headless-shell"))?;
    let err = |what: &'static str| move |e: String| Error::input(format!("the browser ({what}): {e}"));
    let mut b = Browser::launch(&exe, 1100, 700).map_err(err("start"))?;
    let ready = "window.chatsplat && window.chatsplat.ready && window.chatsplat.frames > 0";
    b.goto(&format!("http://{addr}/"), ready, Duration::from_secs(300)).map_err(err("the page"))?;
    b.wait_for("window.chatsplat.idle", Duration::from_secs(120)).map_err(err("idle"))?;
    let rect = b.eval("window.chatsplat.canvasRect()").map_err(err("the canvas"))?;
    let camera = b.eval("window.chatsplat.camera()").map_err(err("the camera"))?;
    let at = targets(&camera)?;
    let (id, x, y) = match object {
        Some(id) => at
            .into_iter()
            .find(|t| t.0 == id)
            .ok_or_else(|| Error::input(format!("object {id} is not in the page's view")))?,
        None => {
            // the largest: most pixels in its selection mask
            let pixels = |id: u64| -> Result<f64> {
                let r = post_json(addr, "/api/select", &json!({"camera": camera, "id": id}))?;
                num(&r["object"]["pixels"], "a selection's pixels")
            };
            let mut best = (at[0], -1.0);
            for t in at {
                let n = pixels(t.0)?;
                if n > best.1 {
                    best = (t, n);
                }
            }
            best.0
        }
    };
    let (left, top) = (num(&rect[0], "the canvas")?, num(&rect[1], "the canvas")?);
    b.click(left + x as f64 + 0.5, top + y as f64 + 0.5).map_err(err("the click"))?;
    let sel = b.wait_for("window.chatsplat.selection", Duration::from_secs(60)).map_err(err("the pick"))?;
    b.wait_for("window.chatsplat.idle", Duration::from_secs(120)).map_err(err("idle"))?;
    std::fs::write(path, b.screenshot().map_err(err("the screenshot"))?.0)
        .map_err(|e| Error::io(path, "writing", e))?;
    println!("object {id} clicked at ({x}, {y}): {sel} -> {}", path.display());
    Ok(())
}
