//! The files of a run, typed: where each file lives ([`GeometryRun`], [`LanguageRun`],
//! [`TeacherDir`]) and a serde struct for every state and index file. Paths inside those files are
//! stored relative to the file's directory (with the absolute path as a fallback), so a run can
//! be moved with its data, or used from any working directory.

use crate::ObjectId;
use crate::error::{Error, Result};
use crate::io;
use crate::language::{LanguageConfig, LanguageField};
use crate::splats::{SplatModel, SplatParams};
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};
use splat_kernels::Camera;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A path stored in a run file: relative to the directory of that file, plus the absolute path
/// it had when written (used when the relative one no longer exists, e.g. a run moved alone).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StoredPath {
    pub relative: PathBuf,
    pub absolute: PathBuf,
}

impl StoredPath {
    /// `to` as stored in a file of directory `base`.
    pub fn new(to: &Path, base: &Path) -> Self {
        let absolute = std::path::absolute(to).unwrap_or_else(|_| to.to_path_buf());
        Self { relative: io::relative_to(to, base), absolute }
    }

    /// The path, resolved against `base` (the directory of the file it was read from).
    pub fn resolve(&self, base: &Path) -> PathBuf {
        let rel = base.join(&self.relative);
        if rel.exists() || !self.absolute.exists() { rel } else { self.absolute.clone() }
    }
}

/// A camera as stored in `cameras.json` (OpenCV pinhole, world-to-camera row-major).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StoredCamera {
    /// The image this camera belongs to (file name in the dataset).
    pub image: String,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    pub width: u32,
    pub height: u32,
    pub near: f32,
    pub far: f32,
    /// World-to-camera, row-major 4x4.
    pub world_to_cam: [[f32; 4]; 4],
}

impl StoredCamera {
    pub fn new(image: &Path, c: &Camera) -> Self {
        let m = c.world_to_cam.to_cols_array_2d();
        Self {
            image: image.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            width: c.width,
            height: c.height,
            near: c.near,
            far: c.far,
            world_to_cam: std::array::from_fn(|r| std::array::from_fn(|k| m[k][r])),
        }
    }

    pub fn camera(&self) -> Camera {
        let m = self.world_to_cam;
        let cols: [[f32; 4]; 4] = std::array::from_fn(|k| std::array::from_fn(|r| m[r][k]));
        Camera {
            world_to_cam: glam::Mat4::from_cols_array_2d(&cols),
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            width: self.width,
            height: self.height,
            near: self.near,
            far: self.far,
        }
    }
}

/// `cameras.json` of a geometry run: the cameras of the training views, then the held-out ones.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSet {
    pub train: Vec<StoredCamera>,
    pub test: Vec<StoredCamera>,
}

impl CameraSet {
    /// Every camera: training views first, then held-out views (the view numbering of chat).
    pub fn all(&self) -> Vec<Camera> {
        self.train.iter().chain(&self.test).map(StoredCamera::camera).collect()
    }

    /// The image file name of every view, in the order of [`all`](Self::all).
    pub fn image_names(&self) -> Vec<String> {
        self.train.iter().chain(&self.test).map(|c| c.image.clone()).collect()
    }
}

/// The dataset a geometry run was trained on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataRef {
    pub dir: StoredPath,
    pub downscale: u32,
    /// The RGB the dataset's transparent pixels were composited over.
    pub background: [f32; 3],
    /// [`crate::data::Dataset::fingerprint`] of the loaded dataset (empty in older runs).
    #[serde(default)]
    pub fingerprint: String,
    /// Whether the dataset has instance masks (the identity field, and so object-level chat, is
    /// trained only then).
    #[serde(default = "yes")]
    pub masks: bool,
    /// The instance masks given with `--masks` (else the dataset's own).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mask_dir: Option<StoredPath>,
}

fn yes() -> bool {
    true
}

/// The scene bounds a geometry run uses (initialisation, learning-rate scale, densification).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Extent {
    /// Mean of the camera centres.
    pub center: [f32; 3],
    /// 1.1 x the largest camera distance from `center` (3DGS's `cameras_extent`).
    pub radius: f32,
    /// The point the cameras look at most (random initialisation is centred there).
    pub focus: [f32; 3],
}

/// `state.json` of a geometry run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GeometryState {
    pub iter: usize,
    /// burn Adam step count of each parameter that has moments.
    pub adam_time: BTreeMap<String, usize>,
    pub extent: Extent,
    pub gaussians: usize,
    /// The SH degree active at `iter` (what renders use).
    pub sh_degree: usize,
    /// RGB background of renders.
    pub background: [f32; 3],
    pub data: DataRef,
}

/// A geometry run directory (`chatsplat train --out`).
#[derive(Clone, Debug, PartialEq)]
pub struct GeometryRun {
    pub dir: PathBuf,
}

impl GeometryRun {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }
    /// Parameters, Adam moments and densification statistics.
    pub fn checkpoint(&self) -> PathBuf {
        self.dir.join("checkpoint.safetensors")
    }
    /// The `GeometryConfig` of the run.
    pub fn config(&self) -> PathBuf {
        self.dir.join("config.json")
    }
    /// [`GeometryState`].
    pub fn state(&self) -> PathBuf {
        self.dir.join("state.json")
    }
    /// [`CameraSet`].
    pub fn cameras(&self) -> PathBuf {
        self.dir.join("cameras.json")
    }
    pub fn metrics(&self) -> PathBuf {
        self.dir.join("metrics.json")
    }
    pub fn renders(&self) -> PathBuf {
        self.dir.join("renders")
    }
    pub fn point_cloud(&self) -> PathBuf {
        self.dir.join("point_cloud.ply")
    }
    pub fn classifier(&self) -> PathBuf {
        self.dir.join("classifier.json")
    }
    /// The files that make the run (what its commands read), named: no output may be written
    /// onto them ([`guard::refuse_overlap`](crate::guard::refuse_overlap)).
    pub fn own_files(&self) -> Vec<(&'static str, PathBuf)> {
        vec![
            ("the geometry run's checkpoint", self.checkpoint()),
            ("the geometry run's config.json", self.config()),
            ("the geometry run's state.json", self.state()),
            ("the geometry run's cameras.json", self.cameras()),
            ("the geometry run's metrics.json", self.metrics()),
            ("the geometry run's classifier.json", self.classifier()),
            ("the geometry run's point_cloud.ply", self.point_cloud()),
        ]
    }
    /// The default language run inside this run.
    pub fn language(&self) -> LanguageRun {
        LanguageRun::new(self.dir.join("language"))
    }

    pub fn read_state(&self) -> Result<GeometryState> {
        io::read_json(&self.state())
    }

    pub fn read_cameras(&self) -> Result<CameraSet> {
        io::read_json(&self.cameras())
    }

    /// The Gaussians of the last checkpoint (parameters only) and the run's state.
    pub fn load_model(&self, device: &Device) -> Result<(SplatModel, GeometryState)> {
        if !self.dir.is_dir() {
            return Err(Error::invalid(&self.dir, "is not a geometry run directory (run `chatsplat train` first)"));
        }
        let state = self.read_state()?;
        // a state past the run's own total does not belong to it (as a resume refuses it)
        let total = io::read_json::<serde_json::Value>(&self.config()).ok().and_then(|c| c["iters"].as_u64());
        if let Some(total) = total.filter(|t| state.iter as u64 > *t) {
            return Err(Error::invalid(
                self.state(),
                format!(
                    "iteration {} is past the {total} iterations the run's config.json asks for: the state does not \
                     belong to this run",
                    state.iter
                ),
            ));
        }
        let path = self.checkpoint();
        let (mut tensors, _) = io::read_f32(&path)?;
        let mut err = None;
        let params = SplatParams::from_fn(|name| match io::take_rank2(&mut tensors, name, &path) {
            Ok((r, c, v)) => Tensor::<2>::from_data(TensorData::new(v, [r, c]), device),
            Err(e) => {
                err.get_or_insert(e);
                Tensor::<2>::zeros([0, 0], device)
            }
        });
        if let Some(e) = err {
            return Err(e);
        }
        let model = SplatModel::from_tensors(params);
        if model.len() != state.gaussians {
            return Err(Error::invalid(
                &path,
                format!("holds {} Gaussians but {} says {}", model.len(), self.state().display(), state.gaussians),
            ));
        }
        Ok((model, state))
    }
}

/// `state.json` of a language run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LanguageState {
    pub iter: usize,
    /// burn Adam step count of each parameter that has moments.
    pub adam_time: BTreeMap<String, usize>,
    /// The teacher directory the field was trained on.
    pub teacher: StoredPath,
    /// The teacher model's directory (absolute since extraction records it so); a scene's
    /// commands chat with it when no `--vlm` is given.
    pub teacher_model: String,
    /// Object crop margin (the teacher's).
    pub margin: f32,
    /// The shapes of the field as trained (grid, width and patch resolved from the teacher).
    pub field: LanguageConfig,
}

/// A language run directory (`chatsplat train-language --out`, default `RUN/language`).
#[derive(Clone, Debug, PartialEq)]
pub struct LanguageRun {
    pub dir: PathBuf,
}

impl LanguageRun {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }
    /// The field, the encoder, their Adam moments and each Gaussian's language contribution.
    pub fn checkpoint(&self) -> PathBuf {
        self.dir.join("language.safetensors")
    }
    /// The `LanguageTrainConfig` of the run.
    pub fn config(&self) -> PathBuf {
        self.dir.join("config.json")
    }
    /// [`LanguageState`].
    pub fn state(&self) -> PathBuf {
        self.dir.join("state.json")
    }
    pub fn metrics(&self) -> PathBuf {
        self.dir.join("metrics.json")
    }
    /// [`Compaction`]: the Gaussians the language maps keep, when the run was compacted.
    pub fn compaction(&self) -> PathBuf {
        self.dir.join("compact.json")
    }
    /// The files that make the run (what its commands read), named: no output may be written
    /// onto them ([`guard::refuse_overlap`](crate::guard::refuse_overlap)).
    pub fn own_files(&self) -> Vec<(&'static str, PathBuf)> {
        vec![
            ("the language run's checkpoint", self.checkpoint()),
            ("the language run's config.json", self.config()),
            ("the language run's state.json", self.state()),
            ("the language run's metrics.json", self.metrics()),
            ("the language run's compact.json", self.compaction()),
        ]
    }
    /// The run's [`Compaction`], if it has one, checked against a geometry of `gaussians` rows.
    pub fn read_compaction(&self, gaussians: usize) -> Result<Option<Compaction>> {
        let path = self.compaction();
        if !path.is_file() {
            return Ok(None);
        }
        let c: Compaction = io::read_json(&path)?;
        if c.gaussians != gaussians {
            return Err(Error::invalid(
                &path,
                format!("was made for {} Gaussians, but the geometry has {gaussians}", c.gaussians),
            ));
        }
        if c.kept.is_empty() || c.kept.windows(2).any(|w| w[0] >= w[1]) || c.kept.last() >= Some(&gaussians) {
            return Err(Error::invalid(&path, "kept: expected ascending row indices below the Gaussian count"));
        }
        Ok(Some(c))
    }
    /// Answers and scores of `chatsplat vqa`.
    pub fn vqa(&self) -> PathBuf {
        self.dir.join("vqa.json")
    }
    /// A view with a picked object highlighted.
    pub fn picked(&self, view: usize, id: ObjectId) -> PathBuf {
        self.dir.join(format!("picked_view{view}_object{id}.png"))
    }
    /// A rendered view.
    pub fn view_png(&self, view: usize) -> PathBuf {
        self.dir.join(format!("view{view}.png"))
    }

    pub fn read_state(&self) -> Result<LanguageState> {
        io::read_json(&self.state())
    }

    /// The teacher directory this run was trained on.
    pub fn teacher(&self) -> Result<TeacherDir> {
        Ok(TeacherDir::new(self.read_state()?.teacher.resolve(&self.dir)))
    }

    /// `Some(iteration)` of the checkpoint when the run has not finished (a finished run writes
    /// `metrics.json` after its last checkpoint): stopped, killed or diverged.
    pub fn unfinished(&self) -> Result<Option<usize>> {
        if self.metrics().is_file() {
            return Ok(None);
        }
        Ok(Some(self.read_state()?.iter))
    }

    /// The trained field (parameters only) and the run's state.
    pub fn load_field(&self, device: &Device) -> Result<(LanguageField, LanguageState)> {
        if !self.dir.is_dir() {
            return Err(Error::invalid(
                &self.dir,
                "is not a language run directory (run `chatsplat train-language` first)",
            ));
        }
        let state = self.read_state()?;
        let path = self.checkpoint();
        let (mut tensors, _) = io::read_f32(&path)?;
        let mut named = Vec::new();
        for name in LanguageField::names(&state.field) {
            let (r, c, v) = io::take_rank2(&mut tensors, &name, &path)?;
            named.push((name, Tensor::<2>::from_data(TensorData::new(v, [r, c]), device)));
        }
        let field = LanguageField::from_named(named).map_err(|e| Error::invalid(&path, e.to_string()))?;
        Ok((field, state))
    }

    /// Everything of the run a scene needs, each file read once: the field and the state, with
    /// `compacted` its compaction (both checked against the `gaussians` of the geometry run
    /// `geometry`), and whether the run finished.
    pub fn open(
        &self,
        geometry: &GeometryRun,
        gaussians: usize,
        compacted: bool,
        device: &Device,
    ) -> Result<OpenedLanguage> {
        let (field, state) = self.load_field(device)?;
        if field.len() != gaussians {
            return Err(Error::invalid(
                self.checkpoint(),
                format!("{} Gaussians, but the geometry run {} has {gaussians}", field.len(), geometry.dir.display()),
            ));
        }
        let compaction = if compacted { self.read_compaction(gaussians)? } else { None };
        Ok(OpenedLanguage { field, state, compaction, finished: self.metrics().is_file() })
    }

    /// Each Gaussian's accumulated language gradient (zero: never seen by a map).
    pub fn read_contribution(&self) -> Result<Vec<f32>> {
        let path = self.checkpoint();
        let (mut tensors, _) = io::read_f32(&path)?;
        let (_, v) =
            tensors.remove("contribution").ok_or_else(|| Error::invalid(&path, "tensor contribution is missing"))?;
        Ok(v)
    }
}

/// A language run opened for a scene ([`LanguageRun::open`]).
pub struct OpenedLanguage {
    pub field: LanguageField,
    pub state: LanguageState,
    /// The Gaussians its language maps keep, when it was opened compacted and has a compaction.
    pub compaction: Option<Compaction>,
    /// Whether the run wrote its `metrics.json` (a stopped, killed or diverged run has not: its
    /// field is its last checkpoint's).
    pub finished: bool,
}

/// What compacting a language run kept (`compact.json`): the Gaussians with the largest language
/// contribution, as few as keep the training views' token L1 within `tolerance` of the whole
/// field's. Inference renders the language maps (and picks objects) from these rows only; RGB
/// stays with every Gaussian. The checkpoint keeps every row, so `--resume` trains on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Compaction {
    /// Gaussians of the geometry run.
    pub gaussians: usize,
    /// The rows kept, ascending.
    pub kept: Vec<usize>,
    /// The largest relative rise of the training views' token L1 (view + object) allowed.
    pub tolerance: f32,
    /// Training-view token L1 (view, object) of the whole field and of the rows kept.
    pub token_l1_full: (f32, f32),
    pub token_l1_kept: (f32, f32),
    /// Each fraction of the Gaussians tried, largest first: (fraction, view L1, object L1).
    pub candidates: Vec<(f64, f32, f32)>,
}

/// One training view in `teacher.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TeacherViewEntry {
    /// The token file, relative to the teacher directory.
    pub file: String,
    /// The view's image in the dataset (a novel view: its name, `novel_K`).
    pub image: String,
    /// Object ids with tokens in this view, ascending.
    pub objects: Vec<ObjectId>,
    /// A novel view's camera: its image was rendered from the frozen geometry there
    /// ([`NovelSource`]), not photographed. `None`: a training photo of the dataset.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<StoredCamera>,
    /// FNV-1a 64 of the token file's bytes as `extract` wrote it (16 hex digits; absent in
    /// indexes written before 2026-12-04): a file changed or replaced since is refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hash: Option<String>,
}

/// Where a teacher's novel views came from: renders of a geometry run at cameras between the
/// training cameras, taught as if they were photos.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NovelSource {
    /// The geometry run that rendered them.
    pub run: StoredPath,
    /// A hash of that run's Gaussians (16 hex digits): a language stage on other Gaussians refuses
    /// the novel views, whose pictures would not be its scene's.
    pub gaussians_hash: String,
    /// How many, and the seed of their cameras.
    pub count: usize,
    pub seed: u64,
}

/// `teacher.json`: the index of a teacher directory (`chatsplat extract --out`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TeacherIndex {
    /// The teacher model's directory (absolute in indexes written since 2026-12-02).
    pub teacher: String,
    /// The dataset the tokens were extracted from.
    pub data: StoredPath,
    /// [`crate::data::Dataset::fingerprint`] of that dataset as loaded (empty in older indexes).
    #[serde(default)]
    pub fingerprint: String,
    pub vision_feature_layer: i64,
    /// The tokens are the tower's state before its last `tower_tail` layers, which run on the
    /// field's tokens at inference (0, as in older indexes: the selected hidden state itself).
    #[serde(default)]
    pub tower_tail: usize,
    /// Token grid side and width.
    pub grid: usize,
    pub dim: usize,
    /// The vision tower's input side and patch size.
    pub image_size: usize,
    pub patch_size: usize,
    /// Storage type of the tokens (`F16`).
    pub dtype: String,
    pub object_margin: f32,
    pub downscale: u32,
    /// The instance masks given with `--masks` (else the dataset's own).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub masks: Option<StoredPath>,
    pub min_object_pixels: usize,
    /// Training photos first, then the novel views (entries with a camera), if any.
    pub views: Vec<TeacherViewEntry>,
    /// The source of the novel views (`None`: photos only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub novel: Option<NovelSource>,
}

/// A teacher directory: `teacher.json` and one token file per training view.
#[derive(Clone, Debug, PartialEq)]
pub struct TeacherDir {
    pub dir: PathBuf,
}

impl TeacherDir {
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }
    pub fn index(&self) -> PathBuf {
        self.dir.join("teacher.json")
    }
    /// Token file of training view `index`.
    pub fn view_file(&self, index: usize) -> PathBuf {
        self.dir.join(Self::view_file_name(index))
    }
    pub fn view_file_name(index: usize) -> String {
        format!("view_{index:04}.safetensors")
    }
    pub fn read_index(&self) -> Result<TeacherIndex> {
        if !self.index().is_file() {
            return Err(Error::invalid(self.index(), "is missing (run `chatsplat extract` first)"));
        }
        io::read_json(&self.index())
    }
}
