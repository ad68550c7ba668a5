"""Does a push tip the object over? The forecast before the wait against the simulation (issue 33, item 5).

    python -m benchmarks.bench_forecast              # writes the "forecast-tipping" section of docs/accuracy.md
    python -m benchmarks.bench_forecast --no-write --quality draft --cases disc

Three objects as the pipeline lifts them from a photo (the silhouette lift, standing on a μ = 0.5 ground): the
example cup (``photos/coffee.png`` with the demo's box), a disc (a round object: a flower, a ball, a fruit) and a
tall bar, both drawn on a plain photo. Each is jelly (E = 20 kPa), a stiffer jelly (E = 100 kPa) and rigid, and is
pushed sideways, on the whole body for 0.25 s, with forces set from the forecast's own thresholds (below and above
the soft body's tipping force, and above the rigid one's). For each run: what the forecast said before
(``feedback.forecast``: "can tip", "may tip" or "rocks"; and what the rigid-body estimate alone, the forecast before
2026-12-06, said) and what the simulation did: the body's tilt about the axis across the push (the best-fit
rotation of its particles, Kabsch: how far it turns its top from the vertical), its largest and its last. It
counts as tipped when its tilt passed 60° (``TIPPED_DEG``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CLIP_FRAMES, FPS, PUSH_S = 48, 24.0, 0.25
#: A run counts as tipped when the body turned this far from upright: over its edge (on the runs of 2026-12-06 the
#: largest tilts were 43° or less, or 90° or more: nothing in between). A rounded body can rest a little tilted
#: past its edge's angle, so that angle is no test.
TIPPED_DEG = 60.0


def synthetic(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """A plain grey wall over a table, with a blue object (a disc, a tall bar or a wide box), and its mask
    (tests/test_feedback_lean.py draws on it too)."""
    h, w = 427, 640
    rng = np.random.default_rng(0)
    im = np.full((h, w, 3), 200.0)
    im[300:] = (120, 140, 160)
    im += rng.normal(0, 4, im.shape)
    yy, xx = np.mgrid[:h, :w]
    if kind == "disc":
        mask = (xx - 320) ** 2 + (yy - 230) ** 2 <= 130 ** 2
    elif kind == "bar":
        mask = (xx >= 270) & (xx < 370) & (yy >= 40) & (yy < 400)
    elif kind == "box":
        mask = (xx >= 120) & (xx < 520) & (yy >= 200) & (yy < 400)
    elif kind == "plain":
        mask = np.zeros((h, w), bool)
    else:
        raise ValueError(kind)
    im[mask] = (40, 90, 170)
    return np.clip(im, 0, 255).astype(np.uint8), mask.astype(np.float32)


def case_input(name: str) -> dict:
    if name == "cup":
        return dict(image=str(ROOT / "photos" / "coffee.png"), box=(55, 6, 498, 395))
    import torch

    im, mask = synthetic(name)
    return dict(image=im, mask=torch.from_numpy(mask))


def tilts(x: np.ndarray) -> np.ndarray:
    """(T,) how far the body leans from upright in each frame, in degrees: the angle between the vertical and
    where the best-fit rotation (Kabsch) from frame 0 takes it (0..180, whichever way it turns)."""
    a = x[0] - x[0].mean(0)
    out = []
    for xt in x:
        u, _, vt = np.linalg.svd(a.T @ (xt - xt.mean(0)))
        d = np.sign(np.linalg.det(vt.T @ u.T))
        r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
        out.append(math.degrees(math.acos(max(-1.0, min(1.0, float(r[1, 1]))))))
    return np.array(out)


def verdict(lines: list[str]) -> str:
    """What the forecast's words say about tipping: "falls" (it cannot stand), "rolls" (a round rigid body),
    "tips", "may tip", "slides" (rather than tips), "rocks" or "stays"."""
    text = " ".join(lines)
    if "cannot hold up" in text:
        return "falls"
    if "it is round: it rolls" in text:
        return "rolls"
    if "can tip over" in text:
        return "tips"
    if "may tip over" in text:  # a soft body's lean, or a toss-up while sliding
        return "may tip"
    if "slides rather than tips" in text:
        return "slides"
    return "rocks" if "rocks" in text else "stays"


def prepared(name: str, material, quality: str):
    from physmotion_core.pipeline import prepare
    from physmotion_core.types import SimSettings

    return prepare(**case_input(name), material=material, report=lambda s: None, _weigh=False,
                   settings=SimSettings(frames=CLIP_FRAMES, fps=FPS, quality=quality))


def run_case(name: str, mat_name: str, E, forces_of, quality: str) -> list[dict]:
    from physmotion_core.feedback import body_facts, forecast, tipping
    from physmotion_core.sim.mpm import resolve_device
    from physmotion_core.sim.simulate import simulate
    from physmotion_core.types import Conditions, Force, Material

    material = Material.preset(mat_name, **({"E": E} if E else {}))
    label = mat_name + (f" (E = {E / 1000:.0f} kPa)" if E else "")
    prep = prepared(name, material, quality)
    facts = body_facts(prep.gaussians, material, prep.settings, prep.conditions.ground(), resolve_device("cpu"))
    tip = tipping(facts, np.array([1.0, 0.0]), np.ones(len(facts.x), bool), 9.81, PUSH_S, material)
    tip_angle = math.degrees(math.atan2(tip.b, tip.h))
    old_need = band_need(facts)
    rows = []
    for F in forces_of(tip.soft_need, tip.need):
        conds = Conditions([Force((F, 0.0, 0.0), t_start=0.0, t_end=PUSH_S)] + list(prep.conditions))

        def said(mat) -> str:
            return verdict(forecast(conds, facts, mat, clip_s=(CLIP_FRAMES - 1) / FPS, camera=prep.camera))

        t = time.perf_counter()
        sim = simulate(prep.gaussians, material, conds, prep.settings, camera=prep.camera)
        wall = time.perf_counter() - t
        tl = tilts(sim.x.numpy().astype(np.float64))
        tipped = bool(tl.max() > TIPPED_DEG)
        rows.append(dict(case=name, material=label, F=round(F, 3), mass=round(facts.total_mass, 3),
                         soft_need=round(tip.soft_need, 3), rigid_need=round(tip.need, 3),
                         tip_angle=round(tip_angle, 1), tilt_max=round(float(tl.max()), 1),
                         tilt_end=round(float(tl[-1]), 1), tipped=bool(tipped), forecast=said(material),
                         rigid_forecast=before(F, old_need), old_need=round(old_need, 3), sim_s=round(wall, 1), particles=len(facts.x)))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def band_need(facts, g: float = 9.81) -> float:
    """The forecast's tipping force until 2026-12-06, for a push along +x on the whole body: its base the particles
    within 5 % of its height of the lowest, b to that base's edge from the centre of mass (no lean)."""
    x = facts.x
    base = x[x[:, 1] <= x[:, 1].min() + 0.05 * np.ptp(x[:, 1])]
    b = max(0.0, float(base[:, 0].max() - facts.com[0]))
    return facts.total_mass * g * b / max(float(facts.com[1] - x[:, 1].min()), 1e-9)


def before(F: float, need: float) -> str:
    """The forecast's words before 2026-12-06: the rigid body's F·h > m·g·b alone, "rocks" from 0.3 of it."""
    return "tips" if F > need else ("rocks" if F > 0.3 * need else "stays")


def agree(forecast: str, tipped: bool) -> bool:
    # a body that rolls turns over and over: the tilt this table counts passes TIPPED_DEG
    return (forecast in ("falls", "tips", "may tip", "rolls")) == tipped


def table(rows: list[dict], quality: str, machine: str, minutes: float) -> str:
    rows = [dict(r, tipped=bool(r["tilt_max"] > TIPPED_DEG), rigid_forecast=before(r["F"], r["old_need"]))
            for r in rows]
    md = [f"Measured by `python -m benchmarks.bench_forecast` on {machine}, quality {quality}, "
          f"{CLIP_FRAMES} frames at {FPS:g} fps, a push of F on the whole body for {PUSH_S} s on a μ = 0.5 ground "
          f"({minutes:.1f} min in all). Forecast: what `forecast` says before the run (\"tips\": F·h > m·g·b; "
          "\"may tip\": a soft body's lean takes it past its edge; \"slides\" rather than tips; \"rocks\"; \"falls\": it cannot "
          "stand under its own weight); before: the rigid body's F·h > m·g·b "
          "alone, the forecast until 2026-12-06 (no lean, no sliding, no buckling). Simulated tilt: degrees from upright; tipped = "
          f"a tilt past {TIPPED_DEG:.0f}° (the runs' largest tilts were 43° or less, or 90° or more).", "",
          "| object | material | F (N) | tips from (soft / rigid, N) | forecast | before (tips from, N) | tilt max / last (°) "
          "| tipping angle (°) | tipped | particles, run (s) |",
          "| --- | --- | ---: | --- | --- | --- | --- | ---: | --- | --- |"]
    for r in rows:
        ok = "" if agree(r["forecast"], r["tipped"]) else " ✗"
        ok_old = "" if agree(r["rigid_forecast"], r["tipped"]) else " ✗"
        md.append(f"| {r['case']} | {r['material']} | {r['F']:.3g} | {r['soft_need']:.3g} / {r['rigid_need']:.3g} | "
                  f"{r['forecast']}{ok} | {r['rigid_forecast']}{ok_old} ({r['old_need']:.3g}) | {r['tilt_max']:.0f} / {r['tilt_end']:.0f} | "
                  f"{r['tip_angle']:.0f} | {'yes' if r['tipped'] else 'no'} | {r['particles']:,}, {r['sim_s']:.0f} |")
    n = len(rows)
    new = sum(agree(r["forecast"], r["tipped"]) for r in rows)
    old = sum(agree(r["rigid_forecast"], r["tipped"]) for r in rows)
    md += ["", f"Tip or not, as the simulation did it: the forecast {new} of {n} runs, before {old} of {n} "
               "(✗: the words disagree with the run).", "", NOTES]
    return "\n".join(md) + "\n"


NOTES = """How the forecast decides (`feedback.tipping`, `lean`, `balance`, `stand_line`):

- **A rigid body** tips when F·h > m·g·b: h the height the push acts at, b from the centre of mass to the edge of
  what it stands on, towards the push: its lowest layer of particles, whose footprint reaches half a lattice
  spacing past their centres. (Until 2026-12-06 the base was every particle within 5 % of the height of the
  lowest: for a flat base the same, but a rounded bottom then counted a base half as wide again as the layer it
  stands on, and the rigid disc, forecast to need 55 N, rolled over at 42 N; with the lowest layer it needs 34 N,
  and it rocks 3° at 24 N and goes over at 42 N. Masses here are the fill's since 2026-12-06, ninth session:
  docs/accuracy.md, "Mass of a filled object".)
- **Sliding**, the ground holds the base with μ·m·g at most, so a body pushed at its centre of mass turns with
  μ·m·g·h_c only: one wider than μ times its height slides rather than tips however hard it is pushed (the rigid
  cup at 135 N slid upright; the forecast before said it would tip). Within 20 % of m·g·b it says it may.
- **A soft body leans** into the push before it tips: its centre of mass moves c·F towards the edge, c from
  Timoshenko's beam through its slices (bending and shear, each slice's own area and second moment), with its own
  weight's sway (P-Δ), and a push switched on at once swings it up to twice as far (a rectangular pulse on an
  undamped oscillator, 2·sin(π·t/T), T = 2π·√(m·c)). The push's moment reaches the base through the same spring
  and swings alike (since 2026-12-07, fourteenth session: its heel lifts from about half the static force), so it
  tips from m·g·b/(max(1, D)·h + m·g·D·c): the jelly cup from 41 N (65 N with the lean's swing alone) instead of
  108 N, the jelly disc from 11 N (13 N) instead of 40 N, the 100 kPa bar from 1.2 N (1.7 N) instead of 4.0 N.
- **Too soft to stand**: when the body's weight reaches what buckles it (the largest eigenvalue of the weight's
  sway through the same beam; Greenhill's (L/L_c)³ for a uniform column), it falls with no push at all, and the
  forecast says so and what stiffness or height lets it stand: the 0.3 m jelly bar (20 kPa) falls with no push,
  at 100 kPa it stands.
- **Not balanced**: the lift stands an object on its lowest point; when its centre of mass lies beyond that base
  (the convex hull of its particles within 5 % of its height of the lowest), it tips over with no push, and the
  forecast says so before any push estimate (a pagoda whose mask ended in a spike of trees below it: its centre of
  mass 4 cm past a 6 cm foot; checked through the simulation in `test_a_drawn_table_on_a_leg_at_its_end_tips_over...`).

The misses (2026-12-07, fourteenth session: 20 of 23; 19 before the moment's swing, 18 in the thirteenth session)
are all "rocks" where the run tipped: the jelly cup at 24.5 N (20 kPa) and 30.7 N (100 kPa) and the 100 kPa disc at
10.4 N, each pushed at 0.6 of the forecast's force, 0.23-0.28 of the rigid one. The table's forces follow the forecast
(0.6 and 1.25 of it), so the moment's swing moved them too: with the lean's swing alone the misses were the same
three at 0.6 of 65 / 97 / 30 N and the 100 kPa bar at 1.0 N, which at 0.6 of the lower force (0.73 N) now stays up
(10°), as does the 20 kPa disc at 6.6 N (34°). So the soft cup and disc tip from lower still than this forecast says,
and the bar does not. Since the contact layer carries the body's spin (it dropped it before, docs/accuracy.md,
"Rocking against a reference"), the one checked at three resolutions, the 100 kPa cup at 0.55 of the rigid force,
tipped at draft, standard and high alike, where the old layer rocked at draft and tipped from standard on; so these
misses look like the forecast's, not the run's. The rigid disc, which the lift now reads as a ball, rolls at both
forces, and since the fourteenth session the push forecast says so ("it is round: it rolls", `rolls_along`, as a
throw's did; the tilt this table counts is the roll's turning, so "rolls" agrees with a tilt past 60°). Also tried (2026-12-06)
and not taken: walking the outline over its edge tilt by tilt (the part of its hull within a lattice spacing of
the ground) and a rigid rocking model (Housner's: the body turning about its contact point under the push and its
weight, integrated in time); both kept the disc's base wider than its lowest layer.
"""


CASES = {  # object -> materials (name, E override) and the forces, from (soft, rigid) tipping forces
    "cup": [("jelly", None), ("jelly", 1e5), ("rigid", None)],
    "disc": [("jelly", None), ("jelly", 1e5), ("rigid", None)],
    "bar": [("jelly", None), ("jelly", 1e5), ("rigid", None)],
}


def forces(soft: float, rigid: float) -> list[float]:
    if soft <= 0:  # it cannot stand: no push, and a push the rigid body would tip at
        return [0.0, 1.25 * rigid]
    if soft < 0.9 * rigid:
        return [0.6 * soft, 1.25 * soft, 1.25 * rigid]
    return [0.7 * rigid, 1.25 * rigid]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quality", default="standard", choices=("draft", "standard", "high"))
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated: " + ", ".join(CASES))
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    args = ap.parse_args(argv)
    from physmotion_core.report import machine_description, update_section

    t = time.perf_counter()
    rows = []
    for name in args.cases.split(","):
        for mat, E in CASES[name]:
            rows += run_case(name, mat, E, forces, args.quality)
    md = table(rows, args.quality, machine_description(), (time.perf_counter() - t) / 60)
    print(md)
    if not args.no_write:
        print("written to", update_section("accuracy.md", "forecast-tipping", md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
