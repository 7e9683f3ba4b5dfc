//! `chatsplat`: 3D conversational Gaussian splatting from the command line. Each subcommand is one
//! file in `cmd/`; the work is done by the `model`, `train` and `eval` libraries.
#![allow(deprecated)] // burn-ndarray is deprecated in burn 0.22 in favour of burn-flex.

mod cmd;

use clap::Parser;
use std::process::ExitCode;

fn main() -> ExitCode {
    model::alloc::keep_freed_memory();
    let cli = cmd::Cli::parse();
    match cmd::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
