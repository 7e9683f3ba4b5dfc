//! SAM's image encoder (transformers' `SamVisionEncoder`): a ViT over `patch`-px patches with a
//! learned absolute position embedding, layers of windowed or global self-attention with
//! decomposed relative positions (MViTv2), and the neck that maps the grid to the prompt width
//! (1x1 conv, channels-first layer norm, 3x3 conv, layer norm).

use crate::config::{Act, VisionConfig};
use crate::weights::{Conv2d, WeightStore, host_matrix, layer_norm, layer_norm_2d, linear, param};
use burn::module::{Module, Param};
use burn::nn::{LayerNorm, Linear};
use burn::tensor::activation::softmax;
use burn::tensor::{Device, Tensor};
use llava_onevision::VlmError;

/// Multi-head self-attention with decomposed relative positions (`SamVisionAttention`).
#[derive(Module, Debug)]
pub struct VisionAttention {
    /// `[D, 3 D]`: q, k, v, each head-major.
    pub qkv: Linear,
    pub proj: Linear,
    /// `[2 size - 1, head_dim]` along the rows and the columns; `size` is the window (the grid for
    /// a global layer).
    pub rel_pos_h: Option<Param<Tensor<2>>>,
    pub rel_pos_w: Option<Param<Tensor<2>>>,
    #[module(skip)]
    pub heads: usize,
}

impl VisionAttention {
    /// # Shapes
    /// `x` `[N, h, w, D]` (windows or the whole grid) -> `[N, h, w, D]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let [n, h, w, d] = x.dims();
        let (heads, t) = (self.heads, h * w);
        let hd = d / heads;
        let qkv = self.qkv.forward(x).reshape([n, t, 3, heads, hd]).permute([2, 0, 3, 1, 4]);
        let part = |i: usize| qkv.clone().narrow(0, i, 1).reshape([n * heads, t, hd]);
        let (q, k, v) = (part(0), part(1), part(2));
        let scale = (hd as f64).powf(-0.5);
        let mut scores = (q.clone() * scale).matmul(k.swap_dims(1, 2));
        if let (Some(rh), Some(rw)) = (&self.rel_pos_h, &self.rel_pos_w) {
            scores = scores + decomposed_rel_pos(q, rh.val(), rw.val(), (h, w), (h, w));
        }
        let out = softmax(scores, 2).matmul(v);
        let out = out.reshape([n, heads, h, w, hd]).permute([0, 2, 3, 1, 4]).reshape([n, h, w, d]);
        self.proj.forward(out)
    }
}

/// The weights `[q k, L]` that take a relative-position table of `len` rows to the `[q, k]`
/// table of rows `get_rel_pos(q, k)` reads: the table linearly interpolated to `2 max(q, k) - 1`
/// rows (torch's `F.interpolate(mode="linear", align_corners=False)`; the identity when the sizes
/// agree), then row `q_i - k_j + (k - 1)` of it, the coordinates of the shorter side stretched
/// (as transformers does, in f32 and truncated).
pub fn rel_pos_weights(q_size: usize, k_size: usize, len: usize) -> Vec<f32> {
    let max_rel = 2 * q_size.max(k_size) - 1;
    let scale = len as f32 / max_rel as f32;
    // output row m of the resized table = l0 row i0 + l1 row i1 of the stored one
    let resized: Vec<(usize, f32, usize, f32)> = (0..max_rel)
        .map(|m| {
            let src = (scale * (m as f32 + 0.5) - 0.5).max(0.0);
            let i0 = (src.floor() as usize).min(len - 1);
            let l1 = (src - i0 as f32).clamp(0.0, 1.0);
            let i1 = if i0 < len - 1 { i0 + 1 } else { i0 };
            (i0, 1.0 - l1, i1, l1)
        })
        .collect();
    let (qf, kf) = (q_size as f64, k_size as f64);
    let (q_scale, k_scale) = ((kf / qf).max(1.0) as f32, (qf / kf).max(1.0) as f32);
    let offset = ((kf - 1.0) * (qf / kf).max(1.0)) as f32;
    let mut out = vec![0f32; q_size * k_size * len];
    for i in 0..q_size {
        for j in 0..k_size {
            let coord = (i as f32 * q_scale - j as f32 * k_scale) + offset;
            let (i0, l0, i1, l1) = resized[(coord as i64).clamp(0, max_rel as i64 - 1) as usize];
            let row = &mut out[(i * k_size + j) * len..][..len];
            row[i0] += l0;
            row[i1] += l1;
        }
    }
    out
}

/// transformers' `get_rel_pos`: the relative-position embeddings of every (query, key) pair.
///
/// # Shapes
/// `rel_pos` `[L, C]` -> `[q_size, k_size, C]`.
pub fn rel_pos_table(q_size: usize, k_size: usize, rel_pos: Tensor<2>) -> Tensor<3> {
    let [len, c] = rel_pos.dims();
    let weights = host_matrix(rel_pos_weights(q_size, k_size, len), q_size * k_size, len, &rel_pos.device());
    weights.matmul(rel_pos).reshape([q_size, k_size, c])
}

/// The additive attention bias of decomposed relative positions: `q · Rh[qy, ky] + q · Rw[qx, kx]`.
///
/// # Shapes
/// `q` `[B, qh qw, C]`, `rel_pos_h` `[Lh, C]`, `rel_pos_w` `[Lw, C]` -> `[B, qh qw, kh kw]`.
pub fn decomposed_rel_pos(
    q: Tensor<3>,
    rel_pos_h: Tensor<2>,
    rel_pos_w: Tensor<2>,
    (qh, qw): (usize, usize),
    (kh, kw): (usize, usize),
) -> Tensor<3> {
    let [b, _, c] = q.dims();
    let rh = rel_pos_table(qh, kh, rel_pos_h); // [qh, kh, C]
    let rw = rel_pos_table(qw, kw, rel_pos_w); // [qw, kw, C]
    let q = q.reshape([b, qh, qw, c]);
    // rel_h[b, y, x, ky] = sum_c q[b, y, x, c] rh[y, ky, c]: one product per query row y
    let by_row = q.clone().permute([1, 0, 2, 3]).reshape([qh, b * qw, c]);
    let rel_h = by_row.matmul(rh.swap_dims(1, 2)).reshape([qh, b, qw, kh]).permute([1, 0, 2, 3]);
    // rel_w[b, y, x, kx] = sum_c q[b, y, x, c] rw[x, kx, c]: one product per query column x
    let by_col = q.permute([2, 0, 1, 3]).reshape([qw, b * qh, c]);
    let rel_w = by_col.matmul(rw.swap_dims(1, 2)).reshape([qw, b, qh, kw]).permute([1, 2, 0, 3]);
    let bias = rel_h.reshape([b, qh, qw, kh, 1]) + rel_w.reshape([b, qh, qw, 1, kw]);
    bias.reshape([b, qh * qw, kh * kw])
}

/// Splits `[B, H, W, C]` into `[B nh nw, ws, ws, C]` windows, zero-padding H and W up to
/// multiples of `ws` (the padding tokens take part in the windows' attention, as in SAM).
fn window_partition(x: Tensor<4>, ws: usize) -> Tensor<4> {
    let [b, h, w, c] = x.dims();
    let (ph, pw) = (h.div_ceil(ws) * ws, w.div_ceil(ws) * ws);
    let device = x.device();
    let mut x = x;
    if ph > h {
        x = Tensor::cat(vec![x, Tensor::zeros([b, ph - h, w, c], &device)], 1);
    }
    if pw > w {
        x = Tensor::cat(vec![x, Tensor::zeros([b, ph, pw - w, c], &device)], 2);
    }
    x.reshape([b, ph / ws, ws, pw / ws, ws, c]).permute([0, 1, 3, 2, 4, 5]).reshape([
        b * (ph / ws) * (pw / ws),
        ws,
        ws,
        c,
    ])
}

/// The inverse of [`window_partition`], dropping the padding: `[B nh nw, ws, ws, C]` -> `[B, h, w, C]`.
fn window_unpartition(x: Tensor<4>, ws: usize, (h, w): (usize, usize)) -> Tensor<4> {
    let [nwin, _, _, c] = x.dims();
    let (nh, nw) = (h.div_ceil(ws), w.div_ceil(ws));
    let b = nwin / (nh * nw);
    let x = x.reshape([b, nh, nw, ws, ws, c]).permute([0, 1, 3, 2, 4, 5]).reshape([b, nh * ws, nw * ws, c]);
    x.narrow(1, 0, h).narrow(2, 0, w)
}

/// One pre-norm ViT layer (`SamVisionLayer`).
#[derive(Module, Debug)]
pub struct VisionLayer {
    pub layer_norm1: LayerNorm,
    pub attn: VisionAttention,
    pub layer_norm2: LayerNorm,
    pub lin1: Linear,
    pub lin2: Linear,
    /// 0: global attention.
    #[module(skip)]
    pub window_size: usize,
    #[module(skip)]
    pub act: Act,
}

impl VisionLayer {
    /// # Shapes
    /// `x` `[B, H, W, D]` -> `[B, H, W, D]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let [_, h, w, _] = x.dims();
        let y = self.layer_norm1.forward(x.clone());
        let y = if self.window_size > 0 {
            window_unpartition(self.attn.forward(window_partition(y, self.window_size)), self.window_size, (h, w))
        } else {
            self.attn.forward(y)
        };
        let x = x + y;
        let y = self.lin2.forward(self.act.apply(self.lin1.forward(self.layer_norm2.forward(x.clone()))));
        x + y
    }
}

/// The image encoder (`SamVisionEncoder`): patch embedding, positions, layers, neck.
#[derive(Module, Debug)]
pub struct ImageEncoder {
    #[module(skip)]
    pub cfg: VisionConfig,
    pub patch_embed: Conv2d,
    /// `[1, grid, grid, D]`
    pub pos_embed: Option<Param<Tensor<4>>>,
    pub layers: Vec<VisionLayer>,
    pub neck_conv1: Conv2d,
    pub neck_layer_norm1: LayerNorm,
    pub neck_conv2: Conv2d,
    pub neck_layer_norm2: LayerNorm,
}

const PRE: &str = "vision_encoder";

impl ImageEncoder {
    pub fn load(w: &WeightStore, cfg: &VisionConfig) -> Result<Self, VlmError> {
        let (d, p, g, heads) = (cfg.hidden_size, cfg.patch_size, cfg.grid(), cfg.num_attention_heads);
        let (out, eps, mlp) = (cfg.output_channels, cfg.layer_norm_eps, cfg.mlp_dim());
        let patch_embed =
            Conv2d::load(w, &format!("{PRE}.patch_embed.projection"), [d, cfg.num_channels, p], p, 0, true)?;
        let pos_embed = if cfg.use_abs_pos { Some(param(w, &format!("{PRE}.pos_embed"), [1, g, g, d])?) } else { None };
        let mut layers = Vec::new();
        for i in 0..cfg.num_hidden_layers {
            let l = format!("{PRE}.layers.{i}");
            let window_size = cfg.window_of(i);
            let size = if window_size == 0 { g } else { window_size };
            let rel = |axis: &str| -> Result<Option<Param<Tensor<2>>>, VlmError> {
                if cfg.use_rel_pos {
                    Ok(Some(param(w, &format!("{l}.attn.rel_pos_{axis}"), [2 * size - 1, d / heads])?))
                } else {
                    Ok(None)
                }
            };
            if !cfg.qkv_bias {
                return Err(VlmError::config(
                    std::path::Path::new("config.json"),
                    "vision_config.qkv_bias = false is not supported",
                ));
            }
            layers.push(VisionLayer {
                layer_norm1: layer_norm(w, &format!("{l}.layer_norm1"), d, eps)?,
                attn: VisionAttention {
                    qkv: linear(w, &format!("{l}.attn.qkv"), d, 3 * d)?,
                    proj: linear(w, &format!("{l}.attn.proj"), d, d)?,
                    rel_pos_h: rel("h")?,
                    rel_pos_w: rel("w")?,
                    heads,
                },
                layer_norm2: layer_norm(w, &format!("{l}.layer_norm2"), d, eps)?,
                lin1: linear(w, &format!("{l}.mlp.lin1"), d, mlp)?,
                lin2: linear(w, &format!("{l}.mlp.lin2"), mlp, d)?,
                window_size,
                act: cfg.hidden_act,
            });
        }
        // The neck's layer norms are `SamLayerNorm` at its default eps (1e-6), not the config's.
        Ok(Self {
            cfg: cfg.clone(),
            patch_embed,
            pos_embed,
            layers,
            neck_conv1: Conv2d::load(w, &format!("{PRE}.neck.conv1"), [out, d, 1], 1, 0, false)?,
            neck_layer_norm1: layer_norm(w, &format!("{PRE}.neck.layer_norm1"), out, 1e-6)?,
            neck_conv2: Conv2d::load(w, &format!("{PRE}.neck.conv2"), [out, out, 3], 1, 1, false)?,
            neck_layer_norm2: layer_norm(w, &format!("{PRE}.neck.layer_norm2"), out, 1e-6)?,
        })
    }

    /// The image embeddings (`SamModel.get_image_embeddings`).
    ///
    /// # Shapes
    /// `pixels` `[B, 3, S, S]` (normalised, padded to `image_size`) -> `[B, output_channels, grid, grid]`.
    pub fn forward(&self, pixels: Tensor<4>) -> Tensor<4> {
        let [_, c, h, w] = pixels.dims();
        let s = self.cfg.image_size;
        assert!(
            c == self.cfg.num_channels && h == s && w == s,
            "the image encoder expects [B, {}, {s}, {s}], got {:?}",
            self.cfg.num_channels,
            pixels.dims()
        );
        let mut x = self.patch_embed.forward(pixels).permute([0, 2, 3, 1]);
        if let Some(pos) = &self.pos_embed {
            x = x + pos.val();
        }
        for layer in &self.layers {
            x = layer.forward(x);
        }
        let x = self.neck_conv1.forward(x.permute([0, 3, 1, 2]));
        let x = layer_norm_2d(&self.neck_layer_norm1, x);
        layer_norm_2d(&self.neck_layer_norm2, self.neck_conv2.forward(x))
    }

    pub fn device(&self) -> Device {
        self.patch_embed.weight.val().device()
    }
}
