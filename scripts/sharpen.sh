#!/usr/bin/env bash
# Where the blur comes from, and the sharper decoder (docs/model.md#where-the-blur-comes-from).
# Each stage reuses what is done; run the training in the background on one thread (THREADS)
# while you work on the other core.
#   ./scripts/sharpen.sh data                  # data/train120, data/val, data/loopnav-test; data/doom-{train100,val,test}
#   ./scripts/sharpen.sh breakdown voxel|doom  # `worldpack eval` of every stage on the test suite (SUITE to change it)
#   ./scripts/sharpen.sh train voxel|doom      # the decoder fine-tune, encoder frozen (MINUTES, STEPS; DECODER_FROM:
#                                              # a model folder whose decoder a new run starts from)
#   ./scripts/sharpen.sh swap voxel|doom       # the served model with that decoder: runs/sharp/<world>/model
#   ./scripts/sharpen.sh head voxel|doom       # the fusion heads retrained on the frames of SHARP (the model with the new
#                                              # decoder; default runs/sharp/<world>/model): the frame kept with MSE + edges
#                                              # (KEPT_STEPS; RUN/kept), and on voxel a head for the frame shown trained
#                                              # with MSE alone, as served (HEAD_STEPS, MINUTES; ADVERSARIAL=W: a pix2pix
#                                              # head instead; RUN/head), paired with hole fill: RUN/head/model
#                                              # (Doom: one head, both frames)
#   ./scripts/sharpen.sh eval voxel|doom       # it against the served model, paired (SUITE to change it;
#                                              # CANDIDATE: another model folder than runs/sharp/<world>/model, OUT: its folder)
# RUN: another run folder than runs/sharp/<world> (a fresh fine-tune beside a finished one).
set -euo pipefail
cd "$(dirname "$0")/.."
threads="${THREADS:-1}"
bin=target/release/worldpack
doom() { (cd doom && PYTHONPATH=.:../train ../.venv-train/bin/python -m worldpack_doom "$@"); }
minutes=(${MINUTES:+--minutes "$MINUTES"})

world="${2:-}"
case "$world" in
  # `row`: how the breakdown names the served model's rows, so `eval` reuses them.
  voxel) served=fixtures/variants/worldpack_geometry_fused_1step; source_ae=fixtures/variants/baseline; row=served
         train=data/train120; val=data/val; suite="${SUITE:-data/loopnav-test}" ;;
  doom)  served=fixtures/doom/geometry_fused; source_ae=fixtures/doom/baseline; row=geometry_fused
         train=data/doom-train100; val=data/doom-val; suite="${SUITE:-data/doom-test}" ;;
  "") [ "${1:-}" = data ] || { echo "usage: $0 data | breakdown|train|swap|eval voxel|doom" >&2; exit 2; } ;;
  *) echo "world: voxel or doom, not $world" >&2; exit 2 ;;
esac
run="${RUN:-runs/sharp/$world}"
out="${OUT:-runs/sharp/eval-$world-$(basename "${suite:-none}")}"

case "${1:-}" in
  data)
    [ -x "$bin" ] || cargo build --release --bin worldpack
    suite_of() { [ -f "$1/index.json" ] || { "$bin" sim loopnav --per-cell "$3" --seed "$2" --out "$1" && "$bin" plan --data "$1"; }; }
    [ -f data/train120/index.json ] || "$bin" sim dataset --trajectories 120 --out data/train120
    suite_of data/val 5 2
    suite_of data/loopnav-test 6 6
    .venv-train/bin/python -m pip install --disable-pip-version-check -q -r doom/requirements.txt
    [ -f data/doom-test/index.json ] || doom suite --split test --count 48 --seed 2 --workers 2 --out ../data/doom-test
    [ -f data/doom-val/index.json ] || doom suite --split train --count 16 --seed 3 --workers 2 --out ../data/doom-val
    [ -f data/doom-train100/index.json ] || doom suite --split train --count 100 --seed 1 --workers 2 --out ../data/doom-train100
    [ -f data/doom-test/plans.json ] || "$bin" plan --data data/doom-test ;;
  breakdown)
    # Every stage between the truth and the frame shown, co-visible as served: the autoencoder's
    # own reconstruction, the denoiser's decoded sample, then each head.
    if [ "$world" = voxel ]; then
      # The 1-step student without a head, and with the 10-step model's (MSE) head.
      ./scripts/model.sh fusion-strip --model "$served" --out runs/sharp/student_raw
      ./scripts/model.sh fusion-strip --model "$served" --out runs/sharp/student_mse_head
      PYTHONPATH=train .venv-train/bin/python -c "from pathlib import Path; from worldpack_train.stages.export import keep_fusion_head
keep_fusion_head(Path('fixtures/variants/worldpack_geometry_fused'), Path('runs/sharp/student_mse_head'))"
      "$bin" eval --suite "$suite" --policies baseline --no-references \
        --extra ten_step=fixtures/variants/worldpack_geometry --extra student=runs/sharp/student_raw \
        --extra ten_step_head=fixtures/variants/worldpack_geometry_fused --extra student_mse_head=runs/sharp/student_mse_head \
        --extra served="$served" --reconstruct served \
        --covisible ten_step --covisible student --covisible ten_step_head --covisible student_mse_head --covisible served \
        --only served_autoencoder --only ten_step_covisible --only student_covisible --only ten_step_head_covisible \
        --only student_mse_head_covisible --only served_covisible \
        --against served_covisible --steps 10 --threads "$threads" --out "runs/sharp/breakdown-voxel-$(basename "$suite")"
    else
      "$bin" eval --suite "$suite" --policies baseline --no-references --models fixtures/doom \
        --extra geometry=fixtures/doom/worldpack --extra geometry_fused="$served" --reconstruct geometry_fused \
        --covisible geometry --covisible geometry_fused \
        --only geometry_fused_autoencoder --only geometry_covisible --only geometry_fused_covisible \
        --against geometry_fused_covisible --steps 10 --threads "$threads" --out "runs/sharp/breakdown-doom-$(basename "$suite")"
    fi ;;
  train)
    [ -f "$run/autoencoder.pt" ] || ./scripts/model.sh recover --model "$source_ae" --run "$run"
    ./scripts/model.sh sharpen-decoder --data "$train" --val "$val" --run "$run" --steps "${STEPS:-20000}" \
        --threads "$threads" "${minutes[@]}" ${DECODER_FROM:+--decoder-from "$DECODER_FROM"} ;;
  head)
    sharp="${SHARP:-$run/model}"
    steps=(--steps 1); [ "$world" = doom ] && steps=(--stride 2)  # the served samplers: the 1-step student, Doom's 10 DDIM steps
    [ -f "$run/head/bare/manifest.json" ] || ./scripts/model.sh fusion-strip --model "$sharp" --out "$run/head/bare"
    [ -f "$run/head/data/truth.npy" ] || "$bin" fusion-data --suite "$train" --model "$run/head/bare" "${steps[@]}" \
        --threads "$threads" --out "$run/head/data"
    # The frame kept: MSE + edges against the truth, the served kept head's recipe, on this decoder's frames.
    ./scripts/model.sh fusion-train --data "$run/head/data" --run "$run/kept" --steps "${KEPT_STEPS:-4000}" --edge-weight 1 \
        --threads "$threads"
    if [ "$world" = doom ]; then
      ./scripts/model.sh fusion-export --run "$run/kept" --model "$run/head/bare" --out "$run/head/model" --data "$run/head/data"
      exit 0
    fi
    ./scripts/model.sh fusion-export --run "$run/kept" --model "$run/head/bare" --out "$run/kept/model" --data "$run/head/data"
    # The frame shown: MSE alone, the served recipe (an edge in the wrong place costs it twice).
    # ADVERSARIAL=W trains the pix2pix head instead (conditional PatchGAN + MSE + edges).
    if [ -n "${ADVERSARIAL:-}" ]; then
      ./scripts/model.sh fusion-train --data "$run/head/data" --run "$run/head" --steps "${HEAD_STEPS:-6000}" --lr 1e-3 \
          --edge-weight 1 --adversarial-weight "$ADVERSARIAL" --threads "$threads" "${minutes[@]}"
    else
      ./scripts/model.sh fusion-train --data "$run/head/data" --run "$run/head" --steps "${HEAD_STEPS:-4000}" \
          --threads "$threads" "${minutes[@]}"
    fi
    ./scripts/model.sh fusion-export --run "$run/head" --model "$run/head/bare" --out "$run/head/shown" --data "$run/head/data"
    ./scripts/model.sh fusion-pair --kept "$run/kept/model" --shown "$run/head/shown" --out "$run/head/model" --hole-fill 7 \
        --data "$run/head/data" ;;
  swap)
    ./scripts/model.sh swap-decoder --model "$served" --run "$run" --out "$run/model" --half ;;
  eval)
    # The breakdown's rows of the served model are the same computation: reused, not rerun.
    mkdir -p "$out/rows"
    for r in "${row}_covisible" "${row}_autoencoder"; do
      f="runs/sharp/breakdown-$world-$(basename "$suite")/rows/$r.json"
      [ -f "$out/rows/$r.json" ] || [ ! -f "$f" ] || cp "$f" "$out/rows/"
    done
    "$bin" eval --suite "$suite" --policies baseline --no-references \
      --extra "$row=$served" --extra sharp="${CANDIDATE:-$run/model}" --reconstruct "$row" --reconstruct sharp \
      --covisible "$row" --covisible sharp \
      --only "${row}_covisible" --only sharp_covisible --only "${row}_autoencoder" --only sharp_autoencoder \
      --against "${row}_covisible" --strip "sharp_covisible,${row}_covisible" --strip-frames 8 \
      --steps 10 --threads "$threads" --out "$out" ;;
  *) echo "usage: $0 data | breakdown|train|swap|eval voxel|doom" >&2; exit 2 ;;
esac
