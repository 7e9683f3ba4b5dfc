//! `chatsplat identity`: a geometry run trained without masks gets its identity field from masks
//! whose ids agree across views (`chatsplat masks --out`, or any tool's), its Gaussians untouched,
//! written as a new run that `extract`, `train-language`, `serve` and `export-ply --object` use.

use model::Backend;
use model::data::{Background, LoadOptions};
use model::guard::{Existing, Kind};
use model::run::GeometryRun;
use scoring::progress::Progress;
use std::path::PathBuf;
use train::masks::identity_run::{IdentityOptions, identity_run};

#[derive(clap::Args)]
pub struct Args {
    /// The capture the run was trained on.
    #[arg(long)]
    pub data: PathBuf,
    /// A geometry run of the capture (`chatsplat train --out`), trained with or without masks.
    #[arg(long)]
    pub run: PathBuf,
    /// Masks whose ids agree across views (`chatsplat masks --out`): `<image stem>.png` per image,
    /// the image's size, 0 = none.
    #[arg(long, value_name = "DIR")]
    pub masks: PathBuf,
    /// The new run: the old run's Gaussians with the identity field.
    #[arg(long)]
    pub out: PathBuf,
    /// Cross-entropy steps on the identity after each Gaussian's vote (0: the vote alone).
    #[arg(long, default_value_t = IdentityOptions::default().iters)]
    pub iters: usize,
    #[arg(long, default_value_t = Backend::Ndarray)]
    pub backend: Backend,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let run = GeometryRun::new(&a.run);
    let mut inputs = run.own_files();
    inputs.push(("the --data directory", a.data.clone()));
    inputs.push(("the --masks directory", a.masks.clone()));
    // the run itself is an input: a new run may not lie inside it (its language run is there)
    inputs.push(("the --run directory", a.run.clone()));
    let existing = Existing::Refuse { instead: "give a new or empty --out (the old run stays as it is)" };
    model::guard::output_folder("--out", &a.out, Kind::GeometryRun, existing, &inputs)?;
    let state = super::masks::check_trained_on(&run, &a.data)?;
    let background = if state.data.background[0] >= 0.5 { Background::White } else { Background::Black };
    let load =
        LoadOptions { downscale: state.data.downscale, background, masks: Some(a.masks.clone()), ..Default::default() };
    let ds = train::pipeline::load_for_geometry(&a.data, &load)?.0;
    let device = a.backend.device()?;
    let opts = IdentityOptions { iters: a.iters, ..Default::default() };
    let bar = Progress::new("identity", "it");
    let out = GeometryRun::new(&a.out);
    let s = model::catch_backend("the identity", || {
        identity_run(&run, &ds, &a.data, &load, &out, &opts, &device, |i, loss| {
            bar.update_with(i, opts.iters, &format!("cross-entropy {loss:.4}"))
        })
    })??;
    println!(
        "{} of {} Gaussians in objects, {} classes; cross-entropy {:.4} -> {:.4}; {} views: identity mIoU {} \
         ({:.1} s) -> {}",
        s.object_gaussians,
        s.gaussians,
        s.classes,
        s.first_loss,
        s.last_loss,
        s.eval.views,
        s.eval.miou.map(|m| format!("{m:.3}")).unwrap_or("-".into()),
        s.seconds,
        a.out.display()
    );
    Ok(())
}
