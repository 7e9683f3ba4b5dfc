//! `masks-bench`: per-view masks matched across views (issue 84) on synthetic scenes the tests do
//! not train on, against Gaga's greedy recipe on the same masks.
//!
//! For each scene (a seed): a geometry run trained without masks, the true masks corrupted as
//! segmenters err (ids shuffled per view, 20 % of masks split, 10 % merged with a neighbour, 10 %
//! missing, fragments, edges moved 1-2 px), then consistent instance mIoU (one id per true object
//! over all views), the object count against the truth, the change when the views come in reverse
//! order, and milliseconds per view (blend weights, matching, greedy) on this machine.
//!
//! cargo run --release -p eval --bin masks-bench -- [--scenes 10] [--first-seed 100] [--json FILE]
#![allow(deprecated)]

use burn::tensor::Device;
use clap::Parser;
use model::data::Dataset;
use model::data::nerfstudio::{LoadOptions, load};
use model::run::GeometryRun;
use std::path::PathBuf;
use std::time::Instant;
use train::geometry::{GeometryConfig, GeometryTrainer, view_at};
use train::masks::ownership::ViewOwners;
use train::masks::{LabelMap, MatchOptions, corrupt, greedy, match_masks, render_labels, score};

#[derive(Parser)]
#[command(name = "masks-bench", about = "per-view masks matched across views, against the greedy baseline")]
struct Args {
    #[arg(long, default_value_t = 10)]
    scenes: usize,
    /// The first scene's seed (the tests use 11 and 12).
    #[arg(long, default_value_t = 100)]
    first_seed: u64,
    #[arg(long, default_value_t = 16)]
    views: usize,
    #[arg(long, default_value_t = 96)]
    width: u32,
    #[arg(long, default_value_t = 84)]
    height: u32,
    /// Geometry iterations per scene.
    #[arg(long, default_value_t = 600)]
    iters: usize,
    /// The segmenter's errors, `key=value` by commas (edge_px, missing, merged, split,
    /// fragments; unnamed keys keep the defaults: 2, 0.1, 0.1, 0.2, 2).
    #[arg(long, default_value = "")]
    errors: String,
    /// An unmasked pixel's vote for the background against a mask's 1 (the matching's default).
    #[arg(long, default_value_t = MatchOptions::default().unmasked)]
    unmasked: f32,
    /// The share of views where two candidates' Gaussians share a mask for them to be one object.
    #[arg(long, default_value_t = MatchOptions::default().together)]
    together: f64,
    /// The share of each other's Gaussians two masks must own to be joined (the matching's default).
    #[arg(long, default_value_t = MatchOptions::default().mutual)]
    mutual: f32,
    /// The blend weight a Gaussian needs in a view to take part in it (the matching's default).
    #[arg(long, default_value_t = MatchOptions::default().min_weight)]
    min_weight: f32,
    /// Write the per-scene rows as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Keep each scene and its geometry run here, and reuse them when the same scene, size and
    /// iterations come again (only the matching is then timed anew).
    #[arg(long)]
    cache: Option<PathBuf>,
}

#[derive(serde::Serialize)]
struct Row {
    seed: u64,
    true_objects: usize,
    /// The true masks (ids consistent) given to the Gaussians and rendered back: what the geometry
    /// allows at this size.
    geometry_miou: f64,
    /// Matched from the true masks with their ids shuffled per view alone.
    ceiling_miou: f64,
    corrupted_miou: f64,
    matched_miou: f64,
    matched_objects: usize,
    reversed_delta: f64,
    greedy_miou: f64,
    greedy_objects: usize,
    weights_ms_per_view: f64,
    match_ms_per_view: f64,
    greedy_ms_per_view: f64,
    /// The surfaces found ([`train::masks::surface`]) are the matched table, and only it.
    surface_is_table: bool,
}

fn errors(spec: &str) -> Result<corrupt::Errors, String> {
    let mut e = corrupt::Errors::default();
    for kv in spec.split(',').filter(|s| !s.trim().is_empty()) {
        let (k, v) = kv.split_once('=').ok_or(format!("--errors: {kv} is not key=value"))?;
        let bad = |_: std::num::ParseFloatError| format!("--errors: {kv}: not a number");
        let int = |_: std::num::ParseIntError| format!("--errors: {kv}: not a whole number");
        match k.trim() {
            "edge_px" => e.edge_px = v.trim().parse().map_err(int)?,
            "missing" => e.missing = v.trim().parse().map_err(bad)?,
            "merged" => e.merged = v.trim().parse().map_err(bad)?,
            "split" => e.split = v.trim().parse().map_err(bad)?,
            "fragments" => e.fragments = v.trim().parse().map_err(int)?,
            other => return Err(format!("--errors: no error named {other}")),
        }
    }
    Ok(e)
}

/// Scene `seed` and a geometry run trained on it without masks: from `--cache` when it holds them.
fn scene(a: &Args, seed: u64, dev: &Device) -> Result<(Dataset, GeometryTrainer), Box<dyn std::error::Error>> {
    let name = format!("seed{seed}-{}x{}-v{}", a.width, a.height, a.views);
    let (dir, keep) = match &a.cache {
        Some(c) => (c.join(&name), true),
        None => (std::env::temp_dir().join(format!("masks-bench-{name}-{}", std::process::id())), false),
    };
    let data = dir.join("data");
    if !data.join("scene.json").is_file() {
        let opts = model::data::synth::SynthOptions {
            seed,
            views: a.views,
            width: a.width,
            height: a.height,
            ..Default::default()
        };
        model::data::synth::write_dataset(&data, &opts, |_, _| {})?;
    }
    let load_opts = LoadOptions { holdout_every: 0, ..Default::default() };
    let ds = load(&data, &load_opts)?;
    let run = GeometryRun::new(dir.join(format!("run-{}", a.iters)));
    if keep && run.state().is_file() {
        let (t, _) = GeometryTrainer::load(&run, dev)?;
        if t.iter == a.iters {
            return Ok((ds, t));
        }
    }
    let mut bare = ds.clone();
    bare.train.iter_mut().for_each(|v| v.instance_ids = None);
    let cfg = GeometryConfig {
        iters: a.iters,
        init_per_view: 400,
        densify_from: 50,
        densify_every: 50,
        densify_until: a.iters * 2 / 3,
        opacity_reset_every: 0,
        checkpoint_every: 0,
        max_gaussians: 12000,
        ..Default::default()
    };
    let mut t = GeometryTrainer::new(&bare, cfg, dev)?;
    while t.iter < a.iters {
        let v = &bare.train[view_at(t.iter, bare.train.len(), t.cfg.seed)];
        t.step(v)?;
    }
    if keep {
        t.save(&run, &train::geometry::data_ref(&bare, &data, &load_opts, &run))?;
    } else {
        std::fs::remove_dir_all(&dir)?;
    }
    Ok((ds, t))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let a = Args::parse();
    let errs = errors(&a.errors)?;
    let dev = Device::ndarray();
    let mopts = MatchOptions {
        unmasked: a.unmasked,
        together: a.together,
        mutual: a.mutual,
        min_weight: a.min_weight,
        ..Default::default()
    };
    let mut rows = Vec::new();
    println!(
        "{:>5} {:>4} {:>8} {:>8} {:>9} {:>13} {:>9} {:>13} {:>9} {:>9} {:>9} {:>7}",
        "seed",
        "objs",
        "geometry",
        "ceiling",
        "corrupt",
        "matched",
        "reversed",
        "greedy",
        "w ms/v",
        "m ms/v",
        "g ms/v",
        "surface"
    );
    for seed in a.first_seed..a.first_seed + a.scenes as u64 {
        let (ds, t) = scene(&a, seed, &dev)?;
        let truth: Vec<LabelMap> = ds.train.iter().map(|v| LabelMap::of_view(v).expect("synthetic masks")).collect();
        let nv = ds.train.len() as f64;
        let t0 = Instant::now();
        let weights = ds.train.iter().map(|v| t.model.blend_weights(&v.camera)).collect::<model::Result<Vec<_>>>()?;
        let weights_ms = t0.elapsed().as_secs_f64() * 1e3 / nv;
        let true_shares = train::masks::soft::Shares::from_maps(&weights, &truth, 1.0);
        let geometry = score::consistency(&truth, &weights.iter().map(|w| true_shares.render(w)).collect::<Vec<_>>());
        let none = corrupt::Errors { edge_px: 0, missing: 0.0, merged: 0.0, split: 0.0, fragments: 0 };
        let shuffled = corrupt::corrupt(&truth, &none, seed);
        let ceiling = score::consistency(&truth, &match_masks(&weights, &shuffled, &mopts).views);
        let noisy = corrupt::corrupt(&truth, &errs, seed);
        let before = score::consistency(&truth, &noisy);
        let t0 = Instant::now();
        let m = match_masks(&weights, &noisy, &mopts);
        let match_ms = t0.elapsed().as_secs_f64() * 1e3 / nv;
        let after = score::consistency(&truth, &m.views);
        let (rw, rn): (Vec<_>, Vec<_>) = weights.iter().cloned().zip(noisy.iter().cloned()).rev().unzip();
        let back: Vec<LabelMap> = match_masks(&rw, &rn, &mopts).views.into_iter().rev().collect();
        let reversed = score::consistency(&truth, &back);
        let t0 = Instant::now();
        let owners: Vec<ViewOwners> = weights.iter().zip(&noisy).map(|(w, n)| ViewOwners::of(w, n, 0.5)).collect();
        let g = greedy::greedy(&owners, weights[0].gaussians);
        let greedy_views: Vec<LabelMap> = weights.iter().map(|w| render_labels(w, &g)).collect();
        let greedy_ms = t0.elapsed().as_secs_f64() * 1e3 / nv;
        let baseline = score::consistency(&truth, &greedy_views);
        // the surfaces found are the table, and only it
        let found = train::masks::surface::of_matched(&t.model, &m);
        let named = score::truth_of(&truth, &m.views);
        let mut tables: Vec<u16> =
            m.objects.iter().map(|o| o.id).filter(|i| named.get(i) == Some(&model::data::synth::TABLE_ID)).collect();
        tables.sort_unstable();
        let row = Row {
            seed,
            true_objects: after.true_objects,
            geometry_miou: geometry.miou,
            ceiling_miou: ceiling.miou,
            corrupted_miou: before.miou,
            matched_miou: after.miou,
            matched_objects: after.predicted_objects,
            reversed_delta: (after.miou - reversed.miou).abs(),
            greedy_miou: baseline.miou,
            greedy_objects: baseline.predicted_objects,
            weights_ms_per_view: weights_ms,
            match_ms_per_view: match_ms,
            greedy_ms_per_view: greedy_ms,
            surface_is_table: !found.is_empty() && found == tables,
        };
        println!(
            "{:>5} {:>4} {:>8.3} {:>8.3} {:>9.3} {:>7.3} ({:>2}) {:>9.4} {:>7.3} ({:>2}) {:>9.1} {:>9.1} {:>9.1} {:>7}",
            row.seed,
            row.true_objects,
            row.geometry_miou,
            row.ceiling_miou,
            row.corrupted_miou,
            row.matched_miou,
            row.matched_objects,
            row.reversed_delta,
            row.greedy_miou,
            row.greedy_objects,
            row.weights_ms_per_view,
            row.match_ms_per_view,
            row.greedy_ms_per_view,
            if row.surface_is_table { "table" } else { "WRONG" }
        );
        rows.push(row);
    }
    let n = rows.len().max(1) as f64;
    let mean = |f: &dyn Fn(&Row) -> f64| rows.iter().map(f).sum::<f64>() / n;
    let exact = rows.iter().filter(|r| r.matched_objects == r.true_objects).count();
    let greedy_exact = rows.iter().filter(|r| r.greedy_objects == r.true_objects).count();
    println!(
        "mean over {} scenes: geometry {:.3}, ceiling {:.3}; corrupted {:.3} -> matched {:.3} (object count \
         exact on {}/{}), greedy {:.3} (exact on {}/{}); largest change with the views reversed {:.4}; ms per \
         view: weights {:.1}, matching {:.1}, greedy {:.1}; the table the one surface on {}/{}",
        rows.len(),
        mean(&|r| r.geometry_miou),
        mean(&|r| r.ceiling_miou),
        mean(&|r| r.corrupted_miou),
        mean(&|r| r.matched_miou),
        exact,
        rows.len(),
        mean(&|r| r.greedy_miou),
        greedy_exact,
        rows.len(),
        rows.iter().map(|r| r.reversed_delta).fold(0.0, f64::max),
        mean(&|r| r.weights_ms_per_view),
        mean(&|r| r.match_ms_per_view),
        mean(&|r| r.greedy_ms_per_view),
        rows.iter().filter(|r| r.surface_is_table).count(),
        rows.len()
    );
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&rows)?)?;
    }
    Ok(())
}
