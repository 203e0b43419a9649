#!/usr/bin/env bash
# Issue 19's retrain in the paper's order: the 4-frame baseline from scratch for
# 25,000 steps at batch 32, then NFP, MR and WorldPack fine-tuned from it with
# the recipe that won (context noise with its level as an input, memory focus,
# and the warped best-overlap frames as the geometry input), 5,000 steps each
# (20% of the baseline's), and the baseline continued for the same 5,000 steps
# with the recipe (no warp: it keeps no memory). Every stage resumes where it
# stopped; run them in the background on one thread each. STEPS sets the
# fine-tunes' length (the run of 2026-11-25 used 4,000, 16%, to fit the chain in a sitting).
#   ./scripts/paper_order.sh baseline            # runs/base25k, then its export
#   ./scripts/paper_order.sh finetune worldpack  # or nearest_frame_packing, memory_retrieval, baseline_continued
#   ./scripts/paper_order.sh eval                # the 48-trajectory test suite, warps from each plan only
# Needs what `./scripts/recipe.sh prepare` makes (data/train120, data/val,
# data/loopnav-test, runs/base with its latent cache).
set -euo pipefail
cd "$(dirname "$0")/.."
base=runs/base25k
out=runs/paper25k
threads="${THREADS:-1}"
steps="${STEPS:-5000}"
bin=target/release/worldpack

case "${1:-}" in
  baseline)
    mkdir -p "$base"
    [ -e "$base/latents" ] || ln -s "$PWD/runs/base/latents" "$base/latents"
    [ -e "$base/autoencoder.pt" ] || ln -s "$PWD/runs/base/autoencoder.pt" "$base/autoencoder.pt"
    [ -f "$base/config.json" ] || cp runs/base/config.json "$base/config.json"
    ./scripts/model.sh train --data data/train120 --run "$base" --policy baseline --steps 25000 --batch 32 \
        --threads "$threads" --context-noise 0.7 --generated-level 0.3 ${MINUTES:+--minutes "$MINUTES"}
    [ -f "$base/model/baseline/manifest.json" ] ||
      ./scripts/model.sh export --run "$base" --policy baseline --layouts baseline --data data/val --out "$base/model/baseline" --half --threads "$threads" ;;
  finetune)
    shift
    [ -f "$base/model/baseline/manifest.json" ] || { echo "the 25,000-step baseline is not finished: run '$0 baseline' first" >&2; exit 2; }
    BASE="$base" OUT="$out" STEPS="$steps" THREADS="$threads" RECIPE="--context-noise 0.7 --generated-level 0.3" PACKED="--warp" \
      ./scripts/recipe.sh train "$@" ;;
  eval)
    # The baseline row is the 25,000-step one; geometry rows take warps only from their own plan's frames.
    mkdir -p "$out/models"
    ln -sfn "$PWD/$base/model/baseline" "$out/models/baseline"
    args=(--suite data/loopnav-test --models "$out/models" --policies baseline --threads "${EVAL_THREADS:-2}" --out "$out/eval-test")
    for name in baseline_continued nearest_frame_packing memory_retrieval worldpack; do
      policy=$name; [ "$name" = baseline_continued ] && policy=baseline
      m="$out/$name/model/$policy"
      [ -f "$m/manifest.json" ] || { echo "missing $m: run '$0 finetune $name'" >&2; exit 2; }
      args+=(--extra "${name}_25k=$m")
      [ "$name" = baseline_continued ] || args+=(--plan-warps "${name}_25k")
    done
    "$bin" eval "${args[@]}" --against worldpack_25k_plan_warps "${@:2}" ;;
  *) echo "usage: $0 baseline | finetune NAME... | eval [eval flags]" >&2; exit 2 ;;
esac
