//! A minimal HTTP/1.1 client for the viewer's tests (one request per connection), a reader of
//! server-sent events, and a `chatsplat serve` process to talk to.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// A response.
#[derive(Debug)]
pub struct Reply {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Reply {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k.eq_ignore_ascii_case(name)).map(|(_, v)| v.as_str())
    }
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
    /// The body as JSON, whatever the status (error replies carry JSON too); panics on other bodies.
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| panic!("not JSON ({e}): {}", self.text()))
    }
    /// The body as JSON of a 200 response; otherwise the status or the parse error, with the body.
    pub fn try_json(&self) -> Result<serde_json::Value, String> {
        if self.status != 200 {
            return Err(format!("HTTP {}: {}", self.status, self.text()));
        }
        serde_json::from_slice(&self.body).map_err(|e| format!("not JSON ({e}): {}", self.text()))
    }
    /// The server-sent events of the body: `(event name, JSON data)`.
    pub fn events(&self) -> Vec<(String, serde_json::Value)> {
        parse_events(&self.text())
    }
}

/// Sends a request with `extra` headers; `body` as JSON when given.
pub fn send(
    addr: &str,
    method: &str,
    path: &str,
    extra: &[(&str, &str)],
    body: Option<&[u8]>,
) -> std::io::Result<Reply> {
    let mut s = open(addr, method, path, extra, body)?;
    let mut raw = Vec::new();
    s.read_to_end(&mut raw)?;
    parse(&raw)
}

/// `GET path`.
pub fn get(addr: &str, path: &str) -> Reply {
    send(addr, "GET", path, &[], None).unwrap()
}

/// `POST path` with a JSON body.
pub fn post(addr: &str, path: &str, body: &serde_json::Value) -> Reply {
    send(addr, "POST", path, &[], Some(body.to_string().as_bytes())).unwrap()
}

/// Opens a connection and sends the request; the caller reads the raw response (e.g. a stream
/// it then drops, to test a client that goes away).
pub fn open(
    addr: &str,
    method: &str,
    path: &str,
    extra: &[(&str, &str)],
    body: Option<&[u8]>,
) -> std::io::Result<TcpStream> {
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(Duration::from_secs(300)))?;
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in extra {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    if let Some(b) = body {
        head.push_str(&format!("Content-Type: application/json\r\nContent-Length: {}\r\n", b.len()));
    }
    head.push_str("\r\n");
    s.write_all(head.as_bytes())?;
    if let Some(b) = body {
        s.write_all(b)?;
    }
    Ok(s)
}

fn bad(msg: &str) -> std::io::Error {
    std::io::Error::new(std::io::ErrorKind::InvalidData, msg.to_string())
}

/// Parses a whole response (chunked or not).
pub fn parse(raw: &[u8]) -> std::io::Result<Reply> {
    let end = raw.windows(4).position(|w| w == b"\r\n\r\n").ok_or_else(|| bad("no end of headers"))?;
    let head = String::from_utf8_lossy(&raw[..end]);
    let mut lines = head.split("\r\n");
    let status_line = lines.next().ok_or_else(|| bad("no status line"))?;
    let status = status_line.split(' ').nth(1).and_then(|s| s.parse().ok()).ok_or_else(|| bad(status_line))?;
    let headers: Vec<(String, String)> =
        lines.filter_map(|l| l.split_once(':').map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))).collect();
    let rest = &raw[end + 4..];
    let chunked = headers.iter().any(|(k, v)| k.eq_ignore_ascii_case("transfer-encoding") && v.contains("chunked"));
    let body = if chunked { dechunk(rest)? } else { rest.to_vec() };
    Ok(Reply { status, headers, body })
}

fn dechunk(mut data: &[u8]) -> std::io::Result<Vec<u8>> {
    let mut out = Vec::new();
    let mut r = BufReader::new(&mut data);
    loop {
        let mut line = String::new();
        if r.read_line(&mut line)? == 0 {
            return Ok(out); // cut short (a stream the server ended): what came
        }
        let size = usize::from_str_radix(line.trim().split(';').next().unwrap_or(""), 16)
            .map_err(|_| bad(&format!("bad chunk size {line:?}")))?;
        if size == 0 {
            return Ok(out);
        }
        let mut chunk = vec![0; size];
        r.read_exact(&mut chunk)?;
        out.extend_from_slice(&chunk);
        let mut crlf = [0; 2];
        r.read_exact(&mut crlf)?;
    }
}

/// The events of a `text/event-stream` body.
pub fn parse_events(text: &str) -> Vec<(String, serde_json::Value)> {
    let mut out = Vec::new();
    for block in text.split("\n\n") {
        let mut name = "message".to_string();
        let mut data = String::new();
        for line in block.lines() {
            if let Some(v) = line.strip_prefix("event:") {
                name = v.trim().to_string();
            } else if let Some(v) = line.strip_prefix("data:") {
                data.push_str(v.strip_prefix(' ').unwrap_or(v));
            }
        }
        if !data.is_empty() {
            let value = serde_json::from_str(&data).unwrap_or(serde_json::Value::String(data));
            out.push((name, value));
        }
    }
    out
}

/// Decodes an 8-bit RGB or RGBA PNG to `(width, height, RGB bytes)`.
pub fn decode_png(bytes: &[u8]) -> (usize, usize, Vec<u8>) {
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().expect("a PNG");
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).expect("a frame");
    let (w, h) = (info.width as usize, info.height as usize);
    let ch = info.color_type.samples();
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    let rgb = buf[..w * h * ch].chunks(ch).flat_map(|p| [p[0], p[1], p[2]]).collect();
    (w, h, rgb)
}

/// A running `chatsplat serve` on a free loopback port.
pub struct Server {
    pub child: Child,
    /// `host:port`.
    pub addr: String,
    log: Arc<Mutex<String>>,
}

impl Server {
    /// `chatsplat serve --run RUN EXTRA..` of the binary `bin`, once it printed its URL.
    pub fn start(bin: &str, run: &Path, extra: &[&str]) -> Server {
        Self::launch(Path::new(bin), run, extra).unwrap_or_else(|e| panic!("{e}"))
    }

    /// [`Server::start`], or why the server did not start (its standard error included).
    pub fn launch(bin: &Path, run: &Path, extra: &[&str]) -> Result<Server, String> {
        let mut child = Command::new(bin)
            .args(["serve", "--addr", "127.0.0.1:0", "--run"])
            .arg(run)
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| format!("cannot start {}: {e}", bin.display()))?;
        let log = Arc::new(Mutex::new(String::new()));
        let (err, l) = (child.stderr.take().expect("piped"), log.clone());
        let reader = std::thread::spawn(move || {
            for line in BufReader::new(err).lines().map_while(|l| l.ok()) {
                l.lock().unwrap().push_str(&format!("{line}\n"));
            }
        });
        let mut out = BufReader::new(child.stdout.take().expect("piped"));
        let mut line = String::new();
        let _ = out.read_line(&mut line);
        let addr = line.trim().strip_prefix("chatsplat viewer: http://").and_then(|a| a.strip_suffix('/'));
        match addr {
            Some(a) => Ok(Server { addr: a.to_string(), child, log }),
            None => {
                // the server exited (or printed something else): its whole standard error
                let _ = child.kill();
                let _ = child.wait();
                let _ = reader.join();
                let err = log.lock().unwrap().clone();
                Err(format!("{} serve printed no URL ({line:?}); its stderr:\n{err}", bin.display()))
            }
        }
    }

    /// What the server wrote to its standard error so far.
    pub fn log(&self) -> String {
        self.log.lock().unwrap().clone()
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    /// SIGTERM, as Ctrl-C would: the server must stop by itself, successfully.
    pub fn stop(mut self) -> String {
        Command::new("kill").args(["-TERM", &self.child.id().to_string()]).status().unwrap();
        let t0 = Instant::now();
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break s;
            }
            assert!(t0.elapsed() < Duration::from_secs(30), "the server did not stop within 30 s");
            std::thread::sleep(Duration::from_millis(50));
        };
        std::thread::sleep(Duration::from_millis(100));
        let log = self.log();
        assert!(status.success(), "exit {status}; stderr:\n{log}");
        log
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The answer of an `/api/ask` event stream and its `done` event, after checking the stream's
/// shape: a 200 event stream from `start` to `done`, whose tokens make the answer `done` holds.
pub fn streamed_answer(r: &Reply) -> (String, serde_json::Value) {
    assert_eq!(r.status, 200, "{}", r.text());
    assert!(r.header("content-type").is_some_and(|t| t.starts_with("text/event-stream")));
    let ev = r.events();
    let names: Vec<&str> = ev.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names.first(), Some(&"start"), "{names:?}");
    assert_eq!(names.last(), Some(&"done"), "{names:?}");
    let streamed: String = ev.iter().filter(|(n, _)| n == "token").map(|(_, v)| v["text"].as_str().unwrap()).collect();
    let done = ev.last().unwrap().1.clone();
    assert_eq!(done["text"].as_str().unwrap(), streamed, "the tokens streamed make the answer");
    (streamed, done)
}
