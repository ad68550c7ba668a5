"""Soak: many videos in one process, watching resident memory and open files.

A ComfyUI server runs for days and calls the same nodes thousands of times; a leak of a few MB or
one file handle per run ends in a crash nobody can reproduce. This generates ``--runs`` coarse
videos of the bundled photo in one process (library path: segment → lift → simulate → render →
blend → mp4), alternating two materials so both the elastic and a plastic code path run, and
records after every run the resident set size (VmRSS) and the number of open file descriptors.

The first runs warm caches (Warp kernels, the rasterizer's scratch buffers, the allocator), so the
growth is judged on the second half: a least-squares slope of RSS against the run index, in
MiB per run, and the change in open descriptors. Writes the "soak" section of docs/reliability.md.

    .venv/bin/python -m benchmarks.bench_soak [--runs 40] [--quick]
"""

from __future__ import annotations

import argparse
import datetime
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from physmotion_core.report import machine_description, update_section

ROOT = Path(__file__).resolve().parent.parent


def rss_mib() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def soak(runs: int, frames: int, grid_res: int) -> list[dict]:
    from physmotion_core.pipeline import generate
    from physmotion_core.types.conditions import Conditions, Force, Region
    from physmotion_core.types.settings import SimSettings

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(runs):
            material = "jelly" if k % 2 == 0 else "plasticine"
            t0 = time.perf_counter()
            res = generate(ROOT / "photos" / "coffee.png", material=material,
                           conditions=Conditions([Force((20.0, 0, 0), Region.at_pixel(200, 150), 0.0, 0.2)]),
                           settings=SimSettings(frames=frames, grid_res=grid_res, device="cpu"),
                           output=Path(tmp) / f"run{k % 3}.mp4", max_gaussians=20_000)
            rows.append({"run": k, "material": material, "seconds": time.perf_counter() - t0,
                         "rss_mib": rss_mib(), "fds": open_fds(), "frames": int(res.frames.shape[0])})
            del res
            print(rows[-1], flush=True)
    return rows


def summarise(rows: list[dict]) -> dict:
    half = rows[len(rows) // 2:]
    x = np.array([r["run"] for r in half], float)
    y = np.array([r["rss_mib"] for r in half], float)
    slope = float(np.polyfit(x, y, 1)[0]) if len(half) > 1 else 0.0
    return {"runs": len(rows), "rss_first": rows[0]["rss_mib"], "rss_mid": half[0]["rss_mib"],
            "rss_last": rows[-1]["rss_mib"], "rss_max": max(r["rss_mib"] for r in rows), "slope": slope,
            "fds_first": rows[0]["fds"], "fds_mid": half[0]["fds"], "fds_last": rows[-1]["fds"],
            "seconds": sum(r["seconds"] for r in rows)}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--grid-res", type=int, default=12)
    ap.add_argument("--quick", action="store_true", help="8 runs (a smoke test of the benchmark itself)")
    args = ap.parse_args()
    runs = 8 if args.quick else args.runs
    rows = soak(runs, args.frames, args.grid_res)
    s = summarise(rows)
    verdict = ("no growth" if s["slope"] < 1.0 and s["fds_last"] <= s["fds_mid"]
               else "GROWTH: investigate")
    md = f"""## Soak: many videos in one process

`benchmarks/bench_soak.py` (its docstring says what it does). {s['runs']} videos of the bundled photo
({args.frames} frames each, grid_res {args.grid_res}, jelly and plasticine alternating, each written
to an mp4), one process. Machine: {machine_description()}. Measured {datetime.date.today().isoformat()}.

| | after run 1 | after run {s['runs'] // 2 + 1} | after run {s['runs']} | max |
|---|---:|---:|---:|---:|
| resident memory (MiB) | {s['rss_first']:.0f} | {s['rss_mid']:.0f} | {s['rss_last']:.0f} | {s['rss_max']:.0f} |
| open file descriptors | {s['fds_first']} | {s['fds_mid']} | {s['fds_last']} | |

Resident memory over the second half: {s['slope']:+.2f} MiB per run (least-squares slope); open
descriptors {s['fds_last'] - s['fds_mid']:+d}. Verdict: **{verdict}** (threshold: a slope below 1 MiB/run, i.e. less
than 1 GiB per thousand videos, and no new descriptors; single runs swing by tens of MiB as the
allocator keeps or returns pages, which the slope averages out). Total {s['seconds']:.0f} s.
"""
    update_section("reliability.md", "soak", md)
    print(md)
    return 0 if verdict == "no growth" else 1


if __name__ == "__main__":
    raise SystemExit(main())
