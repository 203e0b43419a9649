#!/usr/bin/env bash
# Runs every test from a fresh clone: sets up the Python venv the tests need,
# builds the workspace, runs `cargo test` and then the pytest suite (which
# checks the Rust geometry against OpenCV through `worldpack geometry`).
set -euo pipefail
cd "$(dirname "$0")/.."

if [ ! -x .venv/bin/python ]; then
  echo "==> creating Python venv in .venv"
  python3 -m venv .venv
fi
echo "==> installing Python test requirements"
.venv/bin/python -m pip install --disable-pip-version-check -q -r tests/requirements.txt
.venv/bin/python -m pip install --disable-pip-version-check -q -e 'clients/python[gym]'

echo "==> cargo test (release: the overlap property tests sample millions of points)"
cargo test --release --workspace

echo "==> pytest (OpenCV convention tests)"
cargo build --release --bin worldpack
WORLDPACK_BIN="$PWD/target/release/worldpack" .venv/bin/python -m pytest tests -q
