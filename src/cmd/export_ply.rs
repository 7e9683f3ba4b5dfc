//! `chatsplat export-ply`: a run's Gaussians as an Inria-layout .ply or a compressed Niantic .spz
//! (`--format`, by default from `--out`'s extension): all of them, one object's (`--object ID`) or
//! all but one object's (`--without ID`), by each Gaussian's identity class.

use anyhow::bail;
use model::ObjectId;
use model::run::GeometryRun;
use std::path::{Path, PathBuf};

/// The file format written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum Format {
    /// Inria-layout 3DGS .ply: every channel as f32, the identity channel included.
    Ply,
    /// Niantic's .spz (Spark, SuperSplat): gzip-compressed and quantised, about a tenth of the
    /// size; lossy, and without the identity channel.
    Spz,
}

impl Format {
    /// By the file name: `.spz` (any case) is spz, anything else ply.
    fn of(path: &Path) -> Self {
        if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("spz")) { Format::Spz } else { Format::Ply }
    }
}

#[derive(clap::Args)]
pub struct Args {
    /// Run directory written by `chatsplat train`.
    #[arg(long)]
    run: PathBuf,
    /// The file to write (.ply or .spz).
    #[arg(long)]
    out: PathBuf,
    /// File format. Default: by --out's extension (.spz: spz, anything else: ply). Given, it wins
    /// over the extension (`--format spz --out scene.bin` writes spz).
    #[arg(long, value_enum)]
    format: Option<Format>,
    /// Only the Gaussians of this object (its identity class, as `ask --object` and the viewer
    /// number objects).
    #[arg(long, conflicts_with = "without")]
    object: Option<ObjectId>,
    /// The scene without this object's Gaussians.
    #[arg(long)]
    without: Option<ObjectId>,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let run = GeometryRun::new(&a.run);
    let mut inputs = run.own_files();
    inputs.extend(run.language().own_files());
    // a file already there is replaced only if it is a splat file (a run's checkpoint or config,
    // whatever its name, is not)
    let splat_file =
        |head: &[u8]| head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n") || head.starts_with(&[0x1f, 0x8b]);
    model::guard::output_file("--out", &a.out, "a .ply or .spz file", splat_file, &inputs)?;
    let (m, state) = run.load_model(&burn::tensor::Device::ndarray())?;
    let (mut cloud, _) = m.to_cloud();
    let total = cloud.len();
    let what = match (a.object, a.without) {
        (Some(id), _) | (_, Some(id)) => {
            let classes = m.gaussian_classes();
            let of_id = classes.iter().filter(|&&c| c == id).count();
            let flag = if a.object.is_some() { "--object" } else { "--without" };
            if id == 0 {
                bail!("{flag} 0: 0 is the background (the Gaussians of no object), not an object");
            }
            if of_id == 0 {
                let mut objects: Vec<ObjectId> = classes.iter().copied().filter(|&c| c != 0).collect();
                objects.sort_unstable();
                objects.dedup();
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
    let format = a.format.unwrap_or_else(|| Format::of(&a.out));
    let dropped = match format {
        Format::Ply => {
            model::ply::write(&a.out, &cloud)?;
            String::new()
        }
        Format::Spz => {
            model::spz::write(&a.out, &cloud)?;
            let names: Vec<&str> = cloud.extra.keys().map(String::as_str).collect();
            if names.is_empty() {
                String::new()
            } else {
                format!("; without {} (.spz cannot hold it)", names.join(", "))
            }
        }
    };
    let size = std::fs::metadata(&a.out).map(|m| m.len()).unwrap_or(0);
    println!(
        "{what}{} of {total} Gaussians (iteration {}) -> {} ({}, {}{dropped})",
        cloud.len(),
        state.iter,
        a.out.display(),
        if format == Format::Spz { "spz" } else { "ply" },
        human_bytes(size)
    );
    Ok(())
}

/// `bytes` for a person: "812 B", "37.4 KB", "5.12 MB" (powers of 1000).
fn human_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    match bytes {
        0..1_000 => format!("{bytes} B"),
        1_000..1_000_000 => format!("{:.1} KB", b / 1e3),
        1_000_000..1_000_000_000 => format!("{:.2} MB", b / 1e6),
        _ => format!("{:.2} GB", b / 1e9),
    }
}
