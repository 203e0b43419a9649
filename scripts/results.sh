#!/usr/bin/env bash
# One command for docs/results.md, the voxel world's results page: the paper's pair
# (`--policies baseline,worldpack`, each run with its best committed weights) and the
# served model (co-visible selection, as `./scripts/serve.sh` runs it) against the
# copy and depth-warp references, on the 48-trajectory test suite. Resumable: rows
# already done with the same settings are reused. STUDY=1 adds `worldpack study`
# (speed against accuracy, pose noise with OpenCV visual odometry on a 224x224
# render of the same suite, failure strata) over the four paper policies and the served model.
#   ./scripts/results.sh                                  # the page as committed
#   SUITE=data/loopnav-fresh53 ./scripts/results.sh       # another suite (made when missing, SEED and PER_CELL)
#   STUDY=1 ./scripts/results.sh                          # with the study (slow)
# Extra arguments go to `worldpack eval`.
set -euo pipefail
cd "$(dirname "$0")/.."
suite="${SUITE:-data/loopnav-test}"
seed="${SEED:-6}"
per_cell="${PER_CELL:-6}"
out="${OUT:-runs/results/$(basename "$suite")}"
served="${SERVED:-fixtures/variants/worldpack_geometry_fused_1step}"
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
  .venv/bin/python -m pip install --disable-pip-version-check -q -r tests/requirements.txt
fi
# The build ./scripts/test.sh makes (cargo test's features; `cargo build --bin` would build the tree again).
[ -x target/release/worldpack ] || cargo test --release --workspace --no-run
bin=target/release/worldpack
if [ ! -f "$suite/index.json" ]; then
  "$bin" sim loopnav --per-cell "$per_cell" --seed "$seed" --out "$suite"
  "$bin" plan --data "$suite"
fi
"$bin" eval --suite "$suite" --out "$out" --policies baseline,worldpack \
  --extra served="$served" --covisible served --only baseline --only worldpack --only served_covisible \
  --threads "${THREADS:-1}" "$@"
study=()
if [ "${STUDY:-0}" != 0 ]; then
  render="${suite}-224"
  if [ ! -f "$render/index.json" ]; then
    "$bin" sim loopnav --per-cell "$per_cell" --seed "$seed" --size 224x224 --out "$render"
  fi
  .venv/bin/python scripts/visual_odometry.py --render "$render" --suite "$suite"
  "$bin" study --suite "$suite" --extra served="$served" --vo poses-vo.npy --out runs/study
  study=(--study runs/study/study.json)
fi
command="./scripts/results.sh${*:+ $*}"
[ "$suite" = data/loopnav-test ] || command="SUITE=$suite $command"
.venv/bin/python scripts/report.py "$out/results.json" "${study[@]}" --command "$command" -o docs/results.md
