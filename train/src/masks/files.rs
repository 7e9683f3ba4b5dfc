//! `chatsplat masks` on files: a geometry run's views, the per-view label PNGs of any segmenter
//! (`DIR/<image stem>.png`, 8- or 16-bit, ids arbitrary per view), matched, written as a masks
//! folder the loaders read (`OUT/<image stem>.png`, 16-bit only where ids pass 255) with
//! `OUT/masks.json`.

use super::{LabelMap, MatchOptions, Matched, match_masks};
use model::error::{Error, Result};
use model::run::GeometryRun;
use model::splats::SplatModel;
use serde::Serialize;
use splat_kernels::Camera;
use splat_kernels::blend::BlendWeights;
use std::path::{Path, PathBuf};

/// What `masks.json` records.
#[derive(Clone, Debug, Serialize)]
pub struct Summary {
    pub objects: Vec<ObjectEntry>,
    pub views: usize,
    /// Views whose per-view mask file was missing (matched as showing no object).
    pub views_without_masks: Vec<String>,
    pub per_view_ms: f64,
    pub options: Options,
}

#[derive(Clone, Debug, Serialize)]
pub struct ObjectEntry {
    pub id: u16,
    pub gaussians: usize,
    pub confidence: f32,
    /// The images whose mask shows it.
    pub views: Vec<String>,
    /// The ground or a table other objects stand on ([`super::surface`]): kept out of `find`.
    pub surface: bool,
}

#[derive(Clone, Debug, Serialize)]
pub struct Options {
    pub min_weight: f32,
    pub mutual: f32,
    pub min_views: usize,
    pub min_gaussians: usize,
    pub together: f64,
    pub unmasked: f32,
}

/// The stem of an image name (`images/r_0.png` -> `r_0`).
pub fn stem(image: &str) -> String {
    Path::new(image).file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| image.to_string())
}

/// Where per-view masks come from.
pub enum PerView<'a> {
    /// `<image stem>.png` per view in a folder; a missing file is a view with no mask.
    Dir(&'a Path),
    /// Made from each view's image file by a segmenter (e.g. SAM's automatic masks), at the
    /// image's size: `(width, height, ids)`.
    Made(&'a mut dyn FnMut(&Path) -> Result<(u32, u32, Vec<u16>)>),
}

/// Reads `dir/<stem>.png` at the camera's size; a missing file is a view with no mask (`None`).
fn read_view(dir: &Path, name: &str, cam: &Camera) -> Result<Option<LabelMap>> {
    let path = dir.join(format!("{}.png", stem(name)));
    if !path.exists() {
        return Ok(None);
    }
    let (w, h, ids) = model::data::read_ids16_any(&path)?;
    at_camera_size(&path, (w, h, ids), cam).map(Some)
}

/// A mask `(w, h, ids)` at the camera's size (a mask `k` times larger sampled every `k` pixels).
fn at_camera_size(path: &Path, (w, h, ids): (u32, u32, Vec<u16>), cam: &Camera) -> Result<LabelMap> {
    let (cw, ch) = (cam.width, cam.height);
    if w % cw != 0 || h % ch != 0 || w / cw != h / ch {
        return Err(Error::invalid(path, format!("is {w}x{h}, not the view's {cw}x{ch} or a whole multiple of it")));
    }
    let k = (w / cw) as usize;
    let ids = (0..ch as usize)
        .flat_map(|y| (0..cw as usize).map(move |x| (y * k, x * k)))
        .map(|(y, x)| ids[y * w as usize + x]);
    Ok(LabelMap { width: cw as usize, height: ch as usize, ids: ids.collect() })
}

/// Matches the per-view masks of `per_view` over the views `names` / `cameras` of `model`
/// (`images[v]`: view v's image file, for a segmenter); returns the result, each view's blend
/// weights, the views without a mask file and the milliseconds per view (the matching, after the
/// masks are read or made).
fn match_run(
    model: &SplatModel,
    names: &[String],
    cameras: &[Camera],
    images: &[PathBuf],
    per_view: &mut PerView,
    opts: &MatchOptions,
) -> Result<(Matched, Vec<BlendWeights>, Vec<String>, f64)> {
    let mut masks = Vec::new();
    let mut missing = Vec::new();
    for ((name, cam), image) in names.iter().zip(cameras).zip(images) {
        let mask = match per_view {
            PerView::Dir(dir) => read_view(dir, name, cam)?,
            PerView::Made(segment) => Some(at_camera_size(image, (*segment)(image)?, cam)?),
        };
        masks.push(mask.unwrap_or_else(|| {
            missing.push(name.clone());
            let (w, h) = (cam.width as usize, cam.height as usize);
            LabelMap { width: w, height: h, ids: vec![0; w * h] }
        }));
    }
    if let PerView::Dir(dir) = per_view
        && missing.len() == names.len()
    {
        return Err(Error::invalid(dir, "holds no <image stem>.png of any of the run's views"));
    }
    let t0 = std::time::Instant::now();
    let weights = cameras.iter().map(|c| model.blend_weights(c)).collect::<Result<Vec<_>>>()?;
    let matched = match_masks(&weights, &masks, opts);
    let ms = t0.elapsed().as_secs_f64() * 1000.0 / names.len().max(1) as f64;
    Ok((matched, weights, missing, ms))
}

/// Writes `OUT/<stem>.png` for every view (its blend weights `weights`, the matching's) at
/// `full_size(view)` (the image's size) and `OUT/masks.json`; returns the summary.
#[allow(clippy::too_many_arguments)]
fn write(
    out: &Path,
    weights: &[BlendWeights],
    matched: &Matched,
    names: &[String],
    missing: Vec<String>,
    per_view_ms: f64,
    opts: &MatchOptions,
    surfaces: &[u16],
    full_size: impl Fn(usize) -> (u32, u32),
) -> Result<Summary> {
    model::io::create_dir(out)?;
    for (v, bw) in weights.iter().enumerate() {
        // rendered at the run's resolution (what a run trained at it reads back), scaled to the
        // image's size by nearest pixel: a run at 1/8 of a phone's photos renders 64x fewer
        // pixels
        let (w, h) = full_size(v);
        let labels = matched.shares.render(bw);
        let (cw, ch) = (bw.width, bw.height);
        let ids: Vec<u16> = (0..h as usize)
            .flat_map(|y| (0..w as usize).map(move |x| (y * ch / h as usize) * cw + x * cw / w as usize))
            .map(|p| labels.ids[p])
            .collect();
        let path: PathBuf = out.join(format!("{}.png", stem(&names[v])));
        model::images::write_ids(&path, w, h, &ids)?;
    }
    let objects = matched
        .objects
        .iter()
        .map(|o| ObjectEntry {
            id: o.id,
            gaussians: o.gaussians,
            confidence: o.confidence,
            views: o.views.iter().map(|&v| names[v].clone()).collect(),
            surface: surfaces.contains(&o.id),
        })
        .collect();
    let o = opts;
    let options = Options {
        min_weight: o.min_weight,
        mutual: o.mutual,
        min_views: o.min_views,
        min_gaussians: o.min_gaussians,
        together: o.together,
        unmasked: o.unmasked,
    };
    let summary = Summary { objects, views: names.len(), views_without_masks: missing, per_view_ms, options };
    model::io::write_json(&out.join("masks.json"), &summary)?;
    Ok(summary)
}

/// `chatsplat masks` whole: the per-view masks of `per_view` (a folder, or made from each image)
/// matched over the views of `run` (trained on the capture `data`), written to `out` at each
/// image's full size.
pub fn match_capture(
    data: &Path,
    run: &GeometryRun,
    mut per_view: PerView,
    out: &Path,
    opts: &MatchOptions,
) -> Result<Summary> {
    let (model, _) = run.load_model(&burn::tensor::Device::ndarray())?;
    let cams = run.read_cameras()?;
    let (names, cameras) = (cams.image_names(), cams.all());
    // the images' files and full sizes (what `train --masks` checks a mask against), by file
    // name; the holdout split changes nothing here (train and test views together)
    let full = model::data::load_any(data, &model::data::LoadOptions { holdout_every: 0, ..Default::default() })?;
    let by_name: std::collections::HashMap<String, (PathBuf, (u32, u32))> = full
        .train
        .iter()
        .chain(&full.test)
        .filter_map(|v| {
            let name = v.image_path.file_name()?.to_string_lossy().into_owned();
            Some((name, (v.image_path.clone(), (v.camera.width, v.camera.height))))
        })
        .collect();
    let views = names
        .iter()
        .map(|n| by_name.get(n).cloned().ok_or_else(|| Error::invalid(data, format!("has no image {n} of the run"))))
        .collect::<Result<Vec<_>>>()?;
    let images: Vec<PathBuf> = views.iter().map(|v| v.0.clone()).collect();
    let (matched, weights, missing, ms) = match_run(&model, &names, &cameras, &images, &mut per_view, opts)?;
    let surfaces = super::surface::of_matched(&model, &matched);
    write(out, &weights, &matched, &names, missing, ms, opts, &surfaces, |v| views[v].1)
}
