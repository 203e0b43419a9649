#!/usr/bin/env bash
# Runs ON the lent GPU machine (no cargo there; torch is): goes on with the
# adversarial 1-step student that `pack.sh train` packed, several weightings at
# once on the one GPU, for MINUTES, and writes each one's checkpoint (EMA,
# discriminator) and log under $OUT. The data are the pieces `pack.sh data`
# made, when earlier calls stashed them (`cuda.sh stash`) or this one carries
# them (Doom: the GPU machine has no ViZDoom); else the carried release binary
# makes TRAJ voxel training trajectories there (seed 0; the first 120 are
# data/train120's).
#
#   device run, carry .device/common .device/train:
#     MINUTES=5 ./scripts/device/train.sh
#   Doom, three calls: carry .device/common/zstd .device/data-1: ./scripts/device/cuda.sh stash
#                      carry .device/data-2: ./scripts/device/cuda.sh stash
#                      carry .device/data-3 .device/train: CONFIGS=... MINUTES=8 ./scripts/device/train.sh
#   CONFIGS: name:adversarial-weight:cap, space-separated (default below); BATCH (64)
set -uo pipefail
cd "$(dirname "$0")/../.."
. scripts/device/zstd.sh
: "${OUT:?set OUT to the folder whose files come back}"
py="${PYTHON:-python3}" minutes="${MINUTES:-5}" batch="${BATCH:-64}" device="${DEVICE:-cuda}"
configs="${CONFIGS:-w05:2:0.05 w15:2:0.15 w40:2:0.4}"
work="${WORK:-/tmp/worldpack-train}"
t0=$(date +%s)
elapsed() { echo "$(( $(date +%s) - t0 )) s"; }
mkdir -p "$work" && export PYTHONPATH="$PWD/train"
zstd -d -q -c .device/train/decoder.tar.zst | tar -xf - -C "$work"
data="$work/data"
stash="${STASH:-/root/worldpack-pieces}"
pieces=$( { ls -d .device/data-* "$stash"/data-* 2>/dev/null || true; } | xargs -rn1 basename | sort -u)
if [ -n "$pieces" ]; then
    for p in $pieces; do  # this call's piece, else the one an earlier call stashed
        f=".device/$p/data.tar.zst"; [ -f "$f" ] || f="$stash/$p/data.tar.zst"
        zstd -d -q -c "$f" | tar -xf - -C "$work" || { echo "could not unpack $f"; exit 1; }
    done
    [ -f "$data/plans.json" ] || { echo "the data pieces have no plans.json: $pieces"; exit 1; }
elif [ ! -f "$data/index.json" ]; then
    bin="$work/worldpack"
    zstd -d -q -f .device/common/worldpack.zst -o "$bin" && chmod +x "$bin"
    "$bin" sim dataset --trajectories "${TRAJ:-240}" --out "$data" > "$work/sim.log"
    "$bin" plan --data "$data" --memory-need > /dev/null
fi
echo "data: $(jq -r '.frames // .total_frames' "$data/index.json" 2>/dev/null || grep -m1 '"frames"' "$data/index.json") frames, $(elapsed)"
first=
for c in $configs; do
    name="${c%%:*}"; run="$work/runs/$name"
    mkdir -p "$run" && cp .device/train/{config.json,autoencoder.pt,cdit-worldpack.pt,distilled-worldpack-1.pt} "$run/"
    if [ -z "$first" ]; then
        first="$run"
        "$py" -m worldpack_train encode --data "$data" --run "$run" --device "$device" > "$OUT/encode.log" 2>&1 || { tail "$OUT/encode.log"; exit 1; }
        echo "encoded: $(elapsed)"
    else
        ln -sfn "$first/latents" "$run/latents"
    fi
done
for c in $configs; do
    IFS=: read -r name weight cap <<< "$c"
    RUN="$work/runs/$name" TRAIN="$data" DECODER="$work/decoder" ADV="$weight" ADV_CAP="$cap" \
        BATCH="$batch" STEPS=1000000 MINUTES="$minutes" DEVICE="$device" THREADS=4 PY="$py -m worldpack_train" \
        ./scripts/distill.sh adversarial > "$work/$name.log" 2>&1 &
done
wait
echo "trained: $(elapsed)"
for c in $configs; do
    name="${c%%:*}"; run="$work/runs/$name"
    tail -c 400 "$work/$name.log" | tr '\r' '\n' | tail -2
    cp "$run/log.jsonl" "$OUT/$name.log.jsonl"
    # What comes back: the EMA weights and the discriminator (the CPU resumes from them), not the optimiser moments.
    "$py" - "$run/distilled-worldpack-1.pt" "$OUT/$name.pt" <<'PY'
import sys, torch
s = torch.load(sys.argv[1], map_location="cpu", weights_only=False)
s.pop("opt", None)
s["model"] = s["ema"]
torch.save(s, sys.argv[2])
print(f"{sys.argv[2]}: step {s['step']}")
PY
done
echo "done: $(elapsed)"
