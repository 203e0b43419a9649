#!/usr/bin/env bash
# The figures the README quotes, each from one saved run: every eval and benchmark below
# writes its summary into docs/figures/NAME.json with the command that made it, and
# `render` writes the README's table and the pages' figure spans from those files
# (tests/test_figures.py fails when a page differs from them). Evals resume: rows already done with the same settings
# are reused (runs/figures/).
#   ./scripts/figures.sh voxel        # the voxel test suite (sim loopnav --per-cell 6 --seed 6, 48 walks):
#                                     # the paper's pair and the served model
#   ./scripts/figures.sh doom         # Doom's test maps (48 walks, seed 2, maps never trained on): the served
#                                     # model and the 4-frame baseline
#   ./scripts/figures.sh miniworld    # MiniWorld's held-out suites, from ./scripts/miniworld.sh eval's runs
#   ./scripts/figures.sh trainer voxel  # the model `worldpack train --from voxel` makes (MODEL: runs/voxel-h1)
#                                     # beside the served one on the voxel test suite (doom: runs/doom-h1, Doom's)
#   ./scripts/figures.sh fullsize     # frames at 224x224: the three worlds' held-out suites rendered at that size,
#                                     # the served models' full-size frames against the 64x64 frame brought up and
#                                     # the full-size fused warp; and the step at 224x224 on one core
#   ./scripts/figures.sh speed        # the main job's step on one core (taskset) and memory selection
#   ./scripts/figures.sh cards        # the served voxel and Doom models' MODEL.md from their test suites' runs
#   ./scripts/figures.sh render       # README.md's table and the pages' figure spans from docs/figures/*.json
# THREADS (1) sets the evals' intra-op threads.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x target/release/worldpack ] || cargo test --release --workspace --no-run
bin=target/release/worldpack
py=.venv/bin/python
threads="${THREADS:-1}"
figures() { PYTHONPATH=train "$py" scripts/figures.py "$@"; }

suite() {  # suite DIR ARGS...: a voxel suite made once, then planned
  local dir=$1; shift
  [ -f "$dir/index.json" ] || "$bin" sim loopnav "$@" --out "$dir"
  [ -f "$dir/plans.json" ] || "$bin" plan --data "$dir"
}

# paper_and_served SUITE MODELS SERVED NAME: the paper's pair (each policy with its own
# weights from MODELS) and the served model, then the summary twice: paired against the
# served model, and against WorldPack (the paper's comparison).
paper_and_served() {
  local s=$1 models=$2 served=$3 name=$4 out="runs/figures/$4"
  local rows=(--suite "$s" --models "$models" --policies baseline,worldpack --extra served="$served" --covisible served
              --only baseline --only worldpack --only served_covisible --probe-frames 32 --threads "$threads" --out "$out")
  "$bin" eval "${rows[@]}" --against worldpack
  figures save "$name-paper" "$out/results.json" --command "./scripts/figures.sh ${FUNCNAME[1]}"
  "$bin" eval "${rows[@]}" --against served_covisible
  figures save "$name" "$out/results.json" --command "./scripts/figures.sh ${FUNCNAME[1]}"
}

voxel() {
  suite data/loopnav-test --per-cell 6 --seed 6
  paper_and_served data/loopnav-test fixtures/variants fixtures/variants/worldpack_geometry_fused_1step voxel-test
}

doom() {
  if [ ! -f data/doom-test/index.json ]; then
    (cd doom && PYTHONPATH=.:../train ../.venv/bin/python -m worldpack_doom suite --split test --count 48 --seed 2 --out ../data/doom-test)
  fi
  [ -f data/doom-test/plans.json ] || "$bin" plan --data data/doom-test
  # The served model and the 4-frame baseline (docs/doom.md has the paper's pair on Doom).
  local out=runs/figures/doom-test
  "$bin" eval --suite data/doom-test --models fixtures/doom --policies baseline --extra served=fixtures/doom/geometry_fused \
    --covisible served --only baseline --only served_covisible --probe-frames 32 --against served_covisible \
    --threads "$threads" --out "$out"
  figures save doom-test "$out/results.json" --command "./scripts/figures.sh doom"
}

miniworld() {
  for s in aba abca; do
    [ -f "runs/mw-eval/mw-test-$s/results.json" ] || ./scripts/miniworld.sh eval "data/mw-test-$s"
    figures save "miniworld-$s" "runs/mw-eval/mw-test-$s/results.json" \
      --command "./scripts/miniworld.sh data && ./scripts/miniworld.sh train && ./scripts/miniworld.sh eval data/mw-test-$s"
  done
}

# trainer WORLD: the model `worldpack train --from WORLD` made (MODEL) beside the served one on
# WORLD's test suite; the served row is the one `./scripts/figures.sh WORLD` ran, reused.
trainer() {
  local world=${1:?usage: $0 trainer voxel|doom} suite served data
  case "$world" in
    voxel) suite=data/loopnav-test served=fixtures/variants/worldpack_geometry_fused_1step data=data/voxel-train101 ;;
    doom) suite=data/doom-test served=fixtures/doom/geometry_fused data=data/doom-train ;;
    *) echo "trainer: voxel or doom, not $world" >&2; exit 2 ;;
  esac
  local model="${MODEL:-runs/$world-h1}" out="runs/figures/$world-test"
  "$bin" eval --suite "$suite" --policies baseline --extra served="$served" --covisible served \
    --extra command="$model" --covisible command --only served_covisible --only command_covisible \
    --probe-frames 32 --against served_covisible --threads "$threads" --out "$out"
  figures save "$world-trainer" "$out/results.json" --command "./scripts/train.sh --data $data --out $model --from $world \
--hours $(PYTHONPATH=train "$py" -c "import json,sys; print(json.load(open(sys.argv[1]))['hours'])" "$model/train.json") \
&& ./scripts/figures.sh trainer $world"
}

speed() {
  taskset -c 0 "$bin" bench walk --sessions 1 --json > runs/figures-walk.json
  figures save-json walk runs/figures-walk.json --command "taskset -c 0 target/release/worldpack bench walk --sessions 1"
  "$bin" bench select --workload loop --json > runs/figures-select.json
  figures save-json select-loop runs/figures-select.json --command "target/release/worldpack bench select --workload loop"
}

# fullsize_eval NAME SUITE MODELS SERVED: the served model's full-size frames on a 224x224 suite,
# paired against the 64x64 frame brought up (NAME) and against the full-size fused warp (NAME-fused).
fullsize_eval() {
  local name=$1 s=$2 models=$3 served=$4 out="runs/figures/$1"
  local rows=(--suite "$s" --models "$models" --policies baseline --extra served="$served" --covisible served
              --only served_covisible --upsampled served_covisible --only served_covisible_upsampled_64
              --probe-frames 32 --threads "$threads" --out "$out")
  "$bin" eval "${rows[@]}" --against reproject_fused
  figures save "$name-fused" "$out/results.json" --command "./scripts/figures.sh fullsize"
  "$bin" eval "${rows[@]}" --against served_covisible_upsampled_64 \
    --strip served_covisible,served_covisible_upsampled_64,reproject_fused --strip-frames 6
  figures save "$name" "$out/results.json" --command "./scripts/figures.sh fullsize"
}

fullsize() {
  [ -f data/loopnav-test224/index.json ] || "$bin" sim loopnav --per-cell 6 --seed 6 --size 224x224 --out data/loopnav-test224
  fullsize_eval fullsize-voxel data/loopnav-test224 fixtures/variants fixtures/variants/worldpack_geometry_fused_1step
  [ -f data/doom-test224/index.json ] || (cd doom && PYTHONPATH=.:../train ../.venv/bin/python -m worldpack_doom suite \
    --split test --count 48 --seed 2 --size 224 --out ../data/doom-test224)
  fullsize_eval fullsize-doom data/doom-test224 fixtures/doom fixtures/doom/geometry_fused
  [ -f data/mw-test-aba224/index.json ] || (cd miniworld && PYTHONPATH=.:../train ../.venv/bin/python -m worldpack_miniworld \
    suite --split test --task aba --count 48 --seed 2 --size 224 --out ../data/mw-test-aba224)
  fullsize_eval fullsize-miniworld data/mw-test-aba224 fixtures/doom fixtures/miniworld/geometry_fused
  # The strip for docs/fullsize.md, in 256 colours (Doom's frames are close to a palette already).
  "$py" -c "import sys; from PIL import Image; Image.open(sys.argv[1]).convert('RGB').quantize(256).save(sys.argv[2], optimize=True)" \
    runs/figures/fullsize-doom/strip.png docs/fullsize/doom-strip.png
  for truth in "" --no-truth; do
    taskset -c 0 "$bin" bench walk --sessions 1 --size 224 $truth --json > "runs/figures-walk224$truth.json"
    figures save-json "walk224$truth" "runs/figures-walk224$truth.json" \
      --command "taskset -c 0 target/release/worldpack bench walk --sessions 1 --size 224 $truth"
  done
}

cards() {
  PYTHONPATH=train "$py" -m worldpack_train.card --ship fixtures/variants/worldpack_geometry_fused_1step \
    --eval docs/figures/voxel-test.json --world voxel
  PYTHONPATH=train "$py" -m worldpack_train.card --ship fixtures/doom/geometry_fused --eval docs/figures/doom-test.json --world Doom
}

mkdir -p runs/figures
case "${1:-}" in
  voxel|doom|miniworld|trainer|fullsize|speed|cards) "$@" ;;
  render) figures render ;;
  *) sed -n '2,20p' "$0"; exit 2 ;;
esac
