//! The scene's Gaussians as files for the browser, Inria `.ply` or Niantic's compressed `.spz`:
//! the whole scene for the page's renderer (which loads the smaller), the scene without the
//! objects the page hides, and one object's Gaussians to download; each Gaussian belongs to the
//! object its identity classifies it as (as `export-ply --object`).

use crate::error::ApiError;
use axum::body::Bytes;
use axum::http::StatusCode;
use model::GaussianCloud;
use model::ObjectId;
use model::chat::ChatSession;
use model::find::ObjectNames;

/// Most objects one request may hide.
pub const MAX_HIDDEN: usize = 64;

/// What the splat routes serve, made once when the server starts.
pub struct SplatFiles {
    /// Position, scale, rotation, opacity and colour (the SH bands only when the run uses them;
    /// no identity channels).
    cloud: GaussianCloud,
    /// Each Gaussian's identity class (0: background).
    classes: Vec<ObjectId>,
    /// The objects that own Gaussians, by id.
    objects: Vec<ObjectId>,
    /// The whole scene as `.ply`, and as `.spz` where the format holds it (positions within
    /// ±2048).
    pub ply: Bytes,
    pub spz: Option<Bytes>,
}

/// A splat file's format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Format {
    Ply,
    Spz,
}

impl Format {
    /// By a file name's extension: `ply` or `spz`.
    pub fn of(ext: &str) -> Option<Format> {
        match ext {
            "ply" => Some(Format::Ply),
            "spz" => Some(Format::Spz),
            _ => None,
        }
    }

    pub fn ext(self) -> &'static str {
        match self {
            Format::Ply => "ply",
            Format::Spz => "spz",
        }
    }
}

impl SplatFiles {
    pub fn of(s: &ChatSession) -> Self {
        let shown = s.scene.shown();
        let (mut cloud, _) = shown.to_cloud();
        cloud.extra.clear();
        if s.scene.sh_degree == 0 {
            cloud.sh_rest.clear();
            cloud.rest_per_gaussian = 0;
        }
        let classes = if s.scene.masks { shown.gaussian_classes() } else { vec![0; cloud.len()] };
        let mut objects: Vec<ObjectId> = classes.iter().copied().filter(|&c| c != 0).collect();
        objects.sort_unstable();
        objects.dedup();
        let ply = model::ply::encode(&cloud).into();
        let spz = model::spz::encode(&cloud).ok().map(Bytes::from);
        Self { cloud, classes, objects, ply, spz }
    }

    /// The sizes of the whole scene's files: `{"ply": bytes, "spz": bytes or null}`.
    pub fn sizes(&self) -> serde_json::Value {
        serde_json::json!({"ply": self.ply.len(), "spz": self.spz.as_ref().map(Bytes::len)})
    }

    fn encode(&self, cloud: &GaussianCloud, format: Format) -> Result<Bytes, ApiError> {
        match format {
            Format::Ply => Ok(model::ply::encode(cloud).into()),
            Format::Spz => model::spz::encode(cloud)
                .map(Bytes::from)
                .map_err(|e| ApiError::status(StatusCode::NOT_FOUND, format!("no .spz of this scene: {e}"))),
        }
    }

    /// The rows of the Gaussians not of the objects in `hidden` (each an object of the scene).
    pub fn kept(&self, hidden: &[ObjectId], field: &'static str) -> Result<Vec<usize>, ApiError> {
        if hidden.len() > MAX_HIDDEN {
            return Err(ApiError::field(field, format!("{} objects to hide; at most {MAX_HIDDEN}", hidden.len())));
        }
        if let Some(id) = hidden.iter().find(|id| !self.objects.contains(id)) {
            return Err(ApiError::field(
                field,
                format!("no object {id} in this scene (its objects: {:?})", self.objects),
            ));
        }
        Ok((0..self.classes.len()).filter(|&i| !hidden.contains(&self.classes[i])).collect())
    }

    /// The scene without the objects in `hidden`.
    pub fn without(&self, hidden: &[ObjectId], format: Format) -> Result<Bytes, ApiError> {
        match (hidden.is_empty(), format, &self.spz) {
            (true, Format::Ply, _) => Ok(self.ply.clone()),
            (true, Format::Spz, Some(spz)) => Ok(spz.clone()),
            _ => self.encode(&self.rows(&self.kept(hidden, "without")?), format),
        }
    }

    /// Object `id`'s Gaussians; 404 for an id that owns none.
    pub fn object(&self, id: ObjectId, format: Format) -> Result<Bytes, ApiError> {
        if !self.objects.contains(&id) {
            return Err(ApiError::status(
                StatusCode::NOT_FOUND,
                format!("no object {id} in this scene (its objects: {:?})", self.objects),
            ));
        }
        let keep: Vec<usize> = (0..self.classes.len()).filter(|&i| self.classes[i] == id).collect();
        self.encode(&self.rows(&keep), format)
    }

    /// `<object id>-<name>.<ext>`, as a download names it ("3-red-cone.ply").
    pub fn object_file_name(id: ObjectId, names: &ObjectNames, format: Format) -> String {
        let name: String = names
            .name(id)
            .chars()
            .map(|c| if c.is_ascii_alphanumeric() { c.to_ascii_lowercase() } else { '-' })
            .collect();
        format!("{id}-{name}.{}", format.ext())
    }

    fn rows(&self, keep: &[usize]) -> GaussianCloud {
        let mut c = self.cloud.clone();
        let mut mask = vec![false; c.len()];
        keep.iter().for_each(|&i| mask[i] = true);
        c.retain(&mask);
        c
    }
}

/// Parses `?without=3,5` (ids separated by commas; empty for none).
pub fn parse_ids(text: &str, field: &'static str) -> Result<Vec<ObjectId>, ApiError> {
    let mut ids = Vec::new();
    for part in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let id = part
            .parse::<ObjectId>()
            .map_err(|_| ApiError::field(field, format!("{part:?} is not an object id (0-{})", ObjectId::MAX)))?;
        if !ids.contains(&id) {
            ids.push(id);
        }
        if ids.len() > MAX_HIDDEN {
            return Err(ApiError::field(field, format!("more than {MAX_HIDDEN} objects")));
        }
    }
    Ok(ids)
}
