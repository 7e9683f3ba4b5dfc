//! SAM's prompt encoder (transformers' `SamPromptEncoder`): points and box corners as random
//! Fourier features of their position (the positional embedding shared with the image grid) plus
//! a learned embedding per kind (negative point, positive point, top-left corner, bottom-right
//! corner; "not a point" replaces a padding point), and a dense embedding: the learned "no mask"
//! vector everywhere, or a mask prompt through two stride-2 convs and a 1x1 conv.

use crate::config::{Act, SamConfig};
use crate::weights::{Conv2d, WeightStore, layer_norm, layer_norm_2d, param, param_any};
use burn::module::{Module, Param};
use burn::nn::LayerNorm;
use burn::tensor::{Device, Int, Tensor, TensorData};
use llava_onevision::VlmError;

/// Random Fourier features of positions in `[0, 1]^2` (`SamPositionalEmbedding`).
#[derive(Module, Debug)]
pub struct PositionalEmbedding {
    /// `[2, F]`: the random frequencies of x and y.
    pub positional_embedding: Param<Tensor<2>>,
}

impl PositionalEmbedding {
    /// `[sin(2π (2c - 1) G), cos(2π (2c - 1) G)]` of coordinates `c` in `[0, 1]`.
    ///
    /// # Shapes
    /// `coords` `[..., 2]` (x, y) -> `[..., 2 F]`.
    pub fn forward<const D: usize>(&self, coords: Tensor<D>) -> Tensor<D> {
        let dims = coords.dims();
        let rows: usize = dims[..D - 1].iter().product();
        let g = self.positional_embedding.val();
        let f = g.dims()[1];
        let c = (coords.reshape([rows, 2]) * 2.0 - 1.0).matmul(g) * (2.0 * std::f64::consts::PI);
        let out = Tensor::cat(vec![c.clone().sin(), c.cos()], 1);
        let mut shape = dims;
        shape[D - 1] = 2 * f;
        out.reshape(shape)
    }
}

/// The mask prompt's convs (`SamMaskEmbedding`).
#[derive(Module, Debug)]
pub struct MaskEmbedding {
    pub conv1: Conv2d,
    pub layer_norm1: LayerNorm,
    pub conv2: Conv2d,
    pub layer_norm2: LayerNorm,
    pub conv3: Conv2d,
    #[module(skip)]
    pub act: Act,
}

impl MaskEmbedding {
    /// # Shapes
    /// `masks` `[B, 1, 4 s, 4 s]` (logits) -> `[B, D, s, s]`.
    pub fn forward(&self, masks: Tensor<4>) -> Tensor<4> {
        let x = self.act.apply(layer_norm_2d(&self.layer_norm1, self.conv1.forward(masks)));
        let x = self.act.apply(layer_norm_2d(&self.layer_norm2, self.conv2.forward(x)));
        self.conv3.forward(x)
    }
}

/// A prompt for one batch of images (`SamModel`'s `input_points`, `input_labels`, `input_boxes`,
/// `input_masks`), in pixels of the `image_size` input.
#[derive(Debug, Clone, Default)]
pub struct Prompt {
    /// `[B, P, n, 2]` (x, y) and their labels `[B, P, n]`: 1 foreground, 0 background, -1 not a
    /// point, -10 padding (ignored).
    pub points: Option<(Tensor<4>, Tensor<3, Int>)>,
    /// `[B, P, 4]` (x1, y1, x2, y2): one box per point batch entry.
    pub boxes: Option<Tensor<3>>,
    /// `[B, 1, 4 s, 4 s]` mask logits.
    pub masks: Option<Tensor<4>>,
}

impl Prompt {
    /// One prompt of `points` (x, y, label) and optionally a box, for one image and one mask batch.
    pub fn single(points: &[(f32, f32, i64)], bbox: Option<[f32; 4]>, device: &Device) -> Self {
        let n = points.len();
        let points = (n > 0).then(|| {
            let xy: Vec<f32> = points.iter().flat_map(|&(x, y, _)| [x, y]).collect();
            let labels: Vec<i64> = points.iter().map(|p| p.2).collect();
            (
                Tensor::from_data(TensorData::new(xy, [1, 1, n, 2]), device),
                Tensor::from_data(TensorData::new(labels, [1, 1, n]), device),
            )
        });
        let boxes = bbox.map(|b| Tensor::from_data(TensorData::new(b.to_vec(), [1, 1, 4]), device));
        Self { points, boxes, masks: None }
    }
}

/// The prompt encoder.
#[derive(Module, Debug)]
pub struct PromptEncoder {
    /// Shared with the image-wide positional embedding (tied in transformers).
    pub shared_embedding: PositionalEmbedding,
    pub mask_embed: MaskEmbedding,
    /// `[1, D]`
    pub no_mask_embed: Param<Tensor<2>>,
    /// `[1, D]` each: negative point, positive point, box top-left, box bottom-right.
    pub point_embed: Vec<Param<Tensor<2>>>,
    /// `[1, D]`
    pub not_a_point_embed: Param<Tensor<2>>,
    /// Side of the image embedding grid.
    #[module(skip)]
    pub embedding_size: usize,
    /// Side of the input image, in pixels.
    #[module(skip)]
    pub image_size: usize,
}

const PRE: &str = "prompt_encoder";

impl PromptEncoder {
    pub fn load(w: &WeightStore, cfg: &SamConfig) -> Result<Self, VlmError> {
        let p = &cfg.prompt_encoder_config;
        let (d, m, eps) = (p.hidden_size, p.mask_input_channels, p.layer_norm_eps);
        let f = cfg.vision_config.num_pos_feats;
        let names =
            ["shared_image_embedding.positional_embedding", "prompt_encoder.shared_embedding.positional_embedding"];
        let mut point_embed = Vec::new();
        for i in 0..p.num_point_embeddings {
            point_embed.push(param(w, &format!("{PRE}.point_embed.{i}.weight"), [1, d])?);
        }
        Ok(Self {
            shared_embedding: PositionalEmbedding { positional_embedding: param_any(w, &names, [2, f])? },
            mask_embed: MaskEmbedding {
                conv1: Conv2d::load(w, &format!("{PRE}.mask_embed.conv1"), [m / 4, 1, 2], 2, 0, true)?,
                layer_norm1: layer_norm(w, &format!("{PRE}.mask_embed.layer_norm1"), m / 4, eps)?,
                conv2: Conv2d::load(w, &format!("{PRE}.mask_embed.conv2"), [m, m / 4, 2], 2, 0, true)?,
                layer_norm2: layer_norm(w, &format!("{PRE}.mask_embed.layer_norm2"), m, eps)?,
                conv3: Conv2d::load(w, &format!("{PRE}.mask_embed.conv3"), [d, m, 1], 1, 0, true)?,
                act: p.hidden_act,
            },
            no_mask_embed: param(w, &format!("{PRE}.no_mask_embed.weight"), [1, d])?,
            point_embed,
            not_a_point_embed: param(w, &format!("{PRE}.not_a_point_embed.weight"), [1, d])?,
            embedding_size: p.embedding_size(),
            image_size: p.image_size,
        })
    }

    /// The positional embedding of every cell of the image embedding grid, at the cells' centres
    /// (`SamModel.get_image_wide_positional_embeddings`).
    ///
    /// # Shapes
    /// -> `[1, D, s, s]`.
    pub fn image_positional_embeddings(&self) -> Tensor<4> {
        let s = self.embedding_size;
        let device = self.no_mask_embed.val().device();
        let coords: Vec<f32> =
            (0..s * s).flat_map(|i| [((i % s) as f32 + 0.5) / s as f32, ((i / s) as f32 + 0.5) / s as f32]).collect();
        let pe = self.shared_embedding.forward(Tensor::<3>::from_data(TensorData::new(coords, [s, s, 2]), &device));
        pe.permute([2, 0, 1]).unsqueeze_dim(0)
    }

    /// Positional embedding of pixel coordinates (x, y) of the `image_size` input.
    fn embed_coords<const D: usize>(&self, coords: Tensor<D>) -> Tensor<D> {
        self.shared_embedding.forward(coords / self.image_size as f64)
    }

    /// `base` where `mask` (`[B, P, n]`, 0 or 1) is 0, `base + e` (`pad`: `e` alone) where it is 1.
    fn where_label(base: Tensor<4>, mask: Tensor<3>, e: Tensor<2>, replace: bool) -> Tensor<4> {
        let m = mask.unsqueeze_dim::<4>(3);
        let e = e.unsqueeze_dims::<4>(&[0, 1]);
        if replace { base * (m.clone().neg() + 1.0) + m * e } else { base + m * e }
    }

    /// Point embeddings (`_embed_points`); `pad` appends a "not a point" (the prompt has no box).
    ///
    /// # Shapes
    /// `points` `[B, P, n, 2]`, `labels` `[B, P, n]` -> `[B, P, n (+1), D]`.
    pub fn embed_points(&self, points: Tensor<4>, labels: Tensor<3, Int>, pad: bool) -> Tensor<4> {
        let [b, p, _, _] = points.dims();
        let device = points.device();
        let mut points = points + 0.5; // the centre of the pixel
        let mut labels = labels;
        if pad {
            points = Tensor::cat(vec![points, Tensor::zeros([b, p, 1, 2], &device)], 2);
            labels = Tensor::cat(vec![labels, Tensor::full([b, p, 1], -1, &device)], 2);
        }
        let is = |v: i64| labels.clone().equal_elem(v).float();
        let mut e = self.embed_coords(points);
        e = Self::where_label(e, is(-1), self.not_a_point_embed.val(), true);
        e = e * (is(-10).neg() + 1.0).unsqueeze_dim::<4>(3);
        e = Self::where_label(e, is(0), self.point_embed[0].val(), false);
        Self::where_label(e, is(1), self.point_embed[1].val(), false)
    }

    /// Box corner embeddings (`_embed_boxes`).
    ///
    /// # Shapes
    /// `boxes` `[B, nb, 4]` -> `[B, nb, 2, D]`.
    pub fn embed_boxes(&self, boxes: Tensor<3>) -> Tensor<4> {
        let [b, nb, _] = boxes.dims();
        let corners = self.embed_coords((boxes + 0.5).reshape([b, nb, 2, 2]));
        let kinds = Tensor::cat(vec![self.point_embed[2].val(), self.point_embed[3].val()], 0);
        corners + kinds.unsqueeze_dims::<4>(&[0, 1])
    }

    /// The sparse (points, then box corners) and dense embeddings of `prompt`.
    ///
    /// # Shapes
    /// -> (`[B, P, n, D]` or `None` without points and boxes, `[B, D, s, s]`).
    pub fn forward(&self, prompt: &Prompt) -> (Option<Tensor<4>>, Tensor<4>) {
        let mut batch = 1;
        let mut sparse = None;
        if let Some((points, labels)) = &prompt.points {
            batch = points.dims()[0];
            sparse = Some(self.embed_points(points.clone(), labels.clone(), prompt.boxes.is_none()));
        }
        if let Some(boxes) = &prompt.boxes {
            batch = boxes.dims()[0];
            let corners = self.embed_boxes(boxes.clone());
            sparse = Some(match sparse {
                Some(points) => Tensor::cat(vec![points, corners], 2),
                None => corners,
            });
        }
        let dense = match &prompt.masks {
            Some(masks) => self.mask_embed.forward(masks.clone()),
            None => {
                let (s, d) = (self.embedding_size, self.no_mask_embed.val().dims()[1]);
                self.no_mask_embed.val().reshape([1, d, 1, 1]).expand([batch, d, s, s])
            }
        };
        (sparse, dense)
    }
}
