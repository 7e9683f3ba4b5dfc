//! `chatsplat export-encoder`: the encoder and scaling adjustment in PyTorch Conv2d layout.

use model::run::{GeometryRun, LanguageRun};
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct Args {
    /// Geometry run directory.
    #[arg(long)]
    pub run: PathBuf,
    /// Language run directory (default: RUN/language).
    #[arg(long)]
    pub language: Option<PathBuf>,
    /// Output .safetensors file.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let geometry = GeometryRun::new(&a.run);
    let lang = a.language.as_ref().map(LanguageRun::new).unwrap_or_else(|| geometry.language());
    let inputs: Vec<_> = lang.own_files().into_iter().chain(geometry.own_files()).collect();
    let safetensors = |head: &[u8]| head.len() > 9 && head[8] == b'{';
    model::guard::output_file("--out", &a.out, "a .safetensors file", safetensors, &inputs)?;
    export(&lang, &a.out)
}

/// Writes the encoder of the language run `lang` to `out`.
pub fn export(lang: &LanguageRun, out: &Path) -> anyhow::Result<()> {
    let (field, state) = lang.load_field(&burn::tensor::Device::ndarray())?;
    let enc = &field.encoder;
    let n = model::language::export::write_encoder(out, enc, &state.field, &state.teacher_model)?;
    println!(
        "encoder ({n} parameters, {} lifting layers, scale/shift {}) -> {}",
        enc.lift_weights.len(),
        enc.scale.is_some(),
        out.display()
    );
    Ok(())
}
