#!/usr/bin/env bash
# The main job: serves the REST API over a committed model and a local store
# (data/worldpack.redb). Without flags it serves what the held-out rollouts
# recommend (docs/geometry.md): fixtures/variants/worldpack_geometry_fused,
# WorldPack as the paper's Algorithm 1 with the observed frames warped into the
# new view and its fusion head blending the frame with that warp, plans and
# warp sources chosen by co-visibility (--covisible), 10 DDIM steps: the best
# row on the 48-trajectory test suite; co-visibility is also the best on the
# occluder suite. With flags, they all go to `worldpack serve` as
# given (its own defaults: fixtures/small, 16 ancestral steps; see
# `cargo run --release -- serve --help`). On first use it installs ONNX
# Runtime (the PyPI wheel, pinned in tests/requirements.txt) into .venv.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ls .venv/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so* >/dev/null 2>&1; then
  echo "==> installing ONNX Runtime into .venv (first run only)"
  [ -x .venv/bin/python ] || python3 -m venv .venv
  .venv/bin/python -m pip install --disable-pip-version-check -q "$(grep '^onnxruntime==' tests/requirements.txt)"
fi
if [ $# -eq 0 ]; then
  set -- --model fixtures/variants/worldpack_geometry_fused --policy worldpack --method ddim --steps 10 --covisible
fi
exec cargo run --release --bin worldpack -- serve "$@"
