//! Reading a teacher directory back for training: the index, each view's object boxes and tokens.
use super::novel::gaussians_hash;
use model::ObjectId;
use model::data::{Dataset, LoadOptions, load_any};
use model::error::{Error, IoContext, Result};
use model::run::{GeometryRun, TeacherDir, TeacherIndex};
use model::splats::SplatModel;
use safetensors::{Dtype, SafeTensors};
use splat_kernels::Camera;
use std::path::{Path, PathBuf};

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
    pub id: ObjectId,
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
    /// Every file is checked against the index: one file per view, holding that view's tokens
    /// (the image its metadata names), of the index's shape, with boxes of the objects the index
    /// lists; files moved, swapped or shared between views are refused.
    pub fn open(dir: &Path) -> Result<Self> {
        let dir = TeacherDir::new(dir);
        let index = dir.read_index()?;
        let mut views = Vec::with_capacity(index.views.len());
        let mut files = std::collections::HashMap::new();
        // views whose token file the index records no hash of (indexes written before 2026-12-04,
        // or edited): read, but said once, by name, since a changed file goes unnoticed there
        let mut unhashed = Vec::new();
        for (i, v) in index.views.iter().enumerate() {
            if let Some(j) = files.insert(v.file.as_str(), i) {
                return Err(Error::invalid(
                    dir.index(),
                    format!("views {j} and {i} both point at {}: run `chatsplat extract` again", v.file),
                ));
            }
            let file = dir.dir.join(&v.file);
            let bytes = std::fs::read(&file).at(&file, "cannot read")?;
            if v.hash.is_none() {
                unhashed.push(i);
            }
            if let Some(want) = &v.hash {
                let got = content_hash(&bytes);
                if got != *want {
                    return Err(Error::invalid(
                        &file,
                        format!(
                            "its content (hash {got}) is not what `chatsplat extract` wrote for view {i} (hash \
                             {want} in {}): the file was changed or replaced; run `chatsplat extract` again",
                            dir.index().display()
                        ),
                    ));
                }
            }
            let header = read_header(&file, &bytes)?;
            if header.image.as_ref().is_some_and(|img| *img != v.image) {
                return Err(Error::invalid(
                    &file,
                    format!(
                        "holds the tokens of {}, but {} lists it for view {i} ({}): the token files were moved or \
                         swapped; run `chatsplat extract` again",
                        header.image.as_deref().unwrap_or_default(),
                        dir.index().display(),
                        v.image
                    ),
                ));
            }
            let (g, d) = (index.grid, index.dim);
            if let Some((name, shape)) = header.shapes.iter().find(|(_, s)| *s != [g, g, d]) {
                return Err(Error::invalid(
                    &file,
                    format!("{name} has shape {shape:?}, but the index says [{g}, {g}, {d}]"),
                ));
            }
            if let Some(o) = header.objects.iter().find(|o| !v.objects.contains(&o.id)) {
                return Err(Error::invalid(
                    &file,
                    format!("holds object {}, which {} does not list for view {i}", o.id, dir.index().display()),
                ));
            }
            views.push(TeacherViewInfo { file, objects: header.objects });
        }
        if let Some(first) = unhashed.first() {
            model::error::warn(format_args!(
                "{}: {} of its {} views (view {first} first) record no hash of their token files, so a file changed \
                 or replaced since `chatsplat extract` wrote it cannot be told; run `chatsplat extract` again to \
                 record them",
                dir.index().display(),
                unhashed.len(),
                index.views.len()
            ));
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
        // an object's box lies in its view
        for ((info, cam), i) in self.views.iter().zip(&out).zip(0..) {
            let (w, h) = (cam.width as usize, cam.height as usize);
            if let Some(o) = info.objects.iter().find(|o| o.bbox[2] > w || o.bbox[3] > h) {
                return Err(Error::invalid(
                    &info.file,
                    format!("object {}'s box {:?} reaches outside view {i} ({w}x{h})", o.id, o.bbox),
                ));
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
    pub fn tokens(&self, view: usize, object: Option<ObjectId>) -> Result<Vec<f32>> {
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

/// What a token file says of itself: the image it was made from, its object boxes and its
/// tensors' shapes.
struct Header {
    image: Option<String>,
    objects: Vec<TeacherObject>,
    shapes: Vec<(String, Vec<usize>)>,
}

/// The hash `teacher.json` records of a token file's bytes (FNV-1a 64, 16 hex digits).
pub fn content_hash(bytes: &[u8]) -> String {
    let mut h = model::data::Fnv::default();
    h.eat(bytes);
    h.hex()
}

fn read_header(file: &Path, bytes: &[u8]) -> Result<Header> {
    let (_, meta) = SafeTensors::read_metadata(bytes)
        .map_err(|e| Error::invalid(file, format!("not a valid safetensors file: {e}")))?;
    let text = meta.metadata().clone().unwrap_or_default();
    let boxes = text.get("boxes_xyxy").cloned().unwrap_or_default();
    let mut objects = Vec::new();
    for item in boxes.split_whitespace() {
        let bad = || Error::invalid(file, format!("malformed box \"{item}\" in boxes_xyxy"));
        let (id, rest) = item.split_once(':').ok_or_else(bad)?;
        let c: Vec<usize> = rest.split(',').map(|x| x.parse().map_err(|_| bad())).collect::<Result<_>>()?;
        if c.len() != 4 || c[2] <= c[0] || c[3] <= c[1] {
            return Err(bad());
        }
        objects.push(TeacherObject { id: id.parse().map_err(|_| bad())?, bbox: [c[0], c[1], c[2], c[3]] });
    }
    let mut shapes: Vec<(String, Vec<usize>)> =
        meta.tensors().into_iter().map(|(name, info)| (name, info.shape.clone())).collect();
    shapes.sort();
    Ok(Header { image: text.get("image").cloned(), objects, shapes })
}
