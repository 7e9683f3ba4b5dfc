//! `view-depth`: every view of a geometry run rendered as expected depth, for segmenters that cut
//! at depth edges as well as colour edges (`eval/masks/classic_segments.py --depth`).
//!
//! Writes `OUT/<image stem>.png` per view of the run (16-bit: depth / the farthest depth drawn in
//! any view x 65535, 0 where nothing was drawn) and `OUT/depth.json` with that scale in the run's
//! units.
//!
//! cargo run --release -p eval --bin view-depth -- --run RUN --out DIR
#![allow(deprecated)]

use burn::tensor::Device;
use model::run::GeometryRun;
use model::splats::{background, host};
use splat_kernels::api::{SplatOptions, splat};
use std::path::PathBuf;

#[derive(clap::Parser)]
#[command(name = "view-depth", about = "a geometry run's views rendered as depth maps (16-bit PNG)")]
struct Args {
    /// Geometry run (`chatsplat train --out`).
    #[arg(long)]
    run: PathBuf,
    /// A new folder for the depth maps.
    #[arg(long)]
    out: PathBuf,
}

eval::bench_main!("view-depth", depth);

fn depth(a: &Args) -> model::Result<()> {
    let run = GeometryRun::new(&a.run);
    // the output guard's rule: nothing onto or around the run's files; and only a new folder
    model::guard::refuse_overlap("--out", &a.out, &run.own_files())?;
    if a.out.exists() {
        return Err(model::Error::invalid(&a.out, "exists: name a new folder for the depth maps"));
    }
    let device = Device::ndarray();
    let (model, _) = run.load_model(&device)?;
    let cams = run.read_cameras()?;
    let mut maps = Vec::new();
    for (name, cam) in cams.image_names().iter().zip(cams.all()) {
        let bg = background([0.0; 3], &device);
        let out = splat(&model.gaussians(&cam, 0), &cam, bg, &SplatOptions { validate: false, ..Default::default() })?;
        let alpha = host(out.alpha.clone());
        let depth: Vec<f32> = host(out.expected_depth())
            .iter()
            .zip(&alpha)
            .map(|(&d, &a)| if a > 0.5 { d.max(0.0) } else { 0.0 })
            .collect();
        maps.push((train::masks::files::stem(name), cam.width, cam.height, depth));
    }
    let far = maps.iter().flat_map(|m| m.3.iter().copied()).fold(0.0f32, f32::max).max(1e-6);
    model::io::create_dir(&a.out)?;
    for (stem, w, h, d) in &maps {
        let q: Vec<u16> = d.iter().map(|&z| (z / far * 65535.0).round() as u16).collect();
        model::images::write_ids(&a.out.join(format!("{stem}.png")), *w, *h, &q)?;
    }
    model::io::write_json(
        &a.out.join("depth.json"),
        &serde_json::json!({ "scale": far / 65535.0, "views": maps.len() }),
    )?;
    println!("{} depth maps (farthest {far:.3}) -> {}", maps.len(), a.out.display());
    Ok(())
}
