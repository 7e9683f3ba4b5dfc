//! Models fetched by their Hugging Face id (issue 85) from a loopback server standing in for the
//! hub (its `resolve/main/<file>` answers: ranges, etags, the commit header, 404 and 401): a
//! fresh fetch into an empty cache, the cache used with the server gone, a download resumed from
//! its `.part`, offline without a cache, a missing file, a corrupt download.

use chatsplat_tests::fake_hub::{COMMIT, FakeHub, Served};
use chatsplat_tests::temp_dir;
use hub::{HubError, wanted};
use std::collections::HashMap;
use std::path::Path;

/// tiny-sam's files as the hub serves them: the weights by SHA-256 (LFS), the config by its git
/// blob hash; `flip` corrupts the weights' bytes after their etag was taken.
fn tiny_sam(flip: bool) -> HashMap<String, Served> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tiny-sam");
    let mut out = Served::files(&dir, &["config.json", "model.safetensors"]);
    if flip {
        let bytes = &mut out.get_mut("model.safetensors").unwrap().bytes;
        let n = bytes.len() - 1;
        bytes[n] ^= 1;
    }
    out
}

fn read(dir: &Path, name: &str) -> Vec<u8> {
    std::fs::read(dir.join(name)).unwrap()
}

fn names(log: &[(String, String)]) -> Vec<String> {
    log.iter().map(|(p, _)| p.rsplit('/').next().unwrap().to_string()).collect()
}

#[test]
fn a_model_is_fetched_by_id_cached_and_used_offline() {
    let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tiny-sam");
    let cache = temp_dir("hub-fresh");
    let server = FakeHub::start("acme/tiny-sam", tiny_sam(false));
    let dir = server.hub(&cache).snapshot("acme/tiny-sam", &wanted::SAM).unwrap();
    assert_eq!(dir, std::path::absolute(&cache).unwrap().join(format!("models--acme--tiny-sam/snapshots/{COMMIT}")));
    for f in ["config.json", "model.safetensors"] {
        assert_eq!(read(&dir, f), read(&source, f), "{f}");
    }
    let asked = names(&server.requests());
    assert!(asked.contains(&"preprocessor_config.json".into()), "the optional file was not asked: {asked:?}");
    sam::Sam::load(&dir, &burn::tensor::Device::flex()).expect("the fetched folder loads as SAM");
    // the server gone: the cache alone, online or offline
    let hub = server.hub(&cache);
    drop(server);
    assert_eq!(hub.snapshot("acme/tiny-sam", &wanted::SAM).unwrap(), dir);
    let offline = hub::Hub { offline: true, ..hub };
    assert_eq!(offline.snapshot("acme/tiny-sam", &wanted::SAM).unwrap(), dir);
    // offline with an empty cache: named, not fetched
    let nothing = temp_dir("hub-empty");
    let empty = hub::Hub { cache: nothing.to_path_buf(), ..offline };
    let e = empty.snapshot("acme/tiny-sam", &wanted::SAM).unwrap_err();
    assert_eq!((e.repo.as_str(), e.file.as_str()), ("acme/tiny-sam", "config.json"), "{e}");
    assert!(e.to_string().contains("HF_HUB_OFFLINE"), "{e}");
}

#[test]
fn an_interrupted_download_resumes_from_its_part_file() {
    let files = tiny_sam(false);
    let weights = &files["model.safetensors"];
    let half = weights.bytes.len() / 2;
    let cache = temp_dir("hub-resume");
    let blobs = cache.join("models--acme--tiny-sam/blobs");
    std::fs::create_dir_all(&blobs).unwrap();
    std::fs::write(blobs.join(format!("{}.part", weights.etag)), &weights.bytes[..half]).unwrap();
    let expect = weights.bytes.clone();
    let server = FakeHub::start("acme/tiny-sam", files);
    let dir = server.hub(&cache).snapshot("acme/tiny-sam", &wanted::SAM).unwrap();
    assert_eq!(read(&dir, "model.safetensors"), expect);
    let asked: Vec<String> = server
        .requests()
        .into_iter()
        .filter(|(p, r)| p.ends_with("model.safetensors") && r != "bytes=0-0")
        .map(|(_, r)| r)
        .collect();
    assert_eq!(asked, vec![format!("bytes={half}-")], "the download started again instead of resuming");
}

#[test]
fn missing_files_unknown_repos_and_corrupt_downloads_are_named() {
    let err = |repo: &str, files: HashMap<String, Served>| -> (HubError, chatsplat_tests::Scratch) {
        let cache = temp_dir("hub-bad");
        let server = FakeHub::start("acme/tiny-sam", files);
        (server.hub(&cache).snapshot(repo, &wanted::SAM).unwrap_err(), cache)
    };
    // no weights at all: neither the single file nor an index
    let mut no_weights = tiny_sam(false);
    no_weights.remove("model.safetensors");
    let (e, _) = err("acme/tiny-sam", no_weights);
    assert!(e.file.starts_with("model.safetensors") && e.message.contains("not found"), "{e}");
    assert!(e.to_string().contains("acme/tiny-sam"), "{e}");
    // a repo the hub does not know (it answers 401 to anyone not logged in)
    let (e, _) = err("acme/nothing-here", tiny_sam(false));
    assert_eq!((e.repo.as_str(), e.file.as_str()), ("acme/nothing-here", "config.json"), "{e}");
    assert!(e.message.contains("does not exist"), "{e}");
    // bytes that differ from their etag: refused and removed, so the next fetch starts again
    let (e, cache) = err("acme/tiny-sam", tiny_sam(true));
    assert_eq!(e.file, "model.safetensors", "{e}");
    assert!(e.message.contains("corrupt"), "{e}");
    let etag = &tiny_sam(false)["model.safetensors"].etag;
    let blobs: Vec<String> = std::fs::read_dir(cache.join("models--acme--tiny-sam/blobs"))
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| !n.ends_with(".lock"))
        .collect();
    assert!(blobs.len() == 1 && !blobs[0].starts_with(etag.as_str()), "the corrupt blob stayed: {blobs:?}");
}

#[test]
fn sharded_weights_are_fetched_through_their_index() {
    // the index names two shards (one of them twice); each is fetched once, beside the index
    let index = r#"{"weight_map": {"a.w": "model-00002-of-00002.safetensors", "b.w": "model-00001-of-00002.safetensors",
        "c.w": "model-00001-of-00002.safetensors"}}"#;
    let scratch = temp_dir("hub-shards");
    std::fs::create_dir_all(&scratch).unwrap();
    let named = [
        ("config.json", b"{}".to_vec()),
        ("model.safetensors.index.json", index.as_bytes().to_vec()),
        ("model-00001-of-00002.safetensors", vec![1u8; 3000]),
        ("model-00002-of-00002.safetensors", vec![2u8; 5000]),
    ];
    for (name, bytes) in &named {
        std::fs::write(scratch.join(name), bytes).unwrap();
    }
    let files = Served::files(&scratch, &named.map(|(n, _)| n));
    let server = FakeHub::start("acme/sharded", files);
    let cache = temp_dir("hub-sharded-cache");
    let want = wanted::Wanted { required: &["config.json"], optional: &[], safetensors: true };
    let dir = server.hub(&cache).snapshot("acme/sharded", &want).unwrap();
    assert_eq!(read(&dir, "model-00002-of-00002.safetensors"), vec![2u8; 5000]);
    assert_eq!(read(&dir, "model-00001-of-00002.safetensors"), vec![1u8; 3000]);
    let shard_gets = names(&server.requests()).iter().filter(|n| n.starts_with("model-0000")).count();
    assert_eq!(shard_gets, 4, "each shard asked once for its etag and once for its bytes");
    // an index naming a file outside the repo is refused
    let bad = scratch.join("bad.json");
    std::fs::write(&bad, r#"{"weight_map": {"a": "../../etc/passwd"}}"#).unwrap();
    assert!(wanted::shards(&bad).is_err(), "a shard outside the repo was accepted");
}
