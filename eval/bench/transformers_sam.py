#!/usr/bin/env python3
"""transformers' SAM automatic masks timed on the CPU: the reference half of sam_vs_transformers.sh.

    python3 eval/bench/transformers_sam.py --model DIR --image PATH [--threads 2] [--out t.json]

Builds a random SAM ViT-B (transformers' SamConfig() defaults: width 768, 12 layers, 1024-px input) into DIR
when DIR has no config.json (seeded; the speed does not depend on the weights' values), then times, on one
image: the image embeddings alone, and the mask-generation pipeline (crops off, 32 x 32 points in batches of 64,
three masks a point, the default filters and NMS), which includes them. Prints and writes a JSON of seconds.
"""
import argparse
import json
import os
import time

import torch
from PIL import Image
from transformers import SamConfig, SamModel, pipeline
from transformers.models.sam.image_processing_pil_sam import SamImageProcessorPil


def build(model_dir):
    torch.manual_seed(0)
    model = SamModel(SamConfig())
    model.save_pretrained(model_dir)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", required=True)
    ap.add_argument("--image", required=True)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--points", type=int, default=32)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--pred-iou", type=float, default=0.88)
    ap.add_argument("--stability", type=float, default=0.95)
    ap.add_argument("--out")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if not os.path.isfile(os.path.join(a.model, "config.json")):
        build(a.model)
    model = SamModel.from_pretrained(a.model).eval()
    proc = SamImageProcessorPil()
    image = Image.open(a.image).convert("RGB")
    gen = pipeline("mask-generation", model=model, image_processor=proc, device="cpu")
    with torch.no_grad():
        pixels = proc(images=image, return_tensors="pt")["pixel_values"]
        model.get_image_embeddings(pixels)  # warm-up
        t0 = time.perf_counter()
        model.get_image_embeddings(pixels)
        encoder = time.perf_counter() - t0
        t0 = time.perf_counter()
        out = gen(
            image,
            points_per_crop=a.points,
            points_per_batch=a.batch,
            pred_iou_thresh=a.pred_iou,
            stability_score_thresh=a.stability,
        )
        total = time.perf_counter() - t0
    r = {
        "encoder_s": encoder,
        "automatic_s": total,
        "masks": len(out["masks"]),
        "image": list(image.size),
        "points": a.points,
        "batch": a.batch,
        "threads": a.threads,
        "torch": torch.__version__,
    }
    print(json.dumps(r))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(r, f)


if __name__ == "__main__":
    main()
