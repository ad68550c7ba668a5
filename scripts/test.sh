#!/usr/bin/env bash
# Set up .venv and run the test suite (CPU only; no weights, no network at test time).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
.venv/bin/python -m pytest -q "$@"
