#!/usr/bin/env bash
# The rollout recipe applied in the paper's order: from the committed 4-frame
# baseline (recovered into runs/base), fine-tune WorldPack (Algorithm 1 plans)
# and nearest frame packing with the recipe, and continue the baseline with the
# same recipe for the same steps (so WorldPack is not compared with a baseline
# that stopped early). Each model is exported; `eval` then rolls all of them
# out on a held-out suite in one run, with paired intervals.
# Resumable: rerun the same command and each stage continues where it stopped.
#   RECIPE="--context-noise 0.7 --generated-level 0.3" ./scripts/recipe.sh train baseline_continued
#   ./scripts/recipe.sh train worldpack
#   SUITE=data/loopnav-test ./scripts/recipe.sh eval
# From a fresh clone, `./scripts/recipe.sh prepare` makes what the others need:
# the first 120 training trajectories with plans and memory need (data/train120),
# the validation suite (data/val, seed 5), the test suite (data/loopnav-test,
# seed 6), the committed baseline recovered into runs/base and the latent cache.
set -euo pipefail
cd "$(dirname "$0")/.."
data="${DATA:-data/train120}"
steps="${STEPS:-2337}"          # 20% of the baseline's 11,683 steps, as the fine-tunes of 2026-11-21
threads="${THREADS:-1}"
recipe="${RECIPE:---context-noise 0.7 --generated-level 0.3}"
out="${OUT:-runs/recipe}"
base="${BASE:-runs/base}"   # the baseline run the fine-tunes start from
packed="${PACKED:-}"        # options for the packed variants only (--warp: the geometry input)
bin=target/release/worldpack

# name -> the policy whose plans it trains on, and options beyond the recipe.
declare -A policy=([baseline_continued]=baseline [worldpack]=worldpack [nearest_frame_packing]=nearest_frame_packing
                   [memory_retrieval]=memory_retrieval)
declare -A extra=([baseline_continued]="" [worldpack]="--memory-focus 0.5" [nearest_frame_packing]="--memory-focus 0.5"
                  [memory_retrieval]="--memory-focus 0.5")

suite() {  # suite DIR SEED: a held-out LoopNav-style suite with its plans
  [ -f "$1/index.json" ] || { "$bin" sim loopnav --per-cell "$3" --seed "$2" --out "$1" && "$bin" plan --data "$1"; }
}

prepare() {
  [ -x "$bin" ] || cargo build --release --bin worldpack
  if [ ! -f "$data/index.json" ]; then
    # Trajectory i of `sim dataset` depends only on i, so these are data/train's first 120.
    "$bin" sim dataset --trajectories 120 --out "$data" && "$bin" plan --data "$data" --memory-need
  fi
  suite data/val 5 2
  suite data/loopnav-test 6 6
  [ -f "$base/cdit-baseline.pt" ] || ./scripts/model.sh recover --model fixtures/variants/baseline_12k --run "$base"
  ./scripts/model.sh encode --data "$data" --run "$base" --threads "$threads"
}

train() {
  local name=$1 run="$out/$1"
  [ -n "${policy[$name]+set}" ] || { echo "unknown model $name; one of ${!policy[*]}" >&2; exit 2; }
  mkdir -p "$run"
  [ -e "$run/autoencoder.pt" ] || ln -s "$PWD/$base/autoencoder.pt" "$run/autoencoder.pt"
  [ -e "$run/latents" ] || ln -s "$PWD/$base/latents" "$run/latents"
  if [ ! -e "$run/config.json" ]; then
    # Where-it-lands positions for the packed variants (the recipe of 2026-11-21); the baseline keeps its config.
    if [ "$name" = baseline_continued ]; then cp "$base/config.json" "$run/config.json"; else
      .venv/bin/python - "$base/config.json" "$run/config.json" <<'PY'
import json, sys
c = json.load(open(sys.argv[1]))
c["cdit"]["landing_depths"] = [2.0, 6.0, 20.0]
c["cdit"]["focal"] = 45.70073621574767 / 64
json.dump(c, open(sys.argv[2], "w"), indent=2)
PY
    fi
  fi
  local p=${policy[$name]}
  # shellcheck disable=SC2086
  ./scripts/model.sh train --data "$data" --run "$run" --policy "$p" --steps "$steps" \
      --init-from "$base/cdit-baseline.pt" --threads "$threads" ${extra[$name]} $recipe \
      $([ "$name" = baseline_continued ] || echo "$packed")
  [ -f "$run/model/$p/manifest.json" ] ||
    ./scripts/model.sh export --run "$run" --policy "$p" --layouts "$p" --data data/val --out "$run/model/$p" --half --threads "$threads"
}

case "${1:-}" in
  prepare) prepare ;;
  train) shift; for name in "$@"; do train "$name"; done ;;
  eval)
    suite="${SUITE:-data/val}"
    # The baseline row is the first-trained baseline the fine-tunes start from.
    mkdir -p "$out/first-baseline"
    [ -e "$out/first-baseline/baseline" ] || ln -s "$PWD/fixtures/variants/baseline_12k" "$out/first-baseline/baseline"
    args=(--suite "$suite" --models "$out/first-baseline" --policies baseline --threads "${EVAL_THREADS:-2}" --out "$out/eval-$(basename "$suite")")
    for name in baseline_continued nearest_frame_packing memory_retrieval worldpack; do
      m="$out/$name/model/${policy[$name]}"
      [ -f "$m/manifest.json" ] && args+=(--extra "${name}_recipe=$m")
    done
    "$bin" eval "${args[@]}" "${@:2}" ;;
  *) echo "usage: $0 prepare | train NAME... | eval [eval flags]" >&2; exit 2 ;;
esac
