#!/usr/bin/env bash
# The checks that need a CUDA GPU, as one script for a lent GPU machine (see the device tool's
# README). Nothing here runs in CI. Prerequisites on that machine: Warp importable (its image has
# PyTorch but not warp-lang: ../shared/tools/warp-to-device packs it into chunks to carry, then
# export PYTHONPATH), the pack's other Python dependencies (carry wheels, see the device README), and
# optionally gsplat. Results land in $OUT (default out/gpu): the pytest log and the docs sections
# the benchmarks rewrite (copy them back into docs/).
#
#   bash scripts/gpu_checks.sh            # everything below, about 8-10 min on an H100/H200 (estimate)
#   QUICK=1 bash scripts/gpu_checks.sh    # the tests and the launch-mode table only
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-out/gpu}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
export PYTHONUNBUFFERED=1
nvidia-smi -L 2>&1 | tee "$OUT/gpu.txt"
# CUDA tests: MPM graph run vs the CPU run, torch rasterizer on CUDA vs CPU, gsplat vs ours, fp16 LGM,
# the Wan controls' probes and clip on CUDA vs CPU.
$PY -m pytest -q -p no:cacheprovider tests/test_sim_graph.py tests/test_render.py tests/test_lgm.py tests/test_controls.py \
    -k "cuda or gsplat or fp16" 2>&1 | tee "$OUT/pytest.log"
# MPM: kernel-by-kernel vs CUDA-graph replay (docs/benchmarks.md, section sim-launch-cuda).
$PY -m benchmarks.bench_sim --launch-only --device cuda:0 2>&1 | tee "$OUT/launch.log"
if [ -z "${QUICK:-}" ]; then
  # MPM throughput against particle count / grid size on the GPU (section sim-throughput).
  $PY -m benchmarks.bench_sim --quick --device cuda:0 2>&1 | tee "$OUT/sim.log"
  # Large scenes: the project vs a minimal MLS-MPM Warp kernel at 55 k and 2.1 M particles, per-kernel split
  # (section sim-scale-cuda; issue 38: the CPU's changes must not slow the GPU path).
  $PY -m benchmarks.bench_sim_scale --device cuda:0 --rounds 3 --steps 20 2>&1 | tee "$OUT/sim_scale.log"
  # Wan controls next to the simulation on the GPU, every CPU template (section controls-gpu; issue 17).
  $PY -m benchmarks.bench_controls 2>&1 | tee "$OUT/controls.log"
  # Enhancement: s/frame and peak memory, full-size random SD 2.1 + 2 ControlNets (docs/enhance.md, gpu).
  $PY -m benchmarks.bench_enhance --gpu --gpu-steps 3 2>&1 | tee "$OUT/enhance.log"
fi
cp docs/benchmarks.md docs/enhance.md "$OUT/" 2>/dev/null
echo "done: $OUT"
