#!/usr/bin/env bash
# MiniWorld end to end (docs/miniworld.md): suites from MiniWorld's rooms in the dataset
# format, a model made by `worldpack train` fine-tuned from the Doom family, and the
# held-out eval on world seeds (and one environment, YMaze) never trained on.
#   ./scripts/miniworld.sh data      # data/mw-{train,val,test-aba,test-abca}: 200 / 16 / 48 / 48 walks, checked and planned
#   ./scripts/miniworld.sh train     # ./scripts/train.sh --from doom --hours HOURS (1.5) -> runs/mw
#   ./scripts/miniworld.sh eval SUITE   # the served configuration against the model it started from, its own
#                                    # baseline and the references, paired (MODEL: runs/mw; THREADS: 2;
#                                    # EVAL_OUT: runs/mw-eval, which `ship` and figures.sh read)
#   ./scripts/miniworld.sh walk      # a REST walk of a held-out ABCA walk through the Python client -> docs/miniworld/
#   ./scripts/miniworld.sh ship      # the served model and its card into fixtures/miniworld/geometry_fused, the card
#                                    # with the held-out suites' tables (from runs/mw-eval/*/results.json)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/release/worldpack
model="${MODEL:-runs/mw}"
mw() { (cd miniworld && PYTHONPATH=.:../train ../.venv/bin/python -m worldpack_miniworld "$@"); }
suite() {  # suite DIR ARGS...: made once, then checked and planned
  local dir=$1; shift
  [ -f "$dir/index.json" ] || mw suite "$@" --out "../$dir"
  "$bin" check --data "$dir"
}

case "${1:-}" in
  data)
    suite data/mw-train --split train --task mixed --count 200 --seed 1
    suite data/mw-val --split train --task mixed --count 16 --seed 3
    suite data/mw-test-aba --split test --task aba --count 48 --seed 2
    suite data/mw-test-abca --split test --task abca --count 48 --seed 4
    for d in data/mw-val data/mw-test-aba data/mw-test-abca; do [ -f "$d/plans.json" ] || "$bin" plan --data "$d"; done ;;
  train)
    ./scripts/train.sh --data data/mw-train --out "$model" --from doom --hours "${HOURS:-1.5}" ;;
  eval)
    s="${2:?usage: $0 eval SUITE}"
    mkdir -p "$model/work/eval-models"
    [ -e "$model/work/eval-models/baseline" ] || ln -s "$PWD/$model/baseline" "$model/work/eval-models/baseline"
    "$bin" eval --suite "$s" --models "$model/work/eval-models" --policies baseline \
      --extra served="$model" --covisible served --extra started_from=fixtures/doom/geometry_fused --covisible started_from \
      --only served_covisible --only started_from_covisible --only baseline --probe-frames 32 \
      --against served_covisible --strip served_covisible,started_from_covisible,baseline --strip-frames 8 \
      --threads "${THREADS:-2}" --out "${EVAL_OUT:-runs/mw-eval}/$(basename "$s")" ;;
  walk)
    mkdir -p docs/miniworld
    "$bin" serve --model "$model" --store /tmp/mw-walk.redb --addr 127.0.0.1:18180 & pid=$!
    trap 'kill $pid' EXIT
    sleep 2
    .venv/bin/python clients/python/examples/suite_walk.py --url http://127.0.0.1:18180 --suite data/mw-test-abca \
      --index "${INDEX:-0}" --out docs/miniworld/rest_walk.png ;;
  ship)
    dst=fixtures/miniworld/geometry_fused
    rm -rf "$dst" && mkdir -p "$dst"
    cp "$model"/{manifest.json,denoiser.weights,MODEL.md,heldout-strip.png,train.json,lineage.json} "$model"/*.onnx "$dst"/
    cp -r "$model/reference" "$dst"/
    # Paths of this checkout become the repository's.
    sed -i "s#$PWD/##g" "$dst"/{train.json,lineage.json,MODEL.md}
    # The folder's name is the model's (as export names it).
    .venv-train/bin/python -c "import sys; from pathlib import Path; from worldpack_train.pipeline import rename_model
rename_model(Path(sys.argv[1]), sys.argv[2], 'geometry_fused')" "$dst" "$(basename "$model")"
    sed -i "1s/.*/# geometry_fused (MiniWorld)/" "$dst/MODEL.md"
    { echo; echo "## On the held-out suites"; echo
      echo "Walks in world seeds (and, for YMaze, an environment) never trained on: \`./scripts/miniworld.sh eval data/mw-test-aba\`"
      echo "and \`... data/mw-test-abca\`. The baseline row is this model's own 4-frame baseline."; echo
      .venv/bin/python -m worldpack_train.card runs/mw-eval/mw-test-aba/results.json runs/mw-eval/mw-test-abca/results.json
    } >> "$dst/MODEL.md"
    du -sh "$dst" ;;
  *) sed -n '2,13p' "$0"; exit 2 ;;
esac
