"""Run every shipped template at full size on this machine and record its cost.

Each API workflow runs in-process (tests/comfy_harness.py, i.e. the same node classes ComfyUI
calls). Written to docs/benchmarks.md, section "templates". Usage:
    .venv/bin/python -m benchmarks.bench_templates [name ...]
"""

from __future__ import annotations

import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from physmotion_core.report import machine_description, update_section

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from comfy_harness import node_classes, prepare_template_inputs, run_prompt  # noqa: E402


def main(names: list[str]) -> int:
    node_classes()
    rows = []
    for path in sorted((ROOT / "example_workflows" / "api").glob("*.json")):
        if names and path.stem not in names:
            continue
        prompt = json.loads(path.read_text())
        if any("Loader" in n["class_type"] for n in prompt.values()):
            print(f"{path.stem}: skipped (needs learned weights)", flush=True)
            continue
        if any(n["class_type"] not in node_classes() for n in prompt.values()):
            print(f"{path.stem}: skipped (needs nodes newer than this harness has)", flush=True)
            continue
        with tempfile.TemporaryDirectory() as tmp:
            os.environ["PHYSMOTION_OUTPUT_DIR"] = tmp
            prepare_template_inputs(prompt, Path(tmp))  # the stand-in .ply of "your own splat"
            t0 = time.perf_counter()
            out = run_prompt(prompt)
            wall = time.perf_counter() - t0
        sims = [r[0] for r in out["results"].values() if r and type(r[0]).__name__ == "SimResult"]
        s = sims[0].stats
        rows.append(f"| {path.stem} | {', '.join(m.name for m in sims[0].materials)} | {s['particles']:,} | "
                    f"{s['grid_res']} | {s['substeps']:,} | {s['stepping_s']:.1f} | "
                    f"{s['particle_substeps_per_s'] / 1e6:.2f} | {wall:.1f} |")
        print(rows[-1], flush=True)
    md = f"""## Templates at full size

Every CPU template of `example_workflows/api/` (those that need no learned weights) run in-process through
the node classes at the template's own settings (frames, grid, quality as shipped; the Warp kernels
already compiled; previews included). Machine: {machine_description()}.
Measured {datetime.date.today().isoformat()}. Re-run: `python -m benchmarks.bench_templates`.

| template | materials | particles | grid_res | substeps | simulation s | M particle-substeps/s | whole workflow s |
| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n"
    if not names:
        update_section("benchmarks.md", "templates", md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
