//! Chatting with a trained scene (ChatSplat, Sec. 3.6): view level (one view's tokens), object
//! level (a clicked pixel -> the rendered identity picks the object -> its masked object map ->
//! tokens) and scene level (tokens of several views in LLaVA-OneVision's multi-image layout).
//! Tokens go through the LLaVA-OneVision projector into the LLM.

use burn::tensor::{Device, Tensor};
use model::vlm::{chat_template, GenerateOptions, Generation, LlavaOnevision, Turn};
use splat_kernels::Camera;
use std::path::{Path, PathBuf};
use train::language::{highlight, spread_views, LanguageScene, TeacherSet};

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

/// Vision tokens for a question, and the picked object when there is one.
pub struct TargetTokens {
    /// One `[T, vision D]` token grid per image.
    pub images: Vec<Tensor<2>>,
    pub picked: Option<u8>,
}

/// A loaded scene + LLaVA-OneVision, ready to answer.
pub struct ChatSession {
    pub vlm: LlavaOnevision,
    pub scene: LanguageScene,
    /// Cameras of the training views, then the held-out views.
    pub cameras: Vec<Camera>,
    pub train_views: usize,
}

/// Answers `question` about `images` (each `[T, vision D]` tokens): the chat template with one
/// `<image>` per grid, each grid projected and followed by `image_newline`.
pub fn answer(vlm: &LlavaOnevision, images: &[Tensor<2>], question: &str, opts: &GenerateOptions, on_text: impl FnMut(&str)) -> Result<Generation, String> {
    let embeds = prompt_embeds(vlm, images, question)?;
    vlm.generate(embeds, opts, on_text).map_err(|e| e.to_string())
}

/// Prompt input embeddings `[L, text D]` for `question` about token grids `images`.
pub fn prompt_embeds(vlm: &LlavaOnevision, images: &[Tensor<2>], question: &str) -> Result<Tensor<2>, String> {
    let prompt = chat_template(&[Turn::user(images.len(), question.to_string())], true);
    let embeds: Vec<Tensor<2>> = images.iter().map(|t| vlm.token_embeds(t.clone())).collect();
    let counts: Vec<usize> = embeds.iter().map(|e| e.dims()[0]).collect();
    let ids = vlm.expand_image_tokens(&vlm.tokenizer.encode(&prompt).map_err(|e| e.to_string())?, &counts).map_err(|e| e.to_string())?;
    vlm.embed_prompt(&ids, &embeds).map_err(|e| e.to_string())
}

impl ChatSession {
    /// Loads geometry run `run`, its language run (`language`, default `run/language`), the
    /// cameras of the scene the teacher was extracted from, and the VLM in `vlm_dir`.
    pub fn open(run: &Path, language: Option<&Path>, vlm_dir: &Path, device: &Device) -> Result<Self, String> {
        let lang: PathBuf = language.map(Path::to_path_buf).unwrap_or_else(|| run.join("language"));
        let scene = LanguageScene::load(run, &lang, device)?;
        let ds = TeacherSet::open(&train::language::teacher_dir(&lang)?)?.dataset()?;
        let vlm = LlavaOnevision::load(vlm_dir, device).map_err(|e| e.to_string())?;
        if vlm.cfg.vision.hidden_size != scene.cfg.dim {
            return Err(format!("{}: vision width {} but the language field was trained for {}", vlm_dir.display(), vlm.cfg.vision.hidden_size, scene.cfg.dim));
        }
        let cameras = ds.train.iter().chain(&ds.test).map(|v| v.camera).collect();
        Ok(Self { vlm, scene, cameras, train_views: ds.train.len() })
    }

    fn camera(&self, view: usize) -> Result<&Camera, String> {
        self.cameras.get(view).ok_or_else(|| format!("view {view} does not exist (the scene has {} views: 0..{})", self.cameras.len(), self.cameras.len()))
    }

    /// The default scene-level views: `k` spread around the scene.
    pub fn scene_views(&self, k: usize) -> Vec<usize> {
        spread_views(&self.cameras[..self.train_views], k)
    }

    /// Tokens of a target. Object level errors when the pixel shows no object.
    pub fn tokens(&self, target: &Target) -> Result<TargetTokens, String> {
        match target {
            Target::View(v) => Ok(TargetTokens { images: vec![self.scene.view_tokens(&self.scene.field, self.camera(*v)?)?], picked: None }),
            Target::Scene(vs) => {
                let images = vs.iter().map(|&v| self.scene.view_tokens(&self.scene.field, self.camera(v)?)).collect::<Result<_, _>>()?;
                Ok(TargetTokens { images, picked: None })
            }
            Target::Object { view, x, y } => {
                let cam = self.camera(*view)?;
                match self.scene.object_tokens_at(cam, *x, *y)? {
                    Some((id, t)) => Ok(TargetTokens { images: vec![t], picked: Some(id) }),
                    None => Err(format!("pixel ({x}, {y}) of view {view} ({}x{}) shows no object", cam.width, cam.height)),
                }
            }
        }
    }

    /// Answers a question about `target`, streaming text to `on_text`.
    pub fn ask(&self, target: &Target, question: &str, opts: &GenerateOptions, on_text: impl FnMut(&str)) -> Result<(Generation, Option<u8>), String> {
        let t = self.tokens(target)?;
        Ok((answer(&self.vlm, &t.images, question, opts, on_text)?, t.picked))
    }

    /// Writes the rendered view as PNG, with `picked` highlighted in red when given.
    pub fn show(&self, view: usize, picked: Option<u8>, path: &Path) -> Result<(), String> {
        let cam = self.camera(view)?;
        let r = self.scene.geometry.render(cam)?;
        let rgb = match picked {
            Some(id) => highlight(&r.rgb, &r.ids, id),
            None => r.rgb.iter().map(|v| v.clamp(0.0, 1.0)).collect(),
        };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|e| format!("{}: cannot create: {e}", dir.display()))?;
        }
        model::images::write_rgb(path, cam.width, cam.height, &rgb)
    }
}
