//! Teacher targets for the language field: LLaVA-OneVision's SigLIP patch features of every
//! training view and of every masked object in it, stored as f16 safetensors (one file per view,
//! written atomically, so an interrupted extraction resumes where it stopped).
//!
//! Object images (the choice ChatSplat's object loss needs, documented here): pixels whose
//! instance id is not the object's are blanked to black, the image is cropped to the object's
//! bounding box grown by `margin` of its size on each side (clamped to the image), padded to a
//! square with black (centred), and resized to the tower's 384x384 with the processor's
//! resampling. Views are the processor's base view: the whole image resized to 384x384.

use crate::data::nerfstudio::{self, LoadOptions, View};
use burn::tensor::Tensor;
use model::vlm::preprocess::RgbImage;
use model::vlm::LlavaOnevision;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Extraction settings.
#[derive(Clone, Debug)]
pub struct ExtractOptions {
    /// Bounding-box margin as a fraction of the box size, per side.
    pub margin: f32,
    /// Objects with fewer mask pixels in a view are skipped there.
    pub min_object_pixels: usize,
    /// Instance ids that are not objects (0 = background).
    pub ignore_ids: Vec<u8>,
    /// Dataset loader options (downscale etc.).
    pub load: LoadOptions,
}

impl Default for ExtractOptions {
    fn default() -> Self {
        Self { margin: 0.1, min_object_pixels: 64, ignore_ids: vec![0], load: LoadOptions::default() }
    }
}

/// What will be extracted for one view.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewPlan {
    pub index: usize,
    pub image: PathBuf,
    /// Object ids with enough pixels, ascending.
    pub objects: Vec<u8>,
}

/// The whole job.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    pub views: Vec<ViewPlan>,
    /// Bytes of f16 tokens that will be written.
    pub bytes: u64,
    pub tokens_per_image: usize,
    pub dim: usize,
}

/// Per-view file name.
pub fn view_file(index: usize) -> String {
    format!("view_{index:04}.safetensors")
}

/// Object ids present in a mask with at least `min_pixels` pixels.
pub fn objects_in(ids: &[u8], opts: &ExtractOptions) -> Vec<u8> {
    let mut count = [0usize; 256];
    for &i in ids {
        count[i as usize] += 1;
    }
    (0..=255u8).filter(|&i| count[i as usize] >= opts.min_object_pixels && !opts.ignore_ids.contains(&i)).collect()
}

pub fn plan(views: &[View], grid: usize, dim: usize, opts: &ExtractOptions) -> Plan {
    let views: Vec<ViewPlan> = views
        .iter()
        .enumerate()
        .map(|(index, v)| ViewPlan { index, image: v.image_path.clone(), objects: v.instance_ids.as_deref().map(|m| objects_in(m, opts)).unwrap_or_default() })
        .collect();
    let images: usize = views.iter().map(|v| 1 + v.objects.len()).sum();
    let tokens = grid * grid;
    Plan { bytes: (images * tokens * dim * 2) as u64, views, tokens_per_image: tokens, dim }
}

/// The masked object image (see the module docs) and its box (x0, y0, x1, y1), or `None` if absent.
pub fn object_image(img: &RgbImage, ids: &[u8], id: u8, margin: f32) -> Option<(RgbImage, [usize; 4])> {
    let w = img.width;
    let [bx0, by0, bx1, by1] = model::language::object_box(ids, img.width, img.height, id, margin)?;
    let (cw, ch) = (bx1 - bx0, by1 - by0);
    let side = cw.max(ch);
    let (ox, oy) = ((side - cw) / 2, (side - ch) / 2);
    let mut data = vec![0u8; side * side * 3];
    for y in by0..by1 {
        for x in bx0..bx1 {
            if ids[y * w + x] == id {
                let d = ((y - by0 + oy) * side + (x - bx0 + ox)) * 3;
                data[d..d + 3].copy_from_slice(&img.data[(y * w + x) * 3..(y * w + x) * 3 + 3]);
            }
        }
    }
    Some((RgbImage::new(side, side, data), [bx0, by0, bx1, by1]))
}

fn f16_bytes(t: Tensor<2>) -> Result<Vec<u8>, String> {
    let v = t.into_data().convert::<f32>().try_to_vec::<f32>().map_err(|e| format!("reading tokens: {e:?}"))?;
    Ok(v.iter().flat_map(|x| half::f16::from_f32(*x).to_le_bytes()).collect())
}

/// Whether `path` already holds a complete view file for `vp`.
fn complete(path: &Path, vp: &ViewPlan, grid: usize, dim: usize) -> bool {
    let Ok(bytes) = std::fs::read(path) else { return false };
    let Ok(st) = SafeTensors::deserialize(&bytes) else { return false };
    let want = |n: &str| st.tensor(n).map(|t| t.shape() == [grid, grid, dim] && t.dtype() == Dtype::F16).unwrap_or(false);
    want("view") && vp.objects.iter().all(|id| want(&format!("object_{id}")))
}

/// Summary of a run.
#[derive(Clone, Debug, PartialEq)]
pub struct ExtractSummary {
    pub written: usize,
    pub skipped: usize,
    pub images: usize,
}

/// Runs the vision tower over every training view of `data` (and its masked objects), writing
/// `out/view_NNNN.safetensors` and `out/teacher.json`. `on_start(plan)` sees the plan before any
/// work; `progress(done, total)` is called after each view.
pub fn extract(
    vlm: &LlavaOnevision,
    data: &Path,
    out: &Path,
    opts: &ExtractOptions,
    on_start: impl FnOnce(&Plan),
    mut progress: impl FnMut(usize, usize),
) -> Result<ExtractSummary, String> {
    let ds = nerfstudio::load(data, &opts.load)?;
    if ds.train.is_empty() {
        return Err(format!("{}: the dataset has no training views", data.display()));
    }
    let grid = vlm.cfg.vision.grid();
    let dim = vlm.cfg.vision.hidden_size;
    let plan = plan(&ds.train, grid, dim, opts);
    on_start(&plan);
    std::fs::create_dir_all(out).map_err(|e| format!("{}: cannot create: {e}", out.display()))?;
    let (mut written, mut skipped, mut images) = (0, 0, 0);
    let total = plan.views.len();
    for (vp, view) in plan.views.iter().zip(&ds.train) {
        let path = out.join(view_file(vp.index));
        if complete(&path, vp, grid, dim) {
            skipped += 1;
            progress(vp.index + 1, total);
            continue;
        }
        let [w, h] = [view.camera.width as usize, view.camera.height as usize];
        let img = RgbImage::from_f32(w, h, &view.rgb);
        let mut tensors: Vec<(String, Vec<u8>)> = vec![("view".into(), f16_bytes(vlm.teacher_tokens(&img))?)];
        let mut boxes = Vec::new();
        if let Some(ids) = &view.instance_ids {
            for &id in &vp.objects {
                let Some((obj, bbox)) = object_image(&img, ids, id, opts.margin) else { continue };
                tensors.push((format!("object_{id}"), f16_bytes(vlm.teacher_tokens(&obj))?));
                boxes.push(format!("{id}:{},{},{},{}", bbox[0], bbox[1], bbox[2], bbox[3]));
            }
        }
        images += tensors.len();
        let views: Vec<(String, TensorView)> = tensors
            .iter()
            .map(|(n, b)| (n.clone(), TensorView::new(Dtype::F16, vec![grid, grid, dim], b).expect("token tensor shape")))
            .collect();
        let mut meta = HashMap::new();
        meta.insert("image".to_string(), vp.image.display().to_string());
        meta.insert("boxes_xyxy".to_string(), boxes.join(" "));
        let tmp = path.with_extension("safetensors.tmp");
        safetensors::serialize_to_file(views, Some(meta), &tmp).map_err(|e| format!("{}: cannot write: {e}", tmp.display()))?;
        std::fs::rename(&tmp, &path).map_err(|e| format!("{}: cannot rename: {e}", path.display()))?;
        written += 1;
        progress(vp.index + 1, total);
    }
    let index = serde_json::json!({
        "teacher": vlm.dir.display().to_string(),
        "data": data.display().to_string(),
        "vision_feature_layer": vlm.cfg.vision_feature_layer,
        "grid": grid,
        "dim": dim,
        "dtype": "F16",
        "object_margin": opts.margin,
        "downscale": opts.load.downscale,
        "min_object_pixels": opts.min_object_pixels,
        "views": plan.views.iter().map(|v| serde_json::json!({
            "file": view_file(v.index),
            "image": v.image.display().to_string(),
            "objects": v.objects,
        })).collect::<Vec<_>>(),
    });
    let path = out.join("teacher.json");
    let tmp = out.join("teacher.json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(&index).unwrap()).map_err(|e| format!("{}: cannot write: {e}", tmp.display()))?;
    std::fs::rename(&tmp, &path).map_err(|e| format!("{}: cannot rename: {e}", path.display()))?;
    Ok(ExtractSummary { written, skipped, images })
}

/// Reads one stored token grid back as f32 `[grid*grid*dim]` (for training and tests).
pub fn read_tokens(path: &Path, name: &str) -> Result<(Vec<usize>, Vec<f32>), String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let st = SafeTensors::deserialize(&bytes).map_err(|e| format!("{}: not a valid safetensors file: {e}", path.display()))?;
    let t = st.tensor(name).map_err(|e| format!("{}: {name}: {e}", path.display()))?;
    if t.dtype() != Dtype::F16 {
        return Err(format!("{}: {name} has dtype {:?}, expected F16", path.display(), t.dtype()));
    }
    Ok((t.shape().to_vec(), t.data().chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect()))
}
