//! The initial values of the encoder's and the token mixer's weights.

use crate::rng::Rng;
use burn::tensor::{Device, Tensor, TensorData};

/// A `[rows, cols]` tensor drawn uniform in ±`bound` from `rng`, row-major.
pub(crate) fn uniform(rng: &mut Rng, rows: usize, cols: usize, bound: f32, device: &Device) -> Tensor<2> {
    let v: Vec<f32> = (0..rows * cols).map(|_| rng.range(-bound, bound)).collect();
    Tensor::from_data(TensorData::new(v, [rows, cols]), device)
}

/// The usual initialisation bound of a layer with `fan_in` inputs: 1/sqrt(fan_in).
pub(crate) fn fan_in_bound(fan_in: usize) -> f32 {
    1.0 / (fan_in as f32).sqrt()
}
