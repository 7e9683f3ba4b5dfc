//! What the page learns about the scene once, at load: its cameras (in the page's camera form),
//! its objects and their names, where to orbit, and its Gaussians as a `.ply` for the browser's
//! splat renderer.

use crate::camera::ViewCamera;
use glam::Vec3;
use model::ObjectId;
use model::chat::{ChatSession, DEFAULT_SCENE_VIEWS};
pub use model::find::ObjectNames;
use model::run::GeometryRun;
use serde::Serialize;

/// One view of the scene.
#[derive(Clone, Debug, Serialize)]
pub struct ViewInfo {
    pub index: usize,
    pub image: String,
    /// "train" or "test" (held out).
    pub split: &'static str,
    pub camera: ViewCamera,
}

/// An object the training views show (a synthetic scene's table is ground, not an object).
#[derive(Clone, Debug, Serialize)]
pub struct ObjectInfo {
    pub id: ObjectId,
    pub name: String,
}

/// A question a model trained on question forms knows (`model::known`).
#[derive(Clone, Debug, Serialize)]
pub struct KnownQuestion {
    /// `view`, `object` or `scene`: the chat scope it is asked in.
    pub level: String,
    pub question: String,
}

/// `GET /api/scene`.
#[derive(Clone, Debug, Serialize)]
pub struct SceneInfo {
    /// The run directory's last two path components (e.g. `demo/run`).
    pub name: String,
    pub views: Vec<ViewInfo>,
    pub objects: Vec<ObjectInfo>,
    /// The point the cameras look at (where orbiting turns around), their mean distance from
    /// it, and the world's up direction as the training cameras hold it.
    pub center: [f32; 3],
    pub radius: f32,
    /// Whether the model holds a conversation (else the page asks every question on its own and
    /// says why: `converse_note`).
    pub converses: bool,
    pub converse_note: Option<String>,
    pub up: [f32; 3],
    pub gaussians: usize,
    pub background: [f32; 3],
    /// Whether object picking works (the geometry was trained with instance masks).
    pub masks: bool,
    pub model: String,
    /// Set when the built-in tabletop model chats about a scene that is not a tabletop: the page
    /// shows it as a banner and marks every answer.
    pub model_note: Option<String>,
    /// For a model trained on question forms (the built-in one, any `train-vlm` model): each form
    /// as a question about this scene, with its level; the page offers those of the chat's scope.
    /// `None` for a model that takes any question.
    pub question_forms: Option<Vec<KnownQuestion>>,
    pub backend: String,
    pub scene_views: usize,
    pub max_new_tokens: usize,
    /// The largest image side the server renders or picks at.
    pub max_side: u32,
    /// The whole scene's splat files in bytes: `{"ply": n, "spz": n or null}` (the page loads the
    /// smaller).
    pub splat_bytes: serde_json::Value,
}

impl SceneInfo {
    /// Reads the scene's cameras and lists the objects its training views show.
    pub fn new(
        s: &ChatSession,
        run: &GeometryRun,
        names: &ObjectNames,
        model: String,
        backend: String,
        max_new_tokens: usize,
    ) -> model::Result<Self> {
        let views = s
            .cameras
            .iter()
            .enumerate()
            .map(|(index, c)| ViewInfo {
                index,
                image: s.images[index].clone(),
                split: if index < s.train_views { "train" } else { "test" },
                camera: ViewCamera::from_camera(c),
            })
            .collect();
        let train = &s.cameras[..s.train_views];
        let objects = model::find::scene_objects(s)?
            .into_iter()
            .filter(|o| names.searched(o.id))
            .map(|o| ObjectInfo { id: o.id, name: names.name(o.id) })
            .collect();
        let converses = s.vlm.converses();
        let state = run.read_state()?;
        let center = Vec3::from_array(state.extent.focus);
        let eyes: Vec<Vec3> = train.iter().map(|c| c.world_to_cam.inverse().w_axis.truncate()).collect();
        let radius = eyes.iter().map(|e| e.distance(center)).sum::<f32>() / eyes.len().max(1) as f32;
        // an OpenCV camera's up is its -y axis: minus the second row of the world-to-camera rotation
        let up: Vec3 = train.iter().map(|c| -c.world_to_cam.row(1).truncate()).sum();
        let up = if up.length() > 1e-6 { up.normalize() } else { Vec3::Y };
        Ok(Self {
            name: short_name(&run.dir),
            views,
            objects,
            center: center.to_array(),
            radius,
            converses,
            converse_note: (!converses).then(|| model::vlm::conversation::SINGLE_TURN_NOTE.to_string()),
            up: up.to_array(),
            gaussians: s.scene.shown().len(),
            background: s.scene.background,
            masks: s.scene.masks,
            model,
            model_note: s.model_note.clone(),
            question_forms: model::known::examples(&s.vlm, &names.objects()).map(|forms| {
                forms
                    .into_iter()
                    .map(|(level, question)| KnownQuestion { level: level.to_string(), question })
                    .collect()
            }),
            backend,
            scene_views: DEFAULT_SCENE_VIEWS.min(s.train_views),
            max_new_tokens,
            max_side: crate::camera::MAX_SIDE,
            splat_bytes: serde_json::Value::Null,
        })
    }
}

fn short_name(dir: &std::path::Path) -> String {
    let parts: Vec<String> =
        dir.components().rev().take(2).map(|c| c.as_os_str().to_string_lossy().into_owned()).collect();
    parts.into_iter().rev().collect::<Vec<_>>().join("/")
}
