#!/usr/bin/env bash
# Doom end to end (docs/doom.md): data from ViZDoom in the dataset format,
# the model family trained on it in the paper's order, rollouts on maps never
# trained on. Each stage resumes or reuses what is done; run them in order,
# in the background on one thread (THREADS) while you work on the other core.
#   ./scripts/doom.sh data                 # data/doom-{train,train-abca,val,test,test-abca}: 400 / 120 / 16 / 48 / 48 walks, checked and planned
#   ./scripts/doom.sh autoencoder          # the voxel autoencoder fine-tuned on Doom frames, then the latent cache
#   ./scripts/doom.sh baseline             # the 4-frame baseline: the paper-order baseline (fixtures/variants/baseline) fine-tuned on Doom (STEPS, MINUTES)
#   ./scripts/doom.sh worldpack            # WorldPack with the warp input: the paper-order WorldPack (fixtures/variants/worldpack) fine-tuned on Doom (STEPS, MINUTES)
# The voxel pair is in the paper's order (that WorldPack is a fine-tune of
# that baseline); on Doom each is fine-tuned for the same steps, so the two can
# train at once, one core each.
#   ./scripts/doom.sh fusion               # its fusion head on ABA and ABCA training walks: the geometry model
#   ./scripts/doom.sh eval                 # the held-out maps: every row with paired intervals (SUITE: data/doom-test)
#   ./scripts/doom.sh student              # a 1-step student of the 10-step geometry model, distilled with ADD's
#                                          # adversarial term (distill --adversarial-weight ADV 0.5, from step 1,000,
#                                          # capped at ADV_CAP 0.1) on frames from the served decoder; TRAIN
#                                          # (data/doom-train100, as sharpen.sh data makes it), STEPS, MINUTES, BATCH (16),
#                                          # RUN (runs/doom/student)
set -euo pipefail
cd "$(dirname "$0")/.."
threads="${THREADS:-1}"
run=runs/doom
bin=target/release/worldpack
doom() { (cd doom && PYTHONPATH=.:../train ../.venv-train/bin/python -m worldpack_doom "$@"); }
recipe=(--context-noise 0.7 --generated-level 0.3)
minutes=(${MINUTES:+--minutes "$MINUTES"})

case "${1:-}" in
  data)
    [ -x "$bin" ] || cargo build --release --bin worldpack
    .venv-train/bin/python -m pip install --disable-pip-version-check -q -r doom/requirements.txt
    workers="${WORKERS:-2}"
    [ -f data/doom-test/index.json ] || doom suite --split test --count 48 --seed 2 --workers "$workers" --out ../data/doom-test
    [ -f data/doom-test-abca/index.json ] || doom suite --split test --task abca --count 48 --seed 4 --workers "$workers" --out ../data/doom-test-abca
    [ -f data/doom-val/index.json ] || doom suite --split train --count 16 --seed 3 --workers "$workers" --out ../data/doom-val
    [ -f data/doom-train/index.json ] || doom suite --split train --count 400 --seed 1 --workers "$workers" --out ../data/doom-train
    [ -f data/doom-train-abca/index.json ] || doom suite --split train --task abca --count 120 --seed 5 --workers "$workers" --out ../data/doom-train-abca
    for d in data/doom-test data/doom-test-abca data/doom-val data/doom-train data/doom-train-abca; do "$bin" check --data "$d"; done
    [ -f data/doom-train/plans.json ] || "$bin" plan --data data/doom-train --memory-need
    [ -f data/doom-val/plans.json ] || "$bin" plan --data data/doom-val
    [ -f data/doom-test/plans.json ] || "$bin" plan --data data/doom-test
    [ -f data/doom-test-abca/plans.json ] || "$bin" plan --data data/doom-test-abca ;;
  autoencoder)
    [ -f "$run/init/cdit-baseline.pt" ] || ./scripts/model.sh recover --model fixtures/variants/baseline --run "$run/init"
    mkdir -p "$run/base"
    [ -f "$run/base/config.json" ] || cp "$run/init/config.json" "$run/base/config.json"
    [ -f "$run/base/autoencoder.pt" ] || cp "$run/init/autoencoder.pt" "$run/base/autoencoder.pt"
    ./scripts/model.sh train-ae --data data/doom-train --run "$run/base" --steps "${STEPS:-3000}" --threads "$threads" "${minutes[@]}"
    ./scripts/model.sh encode --data data/doom-train --run "$run/base" --threads "$threads" ;;
  baseline)
    ./scripts/model.sh train --data data/doom-train --run "$run/base" --policy baseline --steps "${STEPS:-3000}" \
        --init-from "$run/init/cdit-baseline.pt" --threads "$threads" "${recipe[@]}" "${minutes[@]}"
    ./scripts/model.sh export --run "$run/base" --policy baseline --layouts baseline --data data/doom-val \
        --out "$run/base/model/baseline" --half --threads "$threads" ;;
  worldpack)
    w="$run/worldpack"
    mkdir -p "$w"
    [ -f "$run/init-wp/cdit-worldpack.pt" ] || ./scripts/model.sh recover --model fixtures/variants/worldpack --run "$run/init-wp"
    [ -e "$w/autoencoder.pt" ] || ln -s "$PWD/$run/base/autoencoder.pt" "$w/autoencoder.pt"
    [ -e "$w/latents" ] || ln -s "$PWD/$run/base/latents" "$w/latents"
    if [ ! -f "$w/config.json" ]; then
      # The Doom camera's focal length over the width, for the where-it-lands positions.
      .venv-train/bin/python - "$run/init-wp/config.json" "$w/config.json" data/doom-train <<'PY'
import json, sys, pathlib
c = json.load(open(sys.argv[1]))
index = json.load(open(pathlib.Path(sys.argv[3]) / "index.json"))
k = json.load(open(pathlib.Path(sys.argv[3]) / index["trajectories"][0]["dir"] / "meta.json"))["intrinsics"]
c["cdit"]["focal"] = k["fx"] / k["width"]
json.dump(c, open(sys.argv[2], "w"), indent=2)
PY
    fi
    ./scripts/model.sh train --data data/doom-train --run "$w" --policy worldpack --steps "${STEPS:-3000}" \
        --init-from "$run/init-wp/cdit-worldpack.pt" --threads "$threads" --memory-focus 0.5 --warp "${recipe[@]}" "${minutes[@]}"
    ./scripts/model.sh export --run "$w" --policy worldpack --layouts worldpack --data data/doom-val \
        --out "$w/model/worldpack" --half --threads "$threads" ;;
  fusion)
    m="${MODEL:-$run/worldpack/model/worldpack}"
    [ -f "$run/fusion-data/truth.npy" ] || "$bin" fusion-data --suite data/doom-train --model "$m" --stride 2 \
        --limit "${LIMIT:-240}" --threads "$threads" --out "$run/fusion-data"
    [ -f "$run/fusion-data-abca/truth.npy" ] || "$bin" fusion-data --suite data/doom-train-abca --model "$m" --stride 2 \
        --threads "$threads" --out "$run/fusion-data-abca"
    ./scripts/model.sh fusion-train --data "$run/fusion-data" "$run/fusion-data-abca" --run "$run/fusion" \
        --steps "${STEPS:-3000}" --threads "$threads" "${minutes[@]}"
    ./scripts/model.sh fusion-export --run "$run/fusion" --model "$m" --out "$run/geometry_fused" --data "$run/fusion-data" ;;
  eval)
    mkdir -p "$run/models"
    ln -sfn "$PWD/$run/base/model/baseline" "$run/models/baseline"
    suite="${SUITE:-data/doom-test}"
    "$bin" eval --suite "$suite" --models "$run/models" --policies baseline --threads "${EVAL_THREADS:-2}" \
        --extra worldpack="$run/worldpack/model/worldpack" \
        --extra geometry_fused="$run/geometry_fused" --covisible geometry_fused \
        --against "${AGAINST:-baseline}" --strip geometry_fused_covisible,worldpack,baseline,reproject_fused \
        --out "$run/eval-$(basename "$suite")" "${@:2}" ;;
  student)
    # ADD trains the one-step student from the teacher's weights with both terms at once: the
    # regression onto the teacher's 10-step landing point, and the discriminator once it has
    # had 1,000 steps to learn what a real frame looks like.
    s="${RUN:-$run/student}"
    train="${TRAIN:-data/doom-train100}"
    [ -f "$train/plans.json" ] || "$bin" plan --data "$train" --memory-need
    RUN="$s" TRAIN="$train" TEACHER=fixtures/doom/geometry_fused_10step STUDENT= DECODER=fixtures/doom/geometry_fused_10step \
        ADV="${ADV:-0.5}" ADV_START=1000 ADV_CAP="${ADV_CAP:-0.1}" THREADS="$threads" ./scripts/distill.sh adversarial ;;
  *) echo "usage: $0 data | autoencoder | baseline | worldpack | fusion | eval | student" >&2; exit 2 ;;
esac
