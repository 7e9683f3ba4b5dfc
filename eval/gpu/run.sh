#!/usr/bin/env bash
# GPU figures in one `device` call (issue 12, item 6). Two steps:
#
#   bash eval/gpu/run.sh pack            # here: release binaries, stripped and xz-compressed
#                                        # together (24 MB for the four; a carry takes 64 MiB)
#                                        # into .gpu/bin/bins.tar.xz, each variant build into its
#                                        # own .gpu/bin/VARIANT.tar.xz; the Vulkan loader .debs into
#                                        # .gl/; gsplat's wheel into .whl/ (all three git-excluded)
#   bash eval/gpu/run.sh bench [OUTDIR]  # there (carry .gpu/bin/bins.tar.xz .gl .whl), or here
#
# The carry holds 64 MiB, the working tree's 29 MB included: the four binaries (24 MB) with
# .whl (6 MB) fit, and the variants (fusion's pair 17.2 MB; spirv's not packed yet) fit in a call of
# their own, which carries .gpu/bin/fusion.tar.xz .gpu/bin/spirv.tar.xz .gl and runs
# CHATSPLAT_GPU_PARTS="fusion spirv". `bench` unpacks every archive it finds.
#
# `bench` unpacks the carried Vulkan loaders when the machine has none, then times, each with the
# command line printed above its output (into OUTDIR, default $OUT or ./gpu-out):
#   splat  splat-bench: the splatting op on wgpu and ndarray, N = 1e5 and 1e6, C = 3 and 32;
#   peers  where torch sees CUDA: gsplat's CUDA rasterizer on the same N, C and image sizes
#          (eval/gpu/gsplat_bench.py; its kernels compile on first use, timed apart) and
#          transformers on CUDA at 0.5B (eval/bench/transformers_vlm.py --device cuda), the
#          reference the vlm step prints its ratios against;
#   vlm    vlm-bench: the published 0.5B configuration (random weights), wgpu, flex and ndarray;
#          then wgpu again with f16 weights (--half);
#   spirv  where packed with CHATSPLAT_GPU_SPIRV=1: splat-bench and vlm-bench (wgpu) built with the
#          `spirv` feature (Vulkan's SPIR-V compiler, cooperative-matrix matmuls; never in CI);
#   fusion where packed with CHATSPLAT_GPU_FUSION=1: splat-bench and vlm-bench (wgpu) built with the
#          `fusion` feature (burn's kernel fusion; the splatting op runs outside it);
#   train  geometry and language training s/iter on a built-in synthetic scene (wgpu), and
#          lang-bench's views/s and objects/s (real-size encoder too) on it;
#   accuracy  splat-bench --accuracy: forward error against the f64 reference and the wgpu
#          backward's error against ndarray, for each way of adding a tile's gradients;
#   reduce splat-bench's wgpu forward+backward with each way (--grad-reduce atomic, plane);
#   cas    splat-bench's wgpu table again with the compare-and-swap float add (--float-add cas),
#          against the native add that the first table used where the adapter has one;
#   bitonic  splat-bench's wgpu table again with the per-tile bitonic sort (--tile-sort bitonic),
#          against the two global radix sorts that the first table used.
# CHATSPLAT_GPU_TRAIN_REDUCE: the language stage runs once per word in it (default "auto"; e.g.
# "atomic plane", each through CHATSPLAT_WGPU_GRAD_REDUCE), CHATSPLAT_GPU_GEO_ITERS and
# CHATSPLAT_GPU_LANG_ITERS shorten the training (defaults 1000 and 300).
# CHATSPLAT_GPU_PARTS picks the parts (default "splat bitonic peers vlm spirv fusion train"; "peers" is "gsplat
# transformers": split them over two calls if one would pass the device's 10-minute limit per
# command; vlm takes its reference from CHATSPLAT_GPU_REFERENCE, default
# OUTDIR/transformers_cuda.json, when there is one).
# CHATSPLAT_GPU_VLM_BACKENDS: vlm-bench's backends (default "wgpu flex ndarray").
# CHATSPLAT_GPU_IMPLS: splat-bench's implementations (default wgpu,ndarray); CHATSPLAT_GPU_STEP_SECS:
# a limit on each step (default 300 s), so that one that hangs leaves the others their time; a
# step that fails or runs out prints its exit status and the next one runs. CHATSPLAT_GPU_QUICK=1 shrinks every
# size and trains on ndarray (a smoke run of the script on the CPU: on lavapipe, 5 language
# iterations took over 25 minutes of kernel compilation; the peers skip without CUDA).
# Never part of CI.
set -euo pipefail
cd "$(dirname "$0")/../.."
bins=(chatsplat splat-bench vlm-bench lang-bench)
unpacked=""

pack() {
    # burn's autotuner on (off in the default build: on lavapipe each candidate kernel costs seconds)
    cargo build --release -p chatsplat -p eval --features chatsplat/autotune,eval/autotune \
        --bin chatsplat --bin splat-bench --bin vlm-bench --bin lang-bench
    rm -rf .gpu/bin
    mkdir -p .gpu/bin
    local stripped
    stripped=$(mktemp -d /tmp/chatsplat-strip.XXXX)
    for b in "${bins[@]}"; do
        strip -o "$stripped/$b" "target/release/$b"
    done
    # one archive with a dictionary that spans all four binaries, which share most of their code:
    # 24 MB against 43 MB compressed one by one (the carry, the working tree included, takes 64 MiB)
    tar -C "$stripped" -cf - "${bins[@]}" | xz --lzma2=preset=6,dict=256MiB -T1 >.gpu/bin/bins.tar.xz
    # the two benchmarks again with one more feature, in its own target folder and archive (the burn stack
    # builds again with other features, about as long as the build above): `spirv` (Vulkan's SPIR-V
    # compiler) and `fusion` (burn's kernel fusion)
    variant() {
        local b
        CARGO_TARGET_DIR="target/$1" cargo build --release -p eval --features "eval/autotune,eval/$1" \
            --bin splat-bench --bin vlm-bench
        for b in splat-bench vlm-bench; do
            strip -o "$stripped/$b-$1" "target/$1/release/$b"
        done
        tar -C "$stripped" -cf - "splat-bench-$1" "vlm-bench-$1" | xz --lzma2=preset=6,dict=256MiB -T1 \
            >".gpu/bin/$1.tar.xz"
    }
    if [ "${CHATSPLAT_GPU_SPIRV:-0}" = 1 ]; then variant spirv; fi
    if [ "${CHATSPLAT_GPU_FUSION:-0}" = 1 ]; then variant fusion; fi
    rm -rf "$stripped"
    mkdir -p .git/info && touch .git/info/exclude
    grep -qx '/.gpu/' .git/info/exclude || echo '/.gpu/' >>.git/info/exclude
    grep -qx '/.gl/' .git/info/exclude || echo '/.gl/' >>.git/info/exclude
    grep -qx '/.whl/' .git/info/exclude || echo '/.whl/' >>.git/info/exclude
    if ! ls .whl/gsplat-*.whl >/dev/null 2>&1; then
        # pure Python (its CUDA kernels compile there on first use); numpy, torch, ninja, rich and
        # jaxtyping, which it needs, are in the GPU machines' image
        python3 -m pip download --no-deps --only-binary=:all: -d .whl gsplat==1.5.3
    fi
    if ! ls .gl/libvulkan1_*.deb >/dev/null 2>&1; then
        local o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
        mkdir -p .gl /tmp/amd64/partial
        # shellcheck disable=SC2086
        apt-get $o update -qq && (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libgl1 libglx0)
    fi
    du -h .gpu/bin/*.tar.xz
    echo "carry: .gpu/bin/bins.tar.xz .gl .whl (a call of their own for the variants: .gpu/bin/fusion.tar.xz"
    echo "  .gpu/bin/spirv.tar.xz .gl, CHATSPLAT_GPU_PARTS=\"fusion spirv\"; 64 MiB a call, the tree's 29 MB included)"
    echo "command: bash eval/gpu/run.sh bench"
}

step() {
    echo
    echo "\$ $*"
    local t0 t1 rc=0
    t0=$(date +%s.%N)
    timeout "${CHATSPLAT_GPU_STEP_SECS:-300}" "$@" || rc=$?
    t1=$(date +%s.%N)
    if [ "$rc" = 0 ]; then
        echo "(wall $(awk "BEGIN{printf \"%.1f\", $t1 - $t0}") s)"
    else
        echo "(wall $(awk "BEGIN{printf \"%.1f\", $t1 - $t0}") s; exit $rc$([ "$rc" = 124 ] && echo ': out of time'))"
    fi
    [ "$rc" = 0 ]
}

bench() {
    local out=${1:-${OUT:-gpu-out}}
    mkdir -p "$out"
    local bin=target/release
    if ls .gpu/bin/*.tar.xz >/dev/null 2>&1; then
        unpacked=$(mktemp -d /tmp/chatsplat-gpu.XXXX)
        trap 'rm -rf "$unpacked"' EXIT
        bin=$unpacked
        local archive
        for archive in .gpu/bin/*.tar.xz; do
            if command -v xz >/dev/null; then
                xz -dc "$archive" | tar -C "$bin" -xf -
            else
                python3 -c 'import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2])' "$archive" "$bin"
            fi
        done
    fi
    if ! ldconfig -p 2>/dev/null | grep -q libvulkan && ls .gl/*.deb >/dev/null 2>&1; then
        for f in .gl/*.deb; do dpkg -x "$f" /; done
        ldconfig
    fi
    if [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ]; then
        export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
    fi
    local quick=${CHATSPLAT_GPU_QUICK:-0} parts=" ${CHATSPLAT_GPU_PARTS:-splat bitonic peers vlm spirv fusion train} "
    parts=${parts/ peers / gsplat transformers }
    # the parts that run the four binaries of bins.tar.xz
    if [[ $parts =~ " "(splat|cas|bitonic|accuracy|reduce|vlm|train)" " ]]; then
        for b in "${bins[@]}"; do
            [ -x "$bin/$b" ] || { echo "error: $bin/$b is missing: run \`bash eval/gpu/run.sh pack\` first" >&2; exit 1; }
        done
    fi
    local n=100000,1000000 c=3,32 res=384x384,1280x720 vlm=0.5b views=32 side=96 be=wgpu
    local geo=${CHATSPLAT_GPU_GEO_ITERS:-1000} lang=${CHATSPLAT_GPU_LANG_ITERS:-300}
    local impls=${CHATSPLAT_GPU_IMPLS:-wgpu,ndarray}
    # the variant builds' vlm-bench (the built-in model in a quick run)
    local variant_vlm=(--random "$vlm" --backend wgpu --reps 2 --decode 16)
    if [ "$quick" = 1 ]; then
        n=10000 c=3 res=384x384 views=8 side=64 geo=20 lang=5 be=ndarray
        variant_vlm=(--backend wgpu --reps 1 --decode 4)
    fi
    local cuda=0
    if python3 -c 'import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)' 2>/dev/null; then
        cuda=1
    fi
    {
        # the GPU and its driver, in the log (eval/gpu/collect.py reads them from there)
        command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
        if [[ $parts == *" splat "* ]]; then
            step "$bin/splat-bench" --n "$n" --c "$c" --res "$res" --impls "$impls" --max-secs 20 || true
        fi
        if [[ $parts == *" cas "* ]]; then
            # the same table with the compare-and-swap loop in place of the native float add
            step "$bin/splat-bench" --n "$n" --c "$c" --res "$res" --impls wgpu --max-secs 20 --float-add cas || true
        fi
        if [[ $parts == *" bitonic "* ]]; then
            # the same table with each tile's list sorted by a bitonic sort in place of the radix sorts
            step "$bin/splat-bench" --n "$n" --c "$c" --res "$res" --impls wgpu --max-secs 20 --tile-sort bitonic ||
                true
        fi
        if [[ $parts == *" accuracy "* ]]; then
            step "$bin/splat-bench" --accuracy || true
        fi
        if [[ $parts == *" reduce "* ]]; then
            for r in atomic plane; do
                step "$bin/splat-bench" --n "$n" --c "$c" --res "$res" --impls wgpu --max-secs 20 --grad-reduce "$r" ||
                    true
            done
        fi
        if [[ $parts == *" gsplat "* || $parts == *" transformers "* ]] && [ "$cuda" = 0 ]; then
            echo "peers: skipped (python3's torch sees no CUDA device)"
        fi
        if [[ $parts == *" gsplat "* ]] && [ "$cuda" = 1 ]; then
            if ! python3 -c 'import gsplat' 2>/dev/null && ls .whl/*.whl >/dev/null 2>&1; then
                python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl
                export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
            fi
            MAX_JOBS=$(nproc) step python3 eval/gpu/gsplat_bench.py --n "$n" --c "$c" --res "$res" \
                --out "$out/gsplat.json" || true
        fi
        if [[ $parts == *" transformers "* ]] && [ "$cuda" = 1 ] && [ "$quick" != 1 ]; then
            step python3 eval/bench/transformers_vlm.py --size "$vlm" --device cuda \
                --threads "$(nproc)" --reps 2 --decode 16 --out "$out/transformers_cuda.json" || true
        fi
        if [[ $parts == *" vlm "* ]]; then
            local reference=()
            local ref=${CHATSPLAT_GPU_REFERENCE:-$out/transformers_cuda.json}
            if [ -f "$ref" ]; then
                reference=(--reference "$ref")
            fi
            if [ "$quick" = 1 ]; then
                step "$bin/vlm-bench" --backend wgpu flex ndarray --reps 1 --decode 4 || true
            else
                # shellcheck disable=SC2086
                step "$bin/vlm-bench" --random "$vlm" --backend ${CHATSPLAT_GPU_VLM_BACKENDS:-wgpu flex ndarray} \
                    --reps 2 --decode 16 \
                    "${reference[@]}" || true
                # f16 weights on wgpu (`--half`; where the adapter has f16 shaders, as the report says)
                step "$bin/vlm-bench" --random "$vlm" --backend wgpu --half --reps 2 --decode 16 || true
            fi
        fi
        # the op and the port built with one more feature: `spirv` (Vulkan's SPIR-V compiler,
        # cooperative-matrix matmuls), `fusion` (burn's kernel fusion, element-wise chains in one kernel)
        local v
        for v in spirv fusion; do
            if [[ $parts == *" $v "* ]]; then
                if [ -x "$bin/vlm-bench-$v" ]; then
                    step "$bin/splat-bench-$v" --n "$n" --c "$c" --res "$res" --impls wgpu --max-secs 20 || true
                    step "$bin/vlm-bench-$v" "${variant_vlm[@]}" || true
                else
                    echo "($v: not packed; CHATSPLAT_GPU_${v^^}=1 bash eval/gpu/run.sh pack builds it)"
                fi
            fi
        done
        if [[ $parts == *" train "* ]]; then
            # the scene and the runs stay out of OUTDIR (the device returns a few files only)
            local work=${CHATSPLAT_GPU_WORK:-/tmp/chatsplat-gpu-work}
            local scene=$work/scene run=$work/run
            rm -rf "$scene" "$run"
            step "$bin/chatsplat" synth --out "$scene" --views "$views" --width "$side" --height "$side" &&
                step "$bin/chatsplat" train --data "$scene" --out "$run" --iters "$geo" --backend "$be" &&
                step "$bin/chatsplat" extract --data "$scene" --out "$scene/teacher" --backend "$be" &&
                for r in ${CHATSPLAT_GPU_TRAIN_REDUCE:-auto}; do
                    CHATSPLAT_WGPU_GRAD_REDUCE=$r step "$bin/chatsplat" train-language --run "$run" \
                        --teacher "$scene/teacher" --iters "$lang" --backend "$be" --no-compact \
                        --out "$run/language-$r" || true
                done
                [ -n "${CHATSPLAT_GPU_TRAIN_REDUCE:-}" ] ||
                    { mv "$run/language-auto" "$run/language" &&
                        step "$bin/lang-bench" --run "$run" --backend "$be" --sweep-iters 0 --reps 3 --full-size &&
                        cp "$run/bench/bench.json" "$out/lang_bench.json"; } || true
        fi
    } 2>&1 | tee "$out/gpu_bench.log"
}

case "${1:-}" in
    pack) pack ;;
    bench) shift; bench "$@" ;;
    *) echo "usage: bash eval/gpu/run.sh pack | bench [OUTDIR]" >&2; exit 2 ;;
esac
