#!/usr/bin/env bash
# Your frames to a served model: `worldpack train` with its set-up. Makes the trainer's
# venv (.venv-train: torch, ONNX, the train/ package) on first use, builds the binary,
# then runs `worldpack train` with the flags given (docs/training.md):
#   ./scripts/train.sh --data DIR --out MODEL_DIR [--from voxel|doom|DIR] [--hours H] [--device cpu|cuda]
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv-train/bin/python ]; then
  echo "==> creating the trainer's venv in .venv-train (torch is large: a few minutes)"
  python3 -m venv .venv-train
fi
if ! .venv-train/bin/python -c "import torch, worldpack_train" 2>/dev/null; then
  .venv-train/bin/python -m pip install --disable-pip-version-check -q -r train/requirements.txt
  .venv-train/bin/python -m pip install --disable-pip-version-check -q --no-deps -e train
fi
# The build ./scripts/test.sh makes; after the tests this compiles nothing.
cargo test --release --workspace --no-run -q
exec target/release/worldpack train "$@"
