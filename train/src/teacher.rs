//! Teacher targets for the language field: LLaVA-OneVision's SigLIP patch features of every
//! training view and of every masked object in it, stored as f16 safetensors (one file per view,
//! written atomically, so an interrupted extraction resumes where it stopped), indexed by
//! `teacher.json` ([`TeacherIndex`]).
//!
//! Views are the processor's base view: the whole image resized to the tower's input. Object
//! images follow the one crop rule of `model::language::crop`: the object's pixels, black
//! elsewhere, the box + margin padded to a square, resized to the tower's input.
//!
//! Novel views ([`NovelViews`]): the frozen geometry rendered at cameras between the training
//! cameras ([`novel_cameras`]), its RGB and rendered identity taught like a photo and its masks.
//! They supervise the field where the capture has no photo, which is where its tokens were
//! worst (held-out views, BENCHMARKS.md).
use burn::tensor::Tensor;
use glam::{Mat3, Mat4, Quat};
use model::data::{Dataset, LoadOptions, View, load_any};
use model::error::{Error, IoContext, Result};
use model::io;
use model::language::{ObjectCrop, objects_in};
use model::rng::Rng;
use model::run::{GeometryRun, NovelSource, StoredCamera, StoredPath, TeacherDir, TeacherIndex, TeacherViewEntry};
use model::splats::{SplatModel, host};
use model::vlm::LlavaOnevision;
use model::vlm::preprocess::RgbImage;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use splat_kernels::Camera;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Novel views: `count` renders of the geometry run `run` at cameras between its training
/// cameras (seeded by `seed`), extracted after the photos.
#[derive(Clone, Debug, PartialEq)]
pub struct NovelViews {
    pub run: GeometryRun,
    pub count: usize,
    pub seed: u64,
}

/// A novel camera lies between a training camera and one of its this many nearest.
pub const NOVEL_NEIGHBOURS: usize = 2;
/// ... at a fraction of the way drawn from this range (never on either camera).
pub const NOVEL_BETWEEN: (f32, f32) = (0.25, 0.75);

/// `count` cameras between the training cameras `train` (seeded): each starts at a training
/// camera drawn at random, goes a fraction [`NOVEL_BETWEEN`] of the way to one of its
/// [`NOVEL_NEIGHBOURS`] nearest (by centre), its centre interpolated linearly and its rotation
/// spherically, with the first camera's intrinsics. Empty with fewer than two cameras.
pub fn novel_cameras(train: &[Camera], count: usize, seed: u64) -> Vec<Camera> {
    if train.len() < 2 {
        return Vec::new();
    }
    let to_world: Vec<Mat4> = train.iter().map(|c| c.world_to_cam.inverse()).collect();
    let centre = |i: usize| to_world[i].w_axis.truncate();
    let rotation = |m: &Mat4| {
        let r = Mat3::from_mat4(*m);
        (r.determinant() > 0.0).then(|| Quat::from_mat3(&r).normalize())
    };
    let mut rng = Rng::new(seed);
    (0..count)
        .map(|_| {
            let i = (rng.next_u64() % train.len() as u64) as usize;
            let mut others: Vec<usize> = (0..train.len()).filter(|&j| j != i).collect();
            let away = |j: usize| centre(j).distance_squared(centre(i));
            others.sort_by(|&a, &b| away(a).total_cmp(&away(b)));
            let j = others[(rng.next_u64() % others.len().min(NOVEL_NEIGHBOURS) as u64) as usize];
            let t = rng.range(NOVEL_BETWEEN.0, NOVEL_BETWEEN.1);
            let c = centre(i).lerp(centre(j), t);
            let to_world = match (rotation(&to_world[i]), rotation(&to_world[j])) {
                (Some(a), Some(b)) => Mat4::from_rotation_translation(a.slerp(b, t), c),
                // a pose with a reflection has no quaternion: the first camera's axes, moved
                _ => {
                    let mut m = to_world[i];
                    m.w_axis = c.extend(1.0);
                    m
                }
            };
            Camera { world_to_cam: to_world.inverse(), ..train[i] }
        })
        .collect()
}

/// A hash of a model's Gaussians (16 hex digits): novel views belong to the Gaussians that
/// rendered them.
pub fn gaussians_hash(splats: &SplatModel) -> String {
    let h = splats
        .tensors()
        .into_named()
        .into_iter()
        .fold(crate::dist::HASH_START, |h, (_, t)| crate::dist::hash_f32(h, &host(t)));
    format!("{h:016x}")
}

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
    /// Novel views rendered from a geometry run, taught after the photos (`None`: photos only).
    pub novel: Option<NovelViews>,
    /// Keep the tower's state before its last this many layers (0: the selected hidden state, as
    /// the paper): a field trained on it leaves those layers to the tower at inference.
    pub tower_tail: usize,
}

/// The tower's layers a field leaves to the tower by default ([`ExtractOptions::tower_tail`]):
/// none, as the paper. One (`--tower-tail 1`) brings ten held-out scenes' count at new poses
/// within 1.2 points of the photos (0: 6.9 under) but reads shapes worse: on the demo scene it
/// answers 88.8 % against 94.2 % at 240 language iterations (BENCHMARKS.md, issue 38 section 3).
pub const DEFAULT_TOWER_TAIL: usize = 0;

impl Default for ExtractOptions {
    fn default() -> Self {
        Self {
            margin: model::language::CROP_MARGIN,
            min_object_pixels: 64,
            ignore_ids: vec![0],
            load: LoadOptions::default(),
            shard: (0, 1),
            novel: None,
            tower_tail: DEFAULT_TOWER_TAIL,
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
    ids: Option<&[u8]>,
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

/// The novel views of one extraction: the geometry that renders them and their cameras.
struct Novel {
    splats: SplatModel,
    sh_degree: usize,
    background: [f32; 3],
    cameras: Vec<Camera>,
    source: NovelSource,
}

impl Novel {
    /// Loads `n.run` (trained on the dataset `ds` from `data`, of fingerprint `now`) and draws
    /// the cameras.
    fn open(
        n: &NovelViews,
        ds: &Dataset,
        now: &str,
        data: &Path,
        out: &TeacherDir,
        device: &burn::tensor::Device,
    ) -> Result<Self> {
        let (splats, state) = n.run.load_model(device)?;
        if !state.data.fingerprint.is_empty() && state.data.fingerprint != now {
            return Err(Error::invalid(
                &n.run.dir,
                format!(
                    "novel views: this geometry run was trained on other data than {} (fingerprint {}, the \
                     dataset's is {now}): give the run trained on it",
                    data.display(),
                    state.data.fingerprint
                ),
            ));
        }
        let train: Vec<Camera> = ds.train.iter().map(|v| v.camera).collect();
        let cameras = novel_cameras(&train, n.count, n.seed);
        if cameras.len() != n.count {
            return Err(Error::invalid(
                data,
                "novel views lie between training cameras: the capture needs at least two",
            ));
        }
        let source = NovelSource {
            run: StoredPath::new(&n.run.dir, &out.dir),
            gaussians_hash: gaussians_hash(&splats),
            count: n.count,
            seed: n.seed,
        };
        Ok(Self { splats, sh_degree: state.sh_degree, background: state.background, cameras, source })
    }

    /// Novel view `k` rendered: its image and identity classes.
    fn render(&self, k: usize) -> Result<(RgbImage, Vec<u8>)> {
        let cam = &self.cameras[k];
        let r = self.splats.render(cam, self.sh_degree, self.background)?;
        let rgb: Vec<f32> = r.rgb.iter().map(|c| c.clamp(0.0, 1.0)).collect();
        Ok((RgbImage::from_f32(cam.width as usize, cam.height as usize, &rgb), r.ids))
    }

    /// The name a novel view goes by in the index and its file.
    fn name(k: usize) -> String {
        format!("novel_{k:04}")
    }
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
        Some(n) if n.count > 0 => Some(Novel::open(n, &ds, &fingerprint, data, out, &vlm.device())?),
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
    let index = TeacherIndex {
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
        let photos = self.photos();
        if ds.train.len() != photos {
            return Err(Error::invalid(
                self.dir.index(),
                format!(
                    "{photos} teacher views of photos but the dataset {} has {} training views",
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

    /// How many of the views are the dataset's training photos (the rest are novel views).
    pub fn photos(&self) -> usize {
        self.index.views.iter().filter(|v| v.camera.is_none()).count()
    }

    /// The camera of every teacher view, in order: the dataset's training cameras, then the
    /// novel views' own.
    pub fn cameras(&self) -> Result<Vec<Camera>> {
        let ds = self.dataset()?;
        let mut photos = ds.train.iter().map(|v| v.camera);
        let mut out = Vec::with_capacity(self.index.views.len());
        for v in &self.index.views {
            match &v.camera {
                Some(c) => out.push(c.camera()),
                None => out.extend(photos.next()),
            }
        }
        Ok(out)
    }

    /// An error when the novel views were rendered from other Gaussians than `splats` (a
    /// language stage's geometry): their pictures are not of its scene.
    pub fn check_novel(&self, splats: &SplatModel, run: &GeometryRun) -> Result<()> {
        let Some(n) = &self.index.novel else { return Ok(()) };
        if gaussians_hash(splats) == n.gaussians_hash {
            return Ok(());
        }
        Err(Error::invalid(
            self.dir.index(),
            format!(
                "its {} novel views were rendered from the geometry run {} (Gaussians {}), not from the Gaussians of \
                 {}: extract again with --run {}",
                n.count,
                n.run.resolve(&self.dir.dir).display(),
                n.gaussians_hash,
                run.dir.display(),
                run.dir.display()
            ),
        ))
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

#[cfg(test)]
mod tests {
    use super::*;
    use model::data::synth::{CAMERA_DISTANCE, LOOK_AT, orbit_camera};

    /// Twelve cameras on a ring around the look-at point.
    fn ring() -> Vec<Camera> {
        (0..12)
            .map(|i| orbit_camera(i as f32 * std::f32::consts::FRAC_PI_6, 0.5, CAMERA_DISTANCE, LOOK_AT, 40.0, 32, 32))
            .collect()
    }

    fn centre(c: &Camera) -> glam::Vec3 {
        c.world_to_cam.inverse().w_axis.truncate()
    }

    #[test]
    fn novel_cameras_lie_between_neighbouring_training_cameras() {
        let train = ring();
        let spacing = centre(&train[0]).distance(centre(&train[1]));
        let novel = novel_cameras(&train, 40, 3);
        assert_eq!(novel.len(), 40);
        assert_eq!(novel, novel_cameras(&train, 40, 3), "seeded");
        assert_ne!(novel, novel_cameras(&train, 40, 4));
        for c in &novel {
            let p = centre(c);
            let nearest = train.iter().map(|t| centre(t).distance(p)).fold(f32::MAX, f32::min);
            // a quarter to three quarters of the way to one of the two nearest (at most 2 spacings)
            assert!(nearest > 0.2 * spacing && nearest < 1.01 * spacing, "{nearest} vs spacing {spacing}");
            // a rigid pose that still looks at the ring's centre (within 3 degrees)
            let r = Mat3::from_mat4(c.world_to_cam);
            assert!((r.determinant() - 1.0).abs() < 1e-4);
            let forward = r.transpose() * glam::Vec3::Z;
            let to_target = (LOOK_AT - p).normalize();
            assert!(forward.angle_between(to_target).to_degrees() < 3.0);
            assert_eq!((c.fx, c.width), (train[0].fx, train[0].width));
        }
        assert!(novel_cameras(&train[..1], 5, 0).is_empty(), "one camera has no neighbour");
    }
}
