#!/usr/bin/env bash
# Runs ON the lent GPU machine: ONNX Runtime's CUDA provider against the CPU
# provider, and the benchmarks on CUDA (docs/device.md). The pieces come from
# `pack.sh common`, `pack.sh cuda` over more than one call: each call's
# `cuda.sh stash` copies what it carried into STASH, which outlives the call
# while the machine is warm, and `cuda.sh check` joins them and runs:
#   1. parity: the served voxel model and fixtures/small, the same walk (40 observed
#      steps, 38 generated) on both providers, latent and frame compared frame by frame;
#   2. bench walk on CUDA at 1, 4 and 16 sessions, and on the CPU at 1 for scale;
#   3. bench imagine on CUDA (K = 1, 4, 16; H = 2), candidates apart and as the
#      example planner draws them (the fork-and-imagine figures on a GPU);
#   4. bench serve at 16 sessions, batching off and on (5 ms window);
#   5. the paper-scale step (CDiT-B/2, 224x224; weights made there, seeded, by
#      `cuda.sh prepare`, which an earlier call can run beside training, or here).
# Every part has its own time limit, and each one's output and time go under $OUT.
set -uo pipefail
cd "$(dirname "$0")/../.."
. scripts/device/zstd.sh
stash="${STASH:-/root/worldpack-pieces}"
mkdir -p "$stash"
case "${1:-}" in
  stash)
    for f in $(cd .device 2>/dev/null && ls -d common/zstd/* 2>/dev/null) common/worldpack.zst common/fixtures.tar.zst ort/ort.tar.zst cuda/providers_cuda.so.zst \
             $(cd .device 2>/dev/null && ls data-*/data.tar.zst 2>/dev/null); do
        [ -f ".device/$f" ] && { mkdir -p "$stash/$(dirname "$f")"; cp -p ".device/$f" "$stash/$f"; }
    done
    ls -R "$stash"; exit 0 ;;
  prepare|check) ;;
  *) echo "usage: $0 stash | prepare | check" >&2; exit 2 ;;
esac
log="${OUT:-/tmp}/cuda.log"
t0=$(date +%s)
note() { echo "[$(( $(date +%s) - t0 )) s] $*" | tee -a "$log"; }
piece() { [ -f ".device/$1" ] && echo ".device/$1" || echo "$stash/$1"; }
provider="${PROVIDER:-cuda}" py="${PYTHON:-python3}"
lib=/tmp/worldpack-ort bin=/tmp/worldpack-bin/worldpack
mkdir -p "$lib" "$(dirname "$bin")"
zstd -d -q -f "$(piece common/worldpack.zst)" -o "$bin" && chmod +x "$bin" || { note "no worldpack binary"; exit 1; }
paper=/tmp/paper
# The paper's shapes, seeded random weights (1.1 GB; CPU work, so `prepare` can run beside training).
paper_weights() {
    "$bin" sim loopnav --per-cell 1 --tasks aba --ranges 5 --seed 9 --size 224x224 --out "$paper/data" \
        && "$bin" plan --data "$paper/data" --policies baseline,worldpack \
        && PYTHONPATH=train timeout 300 "$py" -m worldpack_train paper-scale --size paper --data "$paper/data" --out "$paper/model"
}
if [ "$1" = prepare ]; then
    mkdir -p "$paper" && paper_weights > "$paper/prepare.log" 2>&1
    echo "paper-scale weights: rc $? in $(( $(date +%s) - t0 )) s"; du -sh "$paper/model"; exit 0
fi
# The fixtures unpack beside the binary, never over a checkout's own.
fixtures=/tmp/worldpack-bin
zstd -d -q -c "$(piece common/fixtures.tar.zst)" | tar -xf - -C "$fixtures" || { note "no fixtures"; exit 1; }
zstd -d -q -c "$(piece ort/ort.tar.zst)" | tar -xf - -C "$lib" || { note "no onnxruntime"; exit 1; }
zstd -d -q -f "$(piece cuda/providers_cuda.so.zst)" -o "$lib/libonnxruntime_providers_cuda.so" || { note "no CUDA provider"; exit 1; }
: "${OUT:?set OUT to the folder whose files come back}"
note "unpacked"
export ORT_DYLIB_PATH="$lib/libonnxruntime.so.1.31.1"
# CUDA 13's runtime, cuBLAS and cuDNN come with the machine's torch, as pip packages.
site=$("$py" -c 'import site; print(site.getsitepackages()[0])')
LD_LIBRARY_PATH="$lib:$(find "$site/nvidia" -name 'lib*.so*' -printf '%h\n' 2>/dev/null | sort -u | paste -sd:)${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export LD_LIBRARY_PATH
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee -a "$log"
ldd "$lib/libonnxruntime_providers_cuda.so" | grep "not found" | tee -a "$log"
part() {  # name, time limit (s), command...: stdout to $OUT/name.json, stderr to the log
    local name=$1 limit=$2; shift 2
    local s=$(date +%s)
    timeout "$limit" "$@" > "$OUT/$name.json" 2>> "$log"
    note "$name: rc $? in $(( $(date +%s) - s )) s"
}
served=$fixtures/fixtures/variants/worldpack_geometry_fused_1step
part parity-served 90 "$bin" bench parity --model "$served" --provider "$provider" --json
part parity-small 90 "$bin" bench parity --model "$fixtures/fixtures/small" --provider "$provider" --steps 10 --json
part walk-cuda 120 "$bin" bench walk --model "$served" --provider "$provider" --sessions 1,4,16 --json
part walk-cpu 60 "$bin" bench walk --model "$served" --sessions 1 --json
part imagine-cuda 120 "$bin" bench imagine --model "$served" --provider "$provider" --horizon 2 --rounds 3 --json
part imagine-drawn-cuda 120 "$bin" bench imagine --model "$served" --provider "$provider" --horizon 2 --rounds 3 --drawn --json
part serve-cuda 120 "$bin" bench serve --model "$fixtures/fixtures/small" --provider "$provider" --sessions 16 --batch-window-ms 5 --json
[ "${PAPER:-1}" = 1 ] || { note "done (no paper scale)"; exit 0; }
[ -f "$paper/model/manifest.json" ] || { paper_weights >> "$log" 2>&1; note "paper-scale weights made"; }
part paper-cuda 150 "$bin" bench step --model "$paper/model" --provider "$provider" --calls 20 --steps 10 --json
note "done"
