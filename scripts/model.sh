#!/usr/bin/env bash
# Trains and exports the model (PyTorch). Never part of the test command.
# Sets up .venv-train from train/requirements.txt on first use, then
# runs `python -m worldpack_train "$@"` (stages: train-ae, encode, train, export).
# See docs/model.md for the whole recipe.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
if [ ! -x "$root/.venv-train/bin/python" ]; then
  echo "==> creating the training venv in .venv-train (torch is large: a few minutes)"
  python3 -m venv "$root/.venv-train"
  "$root/.venv-train/bin/python" -m pip install --disable-pip-version-check -q -r "$root/train/requirements.txt"
fi
PYTHONPATH="$root/train${PYTHONPATH:+:$PYTHONPATH}" exec "$root/.venv-train/bin/python" -m worldpack_train "$@"
