#!/usr/bin/env python3
"""Reference automatic masks for the tiny SAM fixture: checkpoints/tiny-sam/auto_reference.safetensors.

Run by hand once after make_tiny_sam.py (CI needs no Python):

    /tmp/samvenv/bin/pip install torchvision    # the pipeline's box NMS
    /tmp/samvenv/bin/python checkpoints/make_tiny_sam_auto.py

transformers' mask-generation pipeline on the tiny random model (checkpoints/tiny-sam) and a small synthetic
image (56 x 40, so that the processor resizes it to 64 x 46 and pads it to 64 x 64): a grid of 8 x 8 points in
batches of 24 (the last batch short), three masks per point, the predicted-IoU and stability filters, box NMS.
The random model's logits are small (mostly within +-2) and its predicted IoU within +-0.7, so the stability
offset is 0.1 (not 1) and each filter is run alone (its predicted IoU is positive only for masks of stability 0,
and the pipeline turns off a threshold of 0 or less) with its threshold set between the candidates' values (no
candidate within 1e-3 of it, so that float noise cannot flip a decision). The PIL image processor is used:
chatsplat's resize is bit-exact with Pillow's. Written per filter: the kept masks (u8, best score first), their
scores and boxes, the thresholds, and the masks that pass the filters (in the order of the points, three per
point) with their scores; the image; and, since the tiny model's masks all span the image (one survives NMS),
torchvision's NMS alone on 60 random boxes.
"""
import os

import numpy as np
import torch
from PIL import Image
from safetensors.torch import save_file
from torchvision.ops import batched_nms
from transformers import SamModel, pipeline
from transformers.models.sam.image_processing_pil_sam import SamImageProcessorPil
from transformers.models.sam.image_processing_sam import _compute_stability_score

DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "tiny-sam")
POINTS, BATCH, NMS, OFFSET = 8, 24, 0.7, 0.1


def image():
    """A gradient with a disc, a bar and a block: something for the masks to follow."""
    h, w = 40, 56
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    rgb = np.stack([40 + 2 * x, 60 + 3 * y, 90 + x + y], -1)
    rgb[(x - 16) ** 2 + (y - 14) ** 2 < 80] = [230, 40, 30]
    rgb[26:34, 6:50] = [20, 200, 60]
    rgb[5:20, 36:52] = [250, 240, 20]
    return np.clip(rgb, 0, 255).astype(np.uint8)


def candidates(model, proc, img):
    """Every candidate's predicted IoU and stability, as the pipeline computes them (for the thresholds)."""
    inputs = proc(images=Image.fromarray(img), return_tensors="pt")
    emb = model.get_image_embeddings(inputs["pixel_values"])
    _, pts, _, labels = proc.generate_crop_boxes(Image.fromarray(img), 64, points_per_crop=POINTS)
    out = model(image_embeddings=emb, input_points=pts[:, :, 0:1, :], input_labels=labels[:, :, 0:1])
    masks = proc.post_process_masks(
        out.pred_masks, inputs["original_sizes"], inputs["reshaped_input_sizes"], binarize=False
    )[0]
    iou = out.iou_scores[0].flatten()
    stab = _compute_stability_score(masks.flatten(0, 1), 0.0, OFFSET)
    return iou, stab, masks.flatten(0, 1) > 0.0


def between(values, lo_share, margin):
    """A threshold near the given quantile with no value within `margin` of it."""
    v = np.sort(values.numpy())
    t = float(np.quantile(v, lo_share))
    while np.min(np.abs(v - t)) < margin:
        t += margin / 2
    return t


def run(model, proc, img, iou, stab, binary, pred_iou, stability):
    """The pipeline with these thresholds (0 turns a filter off, as in the pipeline), and the masks that pass."""
    gen = pipeline("mask-generation", model=model, image_processor=proc, device="cpu")
    out = gen(
        Image.fromarray(img),
        points_per_crop=POINTS,
        points_per_batch=BATCH,
        pred_iou_thresh=pred_iou,
        stability_score_thresh=stability,
        stability_score_offset=OFFSET,
        crops_nms_thresh=NMS,
        output_bboxes_mask=True,
    )
    masks = torch.stack([torch.as_tensor(np.asarray(m)) for m in out["masks"]]).to(torch.uint8)
    passed = torch.ones_like(iou, dtype=torch.bool)
    if pred_iou > 0:
        passed &= iou > pred_iou
    if stability > 0:
        passed &= stab > stability
    print(f"pred_iou {pred_iou:.4f} stability {stability:.4f}: {len(iou)} candidates, {int(passed.sum())} pass the")
    print(f"    filters, {masks.shape[0]} kept after NMS, of {masks.flatten(1).sum(1).tolist()} pixels")
    return {
        "masks": masks.contiguous(),
        "scores": out["scores"].float().contiguous(),
        "boxes": torch.as_tensor(out["bounding_boxes"]).float().contiguous(),
        "thresholds": torch.tensor([pred_iou, stability, OFFSET, 0.0, NMS], dtype=torch.float32),
        "passed": binary[passed].to(torch.uint8).contiguous(),
        "passed_scores": iou[passed].contiguous(),
    }


def main():
    torch.manual_seed(0)
    model = SamModel.from_pretrained(DIR, attn_implementation="eager").eval()
    proc = SamImageProcessorPil(size={"longest_edge": 64}, pad_size={"height": 64, "width": 64})
    img = image()
    out = {"image": torch.from_numpy(img), "grid": torch.tensor([POINTS, BATCH], dtype=torch.float32)}
    with torch.no_grad():
        iou, stab, binary = candidates(model, proc, img)
        # each filter alone: the random model's predicted IoU is positive only for masks of stability 0
        for name, pred_iou, stability in [
            ("stability", 0.0, between(stab, 0.75, 1e-3)),
            ("iou", between(iou[iou > 0], 0.4, 1e-3), 0.0),
        ]:
            for k, v in run(model, proc, img, iou, stab, binary, pred_iou, stability).items():
                out[f"{name}.{k}"] = v
    # torchvision's NMS alone on boxes that overlap in every way (the tiny model's masks all span the image)
    g = torch.Generator().manual_seed(5)
    corner = torch.randint(0, 12, (60, 2), generator=g)
    out["nms_boxes"] = torch.cat([corner, corner + torch.randint(8, 30, (60, 2), generator=g)], 1).float()
    out["nms_scores"] = torch.rand(60, generator=g)
    out["nms_keep"] = batched_nms(out["nms_boxes"], out["nms_scores"], torch.zeros(60), NMS).float()
    save_file(out, os.path.join(DIR, "auto_reference.safetensors"))


if __name__ == "__main__":
    main()
