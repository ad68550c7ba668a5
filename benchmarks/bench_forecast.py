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
rotation of its particles, Kabsch: how far it turns its top from the vertical), its largest and its last. It counts as tipped when
the last tilt is past the rigid body's tipping angle atan(b/h) (it went over its edge and stayed) or the tilt ever
passed 90°.
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
    """What the forecast's words say about tipping: "falls" (it cannot stand), "tips", "may tip", "slides"
    (rather than tips), "rocks" or "stays"."""
    text = " ".join(lines)
    if "cannot hold up" in text:
        return "falls"
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
    rows = []
    for F in forces_of(tip.soft_need, tip.need):
        conds = Conditions([Force((F, 0.0, 0.0), t_start=0.0, t_end=PUSH_S)] + list(prep.conditions))

        def said(mat) -> str:
            return verdict(forecast(conds, facts, mat, clip_s=(CLIP_FRAMES - 1) / FPS, camera=prep.camera))

        t = time.perf_counter()
        sim = simulate(prep.gaussians, material, conds, prep.settings, camera=prep.camera)
        wall = time.perf_counter() - t
        tl = tilts(sim.x.numpy().astype(np.float64))
        tipped = tl[-1] > tip_angle or tl.max() > 90.0
        rows.append(dict(case=name, material=label, F=round(F, 3), mass=round(facts.total_mass, 3),
                         soft_need=round(tip.soft_need, 3), rigid_need=round(tip.need, 3),
                         tip_angle=round(tip_angle, 1), tilt_max=round(float(tl.max()), 1),
                         tilt_end=round(float(tl[-1]), 1), tipped=bool(tipped), forecast=said(material),
                         rigid_forecast=before(F, tip.need), sim_s=round(wall, 1), particles=len(facts.x)))
        print(json.dumps(rows[-1]), flush=True)
    return rows


def before(F: float, need: float) -> str:
    """The forecast's words before 2026-12-06: the rigid body's F·h > m·g·b alone, "rocks" from 0.3 of it."""
    return "tips" if F > need else ("rocks" if F > 0.3 * need else "stays")


def agree(forecast: str, tipped: bool) -> bool:
    return (forecast in ("falls", "tips", "may tip")) == tipped


def table(rows: list[dict], quality: str, machine: str, minutes: float) -> str:
    md = [f"Measured by `python -m benchmarks.bench_forecast` on {machine}, quality {quality}, "
          f"{CLIP_FRAMES} frames at {FPS:g} fps, a push of F on the whole body for {PUSH_S} s on a μ = 0.5 ground "
          f"({minutes:.1f} min in all). Forecast: what `forecast` says before the run (\"tips\": F·h > m·g·b; "
          "\"may tip\": a soft body's lean takes it past its edge; \"slides\" rather than tips; \"rocks\"; \"falls\": it cannot "
          "stand under its own weight); before: the rigid body's F·h > m·g·b "
          "alone, the forecast until 2026-12-06 (no lean, no sliding, no buckling). Simulated tilt: degrees from upright; tipped = "
          "its last tilt past the tipping angle atan(b/h), or any tilt past 90°.", "",
          "| object | material | F (N) | tips from (soft / rigid, N) | forecast | before | tilt max / last (°) "
          "| tipping angle (°) | tipped | particles, run (s) |",
          "| --- | --- | ---: | --- | --- | --- | --- | ---: | --- | --- |"]
    for r in rows:
        ok = "" if agree(r["forecast"], r["tipped"]) else " ✗"
        ok_old = "" if agree(r["rigid_forecast"], r["tipped"]) else " ✗"
        md.append(f"| {r['case']} | {r['material']} | {r['F']:.3g} | {r['soft_need']:.3g} / {r['rigid_need']:.3g} | "
                  f"{r['forecast']}{ok} | {r['rigid_forecast']}{ok_old} | {r['tilt_max']:.0f} / {r['tilt_end']:.0f} | "
                  f"{r['tip_angle']:.0f} | {'yes' if r['tipped'] else 'no'} | {r['particles']:,}, {r['sim_s']:.0f} |")
    n = len(rows)
    new = sum(agree(r["forecast"], r["tipped"]) for r in rows)
    old = sum(agree(r["rigid_forecast"], r["tipped"]) for r in rows)
    md += ["", f"Tip or not, as the simulation did it: the forecast {new} of {n} runs, before {old} of {n} "
               "(✗: the words disagree with the run).", "", NOTES]
    return "\n".join(md) + "\n"


NOTES = """How the forecast decides (`feedback.tipping`, `lean`, `stand_line`):

- **A rigid body** tips when F·h > m·g·b: h the height the push acts at, b from the centre of mass to the edge of
  its base (its particles within 5 % of its height of the lowest) it is pushed towards.
- **Sliding**, the ground holds the base with μ·m·g at most, so a body pushed at its centre of mass turns with
  μ·m·g·h_c only: one wider than μ times its height slides rather than tips however hard it is pushed (the rigid
  cup at 156 N slid 0.4 m upright; the forecast before said it would tip). Within 20 % of m·g·b it says it may.
- **A soft body leans** into the push before it tips: its centre of mass moves c·F towards the edge, c from
  Timoshenko's beam through its slices (bending and shear, each slice's own area and second moment), with its own
  weight's sway (P-Δ), and a push switched on at once swings it up to twice as far (a rectangular pulse on an
  undamped oscillator, 2·sin(π·t/T), T = 2π·√(m·c)). It tips from m·g·b/(h + m·g·D·c): the jelly cup from 75 N
  instead of 125 N, the jelly disc from 23 N instead of 60 N.
- **Too soft to stand**: when the body's weight reaches what buckles it (the largest eigenvalue of the weight's
  sway through the same beam; Greenhill's (L/L_c)³ for a uniform column), it falls with no push at all, and the
  forecast says so and what stiffness or height lets it stand: the 0.3 m jelly bar (20 kPa) falls with no push,
  at 100 kPa it stands.

- **Not balanced**: the lift stands an object on its lowest point; when its centre of mass lies beyond that base
  (the convex hull of its lowest particles), it tips over with no push (`balance`), and the forecast says so
  before any push estimate (a pagoda whose mask ended in a spike of trees below it: its centre of mass 4 cm past
  a 6 cm foot; checked through the simulation in `test_a_drawn_table_on_a_leg_at_its_end_tips_over...`).

The misses are the disc, a rounded bottom: it goes over with less than the forecast's force (the rigid disc at
70 % of its tipping force rolled onto its face at standard quality, while at draft quality, whose coarser grid
flattens the contact, it rocked back). Tried and not taken (2026-12-06): the base as the part of the outline
within one lattice spacing of the ground, walked over the edge tilt by tilt (b 0.058 m instead of 0.072 m for
the disc: 48 N, still over 42 N), and a rigid rocking model (Housner's: the body turning about its contact
point under the push and its weight, integrated in time), which has the disc at 42 N rock 1-5° and at 75 N not
go over; the simulation's rounded body rolls more readily than either, which is not explained yet. The cup's jelly at 60 %
of its soft tipping force leaned 45° by the clip's end, just under its tipping angle: a near miss the other way.
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
