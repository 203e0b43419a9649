#!/usr/bin/env bash
# One command for docs/results.md: makes the evaluation suite when missing,
# runs `worldpack eval` (resumable: rows already done with the same settings
# are reused) and writes the report with its pictures.
#   ./scripts/results.sh                      # the documented default run
#   PER_CELL=1 MAX_FRAMES=40 ./scripts/results.sh --steps 4   # a quick look
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
probe=()
if [ -f docs/probe/probe.json ]; then probe=(--probe docs/probe/probe.json); fi
.venv/bin/python scripts/report.py "$out/results.json" "${probe[@]}" --command "./scripts/results.sh $*" -o docs/results.md
