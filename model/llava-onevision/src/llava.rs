//! `LlavaOnevisionForConditionalGeneration`: vision tower -> projector -> anyres packing with the
//! image-newline embedding -> spliced into the Qwen2 input embeddings at the `<image>` placeholders.

use super::VlmError;
use super::config::{LlavaConfig, ProcessorConfig, load_processor_config, read_llava_config};
use super::layers::{act, half_linear, init_linear, linear, load_linear, normal};
use super::preprocess::{AnyresGrid, ImagePatches, RgbImage, anyres_views, base_view, num_image_tokens};
use super::qwen2::{KvCache, Qwen2};
use super::siglip::VisionTower;
use super::tokenizer::{ChatTokenizer, Turn};
use super::weights::{HfTensors, WeightStore};
use base::Rng;
use burn::module::{Module, Param};
use burn::nn::Linear;
use burn::tensor::{Device, Tensor, TensorData};
use std::path::{Path, PathBuf};

/// The projector: linear, activation, linear.
#[derive(Module, Debug)]
pub struct Projector {
    pub l1: Linear,
    pub l2: Linear,
    #[module(skip)]
    pub act: super::config::Act,
}

impl Projector {
    /// `[..., vision D]` -> `[..., text D]`.
    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        linear(&self.l2, act(self.act, linear(&self.l1, x)))
    }
}

/// A LLaVA-OneVision model: the modules (a burn `Module`, trainable) with its config, image
/// processor settings and tokenizer.
#[derive(Module, Debug)]
pub struct LlavaOnevision {
    #[module(skip)]
    pub dir: PathBuf,
    #[module(skip)]
    pub cfg: LlavaConfig,
    #[module(skip)]
    pub processor: ProcessorConfig,
    pub vision: VisionTower,
    pub projector: Projector,
    /// `[text D]`
    pub image_newline: Param<Tensor<1>>,
    pub llm: Qwen2,
    #[module(skip)]
    pub tokenizer: ChatTokenizer,
}

impl LlavaOnevision {
    /// Loads `config.json`, the image processor config, `tokenizer.json` and the safetensors weights of `dir`.
    pub fn load(dir: &Path, device: &Device) -> Result<Self, VlmError> {
        Self::load_with(dir, device, false)
    }

    /// [`LlavaOnevision::load`], with `half`: the linear layers and embeddings held in f16 as they
    /// are read (half the memory of f32; activations, norms and attention stay f32).
    pub fn load_with(dir: &Path, device: &Device, half: bool) -> Result<Self, VlmError> {
        if !dir.is_dir() {
            return Err(VlmError::config(
                dir,
                "is not a directory (expected a Hugging Face LLaVA-OneVision model directory)",
            ));
        }
        let cfg = read_llava_config(dir)?;
        let processor = load_processor_config(dir, &cfg)?;
        let tokenizer = ChatTokenizer::load(dir, cfg.image_token_id)?;
        let w = WeightStore::open(dir, device)?.with_half(half);
        let (dv, dt) = (cfg.vision.hidden_size, cfg.text.hidden_size);
        let projector = Projector {
            l1: load_linear(&w, "multi_modal_projector.linear_1", dv, dt, cfg.projector_bias)?,
            l2: load_linear(&w, "multi_modal_projector.linear_2", dt, dt, cfg.projector_bias)?,
            act: cfg.projector_act,
        };
        Ok(Self {
            vision: VisionTower::load(&w, &cfg)?,
            projector,
            image_newline: Param::from_tensor(w.tensor("image_newline", [dt])?),
            llm: Qwen2::load(&w, &cfg.text)?,
            tokenizer,
            processor,
            cfg,
            dir: dir.to_path_buf(),
        })
    }

    /// A freshly initialised model of `cfg` (for training from scratch), reproducible from `seed`
    /// on every backend.
    pub fn init(
        cfg: LlavaConfig,
        processor: ProcessorConfig,
        tokenizer: ChatTokenizer,
        seed: u64,
        device: &Device,
    ) -> Self {
        Self::init_with(cfg, processor, tokenizer, seed, device, false)
    }

    /// [`LlavaOnevision::init`], with the decoder held in f16 layer by layer as it is drawn and
    /// the rest halved at the end when `half`: the weights of `init(..).half()` at the peak memory
    /// of the f16 model (a random 7B fits a 24 GB machine this way, 30 GB in f32 does not).
    pub fn init_with(
        cfg: LlavaConfig,
        processor: ProcessorConfig,
        tokenizer: ChatTokenizer,
        seed: u64,
        device: &Device,
        half: bool,
    ) -> Self {
        let mut rng = Rng::new(seed ^ 0x11A7_A0E1);
        let (dv, dt) = (cfg.vision.hidden_size, cfg.text.hidden_size);
        let projector = Projector {
            l1: init_linear(&mut rng, dv, dt, cfg.projector_bias, 1.0 / (dv as f32).sqrt(), device),
            l2: init_linear(&mut rng, dt, dt, cfg.projector_bias, 1.0 / (dt as f32).sqrt(), device),
            act: cfg.projector_act,
        };
        let vision = VisionTower::init(&cfg, &mut rng, device);
        let image_newline = Param::from_tensor(normal(&mut rng, [dt], 0.02, device));
        let llm = Qwen2::init_with(&cfg.text, &mut rng, device, half);
        let m = Self { vision, projector, image_newline, llm, tokenizer, processor, cfg, dir: PathBuf::new() };
        if half { m.half_outside_llm() } else { m }
    }

    /// The same model with its linear layers and embeddings held in f16 (what
    /// [`LlavaOnevision::load_with`] does while reading).
    pub fn half(self) -> Self {
        let m = self.half_outside_llm();
        Self { llm: m.llm.half(), ..m }
    }

    /// The vision tower and the projector held in f16.
    fn half_outside_llm(self) -> Self {
        let projector = Projector {
            l1: half_linear(self.projector.l1),
            l2: half_linear(self.projector.l2),
            act: self.projector.act,
        };
        Self { vision: self.vision.half(), projector, ..self }
    }

    /// Every tensor under the llava-hf checkpoint names and layouts (what the loader reads).
    pub fn export(&self) -> HfTensors {
        let mut out = HfTensors::default();
        self.vision.export(&mut out);
        out.linear("multi_modal_projector.linear_1", &self.projector.l1);
        out.linear("multi_modal_projector.linear_2", &self.projector.l2);
        out.vector("image_newline", self.image_newline.val());
        self.llm.export(&mut out);
        out
    }

    pub fn device(&self) -> Device {
        self.image_newline.val().device()
    }

    /// Pixels `[views, 3, S, S]` of preprocessed views on the device.
    pub fn pixels(&self, patches: &ImagePatches) -> Tensor<4> {
        let s = self.processor.size.0;
        Tensor::from_data(
            TensorData::new(patches.pixel_values(&self.processor), [patches.views.len(), 3, s, s]),
            &self.device(),
        )
    }

    /// The teacher features ChatSplat distils: the selected SigLIP hidden state `[B, tokens, vision D]`.
    pub fn vision_features(&self, pixels: Tensor<4>) -> Tensor<3> {
        self.vision.forward(pixels)
    }

    /// Base-view teacher tokens of an image: resized to the tower's size like the processor, `[tokens, vision D]`.
    pub fn teacher_tokens(&self, img: &RgbImage) -> Tensor<2> {
        self.teacher_tokens_before_tail(img, 0)
    }

    /// [`teacher_tokens`](Self::teacher_tokens) taken before the tower's last `tail` layers
    /// (at most [`tower_layers`](Self::tower_layers)): what a field that leaves those layers to
    /// the tower ([`tower_tail`](Self::tower_tail)) learns, `[tokens, vision D]`.
    pub fn teacher_tokens_before_tail(&self, img: &RgbImage, tail: usize) -> Tensor<2> {
        let view = base_view_unpadded(img, &self.processor);
        let f = self.vision.state_before_tail(self.pixels(&view), tail);
        let [_, t, d] = f.dims();
        f.reshape([t, d])
    }

    /// Layers of the vision tower as loaded (those up to the selected hidden state).
    pub fn tower_layers(&self) -> usize {
        self.vision.layers.len()
    }

    /// Runs the tower's last `tail` layers on tokens `[T, vision D]` taken before them (a field's
    /// tokens trained on [`teacher_tokens_before_tail`](Self::teacher_tokens_before_tail)); the
    /// identity for `tail` = 0, as the paper's field feeds the projector directly.
    pub fn tower_tail(&self, tokens: Tensor<2>, tail: usize) -> Tensor<2> {
        if tail == 0 {
            return tokens;
        }
        let [t, d] = tokens.dims();
        self.vision.tail(tokens.reshape([1, t, d]), tail).reshape([t, d])
    }

    /// Preprocesses one image for a single-image (anyres) or multi-image (base view) prompt. A
    /// model whose only anyres resolution is its base size (`image_grid_pinpoints` = one square
    /// of `image_size`) gets the base view for single images too: anyres would only repeat it.
    pub fn preprocess(&self, img: &RgbImage, multi_image: bool) -> ImagePatches {
        let base_only = self.processor.pinpoints == [self.processor.size];
        if multi_image || base_only { base_view(img, &self.processor) } else { anyres_views(img, &self.processor) }
    }

    /// Packs projected features `[views, tokens, D]` of one image into its prompt embeddings `[N, D]`.
    pub fn pack(&self, projected: Tensor<3>, patches: &ImagePatches) -> Tensor<2> {
        let [v, t, d] = projected.dims();
        let base = projected.clone().narrow(0, 0, 1).reshape([t, d]);
        let newline = self.image_newline.val().unsqueeze_dim::<2>(0);
        if !patches.anyres || v == 1 {
            return Tensor::cat(vec![base, newline], 0);
        }
        let g = self.cfg.vision.grid();
        let grid = AnyresGrid::new(&self.cfg, patches.orig_hw);
        let (ph, pw) = grid.patches;
        assert_eq!(v - 1, ph * pw, "pack: {} anyres views for a {ph}x{pw} grid", v - 1);
        // [ph, pw, g, g, D] -> [D, ph*g, pw*g]
        let map = projected.narrow(0, 1, v - 1).reshape([ph, pw, g, g, d]).permute([4, 0, 2, 1, 3]).reshape([
            d,
            ph * g,
            pw * g,
        ]);
        let (r0, c0, h, w) = grid.crop;
        let mut map = map.narrow(1, r0, h).narrow(2, c0, w);
        if let Some((nh, nw)) = grid.shrink {
            map = bilinear_resize(map, nh, nw);
        }
        let [_, h, w] = map.dims();
        let nl = self.image_newline.val().reshape([d, 1, 1]).expand([d, h, 1]);
        let map = Tensor::cat(vec![map, nl], 2).reshape([d, h * (w + 1)]).transpose();
        Tensor::cat(vec![base, map], 0)
    }

    /// Prompt embeddings `[N, text D]` of one image.
    pub fn image_embeds(&self, patches: &ImagePatches) -> Tensor<2> {
        let f = self.vision_features(self.pixels(patches));
        self.pack(self.projector.forward(f), patches)
    }

    /// Prompt embeddings `[T + 1, text D]` of vision tokens `[T, vision D]` taken as one base view
    /// (the multi-image layout: projected tokens, then `image_newline`). This is how ChatSplat's
    /// encoded tokens enter the LLM in place of the vision tower's output.
    pub fn token_embeds(&self, tokens: Tensor<2>) -> Tensor<2> {
        let [t, d] = tokens.dims();
        let p = self.projector.forward(tokens.reshape([1, t, d]));
        let dt = p.dims()[2];
        Tensor::cat(vec![p.reshape([t, dt]), self.image_newline.val().unsqueeze_dim::<2>(0)], 0)
    }

    /// Prompt input embeddings `[L, text D]` of one user turn asking `question` about images
    /// given as packed prompt embeddings (`image_embeds` of a preprocessed image, or
    /// `token_embeds` of a token grid): the chat template with one `<image>` per image, each
    /// expanded to its number of rows. The one place prompts are assembled.
    pub fn prompt_embeds(&self, question: &str, images: &[Tensor<2>]) -> Result<Tensor<2>, VlmError> {
        let counts: Vec<usize> = images.iter().map(|e| e.dims()[0]).collect();
        let ids = self.prompt_ids(question, &counts)?;
        self.embed_prompt(&ids, images)
    }

    /// Length in tokens of the prompt [`prompt_embeds`](Self::prompt_embeds) builds for `question`
    /// about images of `counts` rows each, or an error when it does not fit the model's context.
    pub fn prompt_len(&self, question: &str, counts: &[usize]) -> Result<usize, VlmError> {
        Ok(self.prompt_ids(question, counts)?.len())
    }

    fn prompt_ids(&self, question: &str, counts: &[usize]) -> Result<Vec<u32>, VlmError> {
        let ids = self.turn_ids(&[Turn::user(counts.len(), question.to_string())], counts)?;
        let max = self.cfg.text.max_positions;
        if ids.len() >= max {
            return Err(VlmError::prompt(format!(
                "the prompt is {} tokens (question {} characters, {} image(s)) but the model takes at most {max}",
                ids.len(),
                question.len(),
                counts.len()
            )));
        }
        Ok(ids)
    }

    /// The ids of `turns` in the chat template, then the assistant's prompt, each `<image>`
    /// expanded to its image's `counts` rows; not checked against the context.
    pub(crate) fn turn_ids(&self, turns: &[Turn], counts: &[usize]) -> Result<Vec<u32>, VlmError> {
        let prompt = self.tokenizer.prompt(turns, true);
        self.expand_image_tokens(&self.tokenizer.encode(&prompt)?, counts)
    }

    /// Number of `<image>` placeholders one image expands to.
    pub fn num_image_tokens(&self, patches: &ImagePatches) -> usize {
        num_image_tokens(&self.cfg, patches)
    }

    /// Input embeddings `[T, D]` of `ids`, each run of image tokens replaced by the next entry of `images`.
    pub fn embed_prompt(&self, ids: &[u32], images: &[Tensor<2>]) -> Result<Tensor<2>, VlmError> {
        let mut parts = Vec::new();
        let mut i = 0;
        let mut next_image = images.iter();
        while i < ids.len() {
            let is_img = ids[i] == self.cfg.image_token_id;
            let mut j = i;
            while j < ids.len() && (ids[j] == self.cfg.image_token_id) == is_img {
                j += 1;
            }
            if is_img {
                let mut run = j - i;
                while run > 0 {
                    let img = next_image.next().ok_or_else(|| {
                        VlmError::prompt(format!(
                            "the prompt has more image placeholders than the {} image(s) given",
                            images.len()
                        ))
                    })?;
                    let n = img.dims()[0];
                    if n > run {
                        return Err(VlmError::prompt(format!(
                            "an image needs {n} placeholder tokens but only {run} follow"
                        )));
                    }
                    parts.push(img.clone());
                    run -= n;
                }
            } else {
                parts.push(self.llm.embed(&ids[i..j]));
            }
            i = j;
        }
        if next_image.next().is_some() {
            return Err(VlmError::prompt("more images than image placeholders in the prompt"));
        }
        Ok(Tensor::cat(parts, 0))
    }

    /// Expands every `<image>` id into the number of placeholders its image takes.
    pub fn expand_image_tokens(&self, ids: &[u32], counts: &[usize]) -> Result<Vec<u32>, VlmError> {
        let mut out = Vec::with_capacity(ids.len() + counts.iter().sum::<usize>());
        let mut c = counts.iter();
        for &id in ids {
            if id == self.cfg.image_token_id {
                let n = *c.next().ok_or_else(|| {
                    VlmError::prompt(format!(
                        "the prompt has more <image> tags than the {} image(s) given",
                        counts.len()
                    ))
                })?;
                out.extend(std::iter::repeat_n(id, n));
            } else {
                out.push(id);
            }
        }
        if c.next().is_some() {
            return Err(VlmError::prompt(format!(
                "{} image(s) given but the prompt has fewer <image> tags",
                counts.len()
            )));
        }
        Ok(out)
    }

    /// Logits `[T, vocab]` of a whole prompt given as input embeddings.
    pub fn logits(&self, embeds: Tensor<2>) -> Tensor<2> {
        let mut cache = KvCache::default();
        self.llm.logits(self.llm.forward(embeds, &mut cache))
    }
}

/// The base view of one image for teacher extraction: a plain resize to the tower's input (what
/// the processor does to the base view of an anyres image).
pub fn base_view_unpadded(img: &RgbImage, cfg: &ProcessorConfig) -> ImagePatches {
    ImagePatches {
        views: vec![super::preprocess::resize(img, cfg.size.1, cfg.size.0, cfg.resample)],
        orig_hw: (img.height, img.width),
        anyres: false,
    }
}

/// torch `F.interpolate(x[None], size, mode="bilinear", align_corners=False)[0]` for `[C, H, W]`.
pub fn bilinear_resize(x: Tensor<3>, out_h: usize, out_w: usize) -> Tensor<3> {
    let [c, h, w] = x.dims();
    let device = x.device();
    // Separable: rows then columns, each a dense [out, in] interpolation matrix.
    let weights = |n_in: usize, n_out: usize| -> Tensor<2> {
        let scale = n_in as f32 / n_out as f32;
        let mut m = vec![0f32; n_out * n_in];
        for o in 0..n_out {
            let src = ((o as f32 + 0.5) * scale - 0.5).max(0.0);
            let i0 = (src.floor() as usize).min(n_in - 1);
            let i1 = if i0 < n_in - 1 { i0 + 1 } else { i0 };
            let l1 = src - i0 as f32;
            m[o * n_in + i0] += 1.0 - l1;
            m[o * n_in + i1] += l1;
        }
        Tensor::from_data(TensorData::new(m, [n_out, n_in]), &device)
    };
    let rows = weights(h, out_h); // [oh, h]
    let cols = weights(w, out_w).transpose(); // [w, ow]
    let y = rows.unsqueeze_dim::<3>(0).expand([c, out_h, h]).matmul(x); // [c, oh, w]
    y.matmul(cols.unsqueeze_dim::<3>(0).expand([c, w, out_w]))
}
