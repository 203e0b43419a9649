#!/usr/bin/env bash
# The main job: `worldpack serve` over the served model and a local store
# (data/worldpack.redb), with the flags given passed on. Without --model it
# serves fixtures/variants/worldpack_geometry_fused_1step as its manifest's
# `serving` block says (1 step, co-visible memory, 32 frames warped); any
# flag overrides only itself (`target/release/worldpack serve --help`).
# On first use it installs ONNX Runtime (the PyPI wheel, pinned in
# tests/requirements.txt) into .venv.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ls .venv/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so* >/dev/null 2>&1; then
  echo "==> installing ONNX Runtime into .venv (first run only)"
  [ -x .venv/bin/python ] || python3 -m venv .venv
  .venv/bin/python -m pip install --disable-pip-version-check -q "$(grep '^onnxruntime==' tests/requirements.txt)"
fi
# The build ./scripts/test.sh makes (cargo test's feature set): after the tests this compiles
# nothing; `cargo run --bin` would build the tree again with another.
cargo test --release --workspace --no-run -q
exec target/release/worldpack serve "$@"
