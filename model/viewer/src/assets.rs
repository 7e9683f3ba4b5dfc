//! The page and its renderer, embedded in the binary: the viewer needs no network and serves no
//! file from disk (a request can only name one of these).

/// One embedded file.
pub struct Asset {
    /// URL path under `/`.
    pub path: &'static str,
    pub content_type: &'static str,
    pub bytes: &'static [u8],
}

macro_rules! asset {
    ($path:literal, $type:expr, $file:literal) => {
        Asset { path: $path, content_type: $type, bytes: include_bytes!(concat!("../web/", $file)) }
    };
}

const JS: &str = "text/javascript; charset=utf-8";

/// Every file the page loads. three.js and Spark are pinned by `web/vendor.sh` (versions in
/// `web/vendor/VERSIONS`, checksums in `web/vendor/SHA256SUMS`).
pub const ASSETS: &[Asset] = &[
    asset!("/", "text/html; charset=utf-8", "index.html"),
    asset!("/app.js", JS, "app.js"),
    asset!("/app.css", "text/css; charset=utf-8", "app.css"),
    asset!("/vendor/three.module.min.js", JS, "vendor/three.module.min.js"),
    asset!("/vendor/three.core.min.js", JS, "vendor/three.core.min.js"),
    asset!("/vendor/three-Pass.js", JS, "vendor/three-Pass.js"),
    asset!("/vendor/spark.module.min.js", JS, "vendor/spark.module.min.js"),
    asset!("/vendor/VERSIONS", "text/plain; charset=utf-8", "vendor/VERSIONS"),
];

/// The asset at URL path `path`, if there is one.
pub fn find(path: &str) -> Option<&'static Asset> {
    let path = if path == "/index.html" { "/" } else { path };
    ASSETS.iter().find(|a| a.path == path)
}
