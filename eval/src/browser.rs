//! A real browser for the viewer's tests: Debian's `chromium-headless-shell` (WebGL2 on
//! SwiftShader), driven over the Chrome DevTools Protocol (JSON over a WebSocket): navigate,
//! evaluate, mouse and keyboard input, screenshots.

use serde_json::{Value, json};
use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tungstenite::{Message, WebSocket};

/// Where the browser is: `$CHATSPLAT_CHROMIUM`, else Debian's package's binary.
pub fn find() -> Option<PathBuf> {
    let given = std::env::var_os("CHATSPLAT_CHROMIUM").map(PathBuf::from);
    given.or_else(|| Some(PathBuf::from("/usr/lib/chromium/chromium-headless-shell"))).filter(|p| p.exists())
}

/// A headless browser with one page.
pub struct Browser {
    child: Child,
    ws: WebSocket<TcpStream>,
    session: String,
    next_id: u64,
    /// Exceptions and console errors of the page, as they came.
    pub page_errors: Vec<String>,
    _profile: crate::scratch::Scratch,
}

type Result<T> = std::result::Result<T, String>;

impl Browser {
    /// Starts the browser with a `width x height` viewport on `about:blank`.
    pub fn launch(exe: &std::path::Path, width: u32, height: u32) -> Result<Self> {
        let profile = crate::scratch::temp_dir("chromium-profile");
        let mut child = Command::new(exe)
            .args([
                "--no-sandbox",
                "--enable-unsafe-swiftshader",
                "--use-angle=swiftshader",
                "--remote-debugging-port=0",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-dev-shm-usage",
                &format!("--window-size={width},{height}"),
            ])
            .arg(format!("--user-data-dir={}", profile.display()))
            .arg("about:blank")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| format!("cannot start {}: {e}", exe.display()))?;
        // "DevTools listening on ws://127.0.0.1:PORT/devtools/browser/ID"
        let stderr = child.stderr.take().expect("piped");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut sent = false;
            for line in BufReader::new(stderr).lines().map_while(|l| l.ok()) {
                if !sent && let Some(i) = line.find("ws://") {
                    let _ = tx.send(line[i..].trim().to_string());
                    sent = true;
                }
            }
        });
        let url = rx.recv_timeout(Duration::from_secs(60)).map_err(|_| {
            let _ = child.kill();
            "the browser printed no DevTools address in 60 s".to_string()
        })?;
        let host = url.trim_start_matches("ws://").split('/').next().unwrap_or("").to_string();
        let stream = TcpStream::connect(&host).map_err(|e| format!("DevTools at {host}: {e}"))?;
        stream.set_read_timeout(Some(Duration::from_secs(300))).map_err(|e| e.to_string())?;
        let (ws, _) = tungstenite::client(url.as_str(), stream).map_err(|e| format!("DevTools handshake: {e}"))?;
        let mut b = Self { child, ws, session: String::new(), next_id: 0, page_errors: vec![], _profile: profile };
        let targets = b.call_browser("Target.getTargets", json!({}))?;
        let page = targets["targetInfos"]
            .as_array()
            .and_then(|t| t.iter().find(|t| t["type"] == "page"))
            .and_then(|t| t["targetId"].as_str())
            .ok_or("the browser has no page")?
            .to_string();
        let attached = b.call_browser("Target.attachToTarget", json!({"targetId": page, "flatten": true}))?;
        b.session = attached["sessionId"].as_str().ok_or("no session")?.to_string();
        b.call("Page.enable", json!({}))?;
        b.call("Runtime.enable", json!({}))?;
        b.call(
            "Emulation.setDeviceMetricsOverride",
            json!({"width": width, "height": height, "deviceScaleFactor": 1, "mobile": false}),
        )?;
        Ok(b)
    }

    fn send(&mut self, method: &str, params: Value, session: bool) -> Result<Value> {
        self.next_id += 1;
        let id = self.next_id;
        let mut msg = json!({"id": id, "method": method, "params": params});
        if session {
            msg["sessionId"] = json!(self.session);
        }
        self.ws.send(Message::text(msg.to_string())).map_err(|e| format!("{method}: {e}"))?;
        loop {
            let m = self.ws.read().map_err(|e| format!("{method}: {e}"))?;
            let Message::Text(t) = m else { continue };
            let v: Value = serde_json::from_str(t.as_str()).map_err(|e| e.to_string())?;
            if v["id"] == id {
                if let Some(e) = v.get("error") {
                    return Err(format!("{method}: {e}"));
                }
                return Ok(v["result"].clone());
            }
            self.note(&v);
        }
    }

    fn note(&mut self, v: &Value) {
        match v["method"].as_str() {
            Some("Runtime.exceptionThrown") => {
                let d = &v["params"]["exceptionDetails"];
                self.page_errors.push(format!("exception: {} {}", d["text"], d["exception"]["description"]));
            }
            Some("Runtime.consoleAPICalled") if v["params"]["type"] == "error" => {
                self.page_errors.push(format!("console.error: {}", v["params"]["args"]));
            }
            _ => {}
        }
    }

    fn call_browser(&mut self, method: &str, params: Value) -> Result<Value> {
        self.send(method, params, false)
    }

    /// A DevTools command to the page.
    pub fn call(&mut self, method: &str, params: Value) -> Result<Value> {
        self.send(method, params, true)
    }

    /// Loads `url` and waits for `ready` (a JavaScript expression) to be true.
    pub fn goto(&mut self, url: &str, ready: &str, timeout: Duration) -> Result<()> {
        self.call("Page.navigate", json!({"url": url}))?;
        self.wait_for(ready, timeout).map(|_| ())
    }

    /// Evaluates `expr` in the page (promises awaited) and returns its value.
    pub fn eval(&mut self, expr: &str) -> Result<Value> {
        let r =
            self.call("Runtime.evaluate", json!({"expression": expr, "awaitPromise": true, "returnByValue": true}))?;
        if let Some(e) = r.get("exceptionDetails") {
            return Err(format!("{expr}: {}", e["exception"]["description"].as_str().unwrap_or(&e.to_string())));
        }
        Ok(r["result"]["value"].clone())
    }

    /// Polls `expr` until it is truthy; its value.
    pub fn wait_for(&mut self, expr: &str, timeout: Duration) -> Result<Value> {
        let t0 = Instant::now();
        loop {
            let v = self.eval(&format!("(() => {{ try {{ return {expr}; }} catch (e) {{ return null; }} }})()"))?;
            let truthy =
                !matches!(&v, Value::Null | Value::Bool(false)) && v.as_f64() != Some(0.0) && v.as_str() != Some("");
            if truthy {
                return Ok(v);
            }
            if t0.elapsed() > timeout {
                // the viewer says why it is not idle
                let why = self
                    .eval("(() => { try { return window.chatsplat.debug(); } catch (e) { return null; } })()")
                    .unwrap_or(Value::Null);
                return Err(format!("waited {timeout:?} for {expr}; page errors: {:?}; page: {why}", self.page_errors));
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// A left click at page pixel `(x, y)` (press and release, no move).
    pub fn click(&mut self, x: f64, y: f64) -> Result<()> {
        self.mouse("mouseMoved", x, y, "none", 0)?;
        self.mouse("mousePressed", x, y, "left", 1)?;
        self.mouse("mouseReleased", x, y, "left", 0)
    }

    /// A left-button drag from `from` to `to` in `steps` moves.
    pub fn drag(&mut self, from: (f64, f64), to: (f64, f64), steps: usize) -> Result<()> {
        self.mouse("mouseMoved", from.0, from.1, "none", 0)?;
        self.mouse("mousePressed", from.0, from.1, "left", 1)?;
        for i in 1..=steps {
            let t = i as f64 / steps as f64;
            self.mouse("mouseMoved", from.0 + t * (to.0 - from.0), from.1 + t * (to.1 - from.1), "left", 1)?;
        }
        self.mouse("mouseReleased", to.0, to.1, "left", 0)
    }

    fn mouse(&mut self, kind: &str, x: f64, y: f64, button: &str, buttons: u32) -> Result<()> {
        let clicks = if kind == "mouseMoved" { 0 } else { 1 };
        self.call(
            "Input.dispatchMouseEvent",
            json!({"type": kind, "x": x, "y": y, "button": button, "buttons": buttons, "clickCount": clicks}),
        )
        .map(|_| ())
    }

    /// Types `text` into the focused element.
    pub fn type_text(&mut self, text: &str) -> Result<()> {
        self.call("Input.insertText", json!({"text": text})).map(|_| ())
    }

    /// Presses and releases a key (e.g. "Enter").
    pub fn key(&mut self, key: &str) -> Result<()> {
        let code = if key == "Enter" { 13 } else { 0 };
        for kind in ["keyDown", "keyUp"] {
            let mut p = json!({"type": kind, "key": key, "code": key, "windowsVirtualKeyCode": code});
            if key == "Enter" && kind == "keyDown" {
                p["text"] = json!("\r");
            }
            self.call("Input.dispatchKeyEvent", p)?;
        }
        Ok(())
    }

    /// A PNG screenshot of the viewport, decoded: `(width, height, RGB bytes)`.
    pub fn screenshot(&mut self) -> Result<(Vec<u8>, (usize, usize, Vec<u8>))> {
        let r = self.call("Page.captureScreenshot", json!({"format": "png"}))?;
        let png = base64(r["data"].as_str().ok_or("no screenshot data")?)?;
        let decoded = crate::http::decode_png(&png);
        Ok((png, decoded))
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.ws.close(None);
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn base64(s: &str) -> Result<Vec<u8>> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => Ok(c - b'A'),
        b'a'..=b'z' => Ok(c - b'a' + 26),
        b'0'..=b'9' => Ok(c - b'0' + 52),
        b'+' => Ok(62),
        b'/' => Ok(63),
        _ => Err(format!("not base64: {}", c as char)),
    };
    let bytes: Vec<u8> = s.bytes().filter(|&c| c != b'=' && !c.is_ascii_whitespace()).collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut acc = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            acc |= (val(c)? as u32) << (18 - 6 * i);
        }
        out.extend_from_slice(&acc.to_be_bytes()[1..chunk.len()]);
    }
    Ok(out)
}
