"""What objects on velocity fields of their own cost (issue 37): the multi-object templates' simulation
with each object on its own grid velocity field (ObjectContact "friction", the default: multi-field
contact) against one field shared by all objects (ObjectContact "shared", the single-field path).

The template runs in-process through the node classes (tests/comfy_harness.py) up to its simulation
node, its Ground & Walls node's object_contact set to each mode in turn; the rounds alternate the
modes (A B B A ...) so that the machine's load falls on both alike. Per substep is the fair unit
(the modes simulate different motion: shared fields stick where objects touch, so the number of
substeps and the frames at rest differ); the whole simulation's stepping time is reported too.
Written to docs/benchmarks.md, section "contact". Usage:
    .venv/bin/python -m benchmarks.bench_contact [--frames N] [--rounds R] [--threads T] [template ...]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

from physmotion_core.report import machine_description, update_section

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from comfy_harness import node_classes, prepare_template_inputs, run_prompt  # noqa: E402

MODES = ("friction", "shared")


def multi_object_templates() -> list[Path]:
    """The API templates that combine objects (a Combine Objects node) and need no learned weights."""
    out = []
    for path in sorted((ROOT / "example_workflows" / "api").glob("*.json")):
        prompt = json.loads(path.read_text())
        classes = {n["class_type"] for n in prompt.values()}
        if "PhysMotionCombineObjects" in classes and not any("Loader" in c for c in classes):
            out.append(path)
    return out


def up_to_simulation(prompt: dict) -> tuple[dict, str, str]:
    """The prompt cut after its simulation node (what feeds it only), the simulation's and the
    Ground node's ids."""
    sim = next(k for k, n in prompt.items() if n["class_type"] == "PhysMotionMPMSimulate")
    ground = next(k for k, n in prompt.items() if n["class_type"] == "PhysMotionGround")
    keep, todo = set(), [sim]
    while todo:
        k = todo.pop()
        if k in keep:
            continue
        keep.add(k)
        todo += [v[0] for v in prompt[k]["inputs"].values() if isinstance(v, list) and len(v) == 2]
    return {k: prompt[k] for k in keep}, sim, ground


def run_once(prompt: dict, sim: str, ground: str, mode: str, frames: int, tmp: Path) -> dict:
    overrides = {f"{ground}.object_contact": mode}
    if frames:
        overrides[f"{sim}.frames"] = frames
    os.environ["PHYSMOTION_OUTPUT_DIR"] = str(tmp)
    prepare_template_inputs(prompt, tmp)
    out = run_prompt(prompt, overrides=overrides)
    (res,) = [r[0] for r in out["results"].values() if r and type(r[0]).__name__ == "SimResult"]
    s = res.stats
    return {"substeps": s["substeps"], "stepping_s": s["stepping_s"], "particles": s["particles"],
            "grid_res": s["grid_res"], "ms_per_substep": 1e3 * s["stepping_s"] / max(s["substeps"], 1)}


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("templates", nargs="*", help="template names (default: every multi-object CPU template)")
    ap.add_argument("--frames", type=int, default=0, help="frames to simulate (0: the template's own)")
    ap.add_argument("--rounds", type=int, default=2, help="A/B rounds (each runs both modes)")
    ap.add_argument("--no-write", action="store_true", help="print only; do not update docs/benchmarks.md")
    args = ap.parse_args(argv)
    node_classes()
    rows = []
    for path in multi_object_templates():
        if args.templates and path.stem not in args.templates:
            continue
        prompt, sim, ground = up_to_simulation(json.loads(path.read_text()))
        runs = {m: [] for m in MODES}
        with tempfile.TemporaryDirectory() as tmp:
            for r in range(args.rounds):
                order = MODES if r % 2 == 0 else MODES[::-1]
                for mode in order:
                    t0 = time.perf_counter()
                    runs[mode].append(run_once(prompt, sim, ground, mode, args.frames, Path(tmp)))
                    print(f"{path.stem} round {r + 1} {mode}: {runs[mode][-1]} ({time.perf_counter() - t0:.1f} s "
                          f"with the front end); load {os.getloadavg()[0]:.2f}", flush=True)
        own, shared = runs["friction"], runs["shared"]
        ratios = [a["ms_per_substep"] / b["ms_per_substep"] for a, b in zip(own, shared)]
        whole = [a["stepping_s"] / b["stepping_s"] for a, b in zip(own, shared)]
        med = lambda rs, key: statistics.median(r[key] for r in rs)  # noqa: E731
        rows.append(f"| {path.stem} | {own[0]['particles']:,} | {own[0]['grid_res']} | "
                    f"{med(shared, 'ms_per_substep'):.2f} | {med(own, 'ms_per_substep'):.2f} | "
                    f"{min(ratios):.2f}-{max(ratios):.2f} | {med(shared, 'substeps'):,.0f} / {med(own, 'substeps'):,.0f} | "
                    f"{med(shared, 'stepping_s'):.1f} / {med(own, 'stepping_s'):.1f} | {min(whole):.2f}-{max(whole):.2f} |")
        print(rows[-1], flush=True)
    frames = f"{args.frames} frames" if args.frames else "the template's frames"
    md = f"""## Objects on velocity fields of their own (issue 37)

What multi-field contact costs on the multi-object CPU templates: each object on its own grid velocity
field (ObjectContact "friction", the default) against one field for all (ObjectContact "shared"), set on
the template's Ground & Walls node; the template runs in-process up to its simulation ({frames}),
{args.rounds} rounds alternating the two modes. Own fields scatter each object's mass gradient too
(p2g) and resolve contact per node (grid_update, two passes over each node's fields). The modes move
differently (shared fields stick where the objects touch), so the substeps differ: the per-substep
ratio is the cost of the method, the whole-simulation ratio what a user waits. Machine:
{machine_description()}, load average {os.getloadavg()[0]:.1f} at the end. Measured {datetime.date.today().isoformat()}.
Re-run: `python -m benchmarks.bench_contact`.

| template | particles | grid_res | shared ms/substep | own fields ms/substep | ratio per substep (rounds) | substeps shared / own | stepping s shared / own | ratio whole (rounds) |
| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n"
    if not args.no_write and not args.templates:
        update_section("benchmarks.md", "contact", md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
