"""Peak memory of `generate` on RGBA cut-outs of a few sizes, against the up-front estimate.

The pipeline refuses a run before it starts when its estimated memory is over what is free
(``physmotion_core.memory.pipeline_need_bytes``). This measures what a run really needs, so the
estimate's constants can be calibrated from numbers instead of guessed: each case runs in a fresh
subprocess that imports the library, resets the kernel's peak-RSS counter (``/proc/self/clear_refs``
with 5, which resets VmHWM), records VmRSS, runs ``generate`` on an RGBA cut-out PNG of the given
size (``max_side=0``: the size is kept) and reads VmHWM. "Measured need" is VmHWM minus the VmRSS
before the run: the memory the run itself adds (the libraries already loaded are not part of it,
and are not part of the free memory it is checked against either).

Writes the "memory" section of docs/reliability.md.

    .venv/bin/python -m benchmarks.bench_memory [--quick]
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

CHILD = r"""
import json, sys, time
import cv2, numpy as np
side, frames, grid, path, out = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5]
width = int(sys.argv[6]) if len(sys.argv) > 6 else side * 4 // 3
from physmotion_core.pipeline import generate
from physmotion_core.types.conditions import Conditions, Force
from physmotion_core.types.settings import SimSettings
import physmotion_core.lift, physmotion_core.render.frames, physmotion_core.segment, physmotion_core.sim
def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
# An RGBA cut-out: a soft-edged ellipse on transparent background, with texture.
h, w = side, width
yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
inside = ((xx - w / 2) / (0.3 * w)) ** 2 + ((yy - h * 0.55) / (0.35 * h)) ** 2 < 1
img = np.zeros((h, w, 4), np.uint8)
img[..., 0] = (40 + 100 * (xx / w)).astype(np.uint8)
img[..., 1] = (60 + 80 * (yy / h)).astype(np.uint8)
img[..., 2] = 200
img[..., 3] = np.where(inside, 255, 0)
cv2.imwrite(path, img)
del img, yy, xx, inside
open("/proc/self/clear_refs", "w").write("5")
before = status("VmRSS")
t0 = time.perf_counter()
res = generate(path, settings=SimSettings(frames=frames, grid_res=grid, device="cpu"), max_side=0,
               conditions=Conditions([Force((5.0, 0, 0))]), output=path + ".mp4", models="none")
seconds = time.perf_counter() - t0
peak = status("VmHWM")
json.dump({"side": side, "width": w, "height": h, "frames": frames, "grid_res": grid, "before": before,
           "peak": peak, "need": peak - before, "seconds": seconds,
           "gaussians": len(res.gaussians), "particles": int(res.sim.stats["particles"])}, open(out, "w"))
"""

# (height, frames[, width]): 4:3 cut-outs unless a width is given; the square 2048 cases are the
# large cut-outs of issue 36 (the per-frame part at that size).
CASES = [(256, 4), (512, 4), (1024, 2), (1024, 6), (1536, 2), (2048, 2, 2048), (2048, 4, 2048), (2048, 8, 2048)]
QUICK = [(256, 4), (1024, 2)]


def measure(side: int, frames: int, width: int | None = None, grid: int = 16) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "m.json"
        subprocess.run([sys.executable, "-c", CHILD, str(side), str(frames), str(grid), str(Path(tmp) / "cutout.png"),
                        str(out), str(width or side * 4 // 3)], check=True, cwd=ROOT)
        return json.loads(out.read_text())


def main() -> None:
    from physmotion_core.memory import fmt_bytes, pipeline_need_bytes
    from physmotion_core.report import machine_description, update_section

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    rows = []
    for case in QUICK if args.quick else CASES:
        r = measure(*case)
        r["estimate"] = pipeline_need_bytes(r["width"], r["height"], r["frames"])
        rows.append(r)
        print(json.dumps(r), flush=True)
    lines = ["## Memory: the up-front estimate against measured peaks", "",
             "`benchmarks/bench_memory.py` (its docstring says how it measures). Each case: an RGBA cut-out "
             "PNG (4:3 unless square, an ellipse) run through `generate` (no models, alpha as the mask, "
             "`max_side=0`, grid_res 16, jelly, a push) in a fresh process; measured need = peak RSS "
             "(VmHWM) minus the RSS before the run. The estimate is `memory.pipeline_need_bytes`, "
             f"which the pipeline checks against free RAM before any work. Machine: {machine_description()}. "
             f"Measured {datetime.date.today().isoformat()}.", "",
             "| cut-out | frames | Gaussians | measured need | estimate | estimate / measured | run (s) |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['width']}x{r['height']} | {r['frames']} | {r['gaussians']} | {fmt_bytes(r['need'])} | "
                     f"{fmt_bytes(r['estimate'])} | {r['estimate'] / r['need']:.2f} | {r['seconds']:.1f} |")
    lines += ["", "```json", json.dumps([{k: r[k] for k in ("width", "height", "frames", "need")} for r in rows]),
              "```"]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        update_section(ROOT / "docs" / "reliability.md", "memory", text)


if __name__ == "__main__":
    main()
