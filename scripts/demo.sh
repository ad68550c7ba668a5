#!/usr/bin/env bash
# Set up .venv and render the bundled photo to out/coffee_jelly.mp4 (no weights, no GPU needed).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
.venv/bin/physmotion generate photos/coffee.png --material jelly --box 55,6,498,395 \
  --force 20,0,0 --at 200,150 --frames 48 --fps 24 \
  -o out/coffee_jelly.mp4 --stats out/coffee_jelly.json "$@"
