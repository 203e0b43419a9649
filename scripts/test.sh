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
.venv/bin/python -m pip install --disable-pip-version-check -q -r tests/requirements.txt -r doom/requirements.txt \
  -r miniworld/requirements.txt
.venv/bin/python -m pip install --disable-pip-version-check -q -e 'clients/python[gym]'
# The trainer's torch-free modules (metrics, the manifest, the data reader), without torch.
.venv/bin/python -m pip install --disable-pip-version-check -q --no-deps -e train

if [ ! -x .venv-train/bin/python ]; then
  # The trainer's own venv: torch (PyPI's wheel, CUDA build, runs on the CPU), for
  # tests/test_train_command.py, which runs `worldpack train` end to end on a tiny dataset.
  echo "==> creating the trainer's venv in .venv-train (torch is large: a few minutes)"
  python3 -m venv .venv-train
fi
.venv-train/bin/python -m pip install --disable-pip-version-check -q -r train/requirements.txt
.venv-train/bin/python -m pip install --disable-pip-version-check -q --no-deps -e train

if [ ! -x .venv-triton/bin/python ]; then
  # The Triton tests start PyPI's tritonserver (nvidia-pytriton). Its Python-backend
  # stub links Debian's libpython3.11, so this venv is made with Debian's python3.11;
  # pytriton needs numpy < 2, so it is a venv of its own.
  echo "==> creating the Triton venv in .venv-triton"
  /usr/bin/python3.11 -m venv .venv-triton
fi
.venv-triton/bin/python -m pip install --disable-pip-version-check -q -r serving/triton/requirements.txt

if ! command -v chromium >/dev/null; then
  # The viewer test drives the page in Debian's Chromium (tests/test_viewer.py).
  echo "==> installing Debian's chromium for the viewer test"
  sudo=""; [ "$(id -u)" = 0 ] || sudo="sudo"
  if ! { $sudo apt-get install -y -q chromium >/dev/null 2>&1 || { $sudo apt-get update -q >/dev/null && $sudo apt-get install -y -q chromium >/dev/null; }; }; then
    echo "could not install chromium (apt-get as root or through sudo): tests/test_viewer.py will fail and say so"
  fi
fi

# The MiniWorld tests (tests/test_miniworld.py) render headless through Mesa's EGL, and
# once on Xvfb's display through xvfb-run: Debian's packages for both.
missing=""
for pkg in libegl1 libegl-mesa0 libgl1-mesa-dri libglu1-mesa xvfb; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing="$missing $pkg"
done
if [ -n "$missing" ]; then
  echo "==> installing Debian's$missing for the MiniWorld tests"
  sudo=""; [ "$(id -u)" = 0 ] || sudo="sudo"
  if ! { $sudo apt-get install -y -q $missing >/dev/null 2>&1 || { $sudo apt-get update -q >/dev/null && $sudo apt-get install -y -q $missing >/dev/null; }; }; then
    echo "could not install$missing (apt-get as root or through sudo): tests/test_miniworld.py will fail and say so"
  fi
fi

echo "==> cargo test (release: the overlap property tests sample millions of points)"
cargo test --release --workspace
echo "==> the criterion benches, each run once untimed (so that they keep building and running)"
cargo test --release --workspace --bench '*'

echo "==> pytest (OpenCV convention tests, ONNX parity, the Python client, the viewer in Chromium, Doom and MiniWorld)"
# `cargo test` built target/release/worldpack for the integration tests, with the
# workspace's features; `cargo build --bin` would build the tree again with others.
[ -x target/release/worldpack ] || cargo test --release --workspace --no-run
WORLDPACK_BIN="$PWD/target/release/worldpack" .venv/bin/python -m pytest tests -q
