#!/usr/bin/env bash
# chatsplat's LLaVA-OneVision port against transformers, one after the other on this machine,
# same random-weight configuration, same thread count (issue 12, item 1). Run by hand:
#
#   bash eval/bench/vlm_vs_transformers.sh [0.5b|7b] [threads] [decode tokens] [backends]
#
# backends: chatsplat's CPU backends to time, default "flex ndarray"; then flex once more with
# the weights held in f16 (--half) unless HALF=0.
#
# Needs python3 (or $PYTHON) with torch and transformers (pip install torch transformers) and a release build
# (`cargo build --release -p eval --bin vlm-bench`). Prints vlm-bench's table, then both side by
# side as ratios; the transformers timings are kept in target/transformers_<size>.json.
set -euo pipefail
size=${1:-0.5b}
threads=${2:-2}
decode=${3:-16}
backends=${4:-flex ndarray}
cd "$(dirname "$0")/../.."
bench=target/release/vlm-bench
[ -x "$bench" ] || { echo "error: $bench is missing: cargo build --release -p eval --bin vlm-bench" >&2; exit 1; }
ref=target/transformers_$size.json
mem_gib=$(awk '/MemTotal/ { print int($2 / 1048576) }' /proc/meminfo)
if [ "$size" = 7b ] && [ "$mem_gib" -lt 40 ]; then
    # transformers builds the 7B in f32 (32 GB), and so would chatsplat without --half: below 40 GiB
    # only chatsplat's f16 copy (15 GB) runs, one pass of each stage without warm-ups (--cold)
    echo "## chatsplat, 7b, weights held in f16, $threads threads ($mem_gib GiB: transformers' f32 7B does not fit)" >&2
    RAYON_NUM_THREADS=$threads "$bench" --random 7b --backend flex --half --cold --decode "$decode"
    exit 0
fi
# chatsplat's prompt for vlm-bench's built-in 700x300 image at the published anyres grid
prefill=2005
echo "## transformers, $size, $threads threads" >&2
${PYTHON:-python3} eval/bench/transformers_vlm.py --size "$size" --threads "$threads" --prefill-tokens "$prefill" \
    --decode "$decode" --reps 1 --out "$ref" >/dev/null
echo "## chatsplat, $size" >&2
RAYON_NUM_THREADS=$threads "$bench" --random "$size" --backend $backends --reps 1 --decode "$decode" --reference "$ref"
if [ "${HALF:-1}" != 0 ]; then
    echo "## chatsplat, $size, weights held in f16" >&2
    RAYON_NUM_THREADS=$threads "$bench" --random "$size" --backend flex --half --reps 1 --decode "$decode" --reference "$ref"
fi
