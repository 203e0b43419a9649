#!/usr/bin/env bash
# One stage of the trainer by hand (`python -m worldpack_train STAGE ...`: train-ae,
# encode, train, distill, export, fusion-*, ...), for research; `./scripts/train.sh`
# runs the whole recipe. Sets up .venv-train from train/requirements.txt on first use.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
if [ ! -x "$root/.venv-train/bin/python" ]; then
  echo "==> creating the training venv in .venv-train (torch is large: a few minutes)"
  python3 -m venv "$root/.venv-train"
  "$root/.venv-train/bin/python" -m pip install --disable-pip-version-check -q -r "$root/train/requirements.txt"
fi
PYTHONPATH="$root/train${PYTHONPATH:+:$PYTHONPATH}" exec "$root/.venv-train/bin/python" -m worldpack_train "$@"
