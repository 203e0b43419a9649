#!/usr/bin/env bash
# The served model's few-step student (docs/model.md): the fused geometry
# model's 10-step DDIM distilled into GRID's steps (distill.py), then given a
# fusion head of its own. Resumable: each stage continues or reuses what is done.
#   ./scripts/distill.sh data      # data/train120 with plans and memory need (as recipe.sh prepare makes it)
#   ./scripts/distill.sh train     # GRID (999,499), TEACHER_STEPS (5 per segment), STEPS, MINUTES, BATCH, DEVICE, EDGE
#   ./scripts/distill.sh export    # -> fixtures/variants/worldpack_geometry_fused_<N>step, with the teacher's fusion head
#   ./scripts/distill.sh head      # replaces that head with the student's own: trained on its predictions,
#                                  # MSE + HEAD_EDGE (1) x the gradient difference loss, HEAD_STEPS (4000)
#   ./scripts/distill.sh pair      # then shows the teacher's head's frame and keeps its own head's
#                                  # (the memory's context for the next frames), in the warp's holes near
#                                  # where it landed with the warp's colours (HOLE_FILL, 7; 0: off)
#   ./scripts/distill.sh adversarial  # the served 1-step student fine-tuned with ADD's adversarial term
#                                  # (distill --adversarial-weight ADV, 0.5, from ADV_START, 200) on frames from DECODER's
#                                  # decoder (a model folder; default the served one's, the spectral-norm decoder); STEPS,
#                                  # MINUTES, BATCH (16), ADV_CAP (the most the term's weight may reach; default none),
#                                  # TRAIN (data/train120); TEACHER (a model folder) and STUDENT (one to go on from; empty:
#                                  # the teacher's weights, as ADD starts) for another world's model; STANDARDISE_JUDGED=1:
#                                  # the discriminator judges standardised frames (dark worlds; a fresh one if it judged raw);
#                                  # JUDGE_HOLES=1: its patches count by their share of the warp's holes;
#                                  # JUDGE=teacher: LADD's discriminator (the frozen teacher's features of latents
#                                  # re-noised below JUDGE_NOISE, 500) in place of the pixel PatchGAN; JUDGE_LR: the
#                                  # discriminator's learning rate (default LR)
#   ./scripts/distill.sh adversarial-export  # -> OUT (RUN/model), with DECODER's decoder and HEADS's fusion heads (a model folder);
#                                  # VAL (data/val): the suite its manifest's metrics are measured on
# RUN (runs/distill/<N>step; runs/distill/adversarial for those two) holds the run; PY runs `python -m worldpack_train`
# (default ./scripts/model.sh, which sets up .venv-train).
set -euo pipefail
cd "$(dirname "$0")/.."
bin="${BIN:-target/release/worldpack}"
teacher=fixtures/variants/worldpack_geometry_fused
grid="${GRID:-999,499}"
n=$(tr ',' '\n' <<<"$grid" | wc -l)
run="${RUN:-runs/distill/${n}step}"
out="${OUT:-fixtures/variants/worldpack_geometry_fused_${n}step}"
# The adversarial student is a 1-step one, exported into its run until it earns a place in fixtures/.
case "${1:-}" in adversarial*) run="${RUN:-runs/distill/adversarial}"; out="${OUT:-$run/model}" ;; esac
decoder="${DECODER:-fixtures/variants/worldpack_geometry_fused_1step}"
read -r -a py <<<"${PY:-./scripts/model.sh}"
case "${1:-}" in
  data)
    [ -x "$bin" ] || cargo build --release --bin worldpack
    [ -f data/train120/index.json ] || { "$bin" sim dataset --trajectories 120 --out data/train120 && "$bin" plan --data data/train120 --memory-need; }
    [ -f data/val/index.json ] || { "$bin" sim loopnav --per-cell 2 --seed 5 --out data/val && "$bin" plan --data data/val; } ;;
  train)
    [ -f "$run/cdit-worldpack.pt" ] || "${py[@]}" recover --model "$teacher" --run "$run"
    "${py[@]}" encode --data data/train120 --run "$run" --device "${DEVICE:-auto}"
    "${py[@]}" distill --data data/train120 --run "$run" --grid "$grid" --teacher-steps "${TEACHER_STEPS:-5}" \
        --steps "${STEPS:-20000}" --batch "${BATCH:-64}" --device "${DEVICE:-auto}" --threads "${THREADS:-1}" \
        ${LR:+--lr "$LR"} ${MINUTES:+--minutes "$MINUTES"} ${EDGE:+--edge-weight "$EDGE"} ;;
  export)
    "${py[@]}" export --run "$run" --policy worldpack --distilled "$n" --layouts worldpack --data data/val --out "$out" \
        --half --fusion-from "$teacher" --threads "${THREADS:-1}" ;;
  head)
    bare="$run/model-without-head"
    [ -f "$bare/manifest.json" ] || "${py[@]}" export --run "$run" --policy worldpack --distilled "$n" --layouts worldpack \
        --data data/val --out "$bare" --half --threads "${THREADS:-1}"
    [ -f "$run/fusion-data/truth.npy" ] || "$bin" fusion-data --suite "${HEAD_DATA:-data/train120}" --model "$bare" \
        --method ddim --steps "$n" --out "$run/fusion-data"
    "${py[@]}" fusion-train --data "$run/fusion-data" --run "$run/head" --steps "${HEAD_STEPS:-4000}" \
        --edge-weight "${HEAD_EDGE:-1}" --threads "${THREADS:-1}"
    "${py[@]}" fusion-export --run "$run/head" --model "$bare" --out "$out" --data "$run/fusion-data" ;;
  pair)
    data=(); [ -f "$run/fusion-data/truth.npy" ] && data=(--data "$run/fusion-data")
    "${py[@]}" fusion-pair --kept "$out" --shown "$teacher" --out "$out" --hole-fill "${HOLE_FILL:-7}" "${data[@]}" ;;
  adversarial)
    train="${TRAIN:-data/train120}"
    student="${STUDENT-fixtures/variants/worldpack_geometry_fused_1step}"
    [ -f "$run/cdit-worldpack.pt" ] || "${py[@]}" recover --model "${TEACHER:-$teacher}" --run "$run"
    [ -f "$run/distilled-worldpack-1.pt" ] || [ -z "$student" ] || "${py[@]}" recover --model "$student" --run "$run"
    "${py[@]}" encode --data "$train" --run "$run" --device "${DEVICE:-auto}"
    "${py[@]}" distill --data "$train" --run "$run" --grid 999 --teacher-steps 10 --steps "${STEPS:-20000}" \
        --batch "${BATCH:-16}" --lr "${LR:-1e-4}" --ema 0.998 --device "${DEVICE:-auto}" --threads "${THREADS:-1}" \
        --adversarial-weight "${ADV:-0.5}" --adversarial-start "${ADV_START:-200}" --decoder-from "$decoder" \
        ${MINUTES:+--minutes "$MINUTES"} ${ADV_CAP:+--adversarial-cap "$ADV_CAP"} ${STANDARDISE_JUDGED:+--standardise-judged} \
        ${JUDGE_HOLES:+--judge-holes} ${JUDGE:+--judge "$JUDGE"} ${JUDGE_NOISE:+--judge-noise "$JUDGE_NOISE"} \
        ${JUDGE_LR:+--judge-lr "$JUDGE_LR"} ;;
  adversarial-export)
    "${py[@]}" export --run "$run" --policy worldpack --distilled 1 --layouts worldpack --data "${VAL:-data/val}" --out "$out" \
        --half --decoder-from "$decoder" --fusion-from "${HEADS:-$decoder}" --threads "${THREADS:-1}" ;;
  *) sed -n '2,19p' "$0"; exit 2 ;;
esac
