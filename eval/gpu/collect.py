#!/usr/bin/env python3
"""One GPU lease's raw figures as one JSON file (issue 63): run here, by hand, on the folder that
`eval/gpu/run.sh bench` filled there and the device tool brought back.

    python3 eval/gpu/collect.py OUTDIR [OUTDIR2 ...] --commit abc1234 --out eval/gpu/results/2026-12-04.json

Reads each folder's `gpu_bench.log` (splat-bench's tables, vlm-bench's side-by-side table, the
nvidia-smi line), `gsplat.json` and `transformers_cuda.json` where present, and writes

    {"device": .., "driver": .., "commit": .., "adapter": ..,
     "splat": [{"res": "1280x720", "n": 100000, "c": 32, "ours_fwd_ms": .., "gsplat_fwd_ms": ..,
                "ours_fwdbwd_ms": .., "gsplat_fwdbwd_ms": .., "ours_cas_fwdbwd_ms": ..}, ..],
     "vlm": [{"stage": "tower" | "prefill" | "decode", "ours": .., "transformers": .., "unit": ..}, ..],
     "transformers": {transformers_cuda.json}}

`ours_cas_fwdbwd_ms` is the compare-and-swap table's figure (`--float-add cas`) where the lease ran
one; likewise `ours_bitonic_*` (`--tile-sort bitonic`), `ours_spirv_*` (the SPIR-V build),
`ours_fusion_*` (the fusion build) and `ours_atomic_*` / `ours_plane_*` (`--grad-reduce`); each vlm
row likewise `ours_half` (`--half`), `ours_spirv` and `ours_fusion` (those builds). Before, the
SPIR-V and `--grad-reduce` tables were read as the default one and overwrote its rows. Exits non-zero, naming the file, when a
folder holds no splat-bench table.
"""
import argparse
import json
import os
import re
import sys


def flavour_of(command):
    """Which table a splat-bench command line makes: "auto" (the default paths), "cas", "bitonic",
    "plane" / "atomic" (--grad-reduce), "spirv" (the SPIR-V build), "fusion" (the fusion build), or None
    (--accuracy)."""
    if "--accuracy" in command:
        return None
    for flag, name in [("splat-bench-spirv", "spirv"), ("splat-bench-fusion", "fusion"), ("--float-add cas", "cas"),
                       ("--tile-sort bitonic", "bitonic"), ("--grad-reduce atomic", "atomic"),
                       ("--grad-reduce plane", "plane")]:
        if flag in command:
            return name
    return "auto"


def splat_tables(log):
    """splat-bench tables of the log: {command flavour: {(res, n, c): (fwd, fwdbwd)}}."""
    tables, flavour = {}, None
    for line in log.splitlines():
        if line.startswith("$ ") and "splat-bench" in line:
            flavour = flavour_of(line)
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if flavour and len(cells) == 10 and re.fullmatch(r"\d+x\d+", cells[0]):
            def ms(s):
                s = s.lstrip("~")
                return float(s) if re.fullmatch(r"[0-9.]+", s) else None
            tables.setdefault(flavour, {})[(cells[0], int(cells[1]), int(cells[2]))] = (ms(cells[5]), ms(cells[6]))
    return tables


def vlm_rows(log, reference):
    """The wgpu row of vlm-bench's tables against transformers' JSON (`reference`): `ours` from the
    default build in f32, and `ours_half` / `ours_spirv` / `ours_fusion` from the `--half` run and the
    SPIR-V and fusion builds where the lease ran them."""
    found, flavour = {}, None
    for line in log.splitlines():
        if line.startswith("$ ") and "vlm-bench" in line:
            flavour = ("spirv" if "vlm-bench-spirv" in line else "fusion" if "vlm-bench-fusion" in line
                       else "half" if "--half" in line else "")
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if flavour is not None and len(cells) == 7 and cells[0] == "wgpu" and cells[1].endswith(" ms"):
            found.setdefault(flavour, (float(cells[1].split()[0]), float(cells[5]), float(cells[6])))
    if "" not in found:
        return []
    stages = [("tower", reference["vision_s"] * 1e3, "ms"),
              ("prefill", reference["prefill_tokens_per_s"], "tokens/s"),
              ("decode", reference["decode_tokens_per_s"], "tokens/s")]
    rows = []
    for k, (stage, peer, unit) in enumerate(stages):
        row = {"stage": stage, "ours": found[""][k], "transformers": peer, "unit": unit}
        for flavour in ["half", "spirv", "fusion"]:
            if flavour in found:
                row["ours_" + flavour] = found[flavour][k]
        rows.append(row)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+")
    ap.add_argument("--commit", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--device", help="the GPU, where the log has no nvidia-smi line")
    ap.add_argument("--driver", help="its driver version, likewise")
    a = ap.parse_args()
    result = {"device": a.device, "driver": a.driver, "commit": a.commit, "adapter": None, "splat": [], "vlm": []}
    tables, gsplat, logs = {}, {}, []
    for d in a.dirs:
        path = os.path.join(d, "gpu_bench.log")
        if not os.path.exists(path):
            sys.exit(f"error: {path}: no such file (the folder `eval/gpu/run.sh bench` wrote)")
        log = open(path, encoding="utf-8").read()
        for flavour, rows in splat_tables(log).items():
            tables.setdefault(flavour, {}).update(rows)
        logs.append(log)
        for line in log.splitlines():
            m = re.match(r"(NVIDIA [^,]+), [0-9]+ MiB, ([0-9.]+)$", line.strip())
            if m:
                result["device"], result["driver"] = m.group(1), m.group(2)
            if line.startswith("adapter `"):
                result["adapter"] = line.strip()
        gs = os.path.join(d, "gsplat.json")
        if os.path.exists(gs):
            for r in json.load(open(gs))["rows"]:
                gsplat[(f"{r['width']}x{r['height']}", r["n"], r["c"])] = (r["forward_ms"], r["forward_backward_ms"])
        tr = os.path.join(d, "transformers_cuda.json")
        if os.path.exists(tr):
            result["transformers"] = json.load(open(tr))
    if "transformers" in result:
        for log in logs:
            result["vlm"] += vlm_rows(log, result["transformers"])
    if "auto" not in tables:
        sys.exit(f"error: {', '.join(a.dirs)}: no splat-bench table in gpu_bench.log")
    for key, (fwd, fb) in sorted(tables["auto"].items(), key=lambda kv: (kv[0][0] != "384x384", kv[0][2], kv[0][1])):
        g = gsplat.get(key, (None, None))
        row = {"res": key[0], "n": key[1], "c": key[2], "ours_fwd_ms": fwd, "gsplat_fwd_ms": g[0],
               "ours_fwdbwd_ms": fb, "gsplat_fwdbwd_ms": g[1]}
        if key in tables.get("cas", {}):
            row["ours_cas_fwdbwd_ms"] = tables["cas"][key][1]
        for other in ["bitonic", "spirv", "fusion", "atomic", "plane"]:
            if key in tables.get(other, {}):
                row[f"ours_{other}_fwd_ms"], row[f"ours_{other}_fwdbwd_ms"] = tables[other][key]
        result["splat"].append(row)
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    tmp = a.out + ".tmp"
    with open(tmp, "w") as f:
        json.dump(result, f, indent=1)
        f.write("\n")
    os.replace(tmp, a.out)
    print(f"{a.out}: {len(result['splat'])} splat rows, {len(result['vlm'])} vlm rows")


if __name__ == "__main__":
    main()
