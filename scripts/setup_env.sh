#!/usr/bin/env bash
# Create (or reuse) .venv and install physmotion with what the tests need. Idempotent.
# TORCH_SPEC picks the torch build (default: the 2.13.0 release; any torch >= 2.1 works).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
python -m pip install --disable-pip-version-check -q --upgrade pip >/dev/null
if ! python -c "import torch" 2>/dev/null; then
  python -m pip install --disable-pip-version-check -q "${TORCH_SPEC:-torch==2.13.0}"
fi
python -m pip install --disable-pip-version-check -q -e ".[test]"
