//! Automatic masks (transformers' mask-generation pipeline without crops): a grid of single-point
//! prompts over the image, decoded in batches into three masks a point, the masks kept whose
//! predicted IoU and stability pass the filters, then box non-maximum suppression. The decoding,
//! the upscaling and the stability counts run on the backend; only the masks that pass the
//! filters come back to the host.

use crate::RgbImage;
use crate::preprocess::Input;
use crate::{Prompt, Sam};
use burn::tensor::{Device, Int, Tensor, TensorData};
use std::time::Instant;

/// A grid of `n x n` points in `[0, 1]^2`, cell centres, `x` fastest: `(x, y)`.
pub fn point_grid(n: usize) -> Vec<[f32; 2]> {
    let at = |i: usize| (2 * i + 1) as f32 / (2 * n) as f32;
    (0..n * n).map(|k| [at(k % n), at(k / n)]).collect()
}

/// The box `[x0, y0, x1, y1]` (inclusive pixels) of a `width`-wide mask; `[0; 4]` when empty.
pub fn mask_box(mask: &[bool], width: usize) -> [u32; 4] {
    let mut b = [u32::MAX, u32::MAX, 0, 0];
    for (p, _) in mask.iter().enumerate().filter(|(_, m)| **m) {
        let (x, y) = ((p % width) as u32, (p / width) as u32);
        b = [b[0].min(x), b[1].min(y), b[2].max(x), b[3].max(y)];
    }
    if b[0] == u32::MAX { [0; 4] } else { b }
}

/// Intersection over union of two boxes, as areas of their corner coordinates (what box
/// non-maximum suppression compares).
pub fn box_iou(a: [u32; 4], b: [u32; 4]) -> f32 {
    let area = |r: [u32; 4]| (r[2].saturating_sub(r[0]) as f32) * (r[3].saturating_sub(r[1]) as f32);
    let (x0, y0) = (a[0].max(b[0]), a[1].max(b[1]));
    let (x1, y1) = (a[2].min(b[2]), a[3].min(b[3]));
    let inter = (x1.saturating_sub(x0) as f32) * (y1.saturating_sub(y0) as f32);
    let union = area(a) + area(b) - inter;
    if union <= 0.0 { 0.0 } else { inter / union }
}

/// Greedy non-maximum suppression: the indices kept, best score first; a box goes when it
/// overlaps a kept one by more than `iou`. Ties keep the earlier index (a stable order).
pub fn nms(boxes: &[[u32; 4]], scores: &[f32], iou: f32) -> Vec<usize> {
    let mut order: Vec<usize> = (0..boxes.len()).collect();
    order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    let mut kept: Vec<usize> = Vec::new();
    for i in order {
        if kept.iter().all(|&k| box_iou(boxes[k], boxes[i]) <= iou) {
            kept.push(i);
        }
    }
    kept
}

/// The thresholds of automatic masks (transformers' defaults). A mask is kept when its predicted
/// IoU passes `pred_iou` and its stability passes `stability`: the share of its logits above
/// `mask_threshold + stability_offset` among those above `mask_threshold - stability_offset`
/// (how little it moves when its threshold does; 0 or less turns a filter off). Boxes overlapping
/// a better mask's by more than `nms_iou` go.
#[derive(Clone, Debug, PartialEq)]
pub struct Filters {
    pub pred_iou: f32,
    pub stability: f32,
    pub mask_threshold: f32,
    pub stability_offset: f32,
    pub nms_iou: f32,
}

impl Default for Filters {
    fn default() -> Self {
        Self { pred_iou: 0.88, stability: 0.95, mask_threshold: 0.0, stability_offset: 1.0, nms_iou: 0.7 }
    }
}

/// How automatic masks are made (the pipeline's defaults: 32 x 32 points, 64 a batch).
#[derive(Clone, Debug, PartialEq)]
pub struct AutoOptions {
    pub points_per_side: usize,
    pub points_per_batch: usize,
    pub filters: Filters,
}

impl Default for AutoOptions {
    fn default() -> Self {
        Self { points_per_side: 32, points_per_batch: 64, filters: Filters::default() }
    }
}

/// Seconds spent in each part of [`Sam::passing_masks_timed`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AutoTimings {
    /// Resizing, normalising and the image encoder.
    pub embeddings_s: f64,
    /// The prompt encoder and the mask decoder over every batch of points.
    pub decode_s: f64,
    /// Upscaling the masks that pass the predicted-IoU filter, the stability counts, and
    /// bringing the masks that pass both to the host.
    pub masks_s: f64,
}

/// One kept mask.
#[derive(Clone, Debug, PartialEq)]
pub struct AutoMask {
    pub mask: Vec<bool>,
    pub bbox: [u32; 4],
    pub predicted_iou: f32,
    pub stability: f32,
}

/// Box non-maximum suppression over masks that passed the filters: the kept ones, best
/// predicted IoU first.
pub fn suppress(passed: Vec<AutoMask>, nms_iou: f32) -> Vec<AutoMask> {
    let boxes: Vec<[u32; 4]> = passed.iter().map(|m| m.bbox).collect();
    let scores: Vec<f32> = passed.iter().map(|m| m.predicted_iou).collect();
    let keep = nms(&boxes, &scores, nms_iou);
    let mut slots: Vec<Option<AutoMask>> = passed.into_iter().map(Some).collect();
    keep.into_iter().filter_map(|i| slots[i].take()).collect()
}

/// One id per pixel from overlapping automatic masks (0 = none): the larger masks painted
/// first, so that a part (a handle, an object on a table) stays on top of what it lies in; ids
/// 1.. in that order (ties: the earlier mask first), at most 65,535 of them.
pub fn label_map(masks: &[AutoMask], pixels: usize) -> Vec<u16> {
    let area = |m: &AutoMask| m.mask.iter().filter(|&&b| b).count();
    let mut order: Vec<usize> = (0..masks.len()).collect();
    // each area counted once (a mask is the image's size), the sort stable
    order.sort_by_cached_key(|&i| std::cmp::Reverse(area(&masks[i])));
    let mut ids = vec![0u16; pixels];
    for (k, &i) in order.iter().enumerate().take(usize::from(u16::MAX)) {
        for (id, _) in ids.iter_mut().zip(&masks[i].mask).filter(|(_, m)| **m) {
            *id = (k + 1) as u16;
        }
    }
    ids
}

impl Sam {
    /// Automatic masks of one image: [`Sam::passing_masks`] then [`suppress`].
    pub fn automatic_masks(&self, img: &RgbImage, o: &AutoOptions, device: &Device) -> Vec<AutoMask> {
        suppress(self.passing_masks(img, o, device), o.filters.nms_iou)
    }

    /// Every mask of the point grid that passes the predicted-IoU and stability filters, at the
    /// image's size, in the order of the points (x fastest), a point's three masks in turn.
    pub fn passing_masks(&self, img: &RgbImage, o: &AutoOptions, device: &Device) -> Vec<AutoMask> {
        self.passing_masks_timed(img, o, device).0
    }

    /// [`Sam::passing_masks`] and where its time went.
    pub fn passing_masks_timed(
        &self,
        img: &RgbImage,
        o: &AutoOptions,
        device: &Device,
    ) -> (Vec<AutoMask>, AutoTimings) {
        let mut times = AutoTimings::default();
        let t = Instant::now();
        let input = Input::new(img, self.cfg.vision_config.image_size, device);
        let embeddings = self.image_embeddings(input.pixels.clone());
        let embeddings = Tensor::from_data(embeddings.into_data(), device); // waits for it
        times.embeddings_s = t.elapsed().as_secs_f64();
        let (h, w) = input.original;
        let grid: Vec<[f32; 2]> =
            point_grid(o.points_per_side).iter().map(|p| [p[0] * w as f32, p[1] * h as f32]).collect();
        let mut out = Vec::new();
        for batch in input.points(&grid).chunks(o.points_per_batch.max(1)) {
            out.extend(self.passing_in_batch(&input, embeddings.clone(), batch, &o.filters, device, &mut times));
        }
        (out, times)
    }

    /// One batch of single-point prompts (points in the input's pixels).
    fn passing_in_batch(
        &self,
        input: &Input,
        embeddings: Tensor<4>,
        points: &[[f32; 2]],
        f: &Filters,
        device: &Device,
        times: &mut AutoTimings,
    ) -> Vec<AutoMask> {
        let t = Instant::now();
        let p = points.len();
        let xy: Vec<f32> = points.iter().flatten().copied().collect();
        let prompt = Prompt {
            points: Some((
                Tensor::from_data(TensorData::new(xy, [1, p, 1, 2]), device),
                Tensor::from_data(TensorData::new(vec![1i64; p], [1, p, 1]), device),
            )),
            ..Prompt::default()
        };
        let (low, iou) = self.segment(embeddings, &prompt, true);
        let [_, _, k, l, _] = low.dims();
        let iou = iou.into_data().convert::<f32>().into_vec::<f32>().expect("f32 IoU");
        times.decode_s += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let sel: Vec<usize> = (0..p * k).filter(|&i| f.pred_iou <= 0.0 || iou[i] > f.pred_iou).collect();
        if sel.is_empty() {
            times.masks_s += t.elapsed().as_secs_f64();
            return Vec::new();
        }
        let index: Vec<i64> = sel.iter().map(|&i| i as i64).collect();
        let index = Tensor::<1, Int>::from_data(TensorData::new(index, [sel.len()]), device);
        let logits = input.upscale(low.reshape([p * k, l, l]).select(0, index));
        let [m, hh, ww] = logits.dims();
        let count = |t: f32| -> Vec<f32> {
            let c = logits.clone().greater_elem(t).float().sum_dim(2).sum_dim(1).reshape([m]);
            c.into_data().convert::<f32>().into_vec::<f32>().expect("f32 counts")
        };
        let (inner, outer) =
            (count(f.mask_threshold + f.stability_offset), count(f.mask_threshold - f.stability_offset));
        let stable: Vec<usize> =
            (0..m).filter(|&j| f.stability <= 0.0 || (outer[j] > 0.0 && inner[j] / outer[j] > f.stability)).collect();
        if stable.is_empty() {
            times.masks_s += t.elapsed().as_secs_f64();
            return Vec::new();
        }
        let index: Vec<i64> = stable.iter().map(|&j| j as i64).collect();
        let index = Tensor::<1, Int>::from_data(TensorData::new(index, [stable.len()]), device);
        let masks = logits.select(0, index).greater_elem(f.mask_threshold);
        let masks = masks.into_data().convert::<bool>().into_vec::<bool>().expect("bool masks");
        let kept = stable
            .iter()
            .zip(masks.chunks_exact(hh * ww))
            .map(|(&j, mask)| AutoMask {
                bbox: mask_box(mask, ww),
                mask: mask.to_vec(),
                predicted_iou: iou[sel[j]],
                stability: if outer[j] > 0.0 { inner[j] / outer[j] } else { 0.0 },
            })
            .collect();
        times.masks_s += t.elapsed().as_secs_f64();
        kept
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_grid_of_cell_centres_x_fastest() {
        let g = point_grid(2);
        assert_eq!(g, vec![[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]]);
    }

    #[test]
    fn boxes_and_suppression() {
        // a 4x3 mask with pixels at (1, 0) and (2, 2)
        let mut m = vec![false; 12];
        m[1] = true;
        m[2 * 4 + 2] = true;
        assert_eq!(mask_box(&m, 4), [1, 0, 2, 2]);
        assert_eq!(mask_box(&[false; 12], 4), [0; 4]);
        let boxes = [[0, 0, 10, 10], [1, 1, 10, 10], [20, 20, 30, 30]];
        assert!((box_iou(boxes[0], boxes[1]) - 0.81).abs() < 1e-6);
        assert_eq!(nms(&boxes, &[0.9, 0.95, 0.5], 0.7), vec![1, 2]);
        assert_eq!(nms(&boxes, &[0.9, 0.95, 0.5], 0.9), vec![1, 0, 2]);
    }

    #[test]
    fn label_maps_paint_the_larger_masks_first() {
        let mask = |on: &[usize]| AutoMask {
            mask: (0..6).map(|p| on.contains(&p)).collect(),
            bbox: [0; 4],
            predicted_iou: 0.9,
            stability: 0.9,
        };
        // a small mask listed first, inside a large one; a third elsewhere
        let masks = [mask(&[1]), mask(&[0, 1, 2, 3]), mask(&[5])];
        assert_eq!(label_map(&masks, 6), vec![1, 2, 1, 1, 0, 3]);
        assert_eq!(label_map(&[], 3), vec![0; 3]);
    }
}
