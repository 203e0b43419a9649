#!/usr/bin/env bash
# One command for docs/results.md: makes the evaluation suite when missing,
# runs `worldpack eval` (resumable: rows already done with the same settings
# are reused), then `worldpack study` (speed against accuracy, pose noise
# with OpenCV visual odometry on a 224x224 render of the same suite, and the
# failure strata; also resumable) and writes the report with its pictures.
#   ./scripts/results.sh                      # the documented default run
#   PER_CELL=1 MAX_FRAMES=40 ./scripts/results.sh --steps 4   # a quick look
#   STUDY=0 ./scripts/results.sh              # rollouts only
# Extra arguments go to `worldpack eval`.
set -euo pipefail
cd "$(dirname "$0")/.."
suite="${SUITE:-data/loopnav-eval}"
per_cell="${PER_CELL:-2}"
out="${OUT:-runs/eval}"
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
  .venv/bin/python -m pip install --disable-pip-version-check -q -r tests/requirements.txt
fi
cargo build --release --bin worldpack
bin=target/release/worldpack
if [ ! -f "$suite/index.json" ]; then
  "$bin" sim loopnav --per-cell "$per_cell" --seed 2 --out "$suite"
fi
args=(--suite "$suite" --out "$out")
if [ -n "${MAX_FRAMES:-}" ]; then args+=(--max-frames "$MAX_FRAMES"); fi
"$bin" eval "${args[@]}" "$@"
study=()
if [ "${STUDY:-1}" != 0 ]; then
  render="${suite}-224"
  if [ ! -f "$render/index.json" ]; then
    "$bin" sim loopnav --per-cell "$per_cell" --seed 2 --size 224x224 --out "$render"
  fi
  .venv/bin/python scripts/visual_odometry.py --render "$render" --suite "$suite"
  "$bin" study --suite "$suite" --extra worldpack_tiny=fixtures/variants/worldpack_tiny --vo poses-vo.npy --out runs/study
  study=(--study runs/study/study.json)
fi
probe=()
if [ -f docs/probe/probe.json ]; then probe=(--probe docs/probe/probe.json); fi
.venv/bin/python scripts/report.py "$out/results.json" "${probe[@]}" "${study[@]}" --command "./scripts/results.sh $*" -o docs/results.md
