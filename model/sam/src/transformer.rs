//! The mask decoder's two-way transformer (transformers' `SamTwoWayTransformer`): the prompt
//! tokens attend to themselves and to the image, and the image attends back to the tokens, with
//! the positional embeddings added to queries and keys (never to values) at every attention.

use crate::config::{Act, MaskDecoderConfig};
use crate::weights::{WeightStore, layer_norm, linear};
use burn::module::Module;
use burn::nn::{LayerNorm, Linear};
use burn::tensor::Tensor;
use burn::tensor::activation::softmax;
use llava_onevision::VlmError;

/// Attention whose q/k/v projections may narrow the width by a downsample rate (`SamAttention`).
#[derive(Module, Debug)]
pub struct Attention {
    pub q_proj: Linear,
    pub k_proj: Linear,
    pub v_proj: Linear,
    pub out_proj: Linear,
    #[module(skip)]
    pub heads: usize,
}

impl Attention {
    fn load(w: &WeightStore, prefix: &str, d: usize, internal: usize, heads: usize) -> Result<Self, VlmError> {
        Ok(Self {
            q_proj: linear(w, &format!("{prefix}.q_proj"), d, internal)?,
            k_proj: linear(w, &format!("{prefix}.k_proj"), d, internal)?,
            v_proj: linear(w, &format!("{prefix}.v_proj"), d, internal)?,
            out_proj: linear(w, &format!("{prefix}.out_proj"), internal, d)?,
            heads,
        })
    }

    /// # Shapes
    /// `q` `[N, Tq, D]`, `k` and `v` `[N, Tk, D]` -> `[N, Tq, D]`.
    pub fn forward(&self, q: Tensor<3>, k: Tensor<3>, v: Tensor<3>) -> Tensor<3> {
        let heads = self.heads;
        let split = |x: Tensor<3>| {
            let [n, t, c] = x.dims();
            x.reshape([n, t, heads, c / heads]).swap_dims(1, 2)
        };
        let (q, k, v) = (split(self.q_proj.forward(q)), split(self.k_proj.forward(k)), split(self.v_proj.forward(v)));
        let [n, _, tq, hd] = q.dims();
        let scores = q.matmul(k.swap_dims(2, 3)) * (hd as f64).powf(-0.5);
        let out = softmax(scores, 3).matmul(v).swap_dims(1, 2).reshape([n, tq, heads * hd]);
        self.out_proj.forward(out)
    }
}

/// The weight `[D, c]` of a projection and its bias `[c]`.
fn weight_bias(l: &Linear) -> (Tensor<2>, Tensor<1>) {
    let w = l.weight.val();
    let c = w.dims()[1];
    let b = l.bias.as_ref().map_or_else(|| Tensor::zeros([c], &w.device()), |b| b.val());
    (w, b)
}

impl Attention {
    /// Image pixels attending to a few tokens, the same as [`Attention::forward`] with the
    /// pixels' projections folded into the tokens': each head's scores are `x (W_q,h K_h^T) + b_q,h
    /// K_h^T` and its output through `out_proj` is `S_h (V_h W_o,h)`, so every pixel costs two
    /// products with `heads x T` columns instead of two through the projections' width.
    ///
    /// # Shapes
    /// `x` `[N, P, D]` (queries), `k` and `v` `[N, T, D]` -> `[N, P, D]`.
    pub fn pixels_to_tokens(&self, x: Tensor<3>, k: Tensor<3>, v: Tensor<3>) -> Tensor<3> {
        let (h, [n, p, d], t) = (self.heads, x.dims(), k.dims()[1]);
        let (wq, bq) = weight_bias(&self.q_proj);
        let c = wq.dims()[1];
        let hd = c / h;
        let heads = |y: Tensor<3>| y.reshape([n, t, h, hd]).swap_dims(1, 2); // [N, h, T, hd]
        let (k, v) = (heads(self.k_proj.forward(k)), heads(self.v_proj.forward(v)));
        // M [N, D, h T]: column (h, t) = W_q,h K_h[t]; beta [N, 1, h T] = b_q,h . K_h[t]
        let wq_h = wq.reshape([d, h, hd]).swap_dims(0, 1).unsqueeze_dim::<4>(0); // [1, h, D, hd]
        let m = wq_h.matmul(k.clone().swap_dims(2, 3)).permute([0, 2, 1, 3]).reshape([n, d, h * t]);
        let beta = bq.reshape([1, h, 1, hd]).matmul(k.swap_dims(2, 3)).reshape([n, 1, h * t]);
        let scores = (x.matmul(m) + beta) * (hd as f64).powf(-0.5);
        let probs = softmax(scores.reshape([n, p, h, t]), 3).reshape([n, p, h * t]);
        // U [N, h T, D]: row (h, t) = V_h[t] W_o,h
        let (wo, bo) = weight_bias(&self.out_proj);
        let wo_h = wo.reshape([h, hd, d]).unsqueeze_dim::<4>(0); // [1, h, hd, D]
        let u = v.matmul(wo_h).reshape([n, h * t, d]);
        probs.matmul(u) + bo.reshape([1, 1, d])
    }

    /// A few tokens attending to the image's pixels, the same as [`Attention::forward`] with the
    /// pixels' projections folded into the tokens': each head's scores are `(Q_h W_k,h^T) x_k^T`
    /// (the key bias adds a constant per row, which the softmax drops) and its output is
    /// `(S_h x_v) W_v,h + b_v,h` (the probabilities sum to 1).
    ///
    /// # Shapes
    /// `q` `[N, T, D]`, `xk` and `xv` `[N, P, D]` (keys, values) -> `[N, T, D]`.
    pub fn tokens_to_pixels(&self, q: Tensor<3>, xk: Tensor<3>, xv: Tensor<3>) -> Tensor<3> {
        let (h, [n, t, d]) = (self.heads, q.dims());
        let (wk, _) = weight_bias(&self.k_proj);
        let c = wk.dims()[1];
        let hd = c / h;
        let q = self.q_proj.forward(q).reshape([n, t, h, hd]).swap_dims(1, 2); // [N, h, T, hd]
        // A [N, D, h T]: column (h, t) = W_k,h Q_h[t]
        let wk_h = wk.reshape([d, h, hd]).swap_dims(0, 1).unsqueeze_dim::<4>(0); // [1, h, D, hd]
        let a = wk_h.matmul(q.swap_dims(2, 3)).permute([0, 2, 1, 3]).reshape([n, d, h * t]);
        let scores = xk.matmul(a) * (hd as f64).powf(-0.5); // [N, P, h T]
        let probs = softmax(scores, 1).swap_dims(1, 2); // [N, h T, P]
        let z = probs.matmul(xv).reshape([n, h, t, d]);
        let (wv, bv) = weight_bias(&self.v_proj);
        let wv_h = wv.reshape([d, h, hd]).swap_dims(0, 1).unsqueeze_dim::<4>(0); // [1, h, D, hd]
        let out = z.matmul(wv_h) + bv.reshape([1, h, 1, hd]); // [N, h, T, hd]
        self.out_proj.forward(out.swap_dims(1, 2).reshape([n, t, c]))
    }
}

/// Self-attention of the tokens, tokens to image, MLP on the tokens, image to tokens
/// (`SamTwoWayAttentionBlock`), each followed by a layer norm.
#[derive(Module, Debug)]
pub struct TwoWayBlock {
    pub self_attn: Attention,
    pub layer_norm1: LayerNorm,
    pub cross_attn_token_to_image: Attention,
    pub layer_norm2: LayerNorm,
    pub lin1: Linear,
    pub lin2: Linear,
    pub layer_norm3: LayerNorm,
    pub layer_norm4: LayerNorm,
    pub cross_attn_image_to_token: Attention,
    /// The first block: the tokens' self-attention sees no positional embedding and has no
    /// residual connection.
    #[module(skip)]
    pub skip_first_layer_pe: bool,
    #[module(skip)]
    pub act: Act,
}

impl TwoWayBlock {
    /// # Shapes
    /// `queries`, `query_pe` `[N, T, D]`; `keys` `[N, HW, D]`, `key_pe` `[N or 1, HW, D]` ->
    /// (queries, keys).
    pub fn forward(
        &self,
        queries: Tensor<3>,
        keys: Tensor<3>,
        query_pe: Tensor<3>,
        key_pe: Tensor<3>,
    ) -> (Tensor<3>, Tensor<3>) {
        let queries = if self.skip_first_layer_pe {
            self.self_attn.forward(queries.clone(), queries.clone(), queries)
        } else {
            let q = queries.clone() + query_pe.clone();
            queries.clone() + self.self_attn.forward(q.clone(), q, queries)
        };
        let queries = self.layer_norm1.forward(queries);

        let q = queries.clone() + query_pe.clone();
        // the keys with their positions: the keys of this attention and the queries of the last
        let k = keys.clone() + key_pe;
        let queries = queries + self.cross_attn_token_to_image.tokens_to_pixels(q, k.clone(), keys.clone());
        let queries = self.layer_norm2.forward(queries);

        let mlp = self.lin2.forward(self.act.apply(self.lin1.forward(queries.clone())));
        let queries = self.layer_norm3.forward(queries + mlp);

        let q = queries.clone() + query_pe;
        let keys =
            self.layer_norm4.forward(keys + self.cross_attn_image_to_token.pixels_to_tokens(k, q, queries.clone()));
        (queries, keys)
    }
}

/// The two-way transformer.
#[derive(Module, Debug)]
pub struct TwoWayTransformer {
    pub layers: Vec<TwoWayBlock>,
    pub final_attn_token_to_image: Attention,
    pub layer_norm_final_attn: LayerNorm,
}

impl TwoWayTransformer {
    pub fn load(w: &WeightStore, prefix: &str, cfg: &MaskDecoderConfig) -> Result<Self, VlmError> {
        let (d, heads, eps) = (cfg.hidden_size, cfg.num_attention_heads, cfg.layer_norm_eps);
        let narrow = d / cfg.attention_downsample_rate;
        let mut layers = Vec::new();
        for i in 0..cfg.num_hidden_layers {
            let l = format!("{prefix}.layers.{i}");
            layers.push(TwoWayBlock {
                self_attn: Attention::load(w, &format!("{l}.self_attn"), d, d, heads)?,
                layer_norm1: layer_norm(w, &format!("{l}.layer_norm1"), d, eps)?,
                cross_attn_token_to_image: Attention::load(
                    w,
                    &format!("{l}.cross_attn_token_to_image"),
                    d,
                    narrow,
                    heads,
                )?,
                layer_norm2: layer_norm(w, &format!("{l}.layer_norm2"), d, eps)?,
                lin1: linear(w, &format!("{l}.mlp.lin1"), d, cfg.mlp_dim)?,
                lin2: linear(w, &format!("{l}.mlp.lin2"), cfg.mlp_dim, d)?,
                layer_norm3: layer_norm(w, &format!("{l}.layer_norm3"), d, eps)?,
                layer_norm4: layer_norm(w, &format!("{l}.layer_norm4"), d, eps)?,
                cross_attn_image_to_token: Attention::load(
                    w,
                    &format!("{l}.cross_attn_image_to_token"),
                    d,
                    narrow,
                    heads,
                )?,
                skip_first_layer_pe: i == 0,
                act: cfg.hidden_act,
            });
        }
        Ok(Self {
            layers,
            final_attn_token_to_image: Attention::load(
                w,
                &format!("{prefix}.final_attn_token_to_image"),
                d,
                narrow,
                heads,
            )?,
            // a plain `nn.LayerNorm(hidden_size)`: torch's default eps 1e-5, not the config's
            layer_norm_final_attn: layer_norm(w, &format!("{prefix}.layer_norm_final_attn"), d, 1e-5)?,
        })
    }

    /// # Shapes
    /// `tokens` `[N, T, D]` (also their positional embedding), `image` `[N, HW, D]` and `image_pe`
    /// `[N or 1, HW, D]`
    /// -> (tokens `[N, T, D]`, image `[N, HW, D]`).
    pub fn forward(&self, tokens: Tensor<3>, image: Tensor<3>, image_pe: Tensor<3>) -> (Tensor<3>, Tensor<3>) {
        let (mut queries, mut keys) = (tokens.clone(), image);
        for layer in &self.layers {
            (queries, keys) = layer.forward(queries, keys, tokens.clone(), image_pe.clone());
        }
        let q = queries.clone() + tokens;
        let k = keys.clone() + image_pe;
        let queries = queries + self.final_attn_token_to_image.tokens_to_pixels(q, k, keys.clone());
        (self.layer_norm_final_attn.forward(queries), keys)
    }
}
