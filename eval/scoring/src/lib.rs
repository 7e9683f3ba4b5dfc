//! Scoring as the `chatsplat` app ships it: answers to question files ([`score`]: offline exact
//! match and keywords, an OpenAI-compatible grader), the paper's three-way comparison
//! ([`compare`]: the VLM on the ground-truth images, on rendered RGB, and ChatSplat's tokens), the
//! progress bar on standard error ([`progress`]) and dependency-free PNG charts ([`plot`]).
//!
//! The benchmarks' and tests' machinery (the headless-Chromium driver, the HTTP test client,
//! launch counts, probes) lives in `eval`, which only benchmarks and tests depend on.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

pub mod compare;
pub mod plot;
pub mod progress;
pub mod score;
