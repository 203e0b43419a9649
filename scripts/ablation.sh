#!/usr/bin/env bash
# The rollout-stability ablation: short fine-tunes of the committed 4-frame
# baseline (fixtures/variants/baseline_12k, recovered into runs/base), one recipe
# change each, then each exported and rolled out on a validation suite of
# held-out seeds (not the test suite). Resumable: rerun the same command and
# every stage continues where it stopped.
#   ./scripts/ablation.sh                       # all rows
#   ./scripts/ablation.sh context_noise rollout # some rows
# Needs data/train (worldpack sim dataset + plan) and runs/base/latents
# (./scripts/model.sh encode --data data/train --run runs/base).
set -euo pipefail
cd "$(dirname "$0")/.."
data="${DATA:-data/train120}"
val="${VAL:-data/val}"
steps="${STEPS:-2000}"
threads="${THREADS:-1}"
base=runs/base
bin=target/release/worldpack

declare -A recipe=(
  [continued]=""
  [context_noise]="--context-noise 0.7 --generated-level 0.3"
  [rollout]="--rollout-share 0.5 --rollout-steps 4"
  [pose_noise]="--pose-noise-translation 0.25 --pose-noise-degrees 2.5"
  # Rollout fine-tuning again, its frames marked with the generated level and sampled as at inference (10 steps).
  [rollout_marked]="--context-noise 0.7 --generated-level 0.3 --rollout-share 0.25 --rollout-steps 10"
)
rows=("$@")
if [ ${#rows[@]} -eq 0 ]; then rows=(context_noise rollout continued pose_noise); fi

[ -f "$base/cdit-baseline.pt" ] || ./scripts/model.sh recover --model fixtures/variants/baseline_12k --run "$base"
[ -f "$val/index.json" ] || { "$bin" sim loopnav --per-cell 2 --seed 5 --out "$val" && "$bin" plan --data "$val"; }

for name in "${rows[@]}"; do
  [ -n "${recipe[$name]+set}" ] || { echo "unknown row $name; one of ${!recipe[*]}" >&2; exit 2; }
  run="runs/ablate/$name"
  mkdir -p "$run"
  [ -e "$run/autoencoder.pt" ] || ln -s "$PWD/$base/autoencoder.pt" "$run/autoencoder.pt"
  [ -e "$run/latents" ] || ln -s "$PWD/$base/latents" "$run/latents"
  [ -e "$run/config.json" ] || cp "$base/config.json" "$run/config.json"
  echo "==> $name: ${recipe[$name]:-(the recipe as before)}"
  # shellcheck disable=SC2086
  ./scripts/model.sh train --data "$data" --run "$run" --policy baseline --steps "$steps" \
      --init-from "$base/cdit-baseline.pt" --threads "$threads" ${recipe[$name]}
  [ -f "$run/model/baseline/manifest.json" ] ||
    ./scripts/model.sh export --run "$run" --policy baseline --layouts baseline --data "$val" --out "$run/model/baseline" --half --threads "$threads"
  "$bin" eval --suite "$val" --models "$run/model" --policies baseline --no-references --threads "$threads" --out "$run/eval"
done
