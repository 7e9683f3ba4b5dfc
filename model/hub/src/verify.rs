//! A downloaded file checked against its etag, the name of its blob in the cache: the SHA-256 of
//! its bytes for files the hub keeps in LFS (weights), the git blob hash (SHA-1 of `blob <len>\0`
//! and the bytes) for the others.

use sha1::Sha1;
use sha2::{Digest, Sha256};
use std::io::Read;
use std::path::Path;

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The hash of `path`'s bytes under `hasher`, after `prefix`.
fn digest<D: Digest>(mut hasher: D, prefix: &[u8], path: &Path) -> std::io::Result<String> {
    hasher.update(prefix);
    let mut f = std::fs::File::open(path)?;
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(hex(&hasher.finalize()))
}

/// The etag-shaped hash of `path`: `len` 64 gives SHA-256, 40 the git blob hash.
pub fn hash(path: &Path, len: usize) -> std::io::Result<Option<String>> {
    let size = std::fs::metadata(path)?.len();
    Ok(match len {
        64 => Some(digest(Sha256::new(), b"", path)?),
        40 => Some(digest(Sha1::new(), format!("blob {size}\0").as_bytes(), path)?),
        _ => None,
    })
}

/// Checks the file a snapshot `pointer` leads to against its blob's name; a file that differs is
/// removed (blob and pointer) so that the next fetch starts again.
pub fn check(pointer: &Path) -> Result<(), String> {
    let blob = std::fs::canonicalize(pointer).map_err(|e| format!("{}: {e}", pointer.display()))?;
    let etag = blob.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_string();
    let is_hex = etag.chars().all(|c| c.is_ascii_hexdigit());
    let got = match hash(&blob, etag.len()) {
        Ok(h) => h.filter(|_| is_hex),
        Err(e) => return Err(format!("{}: {e}", blob.display())),
    };
    match got {
        Some(h) if h != etag.to_lowercase() => {
            let _ = std::fs::remove_file(pointer);
            let _ = std::fs::remove_file(&blob);
            Err(format!("the download is corrupt (its hash is {h}, the hub's etag {etag}); removed, fetch again"))
        }
        _ => Ok(()),
    }
}
