#!/usr/bin/env bash
# Create (or reuse) .venv and install physmotion with what the tests need. Idempotent.
# TORCH_SPEC picks the torch build (default: torch 2.14.1 + torchvision 0.29.1, a pair that imports together;
# segment-anything needs torchvision. Any torch >= 2.1 with its matching torchvision works).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
python -m pip install --disable-pip-version-check -q --upgrade pip >/dev/null
if ! python -c "import torch, torchvision" 2>/dev/null; then
  # shellcheck disable=SC2086
  python -m pip install --disable-pip-version-check -q ${TORCH_SPEC:-torch==2.14.1 torchvision==0.29.1}
fi
python -m pip install --disable-pip-version-check -q -e ".[test]"
