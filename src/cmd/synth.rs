//! `chatsplat synth`: the built-in synthetic tabletop as a dataset.

use model::data::synth::{SynthOptions, write_dataset};
use model::guard::{Existing, Kind};
use scoring::progress::Progress;
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct Args {
    /// Scene seed (what is on the table, the table, the background, the light).
    #[arg(long, default_value_t = model::data::synth::DEFAULT_SEED)]
    pub seed: u64,
    /// Output directory.
    #[arg(long, default_value = "out/synth")]
    pub out: PathBuf,
    /// Number of views around the table.
    #[arg(long, default_value_t = 48)]
    pub views: usize,
    #[arg(long, default_value_t = 96)]
    pub width: u32,
    #[arg(long, default_value_t = 96)]
    pub height: u32,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let opts = SynthOptions { seed: a.seed, views: a.views, width: a.width, height: a.height, ..Default::default() };
    // an earlier tabletop is written again; a capture, a run or files of the user's are not
    model::guard::output_folder("--out", &a.out, Kind::Tabletop, Existing::GoOn, &[])?;
    write(&a.out, &opts)
}

/// Writes the tabletop of `opts` to `out` with a progress bar and a summary line.
pub fn write(out: &Path, opts: &SynthOptions) -> anyhow::Result<()> {
    let t0 = std::time::Instant::now();
    let bar = Progress::new("synth", "views");
    write_dataset(out, opts, |done, total| bar.update(done, total))?;
    println!(
        "wrote {} views of seed {} ({}x{}) with masks, depth, transforms.json, scene.json and questions.json \
            to {} in {:.1} s",
        opts.views,
        opts.seed,
        opts.width,
        opts.height,
        out.display(),
        t0.elapsed().as_secs_f64()
    );
    Ok(())
}
