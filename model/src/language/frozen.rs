//! The encoder at inference. Its weights no longer change, so the last lifting layer is folded
//! into the patch convolution once, when the encoder is frozen, instead of for every map as
//! training must ([`Encoder::tokens_raw`]).

use super::Encoder;
use burn::tensor::Tensor;

/// An [`Encoder`] whose weights are fixed, with its last lifting layer folded into the patch
/// convolution. Same tokens as [`Encoder::forward_level`] up to rounding.
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
}
