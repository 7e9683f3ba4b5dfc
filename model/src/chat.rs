//! Chatting with a trained scene (ChatSplat, Sec. 3.6): view level (one view's tokens), object
//! level (a clicked pixel -> the rendered identity picks the object -> its masked object map ->
//! tokens) and scene level (tokens of several views in LLaVA-OneVision's multi-image layout).
//! Tokens go through the LLaVA-OneVision projector into the LLM.

use crate::error::{Error, Result};
use crate::language::FrozenEncoder;
use crate::run::{GeometryRun, LanguageRun};
use crate::scene::{LanguageScene, highlight, spread_views};
use crate::vlm::{GenerateOptions, Generation, LlavaOnevision};
use burn::tensor::{Device, Tensor};
use splat_kernels::Camera;
use std::path::Path;

/// What a question is about.
#[derive(Clone, Debug, PartialEq)]
pub enum Target {
    /// View-level chat with view `i` (training views, then held-out views).
    View(usize),
    /// Object-level chat: the object under pixel `(x, y)` of view `view`.
    Object { view: usize, x: usize, y: usize },
    /// Scene-level chat over these views.
    Scene(Vec<usize>),
}

impl std::fmt::Display for Target {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Target::View(v) => write!(f, "view {v}"),
            Target::Object { view, x, y } => write!(f, "view {view} object at ({x}, {y})"),
            Target::Scene(vs) => write!(f, "scene {vs:?}"),
        }
    }
}

/// Vision tokens for a question, and the picked object when there is one.
pub struct TargetTokens {
    /// One `[T, vision D]` token grid per image.
    pub images: Vec<Tensor<2>>,
    pub picked: Option<u8>,
}

/// Answers `question` about token grids `images` (each `[T, vision D]`, one base view each, as
/// ChatSplat feeds them), streaming text to `on_text`.
pub fn answer(
    vlm: &LlavaOnevision,
    images: &[Tensor<2>],
    question: &str,
    opts: &GenerateOptions,
    on_text: impl FnMut(&str),
) -> Result<Generation> {
    let embeds: Vec<Tensor<2>> = images.iter().map(|t| vlm.token_embeds(t.clone())).collect();
    let prompt = vlm.prompt_embeds(question, &embeds)?;
    Ok(vlm.generate(prompt, opts, on_text)?)
}

/// A loaded scene + LLaVA-OneVision, ready to answer.
pub struct ChatSession {
    pub vlm: LlavaOnevision,
    pub scene: LanguageScene,
    /// The scene's encoder, frozen for inference (its fold formed once).
    pub encoder: FrozenEncoder,
    pub language: LanguageRun,
    /// Cameras of the training views, then the held-out views.
    pub cameras: Vec<Camera>,
    /// The image file name of each view.
    pub images: Vec<String>,
    pub train_views: usize,
}

impl ChatSession {
    /// Loads geometry run `run`, its language run (`language`, default `run/language`), the
    /// run's cameras and the VLM in `vlm_dir`.
    pub fn open(run: &GeometryRun, language: Option<&Path>, vlm_dir: &Path, device: &Device) -> Result<Self> {
        let language = language.map(LanguageRun::new).unwrap_or_else(|| run.language());
        let scene = LanguageScene::load(run, &language, device)?;
        let cams = run.read_cameras()?;
        let vlm = LlavaOnevision::load(vlm_dir, device)?;
        if vlm.cfg.vision.hidden_size != scene.cfg.dim {
            return Err(Error::invalid(
                vlm_dir,
                format!(
                    "vision width {} but the language field was trained for {}",
                    vlm.cfg.vision.hidden_size, scene.cfg.dim
                ),
            ));
        }
        Ok(Self {
            vlm,
            encoder: FrozenEncoder::new(scene.field.encoder.clone()),
            scene,
            language,
            cameras: cams.all(),
            images: cams.image_names(),
            train_views: cams.train.len(),
        })
    }

    /// The camera of view `view`, or an error naming the views there are.
    pub fn camera(&self, view: usize) -> Result<&Camera> {
        self.cameras.get(view).ok_or_else(|| {
            Error::input(format!(
                "view {view} does not exist (the scene has {} views: 0..{})",
                self.cameras.len(),
                self.cameras.len()
            ))
        })
    }

    /// The default scene-level views: `k` (at least 1) spread around the training views.
    pub fn scene_views(&self, k: usize) -> Result<Vec<usize>> {
        if k == 0 {
            return Err(Error::input("scene level needs at least one view"));
        }
        Ok(spread_views(&self.cameras[..self.train_views], k))
    }

    /// View-level tokens `[T, D]` of view `view`.
    pub fn view_tokens(&self, view: usize) -> Result<Tensor<2>> {
        let map = self.scene.view_map(&self.scene.field, self.camera(view)?)?;
        Ok(self.encoder.forward_level(map, false))
    }

    /// Tokens of a target. Object level errors when the pixel shows no object.
    pub fn tokens(&self, target: &Target) -> Result<TargetTokens> {
        match target {
            Target::View(v) => Ok(TargetTokens { images: vec![self.view_tokens(*v)?], picked: None }),
            Target::Scene(vs) => {
                if vs.is_empty() {
                    return Err(Error::input("scene level needs at least one view"));
                }
                let images = vs.iter().map(|&v| self.view_tokens(v)).collect::<Result<_>>()?;
                Ok(TargetTokens { images, picked: None })
            }
            Target::Object { view, x, y } => {
                let cam = self.camera(*view)?;
                match self.scene.object_map_at(cam, *x, *y)? {
                    Some((id, map)) => {
                        Ok(TargetTokens { images: vec![self.encoder.forward_level(map, true)], picked: Some(id) })
                    }
                    None => Err(Error::input(format!(
                        "pixel ({x}, {y}) of view {view} ({}x{}) shows no object",
                        cam.width, cam.height
                    ))),
                }
            }
        }
    }

    /// Answers a question about `target`, streaming text to `on_text`; returns the generation
    /// and the picked object (object level).
    pub fn ask(
        &self,
        target: &Target,
        question: &str,
        opts: &GenerateOptions,
        on_text: impl FnMut(&str),
    ) -> Result<(Generation, Option<u8>)> {
        let t = self.tokens(target)?;
        Ok((answer(&self.vlm, &t.images, question, opts, on_text)?, t.picked))
    }

    /// Writes the rendered view as PNG, with `picked` highlighted in red when given.
    pub fn show(&self, view: usize, picked: Option<u8>, path: &Path) -> Result<()> {
        let cam = self.camera(view)?;
        let r = self.scene.render(cam)?;
        let rgb = match picked {
            Some(id) => highlight(&r.rgb, &r.ids, id),
            None => r.rgb.iter().map(|v| v.clamp(0.0, 1.0)).collect(),
        };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            crate::io::create_dir(dir)?;
        }
        crate::images::write_rgb(path, cam.width, cam.height, &rgb)
    }
}
