//! SAM port: parity with transformers' `SamModel` on the tiny random fixture in
//! checkpoints/tiny-sam (built by checkpoints/make_tiny_sam.py), on ndarray (the whole pipeline
//! also on flex and wgpu): the image embeddings, the relative-position tables (resized and for unequal
//! query and key sizes), the prompt embeddings (points with a box, points alone with their
//! padding point, a mask prompt), and the masks and IoU of the mask decoder; and automatic masks
//! against transformers' mask-generation pipeline (checkpoints/make_tiny_sam_auto.py).
#![allow(deprecated)] // burn-ndarray and TensorData::to_vec are deprecated in burn 0.22; the card names ndarray.

use burn::tensor::{Device, Int, Tensor, TensorData};
use safetensors::{Dtype, SafeTensors};
use sam::automatic::{AutoMask, AutoOptions, Filters, nms, suppress};
use sam::image_encoder::rel_pos_table;
use sam::{Prompt, RgbImage, Sam};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Tolerance on max |ours - transformers| / max |transformers|.
const TOL: f32 = 1e-4;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../checkpoints/tiny-sam")
}

struct Reference(HashMap<String, (Vec<usize>, Vec<f32>)>);

impl Reference {
    fn read() -> Self {
        let bytes = std::fs::read(fixture().join("reference.safetensors")).expect("reference.safetensors");
        let st = SafeTensors::deserialize(&bytes).expect("valid reference");
        let mut out = HashMap::new();
        for (name, v) in st.tensors() {
            assert_eq!(v.dtype(), Dtype::F32, "{name}");
            let values = v.data().chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect();
            out.insert(name, (v.shape().to_vec(), values));
        }
        Self(out)
    }

    fn get(&self, name: &str) -> &(Vec<usize>, Vec<f32>) {
        self.0.get(name).unwrap_or_else(|| panic!("reference has no {name}"))
    }

    fn tensor<const D: usize>(&self, name: &str, device: &Device) -> Tensor<D> {
        let (shape, values) = self.get(name);
        Tensor::from_data(TensorData::new(values.clone(), shape.clone()), device)
    }

    /// `ours` against `name`: same shape, max abs difference within [`TOL`] of the reference's
    /// max abs value; returns that relative error.
    fn check<const D: usize>(&self, name: &str, ours: Tensor<D>) -> f32 {
        let (shape, want) = self.get(name);
        assert_eq!(&ours.dims().to_vec(), shape, "{name}: shape");
        let got = ours.into_data().to_vec::<f32>().expect("f32");
        let diff = got.iter().zip(want).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
        let scale = want.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        let rel = diff / scale;
        println!("{name:28} max abs diff {diff:.3e}, relative {rel:.3e}");
        assert!(rel <= TOL, "{name}: max abs diff {diff} is {rel} of the reference's max {scale}");
        rel
    }
}

fn model(device: &Device) -> Sam {
    Sam::load(&fixture(), device).expect("tiny SAM loads")
}

/// Points (x, y) and labels of the reference's prompt.
fn points(r: &Reference, device: &Device) -> (Tensor<4>, Tensor<3, Int>) {
    let (shape, labels) = r.get("input_labels");
    let labels: Vec<i64> = labels.iter().map(|&l| l as i64).collect();
    (r.tensor("input_points", device), Tensor::from_data(TensorData::new(labels, shape.clone()), device))
}

#[test]
fn image_embeddings_match_transformers() {
    let device = Device::ndarray();
    let (r, sam) = (Reference::read(), model(&device));
    r.check("image_embeddings", sam.image_embeddings(r.tensor("pixel_values", &device)));
}

#[test]
fn relative_position_tables_match_transformers() {
    let device = Device::ndarray();
    let r = Reference::read();
    for (name, q, k) in [("rel_pos_4_4", 4, 4), ("rel_pos_2_5", 2, 5), ("rel_pos_5_3", 5, 3)] {
        r.check(name, rel_pos_table(q, k, r.tensor("rel_pos", &device)));
    }
}

#[test]
fn prompt_embeddings_match_transformers() {
    let device = Device::ndarray();
    let (r, sam) = (Reference::read(), model(&device));
    let pe = &sam.prompt_encoder;
    r.check("image_positional_embeddings", pe.image_positional_embeddings());
    let prompt =
        Prompt { points: Some(points(&r, &device)), boxes: Some(r.tensor("input_boxes", &device)), masks: None };
    let (sparse, dense) = pe.forward(&prompt);
    r.check("sparse_embeddings", sparse.expect("sparse"));
    r.check("dense_embeddings", dense);
    let alone = Prompt { points: Some(points(&r, &device)), ..Prompt::default() };
    r.check("points_sparse_embeddings", pe.forward(&alone).0.expect("sparse"));
    let with_mask = Prompt { masks: Some(r.tensor("input_masks", &device)), ..prompt };
    r.check("mask_dense_embeddings", pe.forward(&with_mask).1);
}

#[test]
fn masks_and_iou_match_transformers() {
    let device = Device::ndarray();
    let (r, sam) = (Reference::read(), model(&device));
    let embeddings: Tensor<4> = r.tensor("image_embeddings", &device);
    let prompt =
        Prompt { points: Some(points(&r, &device)), boxes: Some(r.tensor("input_boxes", &device)), masks: None };
    let (masks, iou) = sam.segment(embeddings.clone(), &prompt, true);
    r.check("pred_masks", masks);
    r.check("iou_scores", iou);
    let alone = Prompt { points: Some(points(&r, &device)), ..Prompt::default() };
    let (masks, iou) = sam.segment(embeddings, &alone, true);
    r.check("points_pred_masks", masks);
    r.check("points_iou_scores", iou);
}

/// The whole pipeline from pixels (our image embeddings into our decoder) on ndarray and flex,
/// and the convenience constructor of a single prompt.
#[test]
fn pixels_to_masks_match_transformers() {
    let r = Reference::read();
    for device in [Device::ndarray(), Device::flex()] {
        let sam = model(&device);
        let embeddings = sam.image_embeddings(r.tensor("pixel_values", &device));
        let prompt = Prompt::single(&[(10.0, 20.0, 1), (41.5, 35.0, 0)], Some([5.0, 8.0, 50.0, 60.0]), &device);
        let (masks, iou) = sam.segment(embeddings, &prompt, true);
        r.check("pred_masks", masks);
        r.check("iou_scores", iou);
    }
}

/// The same on wgpu (lavapipe in CI, any GPU): the image embeddings, then the masks and IoU
/// predictions from them; skipped with a message where no adapter can run the op.
#[test]
fn pixels_to_masks_match_transformers_on_wgpu() {
    let Some(device) = chatsplat_tests::wgpu_device() else { return };
    let r = Reference::read();
    let sam = model(&device);
    let embeddings = sam.image_embeddings(r.tensor("pixel_values", &device));
    r.check("image_embeddings", embeddings.clone());
    let prompt = Prompt::single(&[(10.0, 20.0, 1), (41.5, 35.0, 0)], Some([5.0, 8.0, 50.0, 60.0]), &device);
    let (masks, iou) = sam.segment(embeddings, &prompt, true);
    r.check("pred_masks", masks);
    r.check("iou_scores", iou);
}

/// checkpoints/tiny-sam/auto_reference.safetensors (checkpoints/make_tiny_sam_auto.py): every
/// tensor as f32, u8 ones converted.
fn auto_reference() -> HashMap<String, (Vec<usize>, Vec<f32>)> {
    let bytes = std::fs::read(fixture().join("auto_reference.safetensors")).expect("auto_reference.safetensors");
    let st = SafeTensors::deserialize(&bytes).expect("valid reference");
    st.tensors()
        .into_iter()
        .map(|(name, v)| {
            let values = match v.dtype() {
                Dtype::U8 => v.data().iter().map(|&b| b as f32).collect(),
                Dtype::F32 => v.data().chunks_exact(4).map(|b| f32::from_le_bytes(b.try_into().unwrap())).collect(),
                other => panic!("{name}: {other:?}"),
            };
            (name, (v.shape().to_vec(), values))
        })
        .collect()
}

/// Masks against the reference's `[K, H, W]` masks: the same count, IoU at least 0.99 each,
/// predicted IoU within 1e-4; returns the least IoU.
fn same_masks(ours: &[AutoMask], want: &(Vec<usize>, Vec<f32>), scores: &[f32], what: &str) -> f64 {
    let (shape, values) = want;
    assert_eq!(ours.len(), shape[0], "{what}: mask count");
    let mut least = 1.0f64;
    for (k, (m, w)) in ours.iter().zip(values.chunks_exact(shape[1] * shape[2])).enumerate() {
        let inter = m.mask.iter().zip(w).filter(|(a, b)| **a && **b > 0.5).count();
        let union = m.mask.iter().zip(w).filter(|(a, b)| **a || **b > 0.5).count();
        let iou = if union == 0 { 1.0 } else { inter as f64 / union as f64 };
        least = least.min(iou);
        assert!(iou >= 0.99, "{what} {k}: IoU {iou} with the pipeline's mask");
        assert!((m.predicted_iou - scores[k]).abs() < 1e-4, "{what} {k}: score {} vs {}", m.predicted_iou, scores[k]);
    }
    println!("{what}: {} masks, least IoU with the pipeline's {least:.4}", ours.len());
    least
}

/// Automatic masks as transformers' mask-generation pipeline makes them on the tiny model (a
/// 56 x 40 image resized and padded to 64, 8 x 8 points in batches of 24, each filter alone with
/// its threshold between the random model's values): the masks that pass the filters, then those
/// NMS keeps, on ndarray (and flex for one filter).
#[test]
fn automatic_masks_match_the_pipeline() {
    let r = auto_reference();
    let (shape, pixels) = &r["image"];
    let img = RgbImage::new(shape[1], shape[0], pixels.iter().map(|&v| v as u8).collect());
    for (filter, device) in
        [("stability", Device::ndarray()), ("iou", Device::ndarray()), ("stability", Device::flex())]
    {
        let at = |name: &str| &r[&format!("{filter}.{name}")];
        let (t, grid) = (&at("thresholds").1, &r["grid"].1);
        let f =
            Filters { pred_iou: t[0], stability: t[1], stability_offset: t[2], mask_threshold: t[3], nms_iou: t[4] };
        let o = AutoOptions { points_per_side: grid[0] as usize, points_per_batch: grid[1] as usize, filters: f };
        let sam = model(&device);
        let passing = sam.passing_masks(&img, &o, &device);
        same_masks(&passing, at("passed"), &at("passed_scores").1, &format!("{filter}: passing"));
        let kept = suppress(passing, o.filters.nms_iou);
        same_masks(&kept, at("masks"), &at("scores").1, &format!("{filter}: kept"));
        let boxes: Vec<u32> = at("boxes").1.iter().map(|&b| b as u32).collect();
        assert_eq!(kept.iter().flat_map(|m| m.bbox).collect::<Vec<_>>(), boxes, "{filter}: boxes");
    }
}

/// Box NMS against torchvision's `batched_nms` on 60 random overlapping boxes (the tiny model's
/// masks all span the image, so the pipeline's own NMS keeps one).
#[test]
fn box_suppression_matches_torchvision() {
    let r = auto_reference();
    let boxes: Vec<[u32; 4]> =
        r["nms_boxes"].1.chunks_exact(4).map(|b| [b[0] as u32, b[1] as u32, b[2] as u32, b[3] as u32]).collect();
    let keep: Vec<usize> = r["nms_keep"].1.iter().map(|&i| i as usize).collect();
    assert!(keep.len() < boxes.len(), "the fixture suppresses some boxes");
    assert_eq!(nms(&boxes, &r["nms_scores"].1, 0.7), keep);
}
