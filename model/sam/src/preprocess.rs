//! What SAM's image processor does around the model (transformers' `SamImageProcessor`): the
//! image resized so that its longest side is the model's input size (Pillow's bilinear filter),
//! scaled to `[0, 1]`, normalised with ImageNet's mean and deviation and zero-padded at the right
//! and bottom to a square; points moved into that input's pixels; and the decoder's
//! low-resolution mask logits brought back to the image (upscaled to the padded input, cropped
//! to the resized image, resized to the original, each bilinear with half-pixel centres).

use burn::tensor::module::interpolate;
use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
use burn::tensor::{Device, Tensor, TensorData};
use llava_onevision::RgbImage;
use llava_onevision::preprocess::resize;

/// ImageNet's per-channel mean and standard deviation (`IMAGENET_DEFAULT_MEAN`, `_STD`).
pub const MEAN: [f32; 3] = [0.485, 0.456, 0.406];
pub const STD: [f32; 3] = [0.229, 0.224, 0.225];
/// Pillow's `BILINEAR`, the processor's resampling filter.
const BILINEAR: u32 = 2;

/// `(height, width)` with the longest side `longest`, each rounded half up
/// (`SamImageProcessor._get_preprocess_shape`).
pub fn resized_shape(height: usize, width: usize, longest: usize) -> (usize, usize) {
    let scale = longest as f64 / height.max(width) as f64;
    ((height as f64 * scale + 0.5) as usize, (width as f64 * scale + 0.5) as usize)
}

/// One image as the model takes it.
#[derive(Debug, Clone)]
pub struct Input {
    /// `[1, 3, S, S]`, S the model's input size.
    pub pixels: Tensor<4>,
    /// `(height, width)` of the image given.
    pub original: (usize, usize),
    /// `(height, width)` of the resized image inside the padded input.
    pub resized: (usize, usize),
    /// S.
    pub size: usize,
}

impl Input {
    /// The image resized, normalised and padded to `size x size`.
    pub fn new(img: &RgbImage, size: usize, device: &Device) -> Self {
        let (h, w) = resized_shape(img.height, img.width, size);
        let small = resize(img, w, h, BILINEAR);
        let mut px = vec![0f32; 3 * size * size];
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let v = small.data[(y * w + x) * 3 + c] as f32 / 255.0;
                    px[(c * size + y) * size + x] = (v - MEAN[c]) / STD[c];
                }
            }
        }
        Self {
            pixels: Tensor::from_data(TensorData::new(px, [1, 3, size, size]), device),
            original: (img.height, img.width),
            resized: (h, w),
            size,
        }
    }

    /// Points `(x, y)` in the original image's pixels moved into the input's pixels
    /// (`_normalize_coordinates`).
    pub fn points(&self, points: &[[f32; 2]]) -> Vec<[f32; 2]> {
        let sx = (self.resized.1 as f64 / self.original.1 as f64) as f32;
        let sy = (self.resized.0 as f64 / self.original.0 as f64) as f32;
        points.iter().map(|p| [p[0] * sx, p[1] * sy]).collect()
    }

    /// The decoder's mask logits at the original image's size (`post_process_masks` without
    /// binarising): upscaled to the padded input, cropped to the resized image, resized to the
    /// original, each bilinear with half-pixel centres.
    ///
    /// # Shapes
    /// `low` `[N, L, L]` -> `[N, H, W]`.
    pub fn upscale(&self, low: Tensor<3>) -> Tensor<3> {
        let [n, l, _] = low.dims();
        let bilinear = |size: [usize; 2]| {
            let mut o = InterpolateOptions::new(InterpolateMode::Bilinear).with_output_size(size);
            o.align_corners = false;
            o
        };
        let (rh, rw) = self.resized;
        let padded = interpolate(low.reshape([n, 1, l, l]), bilinear([self.size, self.size]));
        let resized = padded.slice([0..n, 0..1, 0..rh, 0..rw]);
        let [oh, ow] = [self.original.0, self.original.1];
        interpolate(resized, bilinear([oh, ow])).reshape([n, oh, ow])
    }
}
