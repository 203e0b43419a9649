#!/usr/bin/env bash
# The main job: serves the REST API over the committed small model
# (fixtures/small) and a local store (data/worldpack.redb). On first use it
# installs ONNX Runtime (the PyPI wheel, pinned in tests/requirements.txt)
# into .venv, where the model runtime finds it. Extra flags go to
# `worldpack serve` (see `cargo run --release -- serve --help`).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ls .venv/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so* >/dev/null 2>&1; then
  echo "==> installing ONNX Runtime into .venv (first run only)"
  [ -x .venv/bin/python ] || python3 -m venv .venv
  .venv/bin/python -m pip install --disable-pip-version-check -q "$(grep '^onnxruntime==' tests/requirements.txt)"
fi
exec cargo run --release --bin worldpack -- serve "$@"
