"""What objects on velocity fields of their own cost (issue 37): the multi-object templates' simulation
with each object on its own grid velocity field (ObjectContact "friction", the default: multi-field
contact) against one field shared by all objects (ObjectContact "shared", the single-field path).

The template runs in-process through the node classes (tests/comfy_harness.py) up to its simulation
node for one frame, which gives the scene's solver as simulate() builds it (particles, materials,
domain, initial velocities, ground); two solvers are then made from it, one per mode, and advanced
frame by frame in turns (A B B A ...: a frame each), so the machine's load falls on both alike
(this machine is shared). Per substep is the method's cost (the modes move differently: shared
fields stick where objects touch, so the substeps differ); the whole span's time ratio is what a
user waits for that part of the clip.
Written to docs/benchmarks.md, section "contact". Usage:
    .venv/bin/python -m benchmarks.bench_contact [--frames N] [template ...]
"""

from __future__ import annotations

import argparse
import datetime
import importlib
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


def scene_solver_args(prompt: dict, sim: str, tmp: Path) -> tuple[tuple, dict, float, float]:
    """Run the prompt's simulation for one frame and return what its MPMSolver was built from (args,
    kwargs), the frame time and the largest step simulate() allowed."""
    simmod = importlib.import_module("physmotion_core.sim.simulate")  # the module (the package exports the function)

    seen = []
    real = simmod.MPMSolver

    class Recording(real):
        def __init__(self, *a, **kw):
            seen.append((a, kw))
            super().__init__(*a, **kw)

    os.environ["PHYSMOTION_OUTPUT_DIR"] = str(tmp)
    prepare_template_inputs(prompt, tmp)
    simmod.MPMSolver = Recording
    try:
        out = run_prompt(prompt, overrides={f"{sim}.frames": 1})
    finally:
        simmod.MPMSolver = real
    (res,) = [r[0] for r in out["results"].values() if r and type(r[0]).__name__ == "SimResult"]
    frame_dt = 1.0 / float(prompt[sim]["inputs"].get("fps", 24.0))
    return seen[-1][0], seen[-1][1], frame_dt, frame_dt / 8


def interleaved(args: tuple, kw: dict, frame_dt: float, max_dt: float, frames: int) -> dict:
    """Advance one solver per mode through ``frames`` frames, a frame each in turns (A B B A ...);
    per mode: substeps, stepping seconds, and the per-frame ms per substep."""
    from physmotion_core.sim.mpm import MPMSolver
    from physmotion_core.types.conditions import ObjectContact

    base = kw.get("object_contact") or ObjectContact()
    solvers = {m: MPMSolver(*args, **{**kw, "object_contact": ObjectContact(m, base.friction)}) for m in MODES}
    for s in solvers.values():
        s.set_limits(max_dt=max_dt)
        s.advance(1e-9)  # record the first programs outside the timing
    stats = {m: {"substeps": 0, "seconds": 0.0, "frame_ms": []} for m in MODES}
    for k in range(frames):
        for m in (MODES if k % 2 == 0 else MODES[::-1]):
            s = solvers[m]
            n0, t0 = s.substeps, time.perf_counter()
            s.begin_frame()
            s.advance((k + 1) * frame_dt, frame=k)
            dt, dn = time.perf_counter() - t0, s.substeps - n0
            stats[m]["substeps"] += dn
            stats[m]["seconds"] += dt
            stats[m]["frame_ms"].append(1e3 * dt / max(dn, 1))
    stats["fields"] = {m: solvers[m].fields for m in MODES}
    stats["particles"] = solvers[MODES[0]].n
    return stats


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("templates", nargs="*", help="template names (default: every multi-object CPU template)")
    ap.add_argument("--frames", type=int, default=24, help="frames to simulate with each mode (from the start)")
    ap.add_argument("--no-write", action="store_true", help="print only; do not update docs/benchmarks.md")
    args = ap.parse_args(argv)
    node_classes()
    rows = []
    loads = [os.getloadavg()[0]]
    for path in multi_object_templates():
        if args.templates and path.stem not in args.templates:
            continue
        prompt, sim, ground = up_to_simulation(json.loads(path.read_text()))
        with tempfile.TemporaryDirectory() as tmp:
            sargs, skw, frame_dt, max_dt = scene_solver_args(prompt, sim, Path(tmp))
        st = interleaved(sargs, skw, frame_dt, max_dt, args.frames)
        loads.append(os.getloadavg()[0])
        own, shared = st["friction"], st["shared"]
        per_frame = sorted(a / b for a, b in zip(own["frame_ms"], shared["frame_ms"]))
        med = statistics.median(per_frame)
        q1, q3 = per_frame[len(per_frame) // 4], per_frame[(3 * len(per_frame)) // 4]
        ms = {m: 1e3 * st[m]["seconds"] / st[m]["substeps"] for m in MODES}
        rows.append(f"| {path.stem} | {st['particles']:,} | {st['fields']['friction']} / {st['fields']['shared']} | "
                    f"{ms['shared']:.2f} | {ms['friction']:.2f} | {med:.2f} ({q1:.2f}-{q3:.2f}) | "
                    f"{shared['substeps']:,} / {own['substeps']:,} | {shared['seconds']:.1f} / {own['seconds']:.1f} | "
                    f"{own['seconds'] / shared['seconds']:.2f} |")
        print(rows[-1], flush=True)
    md = f"""## Objects on velocity fields of their own (issue 37)

What multi-field contact costs on the multi-object CPU templates: each object on its own grid velocity
field (ObjectContact "friction", the template's setting) against one field for all (ObjectContact
"shared"). The scene is the template's own (its front end run in-process, the solver simulate() builds);
two solvers, one per mode, simulate its first {args.frames} frames a frame each in turns (A B B A ...),
so the load of this shared machine falls on both alike. Own fields scatter each object's mass
gradient too (p2g) and resolve contact per node (grid_update: two passes over each node's fields,
the fill check). The modes move differently (shared fields stick where the objects touch), so the
substeps differ: the per-substep ratio (median over the frames, quartiles in brackets) is the
method's cost, the span's time ratio what a user waits for those frames. Machine:
{machine_description()}, load average {min(loads):.1f}-{max(loads):.1f}. Measured {datetime.date.today().isoformat()}.
Re-run: `python -m benchmarks.bench_contact`.

| template | particles | fields own / shared | shared ms/substep | own fields ms/substep | ratio per substep | substeps shared / own | stepping s shared / own | ratio, the span |
| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n"
    if not args.no_write and not args.templates:
        update_section("benchmarks.md", "contact", md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
