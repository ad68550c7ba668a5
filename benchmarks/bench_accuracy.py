"""Run time against error: sweep grid resolution, particles per cell, CFL number and transfer
scheme on scenes with a known answer, draw the Pareto front, and compare with the fixed 1e-4 s
substep the PhysGaussian configs use.

    python -m benchmarks.bench_accuracy           # writes the "runtime-vs-error" section of docs/accuracy.md
    python -m benchmarks.bench_accuracy --quick   # a smaller sweep                  and docs/accuracy_pareto.png

Scenes:
* the free-free elastic bar (E 1e5 Pa, ρ 1000, ν 0, c = 10 m/s, L = 1 m) started in its first
  longitudinal mode: error = |period / (2L/c) − 1|, measured over 1.5 periods;
* a block sliding to a stop on Coulomb ground (μ 0.3, v0 1 m/s): error = |distance / (v0²/2μg) − 1|;
* a jelly cube pushed along the ground (the demo's load case) for the fixed-step comparison, with
  the error against a converged run (CFL 0.1): RMS particle-position difference / cube size.
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import time
from pathlib import Path

import numpy as np

from physmotion_core.report import DOCS, machine_description, update_section
from physmotion_core.types.material import material_preset
from physmotion_core.sim.simulate import simulate
from physmotion_core.types.conditions import Conditions, Force, Ground
from physmotion_core.types.settings import SimSettings
from physmotion_core.validate import cases as C
from physmotion_core.validate.stress import gaussian_box


def bar_point(cells, ppc_axis, cfl, transfer, fixed_dt=0.0):
    t0 = time.perf_counter()
    measured, expected, s = C.bar_period(cells, ppc_axis, cfl, transfer, periods=1.5, fixed_dt=fixed_dt)
    sec = time.perf_counter() - t0
    return dict(scene="bar", cells=cells, ppc=ppc_axis**3, cfl=cfl, transfer=transfer, fixed_dt=fixed_dt,
                seconds=sec, error=abs(measured / expected - 1), substeps=s.substeps, particles=s.n)


def _friction(cells, cfl):
    from physmotion_core.sim.mpm import MPMSolver
    from physmotion_core.validate.harness import box_domain, lattice, momentum, run_sampled

    dx = 0.1 / cells
    x, vol = lattice((0.0, 0.0, -0.05), (0.1, 0.05, 0.05), dx / 2)
    ground = Ground(0.0, "friction", 0.3)
    d = 1.0 / (2 * 0.3 * C.G)
    dom = box_domain((-0.1, 0.0, -0.15), (d + 0.4, 0.3, 0.15), dx, ground=ground)
    s = MPMSolver(x, vol, np.zeros(len(x), np.int64), [C._elastic(2e5)], dom, ground=ground, cfl=cfl,
                  v0=np.tile([1.0, 0.0, 0.0], (len(x), 1)))
    x0 = momentum(s)[2][0]
    (com,) = run_sampled(s, [1.5 / (0.3 * C.G)], lambda s: momentum(s)[2], max_dt=C.FRAME_DT / C.MIN_SUBSTEPS)
    return (com[0] - x0) / d - 1


def pareto(points):
    front = []
    for p in sorted(points, key=lambda p: (p["seconds"], p["error"])):
        if not front or p["error"] < front[-1]["error"]:
            front.append(p)
    return front


def push_scene(fixed_dt=0.0, cfl=0.4, grid_res=16):
    g = gaussian_box((-0.05, 0.0125, -0.05), (0.05, 0.1125, 0.05), (10, 10, 10))
    conds = Conditions([Ground(0.0, "friction", 0.5), Force((20.0, 0.0, 0.0), t_end=0.1)])
    settings = SimSettings(frames=13, fps=24, grid_res=grid_res, cfl=cfl, fixed_dt=fixed_dt, device="cpu",
                           rest_speed=0.0, max_substeps_per_frame=1_000_000)
    t0 = time.perf_counter()
    res = simulate(g, material_preset("jelly"), conds, settings, record_all=True)
    return res, time.perf_counter() - t0


def plot(points, front, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    colours = {1: "tab:blue", 8: "tab:orange", 27: "tab:green"}
    for p in points:
        ax.scatter(p["seconds"], max(p["error"], 1e-6), c=colours.get(p["ppc"], "k"),
                   marker="o" if p["transfer"] == "apic" else "x", s=18 + 4 * p["cells"] ** 0.5, alpha=0.8)
    ax.plot([p["seconds"] for p in front], [max(p["error"], 1e-6) for p in front], "k--", lw=1, label="Pareto front")
    for ppc, c in colours.items():
        ax.scatter([], [], c=c, label=f"{ppc} particles/cell")
    ax.scatter([], [], c="gray", marker="x", label="PIC transfer (o = APIC)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("run time (s, CPU)")
    ax.set_ylabel("relative period error")
    ax.set_title("Elastic bar: run time against error (marker size ~ grid cells)")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def presets_section() -> None:
    """The quality presets' cost and error on the bar (the object's largest extent = the bar)."""
    from physmotion_core.types.settings import AUTO_GRID_RES, QUALITY

    lines = [f"Measured {datetime.date.today()} on {machine_description()}.", "",
             "`quality` scales the automatic grid (grid_res = 0: "
             f"{AUTO_GRID_RES['cpu']} cells across the object on CPU, {AUTO_GRID_RES['cuda']} on CUDA) and sets "
             "particles per cell. Each preset on the elastic bar, CPU grid, CFL 0.4, APIC:", "",
             "| preset | cells across | particles/cell | substeps | run time (s) | period error |",
             "|---|---:|---:|---:|---:|---:|"]
    pts = []
    for name, (scale, ppc) in QUALITY.items():
        cells = max(4, int(round(AUTO_GRID_RES["cpu"] * scale)))
        p = bar_point(cells, round(ppc ** (1 / 3)), 0.4, "apic")
        pts.append(p)
        lines.append(f"| {name} | {cells} | {ppc} | {p['substeps']} | {p['seconds']:.2f} | {p['error']:.2e} |")
    err = [pts[i]["error"] / pts[i + 1]["error"] for i in range(len(pts) - 1)]
    cost = [pts[i + 1]["seconds"] / pts[i]["seconds"] for i in range(len(pts) - 1)]
    lines += ["", "Why these: each preset is 1.5× the previous resolution; here that bought "
              f"{min(err):.1f}–{max(err):.1f}× less error for {min(cost):.1f}–{max(cost):.1f}× the time (a full 3-D "
              "object's cost grows as cells⁴, particles × substeps, so expect ~5× per step there). The bar cannot judge particles per cell (a small-strain wave is as accurate "
              "with 1 particle per cell, see the table above), but large deformation can: with 1 per cell, "
              "stretched material opens gaps between particles (numerical fracture), so every preset keeps 8. "
              "CFL 0.4 is the default: 0.6 is as accurate on the bar and 1.5× cheaper, but the stress matrix "
              "found 0.9 unstable for rubber (docs/stability.md), and 0.4 keeps a margin for impacts."]
    update_section("accuracy.md", "presets", "## Quality presets\n\n" + "\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--presets-only", action="store_true", help="only re-measure the quality presets' table")
    args = ap.parse_args()
    presets_section()
    if args.presets_only:
        return
    cells = (10, 20, 40) if args.quick else (10, 20, 40, 80)
    points = []
    for c, k, cfl, tr in itertools.product(cells, (1, 2, 3), (0.2, 0.4, 0.6), ("apic", "pic")):
        if c == 80 and k == 3 and cfl == 0.2:
            continue  # ~4 min for a point the front does not need
        p = bar_point(c, k, cfl, tr)
        points.append(p)
        print(p, flush=True)
    front = pareto([p for p in points if np.isfinite(p["error"])])
    plot(points, front, DOCS / "accuracy_pareto.png")

    fr = []
    for c, cfl in itertools.product((4, 8, 16), (0.2, 0.4, 0.6)):
        t0 = time.perf_counter()
        err = abs(_friction(c, cfl))
        fr.append((c, cfl, time.perf_counter() - t0, err))
        print("friction", fr[-1], flush=True)

    # PhysGaussian's fixed 1e-4 s step against ours on the same grids (their 50-200³ over a 2 m box
    # is dx 0.04-0.01 m: 25-100 cells along the 1 m bar).
    pg = []
    for c in (25, 50, 100):
        a = bar_point(c, 2, 0.4, "apic")
        f = bar_point(c, 2, 0.4, "apic", fixed_dt=1e-4)
        pg.append((c, a, f))
        print("fixed", c, a, f, flush=True)
    ref, _ = push_scene(cfl=0.1)
    push = []
    for label, kw in (("adaptive CFL 0.4 (ours)", {}), ("fixed 1e-4 s (PhysGaussian)", {"fixed_dt": 1e-4})):
        res, sec = push_scene(**kw)
        diff = np.sqrt(((res.x[-1] - ref.x[-1]) ** 2).sum(-1).mean()).item() / 0.1
        push.append((label, res.stats["substeps"], sec, diff))
        print(push[-1], flush=True)

    from physmotion_core.sim.mpm import cpu_threads

    lines = [f"Measured {datetime.date.today()} on {machine_description()} (Warp CPU, {cpu_threads()} simulator "
             "thread(s)).", "",
             "### Elastic bar: the sweep", "",
             f"{len(points)} settings: cells along the bar {cells}, 1 / 8 / 27 particles per cell, CFL 0.2 / 0.4 / "
             "0.6, APIC and PIC transfer. Error = |period / (2L/c) − 1|. Plot: `accuracy_pareto.png`.", "",
             "![run time against error](accuracy_pareto.png)", "",
             "**Pareto front** (no setting is both faster and more accurate):", "",
             "| cells | particles/cell | CFL | transfer | substeps | run time (s) | period error |",
             "|---:|---:|---:|---|---:|---:|---:|"]
    lines += [f"| {p['cells']} | {p['ppc']} | {p['cfl']} | {p['transfer']} | {p['substeps']} | {p['seconds']:.2f} | "
              f"{p['error']:.2e} |" for p in front]
    by = {}
    for p in points:
        by.setdefault((p["cells"], p["ppc"], p["transfer"]), []).append(p)
    lines += ["", "Effect of each knob (median over the others, APIC unless stated):", "",
              "| knob | setting | median error | median time (s) |", "|---|---|---:|---:|"]
    for knob, vals in (("cells", cells), ("ppc", (1, 8, 27)), ("cfl", (0.2, 0.4, 0.6)), ("transfer", ("apic", "pic"))):
        for v in vals:
            sel = [p for p in points if p[knob] == v and (knob == "transfer" or p["transfer"] == "apic")]
            if sel:
                lines.append(f"| {knob} | {v} | {np.median([p['error'] for p in sel]):.2e} | "
                             f"{np.median([p['seconds'] for p in sel]):.2f} |")
    lines += ["", "### Friction stopping distance: grid and CFL", "",
              "| cells along the block | CFL | run time (s) | distance error |", "|---:|---:|---:|---:|"]
    lines += [f"| {c} | {cfl} | {sec:.2f} | {err:.2%} |" for c, cfl, sec, err in fr]
    lines += ["", "### Against PhysGaussian's fixed step (substep 1e-4 s)", "",
              "Same scene, same grid, same particles; only the step rule differs.", "",
              "| scene | grid | step rule | substeps | run time (s) | error |", "|---|---|---|---:|---:|---:|"]
    for c, a, f in pg:
        lines.append(f"| bar | {c} cells | adaptive CFL 0.4 | {a['substeps']} | {a['seconds']:.2f} | {a['error']:.2e} |")
        lines.append(f"| bar | {c} cells | fixed 1e-4 s | {f['substeps']} | {f['seconds']:.2f} | {f['error']:.2e} |")
    for label, steps, sec, diff in push:
        lines.append(f"| pushed jelly cube (13 frames) | 16 cells | {label} | {steps} | {sec:.2f} | "
                     f"{diff:.2e} (RMS vs CFL 0.1, / size) |")
    speed = [f["seconds"] / a["seconds"] for _, a, f in pg]
    (_, steps_a, sec_a, diff_a), (_, steps_f, sec_f, diff_f) = push
    lines += ["", f"On the bar the adaptive step is {min(speed):.1f}–{max(speed):.1f}× faster at comparable error "
              "(both sit on the grid's error and a ~1e-3 floor of the period measurement). On the pushed jelly "
              f"cube (large deformation, contact, friction) neither rule matches a CFL 0.1 reference run closely: "
              f"the adaptive step (CFL 0.4, {steps_a} substeps) is off by {diff_a:.1%} of the cube's size and the "
              f"fixed 1e-4 s step ({steps_f} substeps, {sec_f / sec_a:.1f}× the time) by {diff_f:.1%}: "
              "even the fixed step, whose dt (1e-4 s) is close to the reference's (~9e-5 s), differs by that much, so "
              "this scene (a soft cube shoved into sliding and tipping on friction ground) is sensitive to small "
              "perturbations and cannot rank the step rules; the bar can. "
              "On stiffer materials the fixed "
              "step is unstable instead (it sits above the CFL limit once √(E/ρ)·1e-4/dx > ~0.4: PhysGaussian's "
              "crash when users raise E), which our step rule adapts to or refuses before the run."]
    update_section("accuracy.md", "runtime-vs-error", "## Run time against error\n\n" + "\n".join(lines))
    print("wrote docs/accuracy.md")


if __name__ == "__main__":
    main()
