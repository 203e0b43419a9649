#!/usr/bin/env bash
# The main job: serves the REST API over a committed model and a local store
# (data/worldpack.redb). Without flags it serves what the held-out rollouts
# and the step benchmark recommend (docs/benchmarks.md#the-main-jobs-step):
# fixtures/variants/worldpack_geometry_fused_1step, WorldPack as the paper's
# Algorithm 1 with the observed frames warped into the new view and a fusion
# head blending the frame with that warp, plans and warp sources chosen by
# co-visibility (--covisible), its sampler distilled from 10 DDIM steps into
# one (the manifest's grid; --steps and --method do not apply to it). With
# flags, they all go to `worldpack serve` as
# given (its own defaults: fixtures/small, 16 ancestral steps; see
# `target/release/worldpack serve --help`). On first use it installs ONNX
# Runtime (the PyPI wheel, pinned in tests/requirements.txt) into .venv.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ls .venv/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so* >/dev/null 2>&1; then
  echo "==> installing ONNX Runtime into .venv (first run only)"
  [ -x .venv/bin/python ] || python3 -m venv .venv
  .venv/bin/python -m pip install --disable-pip-version-check -q "$(grep '^onnxruntime==' tests/requirements.txt)"
fi
if [ $# -eq 0 ]; then
  set -- --model fixtures/variants/worldpack_geometry_fused_1step --policy worldpack --method ddim --steps 1 --covisible
fi
# The build ./scripts/test.sh makes (cargo test's feature set): after the tests this compiles
# nothing; `cargo run --bin` would build the tree again with another.
cargo test --release --workspace --no-run -q
exec target/release/worldpack serve "$@"
