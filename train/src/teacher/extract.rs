//! Extraction: the vision tower over every view and its masked objects, one f16 file per view,
//! then the index.
use super::novel::Novel;
use super::{ExtractOptions, Plan, ViewPlan, plan};
use burn::tensor::Tensor;
use model::ObjectId;
use model::data::load_any;
use model::error::{Error, IoContext, Result};
use model::io;
use model::language::ObjectCrop;
use model::run::{StoredCamera, StoredPath, TeacherDir, TeacherIndex, TeacherViewEntry};
use model::vlm::LlavaOnevision;
use model::vlm::preprocess::RgbImage;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

fn f16_bytes(t: Tensor<2>) -> Result<Vec<u8>> {
    let v =
        t.into_data().convert::<f32>().to_vec::<f32>().map_err(|e| Error::input(format!("reading tokens: {e:?}")))?;
    Ok(v.iter().flat_map(|x| half::f16::from_f32(*x).to_le_bytes()).collect())
}

/// Whether `path` already holds a complete view file for `vp` made with these settings (a novel
/// view's: rendered from the Gaussians of hash `gaussians`).
fn complete(path: &Path, vp: &ViewPlan, grid: usize, dim: usize, margin: f32, gaussians: Option<&str>) -> bool {
    let Ok(bytes) = std::fs::read(path) else { return false };
    let Ok(st) = SafeTensors::deserialize(&bytes) else { return false };
    let Ok((_, meta)) = SafeTensors::read_metadata(&bytes) else { return false };
    let meta = meta.metadata().clone().unwrap_or_default();
    let same_margin = meta.get("margin").is_some_and(|m| *m == margin.to_string());
    let same_source = meta.get(GAUSSIANS_KEY).map(String::as_str) == gaussians;
    let want =
        |n: &str| st.tensor(n).map(|t| t.shape() == [grid, grid, dim] && t.dtype() == Dtype::F16).unwrap_or(false);
    same_margin && same_source && want("view") && vp.objects.iter().all(|id| want(&format!("object_{id}")))
}

/// A novel view file's metadata key: the hash of the Gaussians that rendered it.
const GAUSSIANS_KEY: &str = "gaussians";

/// Encodes view image `img` and its objects `vp.objects` (masked by `ids`) with the vision tower
/// and writes them to `path` atomically; returns the images encoded.
fn write_view(
    vlm: &LlavaOnevision,
    path: &Path,
    vp: &ViewPlan,
    img: &RgbImage,
    ids: Option<&[ObjectId]>,
    margin: f32,
    gaussians: Option<&str>,
    tail: usize,
) -> Result<usize> {
    let grid = vlm.cfg.vision.grid();
    let dim = vlm.cfg.vision.hidden_size;
    let (w, h) = (img.width, img.height);
    let mut tensors: Vec<(String, Vec<u8>)> =
        vec![("view".into(), f16_bytes(vlm.teacher_tokens_before_tail(img, tail))?)];
    let mut boxes = Vec::new();
    if let Some(ids) = ids {
        for &id in &vp.objects {
            let Some(crop) = ObjectCrop::of(ids, w, h, id, margin) else { continue };
            let obj = crop.masked_image(img, ids, id);
            tensors.push((format!("object_{id}"), f16_bytes(vlm.teacher_tokens_before_tail(&obj, tail))?));
            let b = crop.bbox;
            boxes.push(format!("{id}:{},{},{},{}", b[0], b[1], b[2], b[3]));
        }
    }
    let shape = vec![grid, grid, dim];
    let views = tensors
        .iter()
        .map(|(n, b)| TensorView::new(Dtype::F16, shape.clone(), b).map(|v| (n.clone(), v)))
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|e| Error::invalid(path, e.to_string()))?;
    let mut meta = HashMap::new();
    meta.insert("image".to_string(), vp.image.display().to_string());
    meta.insert("boxes_xyxy".to_string(), boxes.join(" "));
    meta.insert("margin".to_string(), margin.to_string());
    if let Some(hash) = gaussians {
        meta.insert(GAUSSIANS_KEY.to_string(), hash.to_string());
    }
    io::write_atomic_with(path, |tmp| {
        safetensors::serialize_to_file(views, Some(meta), tmp)
            .map_err(|e| Error::invalid(tmp, format!("cannot write: {e}")))
    })?;
    Ok(tensors.len())
}
/// Summary of a run.
#[derive(Clone, Debug, PartialEq)]
pub struct ExtractSummary {
    pub written: usize,
    pub skipped: usize,
    pub images: usize,
    /// Whether the index was written (every view's file is complete); a shard that finishes
    /// before the others leaves it to them.
    pub indexed: bool,
    /// Views whose files are complete, of all.
    pub views_done: usize,
    pub views: usize,
}

/// Novel views a capture may ask for, per training photo.
pub const MAX_NOVEL_PER_PHOTO: usize = 10;

/// Refuses a plan of `bytes` (less what `out` already holds) that the disk under `out` cannot
/// take; `what` names what asked for it.
fn fits_on_disk(out: &TeacherDir, bytes: u64, what: &str) -> Result<()> {
    let held: u64 = std::fs::read_dir(&out.dir)
        .map(|d| d.flatten().filter_map(|e| e.metadata().ok()).map(|m| m.len()).sum())
        .unwrap_or(0);
    let needed = bytes.saturating_sub(held);
    match model::alloc::free_disk(&out.dir) {
        Some(free) if needed > free => Err(Error::invalid(
            &out.dir,
            format!(
                "{what} need about {:.1} GB of disk here, and {:.1} GB are free: nothing was written",
                needed as f64 / 1e9,
                free as f64 / 1e9
            ),
        )),
        _ => Ok(()),
    }
}

/// Runs the vision tower over every training view of the dataset in `data` (any supported format)
/// and its masked objects, writing one token file per view and `teacher.json` into `out`.
/// Complete files made with the same settings are kept (an interrupted run resumes);
/// `teacher.json` is written last. `on_start(plan)` sees the plan before any work;
/// `progress(done, total)` is called after each view.
pub fn extract(
    vlm: &LlavaOnevision,
    data: &Path,
    out: &TeacherDir,
    opts: &ExtractOptions,
    on_start: impl FnOnce(&Plan),
    mut progress: impl FnMut(usize, usize),
) -> Result<ExtractSummary> {
    let ds = load_any(data, &opts.load)?;
    if ds.train.is_empty() {
        return Err(Error::invalid(data, "the dataset has no training views"));
    }
    if opts.tower_tail > vlm.tower_layers() {
        return Err(Error::invalid(
            &vlm.dir,
            format!(
                "tower tail {}: this vision tower has {} layers (the tail is at most that many)",
                opts.tower_tail,
                vlm.tower_layers()
            ),
        ));
    }
    let grid = vlm.cfg.vision.grid();
    let dim = vlm.cfg.vision.hidden_size;
    let mut plan = plan(&ds.train, grid, dim, opts);
    let photos = ds.train.len();
    let fingerprint = ds.fingerprint();
    let novel = match &opts.novel {
        Some(n) if n.count > 0 => {
            // bounded before any camera is drawn or view rendered: a novel view costs the disk of
            // an average photo's tokens
            let most = MAX_NOVEL_PER_PHOTO * photos;
            if n.count > most {
                return Err(Error::input(format!(
                    "--novel-views {}: at most {most} for this capture ({MAX_NOVEL_PER_PHOTO} per training photo, \
                     {photos} photos)",
                    n.count
                )));
            }
            let per_view = plan.bytes / photos as u64;
            fits_on_disk(out, plan.bytes + per_view * n.count as u64, "--novel-views")?;
            Some(Novel::open(n, &ds, &fingerprint, data, out, &vlm.device())?)
        }
        _ => None,
    };
    // novel view `k` of plan index `index`, with its geometry
    let novel_at = |index: usize| novel.as_ref().and_then(|n| index.checked_sub(photos).map(|k| (n, k)));
    if let Some(n) = &novel {
        // the objects of a novel view are those its rendered identity shows
        for k in 0..n.cameras.len() {
            let ids = n.splats.render_ids(&n.cameras[k])?;
            let objects = opts.objects(&ids);
            plan.bytes += ((1 + objects.len()) * plan.tokens_per_image * dim * 2) as u64;
            plan.views.push(ViewPlan { index: photos + k, image: PathBuf::from(Novel::name(k)), objects });
        }
    }
    let gaussians = |vp: &ViewPlan| novel_at(vp.index).map(|(n, _)| n.source.gaussians_hash.clone());
    fits_on_disk(out, plan.bytes, "the teacher tokens")?;
    on_start(&plan);
    io::create_dir(&out.dir)?;
    // tokens made from other data, another downscale or masks, or by another teacher are redone,
    // and the old index goes first: an interrupted re-run leaves no index rather than a mixed one
    // (so does one with other novel views; their files carry the hash of the Gaussians they
    // were rendered from)
    let masks = opts.load.masks.as_ref().map(|m| StoredPath::new(m, &out.dir));
    let new_novel = novel.as_ref().map(|n| n.source.clone());
    let old = out.index().is_file().then(|| out.read_index());
    let stale = match &old {
        Some(Ok(old)) => {
            old.fingerprint != fingerprint
                || old.downscale != opts.load.downscale
                || old.masks.as_ref().map(|m| m.absolute.clone()) != masks.as_ref().map(|m| m.absolute.clone())
                || old.teacher != vlm.dir.display().to_string()
                || old.tower_tail != opts.tower_tail
        }
        Some(Err(_)) => true,
        None => false,
    };
    let other_novel = matches!(&old, Some(Ok(old)) if old.novel != new_novel);
    if stale || other_novel {
        std::fs::remove_file(out.index()).map_err(|e| Error::invalid(out.index(), format!("cannot remove: {e}")))?;
    }
    let (mut written, mut skipped, mut images) = (0, 0, 0);
    let total = plan.views.len();
    let (shard, shards) = opts.shard;
    if shards == 0 || shard >= shards {
        return Err(Error::input(format!("extract shard {shard}/{shards}: the index must be below the count")));
    }
    for vp in &plan.views {
        if vp.index % shards != shard {
            continue;
        }
        let path = out.view_file(vp.index);
        let hash = gaussians(vp);
        if !stale && complete(&path, vp, grid, dim, opts.margin, hash.as_deref()) {
            skipped += 1;
            progress(vp.index + 1, total);
            continue;
        }
        let (img, ids) = match (ds.train.get(vp.index), novel_at(vp.index)) {
            (Some(view), _) => {
                let [w, h] = [view.camera.width as usize, view.camera.height as usize];
                (RgbImage::from_f32(w, h, &view.rgb), view.instance_ids.clone())
            }
            (None, Some((n, k))) => {
                let (img, ids) = n.render(k)?;
                (img, Some(ids))
            }
            (None, None) => return Err(Error::input(format!("extract: view {} is past the dataset", vp.index))),
        };
        images += write_view(vlm, &path, vp, &img, ids.as_deref(), opts.margin, hash.as_deref(), opts.tower_tail)?;
        written += 1;
        progress(vp.index + 1, total);
    }
    let mut index = TeacherIndex {
        // absolute: a scene's commands find the model from any directory
        teacher: std::path::absolute(&vlm.dir).unwrap_or_else(|_| vlm.dir.clone()).display().to_string(),
        data: StoredPath::new(data, &out.dir),
        fingerprint,
        vision_feature_layer: vlm.cfg.vision_feature_layer,
        tower_tail: opts.tower_tail,
        grid,
        dim,
        image_size: vlm.cfg.vision.image_size,
        patch_size: vlm.cfg.vision.patch_size,
        dtype: "F16".into(),
        object_margin: opts.margin,
        downscale: opts.load.downscale,
        masks,
        min_object_pixels: opts.min_object_pixels,
        views: plan
            .views
            .iter()
            .map(|v| TeacherViewEntry {
                file: TeacherDir::view_file_name(v.index),
                image: v.image.display().to_string(),
                objects: v.objects.clone(),
                camera: novel_at(v.index).map(|(n, k)| StoredCamera::new(&v.image, &n.cameras[k])),
                hash: None,
            })
            .collect(),
        novel: new_novel,
    };
    // the index only over a complete set: with shards, the last to finish writes it (through a
    // temporary file of its own: two may finish at once)
    let done = plan
        .views
        .iter()
        .filter(|vp| complete(&out.view_file(vp.index), vp, grid, dim, opts.margin, gaussians(vp).as_deref()))
        .count();
    let indexed = done == total;
    if indexed {
        // each file's content, so that a file changed or swapped later is refused
        for (entry, vp) in index.views.iter_mut().zip(&plan.views) {
            let file = out.view_file(vp.index);
            entry.hash = Some(super::read::content_hash(&std::fs::read(&file).at(&file, "cannot read")?));
        }
        let text = serde_json::to_string_pretty(&index)
            .map_err(|e| Error::invalid(out.index(), format!("cannot encode JSON: {e}")))?;
        let tmp = out.dir.join(format!("teacher.json.{}.tmp", std::process::id()));
        std::fs::write(&tmp, text).at(&tmp, "cannot write")?;
        std::fs::rename(&tmp, out.index()).at(out.index(), "cannot rename into place")?;
    }
    Ok(ExtractSummary { written, skipped, images, indexed, views_done: done, views: total })
}
