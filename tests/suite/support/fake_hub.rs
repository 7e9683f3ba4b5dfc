//! A loopback server standing in for the Hugging Face hub: `/<repo>/resolve/main/<file>` answered
//! as the hub answers (byte ranges, `ETag`, `X-Repo-Commit`; 404 for a file the repo lacks, 401 for
//! a repo it does not know), every request's path and range logged.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::sync::{Arc, Mutex};

/// The commit every answer names.
pub const COMMIT: &str = "0123456789abcdef0123456789abcdef01234567";

/// One file the fake hub serves: its bytes and the etag it gives them.
pub struct Served {
    pub bytes: Vec<u8>,
    pub etag: String,
}

impl Served {
    /// `names` in `dir` with the etags the hub gives them: SHA-256 for weights (LFS), the git blob
    /// hash for the others.
    pub fn files(dir: &Path, names: &[&str]) -> HashMap<String, Served> {
        let served = |name: &&str| {
            let p = dir.join(name);
            let etag = hub::verify::hash(&p, if name.ends_with(".safetensors") { 64 } else { 40 }).unwrap().unwrap();
            (name.to_string(), Served { bytes: std::fs::read(&p).unwrap(), etag })
        };
        names.iter().map(served).collect()
    }
}

/// A hub on 127.0.0.1 serving one repo; every request's path and range are logged.
pub struct FakeHub {
    pub endpoint: String,
    log: Arc<Mutex<Vec<(String, String)>>>,
    listener: Option<std::thread::JoinHandle<()>>,
    stop: Arc<std::sync::atomic::AtomicBool>,
}

impl FakeHub {
    /// Serves `files` as the repo `repo` until dropped.
    pub fn start(repo: &str, files: HashMap<String, Served>) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let endpoint = format!("http://{}", listener.local_addr().unwrap());
        let log = Arc::new(Mutex::new(Vec::new()));
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (l, s, prefix) = (log.clone(), stop.clone(), format!("/{repo}/resolve/main/"));
        let handle = std::thread::spawn(move || {
            for conn in listener.incoming() {
                if s.load(std::sync::atomic::Ordering::SeqCst) {
                    break;
                }
                if let Ok(c) = conn {
                    answer(c, &prefix, &files, &l);
                }
            }
        });
        Self { endpoint, log, listener: Some(handle), stop }
    }

    /// A client of this server keeping its cache in `cache`, without progress bars.
    pub fn hub(&self, cache: &Path) -> hub::Hub {
        hub::Hub {
            endpoint: self.endpoint.clone(),
            cache: cache.to_path_buf(),
            offline: false,
            progress: false,
            token: None,
        }
    }

    /// `(path, range)` of every request so far.
    pub fn requests(&self) -> Vec<(String, String)> {
        self.log.lock().unwrap().clone()
    }
}

impl Drop for FakeHub {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::SeqCst);
        let _ = TcpStream::connect(self.endpoint.trim_start_matches("http://"));
        if let Some(h) = self.listener.take() {
            let _ = h.join();
        }
    }
}

/// One request on `c`, answered and closed.
fn answer(mut c: TcpStream, prefix: &str, files: &HashMap<String, Served>, log: &Mutex<Vec<(String, String)>>) {
    let mut reader = BufReader::new(c.try_clone().unwrap());
    let mut line = String::new();
    reader.read_line(&mut line).unwrap_or(0);
    let path = line.split_whitespace().nth(1).unwrap_or("").to_string();
    let mut range = String::new();
    loop {
        let mut h = String::new();
        if reader.read_line(&mut h).unwrap_or(0) == 0 || h.trim().is_empty() {
            break;
        }
        if let Some((k, v)) = h.split_once(':')
            && k.eq_ignore_ascii_case("range")
        {
            range = v.trim().to_string();
        }
    }
    log.lock().unwrap().push((path.clone(), range.clone()));
    let reply = |c: &mut TcpStream, status: &str, headers: String, body: &[u8]| {
        let head = format!("HTTP/1.1 {status}\r\nContent-Length: {}\r\nConnection: close\r\n{headers}\r\n", body.len());
        let _ = c.write_all(head.as_bytes()).and_then(|_| c.write_all(body));
    };
    let Some(name) = path.strip_prefix(prefix) else {
        return reply(&mut c, "401 Unauthorized", String::new(), b"Repository not found");
    };
    let Some(f) = files.get(name) else {
        return reply(&mut c, "404 Not Found", format!("X-Repo-Commit: {COMMIT}\r\n"), b"Entry not found");
    };
    let len = f.bytes.len();
    let spec = range.strip_prefix("bytes=").unwrap_or("0-");
    let (a, b) = spec.split_once('-').unwrap_or(("0", ""));
    let a: usize = a.parse().unwrap_or(0);
    let b: usize = b.parse().map_or(len - 1, |b: usize| b.min(len - 1));
    let headers = format!(
        "Content-Range: bytes {a}-{b}/{len}\r\nETag: \"{}\"\r\nX-Repo-Commit: {COMMIT}\r\nAccept-Ranges: bytes\r\n",
        f.etag
    );
    reply(&mut c, "206 Partial Content", headers, &f.bytes[a..=b]);
}
