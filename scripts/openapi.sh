#!/usr/bin/env bash
# docs/openapi.json from a real server: starts `worldpack serve --memory-only` on a free
# port, fetches /openapi.json and writes it (tests/test_docs_references.py fails when the
# saved document differs from the served one). WORLDPACK_BIN picks another binary.
set -euo pipefail
cd "$(dirname "$0")/.."
exec .venv/bin/python tests/test_docs_references.py --write
