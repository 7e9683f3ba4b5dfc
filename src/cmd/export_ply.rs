//! `chatsplat export-ply`: a run's Gaussians as an Inria-layout .ply.

use model::run::GeometryRun;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Run directory written by `chatsplat train`.
    #[arg(long)]
    run: PathBuf,
    #[arg(long)]
    out: PathBuf,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let run = GeometryRun::new(&a.run);
    model::io::refuse_output_onto("--out", &a.out, &run.own_files())?;
    let (m, state) = run.load_model(&burn::tensor::Device::ndarray())?;
    let (cloud, _) = m.to_cloud();
    model::ply::write(&a.out, &cloud)?;
    println!("{} Gaussians (iteration {}) -> {}", cloud.len(), state.iter, a.out.display());
    Ok(())
}
