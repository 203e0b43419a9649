#!/usr/bin/env bash
# Makes what a lent GPU machine needs, here, into the git-ignored folder
# .device/, and keeps the tree that travels with each call under the device
# tool's 64 MiB (docs/device.md). Nothing here runs on the GPU machine.
#
#   ./scripts/device/pack.sh common   # .device/common: the stripped release worldpack (zstd), the fixtures the checks read
#   ./scripts/device/pack.sh train    # .device/train: a student run's weights to go on from (RUN, EMA and discriminator only)
#                                     #   and the decoder it trains against (DECODER, a model folder)
#   ./scripts/device/pack.sh data     # .device/data-1, -2, ...: a dataset to train on (DATA), in pieces of at most PIECE_MB
#                                     #   (45) compressed, one call each, for a world the GPU machine cannot simulate (Doom)
#   ./scripts/device/pack.sh cuda     # .device/ort, .device/cuda: ONNX Runtime 1.31.1's CUDA build, sm_90 code only
#   ./scripts/device/pack.sh slim     # take fixtures/ and docs/ out of git's index (they stay on disk) so they do not travel
#   ./scripts/device/pack.sh restore  # put them back (git reset); run it before any commit
#
# The tree alone is 178 MB, nearly all of it fixtures; with fixtures/ and
# docs/ out of the index and ignored it is about 2 MB. What the checks read
# of fixtures/ travels in .device/common instead, compressed.
set -euo pipefail
cd "$(dirname "$0")/../.."
dev=.device
exclude=.git/info/exclude
mkdir -p "$dev" .git/info
grep -qx "/$dev/" "$exclude" 2>/dev/null || echo "/$dev/" >> "$exclude"
size() { du -b "$@" | awk '{ s += $1 } END { printf "%.1f MB\n", s / 1e6 }'; }

case "${1:-}" in
  common)
    cargo build --release --bin worldpack
    mkdir -p "$dev/common"
    # The GPU machine has no zstd: this one travels with the libraries it links.
    mkdir -p "$dev/common/zstd" && cp /usr/bin/zstd "$dev/common/zstd/"
    ldd /usr/bin/zstd | awk '/=> \// && !/libc.so/ { print $3 }' | xargs -I{} cp -L {} "$dev/common/zstd/"
    strip -o "$dev/worldpack" target/release/worldpack
    zstd -19 -q -f "$dev/worldpack" -o "$dev/common/worldpack.zst" && rm "$dev/worldpack"
    tar -cf - fixtures/small fixtures/variants/worldpack_geometry_fused_1step fixtures/variants/worldpack_geometry_fused_1step_mse \
        | zstd -19 -q -f -o "$dev/common/fixtures.tar.zst"
    echo "$dev/common: $(size "$dev/common")" ;;
  train)
    run="${RUN:-runs/adv-cap}"
    mkdir -p "$dev/train"
    cp "$run/config.json" "$run/autoencoder.pt" "$dev/train/"
    # Only what a resumed run reads: the teacher's EMA, the student's EMA and the discriminator with its moments.
    .venv-train/bin/python - "$run" "$dev/train" <<'PY'
import sys, torch
run, out = sys.argv[1], sys.argv[2]
t = torch.load(f"{run}/cdit-worldpack.pt", map_location="cpu", weights_only=False)
t.pop("model", None)
torch.save(t, f"{out}/cdit-worldpack.pt")
s = torch.load(f"{run}/distilled-worldpack-1.pt", map_location="cpu", weights_only=False)
for k in ("model", "opt"):
    s.pop(k, None)
torch.save(s, f"{out}/distilled-worldpack-1.pt")
print(f"student at step {s['step']}")
PY
    # The decoder travels as decoder/ whatever its folder here is called.
    tar -cf - -C "${DECODER:-runs/sharp/voxel-sn/model}" --transform 's,^\.,decoder,' . | zstd -19 -q -f -o "$dev/train/decoder.tar.zst"
    echo "$dev/train: $(size "$dev/train")" ;;
  data)
    data="${DATA:?set DATA to the dataset folder (e.g. data/doom-train100)}"
    [ -f "$data/plans.json" ] || { echo "$data has no plans.json: run worldpack plan --data $data --memory-need first" >&2; exit 1; }
    rm -rf "$dev"/data-* && mkdir -p "$dev/data-1"
    # Pieces by trajectory, cut when the raw bytes reach PIECE_MB times the ratio zstd -19 gets on these frames (about 4).
    budget=$(( ${PIECE_MB:-45} * 4 * 1000000 )) n=1 used=0 list=("$data/index.json" "$data/plans.json")
    pack_piece() { tar -cf - --transform "s,^${data%/},data," "${list[@]}" | zstd -19 --long=27 -T1 -q -f -o "$dev/data-$n/data.tar.zst"; }
    for t in "$data"/*/; do
        b=$(du -sb "$t" | cut -f1)
        if [ "$used" -gt 0 ] && [ $(( used + b )) -gt "$budget" ]; then pack_piece; n=$((n + 1)) used=0 list=(); mkdir -p "$dev/data-$n"; fi
        list+=("${t%/}") used=$(( used + b ))
    done
    pack_piece
    for d in "$dev"/data-*; do echo "$d: $(size "$d")"; done ;;
  cuda)
    wheel=onnxruntime_gpu-1.31.1-cp312-cp312-manylinux_2_28_x86_64.whl
    mkdir -p "$dev/ort" "$dev/cuda" "$dev/wheel"
    [ -f "$dev/wheel/$wheel" ] || python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 -d "$dev/wheel" onnxruntime-gpu==1.31.1
    unzip -o -q -j "$dev/wheel/$wheel" 'onnxruntime/capi/libonnxruntime*.so*' -d "$dev/wheel/libs"
    tar -cf - -C "$dev/wheel/libs" libonnxruntime.so.1.31.1 libonnxruntime_providers_shared.so | zstd -19 -q -f -o "$dev/ort/ort.tar.zst"
    # H100 and H200 are sm_90: the other architectures' cubins (141 of 218 MB) are zeroed, not cut.
    [ -f "$dev/cuda/providers_cuda.so.zst" ] || { python3 scripts/device/fatbin_keep.py "$dev/wheel/libs/libonnxruntime_providers_cuda.so" "$dev/wheel/cuda90.so" --keep 90
        zstd -19 --long=27 -q -f "$dev/wheel/cuda90.so" -o "$dev/cuda/providers_cuda.so.zst"; }
    echo "$dev/ort: $(size "$dev/ort"); $dev/cuda: $(size "$dev/cuda")" ;;
  slim)
    git diff --quiet HEAD -- fixtures docs || { echo "fixtures/ or docs/ have uncommitted changes: commit them first" >&2; exit 1; }
    git rm -r -q --cached fixtures docs
    printf '/fixtures/\n/docs/\n' >> "$exclude"
    echo "travels: $(git ls-files -z | xargs -0 du -cb | tail -1 | awk '{ printf "%.1f MB", $1 / 1e6 }') tracked" ;;
  restore)
    git reset -q -- fixtures docs
    sed -i '\#^/fixtures/$#d; \#^/docs/$#d' "$exclude"
    git status --short | head ;;
  *) echo "usage: $0 common | train | data | cuda | slim | restore" >&2; exit 2 ;;
esac
