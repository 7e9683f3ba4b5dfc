//! The encoder while its weights do not change: at inference for good, in training for one step.
//! The last lifting layer is folded into the patch convolution once, when the encoder is frozen,
//! instead of for every map ([`Encoder::tokens_raw`]).

use super::Encoder;
use burn::tensor::{Int, Tensor, TensorData};

/// An [`Encoder`] whose weights are fixed, with its last lifting layer folded into the patch
/// convolution. Same tokens as [`Encoder::forward_level`] up to rounding. Frozen from an encoder
/// of autodiff tensors, the fold is one node of the graph: every map of a training step shares it,
/// and its gradient reaches the lifting and patch weights once.
pub struct FrozenEncoder {
    encoder: Encoder,
    /// `[patch² x hidden, D]` folded patch weight and its `[1, D]` bias (absent without lifting).
    folded: Option<(Tensor<2>, Tensor<2>)>,
}

impl FrozenEncoder {
    /// Freezes `encoder`, forming the folded patch weight now. Once formed the fold always pays:
    /// per pixel the plain path multiplies `hidden x D` (last lifting layer) plus `D x D` (patch
    /// convolution), the folded one `hidden x D` alone. At LLaVA-OneVision's size (hidden 128,
    /// D 1152) that is a tenth of the work; the fold itself (66 G multiply-adds there) is paid
    /// once instead of per map. Without lifting there is nothing to fold.
    pub fn new(encoder: Encoder) -> Self {
        let folded = (!encoder.lift_weights.is_empty()).then(|| encoder.folded_patch());
        Self { encoder, folded }
    }

    /// Freezes `encoder` for maps of `dims` `[H, W, C]` (one training step's), folding only where
    /// that is cheaper even for a single map ([`Encoder::tokens_raw`]'s rule): never for the
    /// built-in model, always at LLaVA-OneVision's size, where a step's view and object maps then
    /// pay the fold (33 G multiply-adds forward, twice that backward) once instead of each.
    pub fn for_maps(encoder: Encoder, dims: [usize; 3]) -> Self {
        let folded = encoder.fold_is_cheaper(&dims).then(|| encoder.folded_patch());
        Self { encoder, folded }
    }

    /// Whether the last lifting layer is folded into the patch convolution.
    pub fn is_folded(&self) -> bool {
        self.folded.is_some()
    }

    /// Encodes a view-level (`object = false`) or a masked object-level map.
    ///
    /// # Shapes
    /// `map` `[H, W, C]` (H = W = grid x patch) -> tokens `[T, D]`.
    pub fn forward_level(&self, map: Tensor<3>, object: bool) -> Tensor<2> {
        let raw = match &self.folded {
            Some((weight, bias)) => self.encoder.tokens_raw_with_fold(map, weight.clone(), bias.clone()),
            None => self.encoder.tokens_raw_plain(map),
        };
        self.encoder.adjust(self.encoder.mix(raw), object)
    }

    /// [`forward_level`](Self::forward_level) of a masked object-level map (`mask_out`: every
    /// pixel outside the `[H * W]` 0/1 `mask` is zero). With the fold, the patches wholly outside
    /// the mask all make the same token, so it is computed once (with its gradient summed once)
    /// and only the patches the object touches are encoded: the same tokens. In a crop the object
    /// often covers under half of the patches, and at LLaVA-OneVision's size an object map's
    /// products are 21 G multiply-adds forward and 42 G backward.
    ///
    /// # Shapes
    /// `map` `[H, W, C]` (H = W = grid x patch), `mask` `H * W` values -> tokens `[T, D]`.
    pub fn forward_object(&self, map: Tensor<3>, mask: &[f32]) -> Tensor<2> {
        let [h, w, c] = map.dims();
        let p = self.encoder.patch();
        let Some((weight, bias)) = self.folded.as_ref().filter(|_| mask.len() == h * w && p > 0) else {
            return self.forward_level(map, true);
        };
        let (gh, gw) = (h / p, w / p);
        let touched = |t: usize| {
            let (y0, x0) = ((t / gw) * p, (t % gw) * p);
            (y0..y0 + p).any(|y| mask[y * w + x0..y * w + x0 + p].iter().any(|&m| m != 0.0))
        };
        let (live, dead): (Vec<usize>, Vec<usize>) = (0..gh * gw).partition(|&t| touched(t));
        if dead.len() < 2 {
            return self.forward_level(map, true);
        }
        // the encoded patches: the touched ones, then one outside the mask
        let rows: Vec<i64> = live.iter().chain(&dead[..1]).map(|&t| t as i64).collect();
        let mut index = vec![live.len() as i64; gh * gw];
        for (i, &t) in live.iter().enumerate() {
            index[t] = i as i64;
        }
        let device = map.device();
        let ints = |v: Vec<i64>| {
            let n = v.len();
            Tensor::<1, Int>::from_data(TensorData::new(v, [n]), &device)
        };
        let n = rows.len();
        let patches = self.encoder.patch_order(map).reshape([gh * gw, p * p * c]);
        let hidden = self.encoder.lift_rows(patches.select(0, ints(rows)).reshape([n * p * p, c]), false);
        let width = hidden.dims()[1];
        let encoded = hidden.reshape([n, p * p * width]).matmul(weight.clone()) + bias.clone();
        let raw = encoded.select(0, ints(index));
        self.encoder.adjust(self.encoder.mix(raw), true)
    }
}
