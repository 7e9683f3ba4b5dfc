//! The benchmarks' and tests' machinery of chatsplat (only benchmarks and tests depend on this
//! crate; the scoring the app ships is `scoring`): the harness the benchmark binaries share
//! (`splat-bench`, `vlm-bench`, `lang-bench`, `vqa-bench`, `viewer-bench`; [`harness`]), the
//! headless-Chromium driver ([`browser`]), the HTTP client of the viewer's API ([`http`]),
//! [`scratch`] paths that `viewer-bench` and the tests share, the research probes' helpers
//! ([`probe`]) and the count of CubeCL kernel launches the benchmarks print ([`launches`]).
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub mod browser;
pub mod harness;
pub mod http;
pub mod launches;
pub mod probe;
pub mod scratch;
