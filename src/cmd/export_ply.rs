//! `chatsplat export-ply`: a run's Gaussians as an Inria-layout .ply: all of them, one object's
//! (`--object ID`) or all but one object's (`--without ID`), by each Gaussian's identity class.

use anyhow::bail;
use model::run::GeometryRun;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Run directory written by `chatsplat train`.
    #[arg(long)]
    run: PathBuf,
    #[arg(long)]
    out: PathBuf,
    /// Only the Gaussians of this object (its identity class, as `ask --object` and the viewer
    /// number objects).
    #[arg(long, conflicts_with = "without")]
    object: Option<u8>,
    /// The scene without this object's Gaussians.
    #[arg(long)]
    without: Option<u8>,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let run = GeometryRun::new(&a.run);
    model::io::refuse_output_onto("--out", &a.out, &run.own_files())?;
    let (m, state) = run.load_model(&burn::tensor::Device::ndarray())?;
    let (mut cloud, _) = m.to_cloud();
    let total = cloud.len();
    let what = match (a.object, a.without) {
        (Some(id), _) | (_, Some(id)) => {
            let classes = m.gaussian_classes();
            let of_id = classes.iter().filter(|&&c| c == id).count();
            if of_id == 0 || id == 0 {
                let mut objects: Vec<u8> = classes.iter().copied().filter(|&c| c != 0).collect();
                objects.sort_unstable();
                objects.dedup();
                let flag = if a.object.is_some() { "--object" } else { "--without" };
                bail!(
                    "{flag} {id}: {} holds no Gaussian of object {id} (its objects: {})",
                    a.run.display(),
                    if objects.is_empty() { "none".to_string() } else { format!("{objects:?}") }
                );
            }
            let keep_object = a.object.is_some();
            let keep: Vec<bool> = classes.iter().map(|&c| (c == id) == keep_object).collect();
            cloud.retain(&keep);
            if keep_object { format!("object {id}: ") } else { format!("without object {id}: ") }
        }
        _ => String::new(),
    };
    model::ply::write(&a.out, &cloud)?;
    println!("{what}{} of {total} Gaussians (iteration {}) -> {}", cloud.len(), state.iter, a.out.display());
    Ok(())
}
