//! Models named by their Hugging Face id (`llava-hf/llava-onevision-qwen2-0.5b-ov-hf`,
//! `facebook/sam-vit-base`, any repo id) fetched into the standard Hugging Face cache through the
//! `hf-hub` crate, so that Python tools and this one share what was downloaded.
//!
//! - Where: `$HF_HOME/hub` (else `~/.cache/huggingface/hub`), the hub's own layout (`models--
//!   owner--name/blobs`, `snapshots/<commit>/`, `refs/main`); the server is `$HF_ENDPOINT` (else
//!   `https://huggingface.co`), a token `$HF_TOKEN` or the cache's `token` file.
//! - A model whose files are all in the cache is used without the network; `HF_HUB_OFFLINE=1`
//!   never asks it.
//! - A download goes to `blobs/<etag>.part` first and picks up where an interrupted one stopped;
//!   each finished file is checked against its etag (SHA-256 for large files, the git blob hash
//!   for the others) before it is used, and removed when it differs.
//! - A local folder is used as it is ([`resolve`]).

pub mod verify;
pub mod wanted;

use hf_hub::api::sync::{ApiBuilder, ApiError, ApiRepo};
use hf_hub::{Cache, Repo};
use std::fmt;
use std::path::{Path, PathBuf};
pub use wanted::Wanted;

/// Why a model could not be had: the repo, the file and what went wrong.
#[derive(Debug, Clone, PartialEq)]
pub struct HubError {
    pub repo: String,
    pub file: String,
    pub message: String,
}

impl fmt::Display for HubError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} of the Hugging Face model {}: {}", self.file, self.repo, self.message)
    }
}

impl std::error::Error for HubError {}

/// Where models are fetched from and kept.
#[derive(Clone, Debug)]
pub struct Hub {
    pub endpoint: String,
    /// The hub cache folder (`$HF_HOME/hub`).
    pub cache: PathBuf,
    /// Never ask the server (`HF_HUB_OFFLINE`).
    pub offline: bool,
    /// A progress bar per download on stderr.
    pub progress: bool,
    pub token: Option<String>,
}

impl Hub {
    /// From `HF_HOME`, `HF_ENDPOINT`, `HF_HUB_OFFLINE` and `HF_TOKEN`, with progress bars.
    pub fn from_env() -> Self {
        let cache = Cache::from_env();
        let var = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
        Self {
            endpoint: var("HF_ENDPOINT").unwrap_or_else(|| "https://huggingface.co".into()),
            offline: var("HF_HUB_OFFLINE").is_some_and(|v| matches!(v.to_lowercase().as_str(), "1" | "true" | "yes")),
            token: var("HF_TOKEN").or_else(|| cache.token()),
            cache: cache.path().clone(),
            progress: true,
        }
    }

    /// The folder holding `repo`'s files that `want` names, fetched into the cache where they
    /// are not there yet.
    pub fn snapshot(&self, repo: &str, want: &Wanted) -> Result<PathBuf, HubError> {
        let err = |file: &str, message: String| HubError { repo: repo.into(), file: file.into(), message };
        let cache = std::path::absolute(&self.cache).map_err(|e| err("the cache", e.to_string()))?;
        let cached = Cache::new(cache.clone()).repo(Repo::model(repo.into()));
        // the cache alone first: every needed file there, or the first one missing
        let missing = match want.fetch(|f| Ok(cached.get(f))) {
            Ok(files) => return same_folder(repo, &files),
            Err(wanted::Missing::File(f) | wanted::Missing::Index(f, _)) => f,
            Err(wanted::Missing::Hub(e)) => return Err(e),
        };
        if self.offline {
            return Err(err(&missing, format!("not in the cache ({}) and HF_HUB_OFFLINE is set", cache.display())));
        }
        let api = ApiBuilder::new()
            .with_endpoint(self.endpoint.clone())
            .with_cache_dir(cache)
            .with_progress(self.progress)
            .with_token(self.token.clone())
            .build()
            .map_err(|e| err("the client", e.to_string()))?;
        let remote = api.model(repo.into());
        let fetch = |file: &str| -> Result<Option<PathBuf>, HubError> {
            if let Some(p) = cached.get(file) {
                return Ok(Some(p));
            }
            match remote.download(file) {
                Ok(p) => verify::check(&p).map(|_| Some(p)).map_err(|m| err(file, m)),
                Err(e) if not_found(&e) => Ok(None),
                Err(e) => Err(err(file, self.explain(&remote, e))),
            }
        };
        let files = want.fetch(|f| fetch(f)).map_err(|e| match e {
            wanted::Missing::File(f) => err(&f, format!("not found at {}", remote.url(&f))),
            wanted::Missing::Hub(e) => e,
            wanted::Missing::Index(f, m) => err(&f, m),
        })?;
        same_folder(repo, &files)
    }

    fn explain(&self, remote: &ApiRepo, e: ApiError) -> String {
        match &e {
            ApiError::RequestError(r) => match r.as_ref() {
                ureq::Error::Status(401 | 403, _) => format!(
                    "refused by {} (the repo does not exist, is private or gated: log in or set HF_TOKEN)",
                    self.endpoint
                ),
                ureq::Error::Status(code, _) => format!("{} answered {code}", remote.url("")),
                ureq::Error::Transport(t) => {
                    format!("could not reach {} ({t}); HF_HUB_OFFLINE=1 uses the cache alone", self.endpoint)
                }
            },
            _ => e.to_string(),
        }
    }
}

fn not_found(e: &ApiError) -> bool {
    matches!(e, ApiError::RequestError(r) if matches!(r.as_ref(), ureq::Error::Status(404, _)))
}

/// The one snapshot folder all `files` lie in.
fn same_folder(repo: &str, files: &[PathBuf]) -> Result<PathBuf, HubError> {
    let dirs: Vec<&Path> = files.iter().filter_map(|f| f.parent()).collect();
    match dirs.first() {
        Some(d) if dirs.iter().all(|x| x == d) => Ok(d.to_path_buf()),
        _ => Err(HubError {
            repo: repo.into(),
            file: "its files".into(),
            message: "they come from different commits (the repo changed while it was fetched): run again".into(),
        }),
    }
}

/// Whether `s` has the shape of a Hugging Face repo id (`owner/name`).
pub fn is_repo_id(s: &str) -> bool {
    let part = |p: &str| {
        !p.is_empty()
            && !p.starts_with(['.', '-'])
            && !p.ends_with('.')
            && p.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
    };
    matches!(s.split_once('/'), Some((o, n)) if part(o) && part(n) && !n.contains('/'))
}

/// `given` when it is a folder here; else, when it has the shape of a repo id, the cached snapshot
/// of that model ([`Hub::from_env`]); else `given` (its loader says what is missing).
pub fn resolve(given: &Path, want: &Wanted) -> Result<PathBuf, HubError> {
    let id = given.to_str().filter(|s| !given.exists() && is_repo_id(s));
    match id {
        Some(id) => {
            let dir = Hub::from_env().snapshot(id, want)?;
            eprintln!("{id}: {}", dir.display());
            Ok(dir)
        }
        None => Ok(given.to_path_buf()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn repo_ids_are_told_from_paths() {
        for id in ["llava-hf/llava-onevision-qwen2-0.5b-ov-hf", "facebook/sam-vit-base", "a/b.c_d"] {
            assert!(is_repo_id(id), "{id}");
        }
        for not in ["checkpoints", "/abs/x", "./a/b", "a/b/c", "a/", "/b", "../x", "a b/c", "a/.git", ""] {
            assert!(!is_repo_id(not), "{not}");
        }
    }
}
