"""Per-view instance masks for `chatsplat masks --per-view` without a learned segmenter.

SAM's weights cannot be downloaded on the machines this project is built on, so this stands in for
a segmenter: scikit-image's Felzenszwalb graph segmentation of each image (colours in [0, 1], smoothed),
segments smaller than `--min-fraction` of the image left unmasked (0). Its ids are arbitrary per
image, as any segmenter's are; `chatsplat masks` makes them agree across views. Like SAM's
automatic masks it splits objects into parts and merges neighbours of similar colour: those are
the errors the matching is built to absorb.

    python3 -m venv /tmp/segvenv && /tmp/segvenv/bin/pip install scikit-image
    /tmp/segvenv/bin/python eval/masks/classic_segments.py --data ../shared/datasets/fox \
        --downscale 8 --out fox-per-view

With `--depth DIR` (each view's depth rendered from a geometry run trained on the capture:
`target/debug/view-depth --run RUN --out DIR`) segments also break where depth jumps, which
separates an object from a background of its own colour.

Writes OUT/<image stem>.png (16-bit ids, the image's size divided by --downscale) for every
frame of the capture's transforms.json (or every image in DATA/images).
"""

import argparse
import json
import os
import sys

import numpy as np
from skimage import io, segmentation, transform


def frames(data):
    """The capture's image paths: transforms.json's frames, else DATA/images/*."""
    paths = []
    for name in ("transforms.json", "transforms_train.json", "transforms_test.json"):
        p = os.path.join(data, name)
        if os.path.isfile(p):
            with open(p) as f:
                for fr in json.load(f)["frames"]:
                    fp = os.path.join(data, fr["file_path"])
                    if not os.path.splitext(fp)[1]:
                        fp += ".png"
                    paths.append(fp)
    if not paths:
        d = os.path.join(data, "images")
        paths = [os.path.join(d, n) for n in sorted(os.listdir(d))]
    return paths


def off_plane(depth, args):
    """Pixels nearer than the view's dominant plane (a wall, a table): inverse depth is affine in
    the pixel coordinates on a plane, fitted by RANSAC; `None` where the view has no dominant
    plane (fewer than half its drawn pixels within the tolerance)."""
    h, w = depth.shape
    drawn = depth > 0
    if drawn.sum() < 100:
        return None
    inv = np.where(drawn, 1.0 / np.maximum(depth.astype(np.float64), 1.0), 0.0)
    ys, xs = np.nonzero(drawn)
    a = np.stack([xs / w, ys / h, np.ones_like(xs, dtype=np.float64)], 1)
    b = inv[ys, xs]
    rng = np.random.default_rng(0)
    tol = args.plane_tolerance * np.median(b)
    best, best_in = None, 0
    for _ in range(200):
        pick = rng.choice(len(b), 3, replace=False)
        try:
            coef = np.linalg.solve(a[pick], b[pick])
        except np.linalg.LinAlgError:
            continue
        n_in = int((np.abs(a @ coef - b) < tol).sum())
        if n_in > best_in:
            best, best_in = coef, n_in
    if best is None or best_in < 0.5 * len(b):
        return None
    inl = np.abs(a @ best - b) < tol
    best = np.linalg.lstsq(a[inl], b[inl], rcond=None)[0]
    yy, xx = np.mgrid[0:h, 0:w]
    plane = best[0] * xx / w + best[1] * yy / h + best[2]
    return drawn & (inv > plane + tol)


def segment(rgb, depth, args):
    """`depth`: None, or the view's rendered depth (0 = nothing drawn) added as a channel of
    `--depth-weight` x log depth, so that segments break where depth jumps."""
    if depth is not None:
        z = depth.astype(np.float32)
        drawn = z > 0
        z = np.log(np.where(drawn, z, z[drawn].max() if drawn.any() else 1.0))
        rgb = np.concatenate([rgb, args.depth_weight * z[..., None]], -1)
    seg = segmentation.felzenszwalb(rgb, scale=args.scale, sigma=args.sigma, min_size=args.min_size)
    near = off_plane(depth, args) if depth is not None and args.plane_tolerance > 0 else None
    if near is not None:
        # what stands off the plane and what lies on it are never one segment
        seg = seg * 2 + near.astype(seg.dtype)
    ids, counts = np.unique(seg, return_counts=True)
    keep = ids[counts >= args.min_fraction * seg.size]
    out = np.zeros(seg.shape, np.uint16)
    for k, i in enumerate(keep):
        out[seg == i] = k + 1
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--downscale", type=int, default=1)
    p.add_argument("--scale", type=float, default=400.0)
    p.add_argument("--sigma", type=float, default=1.0)
    p.add_argument("--min-size", type=int, default=60)
    p.add_argument("--min-fraction", type=float, default=0.01)
    p.add_argument("--depth", help="rendered depth maps, DIR/<image stem>.png (eval's view-depth)")
    p.add_argument("--depth-weight", type=float, default=3.0)
    p.add_argument("--plane-tolerance", type=float, default=0.05,
                   help="with --depth: segments are cut where pixels leave the view's dominant plane by more "
                        "than this share of its inverse depth (0: off)")
    args = p.parse_args()
    if os.path.exists(args.out) and os.listdir(args.out):
        sys.exit(f"{args.out}: exists and is not empty; name a new folder")
    os.makedirs(args.out, exist_ok=True)
    for path in frames(args.data):
        img = io.imread(path)[..., :3].astype(np.float32) / 255.0
        if args.downscale > 1:
            h, w = img.shape[0] // args.downscale, img.shape[1] // args.downscale
            img = transform.resize(img, (h, w), anti_aliasing=True)
        stem = os.path.splitext(os.path.basename(path))[0]
        depth = None
        if args.depth:
            depth = io.imread(os.path.join(args.depth, stem + ".png"))
            if depth.shape != img.shape[:2]:
                sys.exit(f"{args.depth}/{stem}.png: {depth.shape[1]}x{depth.shape[0]}, not the image's "
                         f"{img.shape[1]}x{img.shape[0]} at --downscale {args.downscale}")
        ids = segment(img, depth, args)
        io.imsave(os.path.join(args.out, stem + ".png"), ids, check_contrast=False)
        print(f"{stem}: {ids.max()} segments", flush=True)


if __name__ == "__main__":
    main()
