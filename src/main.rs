//! `chatsplat`: 3D conversational Gaussian splatting from the command line. Each subcommand is one
//! file in `cmd/`; the work is done by the `model`, `train` and `eval` libraries.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

mod cmd;
mod ranks;

use clap::Parser;
use std::process::ExitCode;

/// Large tensors' blocks mapped with huge pages and reused ([`model::alloc::KeepLarge`]).
#[global_allocator]
static ALLOC: model::alloc::KeepLarge = model::alloc::KeepLarge;

fn main() -> ExitCode {
    model::alloc::keep_freed_memory();
    let cli = cmd::Cli::parse();
    let (name, data_parallel) = cli.name();
    let ranks = match ranks::Ranks::join(name, data_parallel) {
        Ok(r) => r,
        Err(e) => return ranks::Ranks::Solo.fail(&e),
    };
    match cmd::run(cli, &ranks) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => ranks.fail(&e),
    }
}
