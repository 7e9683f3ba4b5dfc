//! Chatting with a trained scene (ChatSplat, Sec. 3.6): view level (the tokens of a view from any
//! camera), object level (a click -> the rendered identity picks the object -> its masked object
//! map -> tokens) and scene level (tokens of several views in LLaVA-OneVision's multi-image
//! layout). Tokens go through the LLaVA-OneVision projector into the LLM.
//!
//! One API serves the REPL (`chatsplat chat`), `chatsplat ask`, `chatsplat vqa` and the browser
//! viewer (`chatsplat serve`): a click is resolved once, by [`ChatSession::click`], into a
//! [`Picked`] that [`Target::Object`] carries; its tokens are computed at its first question and
//! kept for the follow-ups. A [`Conversation`] about one target keeps its earlier questions and
//! answers and their keys and values: a follow-up is a new user turn after them, and only its own
//! tokens are prefilled.

use crate::ObjectId;
use crate::error::{Error, Result};
use crate::language::FrozenEncoder;
use crate::run::{GeometryRun, LanguageRun};
use crate::scene::{LanguageScene, highlight, spread_views};
use crate::vlm::{Exchange, GenerateOptions, Generation, LlavaOnevision, PromptCache};
use burn::tensor::{Device, Tensor};
use splat_kernels::Camera;
use std::ops::ControlFlow;
use std::path::Path;
use std::sync::{Arc, OnceLock};

/// Views that scene-level chat spreads around the scene when the user does not say how many
/// (the question files' number: see [`crate::question_file::SCENE_VIEWS`]).
pub use crate::question_file::SCENE_VIEWS as DEFAULT_SCENE_VIEWS;

/// An object picked by a click in a view: resolved once (one identity render of the view) and
/// carried by [`Target::Object`]. Clones share the object's tokens once computed.
#[derive(Clone, Debug)]
pub struct Picked {
    /// The camera the object was picked in (any pose and size).
    pub camera: Camera,
    /// The object's instance id (0 is the background).
    pub id: ObjectId,
    /// The object's crop box in the view, `[x0, y0, x1, y1)` (mask box + the teacher's margin).
    pub bbox: [usize; 4],
    /// The rendered identity of the whole view, `[H * W]` row-major: the object is where it is `id`.
    pub ids: Vec<ObjectId>,
    tokens: Arc<OnceLock<Tensor<2>>>,
}

impl Picked {
    /// The object's pixels in the view (`ids == id`).
    pub fn pixels(&self) -> usize {
        self.ids.iter().filter(|&&i| i == self.id).count()
    }

    /// Whether view pixel `(x, y)` shows the object.
    pub fn covers(&self, x: usize, y: usize) -> bool {
        x < self.camera.width as usize && self.ids.get(y * self.camera.width as usize + x) == Some(&self.id)
    }
}

/// What a question is about.
#[derive(Clone, Debug)]
pub enum Target {
    /// View level: the view from this camera (a training view's or any other).
    View(Camera),
    /// Object level: a picked object.
    Object(Picked),
    /// Scene level: the views from these cameras together.
    Scene(Vec<Camera>),
}

impl Target {
    /// How many token grids (images) the target's prompt holds.
    pub fn images(&self) -> usize {
        match self {
            Target::Scene(cs) => cs.len(),
            _ => 1,
        }
    }
}

impl std::fmt::Display for Target {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Target::View(c) => write!(f, "view {}x{}", c.width, c.height),
            Target::Object(p) => write!(f, "object {}", p.id),
            Target::Scene(cs) => write!(f, "scene ({} views)", cs.len()),
        }
    }
}

/// Answers `question` about token grids `images` (each `[T, vision D]`, one base view each, as
/// ChatSplat feeds them), streaming text to `on_text`.
pub fn answer(
    vlm: &LlavaOnevision,
    images: &[Tensor<2>],
    question: &str,
    opts: &GenerateOptions,
    mut on_text: impl FnMut(&str),
) -> Result<Generation> {
    answer_until(vlm, images, question, opts, |piece| {
        if !piece.is_empty() {
            on_text(piece);
        }
        ControlFlow::Continue(())
    })
}

/// [`answer`], where `on_step` sees every decoding step (with the new text, possibly empty) and
/// stops the generation by returning `Break` (a closed connection, a stop button).
pub fn answer_until(
    vlm: &LlavaOnevision,
    images: &[Tensor<2>],
    question: &str,
    opts: &GenerateOptions,
    on_step: impl FnMut(&str) -> ControlFlow<()>,
) -> Result<Generation> {
    let embeds: Vec<Tensor<2>> = images.iter().map(|t| vlm.token_embeds(t.clone())).collect();
    let prompt = vlm.prompt_embeds(question, &embeds)?;
    Ok(vlm.generate_until(prompt, opts, on_step)?)
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
    /// Set when the built-in tabletop model answers about a scene that is not a built-in
    /// tabletop: what to tell the user (once, and beside every answer).
    pub model_note: Option<String>,
}

/// What to tell the user when the built-in tabletop model (`vlm_dir`) chats about the scene the
/// geometry `run` (of state `state`) was trained on and that scene is not a built-in tabletop
/// (its dataset holds no synthetic `scene.json`): its answers name tabletop colours and shapes
/// whatever the scene shows. `None` for another model, a tabletop, or a dataset no longer there.
pub fn builtin_model_note(run: &GeometryRun, state: &crate::run::GeometryState, vlm_dir: &Path) -> Option<String> {
    let builtin = crate::vlm::default_model_dir().ok()?;
    if crate::io::resolved(&builtin) != crate::io::resolved(vlm_dir) {
        return None;
    }
    let data = crate::io::resolved(&state.data.dir.resolve(&run.dir));
    let tabletop = crate::io::read_json::<crate::data::synth::scene::SynthScene>(&data.join("scene.json")).is_ok();
    (data.is_dir() && !tabletop).then(|| {
        format!(
            "the built-in model knows only the synthetic tabletops (their colours, shapes and question types), and \
             {} is not one: its answers are not about this scene. Give --vlm a LLaVA-OneVision folder \
             (llava-onevision-qwen2-*-ov-hf) for real captures",
            data.display()
        )
    })
}

impl ChatSession {
    /// Loads geometry run `run`, its language run (`language`, default `run/language`; a
    /// compacted one renders its language maps from the Gaussians it kept), the run's cameras and
    /// the VLM in `vlm_dir`.
    pub fn open(run: &GeometryRun, language: Option<&Path>, vlm_dir: &Path, device: &Device) -> Result<Self> {
        Self::open_as(run, language, vlm_dir, device, true)
    }

    /// [`open`](Self::open) with every Gaussian for the language maps, a compacted run's too
    /// (what benchmarks compare a compaction against).
    pub fn open_full(run: &GeometryRun, language: Option<&Path>, vlm_dir: &Path, device: &Device) -> Result<Self> {
        Self::open_as(run, language, vlm_dir, device, false)
    }

    fn open_as(
        run: &GeometryRun,
        language: Option<&Path>,
        vlm_dir: &Path,
        device: &Device,
        compact: bool,
    ) -> Result<Self> {
        let language = language.map(LanguageRun::new).unwrap_or_else(|| run.language());
        let (splats, state) = run.load_model(device)?;
        let opened = language.open(run, splats.len(), compact, device)?;
        // after the loads, which name a missing or broken run better
        if !opened.finished {
            crate::error::warn(format_args!(
                "{}: this language run stopped at iteration {} before it finished (it has no metrics.json): \
                    its field is that checkpoint's; `chatsplat train-language --resume` finishes it",
                language.dir.display(),
                opened.state.iter
            ));
        }
        let model_note = builtin_model_note(run, &state, vlm_dir);
        let scene = LanguageScene::of(splats, &state, opened);
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
        if scene.cfg.tower_tail > vlm.tower_layers() {
            return Err(Error::invalid(
                vlm_dir,
                format!(
                    "the language field in {} leaves the vision tower's last {} layers to run on its tokens, but \
                        this tower has {}: chat with the model it was taught by",
                    language.dir.display(),
                    scene.cfg.tower_tail,
                    vlm.tower_layers()
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
            model_note,
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
        if k == 0 || k > self.train_views {
            return Err(Error::input(format!(
                "scene level takes 1 to {} views (the scene's training views), not {k}",
                self.train_views
            )));
        }
        Ok(spread_views(&self.cameras[..self.train_views], k))
    }

    /// Scene level over `k` views spread around the training views.
    pub fn scene_target(&self, k: usize) -> Result<Target> {
        Ok(Target::Scene(self.scene_views(k)?.into_iter().map(|v| self.cameras[v]).collect()))
    }

    /// View-level tokens `[T, D]` of the view from `camera` (any pose and size), through the
    /// tower's last layers where the field was taught before them (`tower_tail`).
    pub fn view_tokens(&self, camera: &Camera) -> Result<Tensor<2>> {
        let map = self.scene.view_map(&self.scene.field, camera)?;
        Ok(self.scene.reader_tokens(&self.vlm, self.encoder.forward_level(map, false)))
    }

    /// The object under pixel `(x, y)` of the view from `camera`: one identity render of the
    /// view. `None` for the background; a pixel outside the view is an error, and so is a scene
    /// trained without instance masks.
    pub fn click(&self, camera: &Camera, x: usize, y: usize) -> Result<Option<Picked>> {
        let (ids, id) = self.scene.identity_at(camera, x, y)?;
        Ok(self.picked(camera, id, ids))
    }

    /// Object `id` in the view from `camera` (a selection followed to a new camera): `None` when
    /// the object is not visible there.
    pub fn select(&self, camera: &Camera, id: ObjectId) -> Result<Option<Picked>> {
        self.scene.check_masks()?;
        let ids = self.scene.splats.render_ids(camera)?;
        Ok(self.picked(camera, id, ids))
    }

    fn picked(&self, camera: &Camera, id: ObjectId, ids: Vec<ObjectId>) -> Option<Picked> {
        let bbox = self.scene.object_box(camera, &ids, id)?;
        Some(Picked { camera: *camera, id, bbox, ids, tokens: Arc::default() })
    }

    /// Object-level tokens `[T, D]` of a picked object: its masked object map (the crop's identity
    /// and object features in one render), encoded; computed once per pick and kept.
    pub fn object_tokens(&self, picked: &Picked) -> Result<Tensor<2>> {
        if let Some(t) = picked.tokens.get() {
            return Ok(t.clone());
        }
        let map = self.scene.object_map_in(&picked.camera, picked.id, picked.bbox)?;
        let tokens = || self.scene.reader_tokens(&self.vlm, self.encoder.forward_level(map, true));
        Ok(picked.tokens.get_or_init(tokens).clone())
    }

    /// The token grids of a target, one `[T, D]` per image.
    pub fn tokens(&self, target: &Target) -> Result<Vec<Tensor<2>>> {
        match target {
            Target::View(c) => Ok(vec![self.view_tokens(c)?]),
            Target::Object(p) => Ok(vec![self.object_tokens(p)?]),
            Target::Scene(cs) => {
                if cs.is_empty() {
                    return Err(Error::input("scene level needs at least one view"));
                }
                cs.iter().map(|c| self.view_tokens(c)).collect()
            }
        }
    }

    /// Prompt length in tokens of `question` about `images` token grids, or an error when the
    /// question is empty or the prompt does not fit the model's context (before any rendering).
    /// An answer length (`option`, e.g. "--max-new-tokens") within 1 and what the model's context
    /// leaves (`max_new_tokens_limit`): a longer one would drop every earlier turn of a
    /// conversation to make room.
    pub fn check_max_new_tokens(&self, option: &str, n: usize) -> Result<()> {
        let context = self.vlm.cfg.text.max_positions;
        let limit = crate::vlm::max_new_tokens_limit(context);
        if !(1..=limit).contains(&n) {
            return Err(Error::input(format!(
                "{option} {n} is outside 1..={limit}: the model's context is {context} tokens, and an answer may \
                 take at most a quarter of it ({} at most), leaving room for the images and earlier turns",
                crate::vlm::MAX_NEW_TOKENS
            )));
        }
        Ok(())
    }

    pub fn check_question(&self, question: &str, images: usize) -> Result<usize> {
        if question.trim().is_empty() {
            return Err(Error::input("the question is empty"));
        }
        Ok(self.vlm.prompt_len(question, &vec![self.scene.cfg.tokens() + 1; images])?)
    }

    /// Answers a question about `target`, streaming text to `on_text`.
    pub fn ask(
        &self,
        target: &Target,
        question: &str,
        opts: &GenerateOptions,
        mut on_text: impl FnMut(&str),
    ) -> Result<Generation> {
        self.ask_until(target, question, opts, |piece| {
            if !piece.is_empty() {
                on_text(piece);
            }
            ControlFlow::Continue(())
        })
    }

    /// [`ask`](Self::ask), stoppable at every decoding step (see [`answer_until`]): the first
    /// question of a new [`Conversation`].
    pub fn ask_until(
        &self,
        target: &Target,
        question: &str,
        opts: &GenerateOptions,
        on_step: impl FnMut(&str) -> ControlFlow<()>,
    ) -> Result<Generation> {
        let mut conversation = Conversation::new(target.clone());
        Ok(self.converse_until(&mut conversation, question, opts, on_step)?.generation)
    }

    /// Asks `question` in `conversation` (after its earlier turns), streaming text to
    /// `on_step` as [`answer_until`] does; the answer becomes one of its turns.
    pub fn converse_until(
        &self,
        conversation: &mut Conversation,
        question: &str,
        opts: &GenerateOptions,
        on_step: impl FnMut(&str) -> ControlFlow<()>,
    ) -> Result<Reply> {
        let next = self.next_turn(conversation, question, opts)?;
        self.answer_turn(conversation, next, opts, on_step)
    }

    /// The first half of [`converse_until`](Self::converse_until): the prompt of `question` in
    /// `conversation`, its oldest turns dropped where the prompt and `opts.max_new_tokens` would
    /// pass the model's context (never the images), and the target's tokens where the prompt
    /// needs them (its first question, or after a drop). An error for an empty question or one
    /// that does not fit the context by itself.
    pub fn next_turn(
        &self,
        conversation: &mut Conversation,
        question: &str,
        opts: &GenerateOptions,
    ) -> Result<NextTurn> {
        self.check_question(question, conversation.target.images())?;
        let counts = vec![self.scene.cfg.tokens() + 1; conversation.target.images()];
        let max = self.vlm.cfg.text.max_positions;
        let mut drop = 0;
        let ids = loop {
            let ids = self.vlm.conversation_ids(&conversation.earlier[drop..], question, &counts)?;
            if drop == conversation.earlier.len() || ids.len() + opts.max_new_tokens.max(1) <= max {
                break ids;
            }
            drop += 1;
        };
        conversation.earlier.drain(..drop);
        conversation.dropped += drop;
        let images = match &conversation.images {
            _ if !self.vlm.needs_images(&conversation.cache, &ids) => Vec::new(),
            Some(images) => images.clone(),
            None => {
                let tokens = self.tokens(&conversation.target)?;
                let images: Vec<Tensor<2>> = tokens.into_iter().map(|t| self.vlm.token_embeds(t)).collect();
                conversation.images.insert(images).clone()
            }
        };
        let cached_tokens = self.vlm.reusable(&conversation.cache, &ids);
        Ok(NextTurn { question: question.to_string(), ids, images, dropped: drop, cached_tokens })
    }

    /// The second half of [`converse_until`](Self::converse_until): generates the answer to
    /// `next` (from [`next_turn`](Self::next_turn) on the same conversation) and keeps the turn.
    pub fn answer_turn(
        &self,
        conversation: &mut Conversation,
        next: NextTurn,
        opts: &GenerateOptions,
        on_step: impl FnMut(&str) -> ControlFlow<()>,
    ) -> Result<Reply> {
        let g = self.vlm.generate_cached(&next.ids, &next.images, &mut conversation.cache, opts, on_step)?;
        conversation.earlier.push(Exchange { question: next.question, answer: g.text.clone() });
        Ok(Reply { generation: g, dropped: next.dropped })
    }

    /// The view from `camera` as RGB `[H * W * 3]` in [0, 1], with `picked` highlighted in red
    /// (the paper's display of a picked object) when given; `picked` must come from `camera`.
    pub fn view_image(&self, camera: &Camera, picked: Option<&Picked>) -> Result<Vec<f32>> {
        let rgb = self.scene.render_rgb(camera)?;
        Ok(match picked {
            Some(p) if 3 * p.ids.len() == rgb.len() => highlight(&rgb, &p.ids, p.id),
            Some(_) => return Err(Error::input("the picked object belongs to a view of another size")),
            None => rgb,
        })
    }

    /// Writes [`view_image`](Self::view_image) as PNG (creating the folder).
    pub fn show(&self, camera: &Camera, picked: Option<&Picked>, path: &Path) -> Result<()> {
        let rgb = self.view_image(camera, picked)?;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            crate::io::create_dir(dir)?;
        }
        crate::images::write_rgb(path, camera.width, camera.height, &rgb)
    }
}

/// A conversation about one target: its earlier questions and answers (the oldest dropped where
/// the context is full), the target's prompt embeddings once computed, and the keys and values
/// of everything said so far. A new target is a new conversation.
#[derive(Clone, Debug)]
pub struct Conversation {
    pub target: Target,
    earlier: Vec<Exchange>,
    dropped: usize,
    images: Option<Vec<Tensor<2>>>,
    cache: PromptCache,
}

impl Conversation {
    pub fn new(target: Target) -> Self {
        Self { target, earlier: Vec::new(), dropped: 0, images: None, cache: PromptCache::default() }
    }

    /// The questions and answers the next question follows (those dropped are not here).
    pub fn exchanges(&self) -> &[Exchange] {
        &self.earlier
    }

    /// Exchanges dropped so far to fit the model's context.
    pub fn dropped(&self) -> usize {
        self.dropped
    }

    /// Tokens whose keys and values are kept.
    pub fn cached_tokens(&self) -> usize {
        self.cache.len()
    }
}

/// A question's prompt in its conversation, ready to answer ([`ChatSession::next_turn`]).
pub struct NextTurn {
    question: String,
    ids: Vec<u32>,
    images: Vec<Tensor<2>>,
    /// Oldest exchanges dropped to make room for this one.
    pub dropped: usize,
    /// Leading prompt tokens the conversation's cache holds (not prefilled again).
    pub cached_tokens: usize,
}

impl NextTurn {
    /// The prompt's length in tokens.
    pub fn prompt_tokens(&self) -> usize {
        self.ids.len()
    }
}

/// An answer in a conversation.
#[derive(Clone, Debug)]
pub struct Reply {
    pub generation: Generation,
    /// Oldest exchanges dropped to make room for this one (say so to the user).
    pub dropped: usize,
}

impl Reply {
    /// What to tell the user when earlier exchanges were dropped for this answer.
    pub fn dropped_note(&self) -> Option<String> {
        (self.dropped > 0).then(|| {
            format!(
                "the oldest {} exchange(s) of this conversation were dropped to fit the model's context (the \
                 images are kept)",
                self.dropped
            )
        })
    }
}
