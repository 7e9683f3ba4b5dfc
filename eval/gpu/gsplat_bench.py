#!/usr/bin/env python3
"""Time gsplat's CUDA rasterizer on the scenes `splat-bench` times chatsplat's op on (issue 12,
item 6): the peer of its wgpu column, on the same GPU in the same `device` call.

Run by `eval/gpu/run.sh bench` on a machine with CUDA (gsplat compiles its kernels on first use,
which takes minutes and is timed apart); by hand:

    python3 eval/gpu/gsplat_bench.py --n 100000,1000000 --c 3,32 --res 384x384,1280x720

The scene follows `splat-bench`'s recipe (the same distributions, not the same draws: a box of
`n` Gaussians 3-5 units in front of a camera at the origin looking down +z, sizes shrinking as
n^(-1/3), random rotations and opacities, `c` feature channels in [0, 1), 50 degrees vertical
field of view, black background). Each figure is the median of up to 5 timed runs after a
warm-up, each run ending with a device synchronisation: forward (features and alpha), and
forward + backward of sum(features) + sum(alpha). Prints a markdown table; `--out` also writes
JSON.
"""
import argparse
import json
import math
import os
import sys
import time


def pairs(text, name):
    out = []
    for part in text.split(","):
        try:
            w, h = part.lower().split("x")
            out.append((int(w), int(h)))
        except ValueError:
            sys.exit(f"error: --{name} {text}: expected WxH[,WxH...]")
    return out


def ints(text, name):
    try:
        return [int(float(v)) for v in text.split(",")]
    except ValueError:
        sys.exit(f"error: --{name} {text}: expected numbers separated by commas")


def scene(torch, n, c, device, seed):
    g = torch.Generator(device="cpu").manual_seed(seed)
    u = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    sigma = 0.8 * (8.0 / n) ** (1.0 / 3.0)
    means = torch.stack([u(n) * 3.0 - 1.5, u(n) * 2.0 - 1.0, 3.0 + u(n) * 2.0], dim=1)
    scales = sigma * (0.3 + u(n, 3))
    quats = u(n, 4) - 0.5
    quats = quats / quats.norm(dim=1, keepdim=True).clamp_min(1e-8)
    opacities = torch.sigmoid(u(n) * 4.0 - 2.0)
    feats = u(n, c)
    return [t.to(device) for t in (means, quats, scales, opacities, feats)]


def median_ms(torch, f):
    f()  # warm-up
    torch.cuda.synchronize()
    times = []
    start = time.perf_counter()
    while len(times) < 5 and (not times or time.perf_counter() - start < 1.5):
        t = time.perf_counter()
        f()
        torch.cuda.synchronize()
        times.append((time.perf_counter() - t) * 1e3)
    times.sort()
    return times[len(times) // 2]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", default="100000,1000000")
    ap.add_argument("--c", default="3,32")
    ap.add_argument("--res", default="384x384,1280x720")
    ap.add_argument("--out", help="also write the figures as JSON (atomically)")
    a = ap.parse_args()
    ns, cs, res = ints(a.n, "n"), ints(a.c, "c"), pairs(a.res, "res")

    import torch

    if not torch.cuda.is_available():
        print(f"gsplat-bench: skipped, torch {torch.__version__} sees no CUDA device", file=sys.stderr)
        return 0
    t0 = time.perf_counter()
    try:
        import gsplat
        from gsplat import rasterization
    except ImportError as e:
        sys.exit(f"error: gsplat is not importable ({e}); eval/gpu/run.sh pack carries its wheel in .whl")
    device = torch.device("cuda")
    # the first call compiles gsplat's CUDA kernels (JIT): timed on its own
    m, q, s, o, f = scene(torch, 1000, 3, device, 0)
    viewmat = torch.eye(4, device=device)[None]
    k = torch.tensor([[[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]]], device=device)
    rasterization(m, q, s, o, f, viewmat, k, 64, 64)
    torch.cuda.synchronize()
    print(f"gsplat {gsplat.__version__}: ready in {time.perf_counter() - t0:.1f} s (kernel compilation)", file=sys.stderr)

    gpu = torch.cuda.get_device_name(device)
    rows = []
    print(f"\n## gsplat {gsplat.__version__} (CUDA, {gpu}), torch {torch.__version__}\n")
    print("| N | C | image | forward ms | forward + backward ms |")
    print("|---|---|---|---|---|")
    for n in ns:
        for c in cs:
            means, quats, scales, opacities, feats = scene(torch, n, c, device, n * 31 + c)
            for w, h in res:
                fy = 0.5 * h / math.tan(math.radians(25.0))
                K = torch.tensor([[[fy, 0, w / 2], [0, fy, h / 2], [0, 0, 1]]], device=device)

                def forward():
                    with torch.no_grad():
                        img, alpha, _ = rasterization(
                            means, quats, scales, opacities, feats, viewmat, K, w, h
                        )
                    return img, alpha

                leaves = [t.detach().clone().requires_grad_(True) for t in (means, quats, scales, opacities, feats)]

                def forward_backward():
                    img, alpha, _ = rasterization(*leaves, viewmat, K, w, h)
                    (img.sum() + alpha.sum()).backward()

                fwd = median_ms(torch, forward)
                bwd = median_ms(torch, forward_backward)
                rows.append({"n": n, "c": c, "width": w, "height": h, "forward_ms": fwd, "forward_backward_ms": bwd})
                print(f"| {n:,} | {c} | {w}x{h} | {fwd:.2f} | {bwd:.2f} |", flush=True)
    if a.out:
        tmp = a.out + ".tmp"
        with open(tmp, "w") as fh:
            json.dump({"gsplat": gsplat.__version__, "torch": torch.__version__, "device": gpu, "rows": rows}, fh, indent=1)
        os.replace(tmp, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
