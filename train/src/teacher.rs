//! Teacher targets for the language field: LLaVA-OneVision's SigLIP patch features of every
//! training view and of every masked object in it, stored as f16 safetensors (one file per view,
//! written atomically, so an interrupted extraction resumes where it stopped), indexed by
//! `teacher.json` ([`TeacherIndex`]).
//!
//! Views are the processor's base view: the whole image resized to the tower's input. Object
//! images follow the one crop rule of `model::language::crop`: the object's pixels, black
//! elsewhere, the box + margin padded to a square, resized to the tower's input.

use burn::tensor::Tensor;
use model::data::{Dataset, LoadOptions, View, load_any};
use model::error::{Error, IoContext, Result};
use model::io;
use model::language::{ObjectCrop, objects_in};
use model::run::{StoredPath, TeacherDir, TeacherIndex, TeacherViewEntry};
use model::vlm::LlavaOnevision;
use model::vlm::preprocess::RgbImage;
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
    /// This worker's shard `(I, N)` of the views: those whose index is I modulo N (`(0, 1)`:
    /// every view). The index is written by the worker that finds every view's file complete.
    pub shard: (usize, usize),
}

impl Default for ExtractOptions {
    fn default() -> Self {
        Self {
            margin: model::language::CROP_MARGIN,
            min_object_pixels: 64,
            ignore_ids: vec![0],
            load: LoadOptions::default(),
            shard: (0, 1),
        }
    }
}

impl ExtractOptions {
    /// The objects of a view that get tokens.
    pub fn objects(&self, ids: &[u8]) -> Vec<u8> {
        objects_in(ids, self.min_object_pixels, &self.ignore_ids)
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

pub fn plan(views: &[View], grid: usize, dim: usize, opts: &ExtractOptions) -> Plan {
    let views: Vec<ViewPlan> = views
        .iter()
        .enumerate()
        .map(|(index, v)| ViewPlan {
            index,
            image: v.image_path.clone(),
            objects: v.instance_ids.as_deref().map(|m| opts.objects(m)).unwrap_or_default(),
        })
        .collect();
    let images: usize = views.iter().map(|v| 1 + v.objects.len()).sum();
    let tokens = grid * grid;
    Plan { bytes: (images * tokens * dim * 2) as u64, views, tokens_per_image: tokens, dim }
}

fn f16_bytes(t: Tensor<2>) -> Result<Vec<u8>> {
    let v =
        t.into_data().convert::<f32>().to_vec::<f32>().map_err(|e| Error::input(format!("reading tokens: {e:?}")))?;
    Ok(v.iter().flat_map(|x| half::f16::from_f32(*x).to_le_bytes()).collect())
}

/// Whether `path` already holds a complete view file for `vp` made with these settings.
fn complete(path: &Path, vp: &ViewPlan, grid: usize, dim: usize, margin: f32) -> bool {
    let Ok(bytes) = std::fs::read(path) else { return false };
    let Ok(st) = SafeTensors::deserialize(&bytes) else { return false };
    let Ok((_, meta)) = SafeTensors::read_metadata(&bytes) else { return false };
    let same_margin = meta.metadata().as_ref().and_then(|m| m.get("margin")).is_some_and(|m| *m == margin.to_string());
    let want =
        |n: &str| st.tensor(n).map(|t| t.shape() == [grid, grid, dim] && t.dtype() == Dtype::F16).unwrap_or(false);
    same_margin && want("view") && vp.objects.iter().all(|id| want(&format!("object_{id}")))
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
    let grid = vlm.cfg.vision.grid();
    let dim = vlm.cfg.vision.hidden_size;
    let plan = plan(&ds.train, grid, dim, opts);
    on_start(&plan);
    io::create_dir(&out.dir)?;
    // tokens made from other data, another downscale or masks, or by another teacher are redone,
    // and the old index goes first: an interrupted re-run leaves no index rather than a mixed one
    let fingerprint = ds.fingerprint();
    let masks = opts.load.masks.as_ref().map(|m| StoredPath::new(m, &out.dir));
    let stale = out.index().is_file()
        && match out.read_index() {
            Ok(old) => {
                old.fingerprint != fingerprint
                    || old.downscale != opts.load.downscale
                    || old.masks.as_ref().map(|m| m.absolute.clone()) != masks.as_ref().map(|m| m.absolute.clone())
                    || old.teacher != vlm.dir.display().to_string()
            }
            Err(_) => true,
        };
    if stale {
        std::fs::remove_file(out.index()).map_err(|e| Error::invalid(out.index(), format!("cannot remove: {e}")))?;
    }
    let (mut written, mut skipped, mut images) = (0, 0, 0);
    let total = plan.views.len();
    let (shard, shards) = opts.shard;
    if shards == 0 || shard >= shards {
        return Err(Error::input(format!("extract shard {shard}/{shards}: the index must be below the count")));
    }
    for (vp, view) in plan.views.iter().zip(&ds.train) {
        if vp.index % shards != shard {
            continue;
        }
        let path = out.view_file(vp.index);
        if !stale && complete(&path, vp, grid, dim, opts.margin) {
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
                let Some(crop) = ObjectCrop::of(ids, w, h, id, opts.margin) else { continue };
                let obj = crop.masked_image(&img, ids, id);
                tensors.push((format!("object_{id}"), f16_bytes(vlm.teacher_tokens(&obj))?));
                let b = crop.bbox;
                boxes.push(format!("{id}:{},{},{},{}", b[0], b[1], b[2], b[3]));
            }
        }
        images += tensors.len();
        let shape = vec![grid, grid, dim];
        let views = tensors
            .iter()
            .map(|(n, b)| TensorView::new(Dtype::F16, shape.clone(), b).map(|v| (n.clone(), v)))
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|e| Error::invalid(&path, e.to_string()))?;
        let mut meta = HashMap::new();
        meta.insert("image".to_string(), vp.image.display().to_string());
        meta.insert("boxes_xyxy".to_string(), boxes.join(" "));
        meta.insert("margin".to_string(), opts.margin.to_string());
        io::write_atomic_with(&path, |tmp| {
            safetensors::serialize_to_file(views, Some(meta), tmp)
                .map_err(|e| Error::invalid(tmp, format!("cannot write: {e}")))
        })?;
        written += 1;
        progress(vp.index + 1, total);
    }
    let index = TeacherIndex {
        teacher: vlm.dir.display().to_string(),
        data: StoredPath::new(data, &out.dir),
        fingerprint,
        vision_feature_layer: vlm.cfg.vision_feature_layer,
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
            })
            .collect(),
    };
    // the index only over a complete set: with shards, the last to finish writes it (through a
    // temporary file of its own: two may finish at once)
    let done = plan.views.iter().filter(|vp| complete(&out.view_file(vp.index), vp, grid, dim, opts.margin)).count();
    let indexed = done == total;
    if indexed {
        let text = serde_json::to_string_pretty(&index)
            .map_err(|e| Error::invalid(out.index(), format!("cannot encode JSON: {e}")))?;
        let tmp = out.dir.join(format!("teacher.json.{}.tmp", std::process::id()));
        std::fs::write(&tmp, text).at(&tmp, "cannot write")?;
        std::fs::rename(&tmp, out.index()).at(out.index(), "cannot rename into place")?;
    }
    Ok(ExtractSummary { written, skipped, images, indexed, views_done: done, views: total })
}

/// Reads one stored token grid back as f32 `[grid*grid*dim]` (for training and tests).
pub fn read_tokens(path: &Path, name: &str) -> Result<(Vec<usize>, Vec<f32>)> {
    let bytes = std::fs::read(path).at(path, "cannot read")?;
    let st = SafeTensors::deserialize(&bytes)
        .map_err(|e| Error::invalid(path, format!("not a valid safetensors file: {e}")))?;
    let t = st.tensor(name).map_err(|e| Error::invalid(path, format!("{name}: {e}")))?;
    if t.dtype() != Dtype::F16 {
        return Err(Error::invalid(path, format!("{name} has dtype {:?}, expected F16", t.dtype())));
    }
    let v: Vec<f32> = t.data().chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect();
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        return Err(Error::invalid(path, format!("{name} holds a non-finite value at flat index {i}")));
    }
    Ok((t.shape().to_vec(), v))
}

/// One object of one teacher view.
#[derive(Clone, Debug, PartialEq)]
pub struct TeacherObject {
    pub id: u8,
    /// `[x0, y0, x1, y1)` crop box in view pixels.
    pub bbox: [usize; 4],
}

/// One training view's teacher file.
#[derive(Clone, Debug, PartialEq)]
pub struct TeacherViewInfo {
    pub file: PathBuf,
    pub objects: Vec<TeacherObject>,
}

/// A teacher directory opened for training: its index and every view's object boxes.
#[derive(Clone, Debug)]
pub struct TeacherSet {
    pub dir: TeacherDir,
    pub index: TeacherIndex,
    pub views: Vec<TeacherViewInfo>,
}

impl TeacherSet {
    /// Reads `teacher.json` and every view file's object boxes.
    pub fn open(dir: &Path) -> Result<Self> {
        let dir = TeacherDir::new(dir);
        let index = dir.read_index()?;
        let mut views = Vec::with_capacity(index.views.len());
        for v in &index.views {
            let file = dir.dir.join(&v.file);
            let objects = read_boxes(&file)?;
            views.push(TeacherViewInfo { file, objects });
        }
        Ok(Self { dir, index, views })
    }

    /// The dataset directory the tokens were extracted from.
    pub fn data_dir(&self) -> PathBuf {
        self.index.data.resolve(&self.dir.dir)
    }

    /// The dataset the tokens were extracted from (same split and downscale).
    pub fn dataset(&self) -> Result<Dataset> {
        let data = self.data_dir();
        let masks = self.index.masks.as_ref().map(|m| m.resolve(&self.dir.dir));
        let ds = load_any(&data, &LoadOptions { downscale: self.index.downscale, masks, ..Default::default() })?;
        if ds.train.len() != self.views.len() {
            return Err(Error::invalid(
                self.dir.index(),
                format!(
                    "{} teacher views but the dataset {} has {} training views",
                    self.views.len(),
                    data.display(),
                    ds.train.len()
                ),
            ));
        }
        let now = ds.fingerprint();
        if !self.index.fingerprint.is_empty() && self.index.fingerprint != now {
            return Err(Error::invalid(
                self.dir.index(),
                format!(
                    "the tokens were extracted from a different version of {} (fingerprint {}, now {now}): \
                     run `chatsplat extract` again",
                    data.display(),
                    self.index.fingerprint
                ),
            ));
        }
        Ok(ds)
    }

    /// Tokens `[grid * grid * dim]` of the view (`None`) or of object `id`.
    pub fn tokens(&self, view: usize, object: Option<u8>) -> Result<Vec<f32>> {
        let name = object.map(|id| format!("object_{id}")).unwrap_or_else(|| "view".into());
        let file = &self.views[view].file;
        let (shape, v) = read_tokens(file, &name)?;
        let (g, d) = (self.index.grid, self.index.dim);
        if shape != [g, g, d] {
            return Err(Error::invalid(file, format!("{name} has shape {shape:?}, expected [{g}, {g}, {d}]")));
        }
        Ok(v)
    }
}

fn read_boxes(file: &Path) -> Result<Vec<TeacherObject>> {
    let bytes = std::fs::read(file).at(file, "cannot read")?;
    let (_, meta) = SafeTensors::read_metadata(&bytes)
        .map_err(|e| Error::invalid(file, format!("not a valid safetensors file: {e}")))?;
    let boxes = meta.metadata().as_ref().and_then(|m| m.get("boxes_xyxy").cloned()).unwrap_or_default();
    let mut out = Vec::new();
    for item in boxes.split_whitespace() {
        let bad = || Error::invalid(file, format!("malformed box \"{item}\" in boxes_xyxy"));
        let (id, rest) = item.split_once(':').ok_or_else(bad)?;
        let c: Vec<usize> = rest.split(',').map(|x| x.parse().map_err(|_| bad())).collect::<Result<_>>()?;
        if c.len() != 4 || c[2] <= c[0] || c[3] <= c[1] {
            return Err(bad());
        }
        out.push(TeacherObject { id: id.parse().map_err(|_| bad())?, bbox: [c[0], c[1], c[2], c[3]] });
    }
    Ok(out)
}
