#!/usr/bin/env bash
# chatsplat's Segment Anything automatic masks against transformers' mask-generation pipeline, one
# after the other on this machine: the same random SAM ViT-B (built by transformers_sam.py into
# target/sam-vit-b-random the first time), the same image, the same thread count. Run by hand:
#
#   bash eval/bench/sam_vs_transformers.sh [image] [threads] [backends]
#
# image: default the first photo of ../shared/datasets/fox (1080x1920), else pass one.
# Needs python3 (or $PYTHON) with torch, torchvision and transformers, and
# `cargo build --workspace --profile test --bin sam-bench`. Prints both side by side as ratios.
set -euo pipefail
cd "$(dirname "$0")/../.."
image=${1:-../shared/datasets/fox/images/0001.jpg}
threads=${2:-2}
backends=${3:-flex ndarray}
bench=target/debug/sam-bench
[ -x "$bench" ] || { echo "error: $bench is missing: cargo build --workspace --profile test --bin sam-bench" >&2; exit 1; }
[ -f "$image" ] || { echo "error: $image: no such image (pass one as the first argument)" >&2; exit 1; }
model=target/sam-vit-b-random
ref=target/transformers_sam.json
echo "## transformers, $threads threads" >&2
${PYTHON:-python3} eval/bench/transformers_sam.py --model "$model" --image "$image" --threads "$threads" --out "$ref"
echo "## chatsplat" >&2
RAYON_NUM_THREADS=$threads "$bench" --model "$model" --image "$image" --backend $backends --reference "$ref"
