"""Old code against new code, interleaved in one process: the jelly drop of bench_sim_scale timed
with the solver of an earlier commit and with this checkout's, alternating round by round.

    git archive <commit> physmotion_core | tar -x -C /tmp/old && mv /tmp/old/physmotion_core /tmp/old/physmotion_old
    python -m benchmarks.bench_sim_ab --old /tmp/old --sizes 38 128

The old package is imported under the name ``physmotion_old`` (its imports are relative). Engines: the
old solver as it was, the old solver with denormals flushed (its kernels in this thread's FTZ mode:
one thread only), and the new solver, each on ``--threads``; plus the material update alone of each
(the same particles' update_material into scratch arrays). Prints the medians and the ratios new/old
of each round; nothing is written.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time

import numpy as np
import warp as wp

from benchmarks.bench_sim_scale import DT, E, NU, RHO, SIZES, material_only, scene, time_material
from physmotion_core.sim.fpmode import FlushedDenormals
from physmotion_core.sim.mpm import Domain, MPMSolver
from physmotion_core.types.material import Material


PRESET = None  # --material: a preset instead of the jelly


def make(pkg, x, vol, v0, C0, g, threads):
    mpm = importlib.import_module(pkg + ".sim.mpm")
    mat = importlib.import_module(pkg + ".types.material")
    jelly = mat.Material(name="jelly", model="fixed_corotated", E=E, nu=NU, density=RHO) if PRESET is None \
        else mat.material_preset(PRESET)
    dom = mpm.Domain(origin=np.zeros(3), dx=1.0 / g, dims=(g + 1,) * 3)
    return mpm.MPMSolver(x, np.full(len(x), vol), np.zeros(len(x), np.int64), [jelly], dom, device="cpu",
                         threads=threads, v0=v0, C0=C0)


class Flushed:
    def __init__(self, s):
        self.s, self.device, self.n = s, s.device, s.n
        self.f = FlushedDenormals("cpu")

    def substep(self, dt):
        with self.f:
            self.s.substep(dt)


def old_material_kernel(K):
    @wp.kernel
    def old_material_only(ps: K.Particles, materials: wp.array(dtype=K.MaterialParams), dt: float,
                          rot: wp.array(dtype=wp.quat), Fout: wp.array(dtype=wp.mat33),
                          tau: wp.array(dtype=wp.mat33), c2: wp.array(dtype=float), offset: int):
        p = wp.tid() + offset
        Cp = ps.C[p]
        Ftrial = ps.F[p] + dt * (Cp * ps.F[p])
        c2[p] = K.update_material(materials[ps.mat_id[p]], Ftrial, Cp, ps.rot[p], ps.plastic[p], dt, p, rot,
                                  ps.plastic, Fout, tau)
    return old_material_only


def material_time(s, kernel, flushed) -> float:
    n = s.n
    rot = wp.clone(s.rot)
    Fout, tau, c2 = wp.empty(n, dtype=wp.mat33), wp.empty(n, dtype=wp.mat33), wp.empty(n, dtype=float)
    t0 = time.perf_counter()
    with flushed:
        for start, count in s._chunk_ranges:
            wp.launch(kernel, dim=count, inputs=[s.particles, s.material_table, DT, rot, Fout, tau, c2, start])
    wp.synchronize_device("cpu")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--old", required=True, help="folder holding the old package as physmotion_old")
    ap.add_argument("--sizes", type=int, nargs="+", default=[38, 128])
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--motion", default="tumble", choices=("tumble", "rest"))
    ap.add_argument("--material", default=None, help="a material preset instead of the jelly (E 2e5)")
    args = ap.parse_args()
    global PRESET
    PRESET = args.material
    sys.path.insert(0, args.old)
    oldK = importlib.import_module("physmotion_old.sim.kernels")
    old_mat = old_material_kernel(oldK)
    print("load average before:", os.getloadavg(), "motion", args.motion)
    for n_side in args.sizes:
        g = SIZES.get(n_side, 2 * n_side)
        x, vol, v0, C0 = scene(n_side, g, args.motion)
        old = make("physmotion_old", x, vol, v0, C0, g, args.threads)
        new = make("physmotion_core", x, vol, v0, C0, g, args.threads)
        engines = {"old": old, "new": new}
        if args.threads == 1:
            engines["old + FTZ"] = Flushed(make("physmotion_old", x, vol, v0, C0, g, 1))
        for e in engines.values():
            for _ in range(2):
                e.substep(DT)
        t = {k: [] for k in engines}
        mt = {"old": [], "old + FTZ": [], "new": []}
        for r in range(args.rounds):
            names = list(engines)
            names = names[r % len(names):] + names[:r % len(names)]
            for k in names:
                t0 = time.perf_counter()
                for _ in range(args.steps):
                    engines[k].substep(DT)
                wp.synchronize_device("cpu")
                t[k].append((time.perf_counter() - t0) / args.steps)
            mt["old"].append(material_time(old, old_mat, _Null()))
            mt["old + FTZ"].append(material_time(old, old_mat, FlushedDenormals("cpu")))
            mt["new"].append(material_time(new, material_only, new._flushed))
            print(f"  {len(x):,} round {r}: " + ", ".join(f"{k} {1e3 * v[-1]:.1f} ms" for k, v in t.items())
                  + " | material alone " + ", ".join(f"{k} {1e9 * v[-1] / len(x):.0f} ns/p" for k, v in mt.items()),
                  flush=True)
        for k in t:
            if k != "old":
                print(f"{len(x):,} particles: {k} / old substep = {np.median(np.asarray(t[k]) / np.asarray(t['old'])):.3f}")
        print(f"{len(x):,} particles: substep ms median " + ", ".join(f"{k} {1e3 * np.median(v):.1f}" for k, v in t.items()))
        print(f"{len(x):,} particles: material alone ns/p median " + ", ".join(
            f"{k} {1e9 * np.median(v) / len(x):.0f}" for k, v in mt.items()) +
            f"; new / (old + FTZ) = {np.median(np.asarray(mt['new']) / np.asarray(mt['old + FTZ'])):.3f}"
            f"; new / old = {np.median(np.asarray(mt['new']) / np.asarray(mt['old'])):.3f}")
        del engines, old, new
    print("load average after:", os.getloadavg())


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


if __name__ == "__main__":
    main()
