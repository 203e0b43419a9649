#!/usr/bin/env bash
# The paper's shapes through the runtime (docs/benchmarks.md, "The paper's
# scale"): 224x224 frames, 4x28x28 latents, a CDiT-B/2 and an SD-VAE-shaped
# autoencoder with random seeded weights; 844 packed context tokens against
# the baseline's 784. Needs torch (scripts/model.sh sets up .venv-train).
#   ./scripts/paper_scale.sh data     # data/paper-224: one ABA trajectory at 224x224, with plans
#   ./scripts/paper_scale.sh smoke    # -> fixtures/paper_tokens (narrow, committed; the tests run it)
#   ./scripts/paper_scale.sh paper    # -> runs/paper/model (CDiT-B/2, about 1.1 GB; not committed)
#   ./scripts/paper_scale.sh bench [--provider cuda]   # bench step on runs/paper/model
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/release/worldpack
data=data/paper-224

case "${1:-}" in
  data)
    [ -x "$bin" ] || cargo build --release
    "$bin" sim loopnav --per-cell 1 --tasks aba --ranges 5 --seed 9 --size 224x224 --out "$data"
    "$bin" plan --data "$data" --policies baseline,worldpack ;;
  smoke)
    ./scripts/model.sh paper-scale --size smoke --data "$data" --out fixtures/paper_tokens --half --threads "${THREADS:-1}" ;;
  paper)
    ./scripts/model.sh paper-scale --size paper --data "$data" --out runs/paper/model --threads "${THREADS:-1}" ;;
  bench)
    "$bin" bench step --model runs/paper/model --calls "${CALLS:-20}" --steps "${STEPS:-10}" --threads "${BENCH_THREADS:-1}" "${@:2}" ;;
  *) echo "usage: $0 data | smoke | paper | bench [bench step options]" >&2; exit 2 ;;
esac
