//! Evaluation of chatsplat: answer scoring ([`score`]: offline exact match / keywords and an
//! OpenAI-compatible grader), dependency-free PNG charts ([`plot`]) and the progress bar shared by
//! the `chatsplat` app and the benchmark binaries (`splat-bench`, `vlm-bench`, `lang-bench`,
//! `vqa-bench`, `viewer-bench`); the headless-Chromium driver ([`browser`]), the HTTP client of the
//! viewer's API ([`http`]), [`scratch`] paths that `viewer-bench` and the tests share, and the
//! count of CubeCL kernel launches the benchmarks print ([`launches`]).
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub mod browser;
pub mod compare;
pub mod harness;
pub mod http;
pub mod launches;
pub mod plot;
pub mod probe;
pub mod progress;
pub mod score;
pub mod scratch;
