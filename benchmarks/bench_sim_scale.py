"""Large scenes on the CPU: the project's MPM solver against a minimal MLS-MPM Warp kernel, at 55 k
and 2.1 M particles, in interleaved rounds, with a per-kernel split.

    python -m benchmarks.bench_sim_scale                 # 55 k and 2.1 M particles; writes the
                                                         # "sim-scale" section of docs/benchmarks.md
    python -m benchmarks.bench_sim_scale --sizes 38      # only the 55 k scene (no write)
    python -m benchmarks.bench_sim_scale --device cuda:0 # the same on a GPU (scripts/gpu_checks.sh)

Scene (the jelly drop of the issue): a cube of n³ particles on a lattice, 2 per cell per axis, in a
unit box of g³ cells (n = 38, g = 64: 54,872 particles; n = 128, g = 128: 2,097,152 particles),
falling under gravity, fixed-corotated, E = 2e5 Pa, ν = 0.3, ρ = 1000 kg/m³, dt = 1e-4 s fixed. Two
motions: "tumble" (thrown down at 1 m/s, spinning at 8.8 rad/s and squeezed at 2/s, so every F turns
and strains from the first substep) and "rest" (released at rest: the velocity field is uniform to
round-off, C ~ 1e-15 1/s). Both engines start from the same lattice, velocities and dt.

The minimal kernel (``MinimalMPM`` below) is what a short MLS-MPM program in Warp does: one thread
per particle with atomics (plain adds on the CPU, where Warp runs a kernel on one thread), the whole
grid cleared and updated every substep, the fixed-corotated stress from an SVD of F, APIC transfers,
walls that stop the velocity into the box's sides. It has no step control, no checks, no spans, no
anchors or plasticity. The project's solver runs its full substep (MPMSolver.substep: CFL bookkeeping,
NaN and domain checks, the compensated F update, warm-started rotations) on 1 and on 2 threads.

Timing: each round runs ``--steps`` substeps of every engine one after the other (the order rotates
per round); the ratios are medians over rounds of project / minimal in the same round, so a load
change between rounds cancels. The per-kernel split synchronises every launch (kernel_times), and
the material update alone is a kernel that runs update_material over the solver's particles into
scratch arrays (the same work g2p does after its gather).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import os
import time

import numpy as np
import warp as wp

from physmotion_core.report import machine_description, update_section
from physmotion_core.sim import kernels as K
from physmotion_core.sim.fpmode import FlushedDenormals
from physmotion_core.sim.mpm import Domain, MPMSolver
from physmotion_core.types.material import Material

wp.config.quiet = True

E, NU, RHO, DT = 2.0e5, 0.3, 1000.0, 1.0e-4
SIZES = {38: 64, 128: 128}  # particles per axis -> grid cells across the unit box


# The tumbling jelly's initial motion: falling at 1 m/s, spinning at 8 rad/s about a tilted axis and
# squeezed along y (rates in 1/s), so every particle's F rotates and strains from the first substep (the
# material update's rotation tracking does real work). "rest": released at rest (only gravity).
SPIN = np.array([3.0, 8.0, 2.0])
SQUEEZE = np.diag([1.0, -2.0, 1.0])
MOTIONS = ("tumble", "rest")


def scene(n_side: int, grid_cells: int, motion: str = "tumble"):
    """Lattice positions (2 per cell per axis, the cube's corner at 0.25 m), particle volume, and the
    initial velocities and affine velocities C (APIC) of ``motion``."""
    dx = 1.0 / grid_cells
    h = 0.5 * dx
    ax = 0.25 + h * (np.arange(n_side) + 0.5)
    x = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3).astype(np.float32)
    v0 = np.zeros_like(x)
    C0 = np.zeros((len(x), 3, 3), np.float32)
    if motion == "tumble":
        W = np.array([[0.0, -SPIN[2], SPIN[1]], [SPIN[2], 0.0, -SPIN[0]], [-SPIN[1], SPIN[0], 0.0]])
        grad = W + SQUEEZE
        r = x - x.mean(0)
        v0 = (r @ grad.T + np.array([0.0, -1.0, 0.0])).astype(np.float32)
        C0[:] = grad
    return x, h ** 3, v0, C0


# ----------------------------------------------------------------------------------------------
# The minimal MLS-MPM kernel (written here, for comparison only)
# ----------------------------------------------------------------------------------------------


@wp.kernel
def m_stress(F: wp.array(dtype=wp.mat33), mu: float, lam: float, tau: wp.array(dtype=wp.mat33)):
    p = wp.tid()
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(F[p], U, sig, V)
    R = U * wp.transpose(V)
    J = wp.determinant(F[p])
    tau[p] = 2.0 * mu * (F[p] - R) * wp.transpose(F[p]) + lam * J * (J - 1.0) * wp.identity(n=3, dtype=float)


@wp.kernel
def m_clear(gm: wp.array3d(dtype=float), gv: wp.array3d(dtype=wp.vec3)):
    i, j, k = wp.tid()
    gm[i, j, k] = 0.0
    gv[i, j, k] = wp.vec3(0.0)


@wp.func
def cell_of(x: wp.vec3, inv_dx: float):
    """The lower corner of a particle's 3x3x3 stencil and the particle's offset from it, in cells."""
    xp = x * inv_dx
    base = wp.vec3i(int(xp[0] - 0.5), int(xp[1] - 0.5), int(xp[2] - 0.5))
    return base, xp - wp.vec3(float(base[0]), float(base[1]), float(base[2]))


@wp.func
def quadratic_weights(fx: wp.vec3):
    """Quadratic B-spline weights of the stencil's three nodes along each axis."""
    w0 = 0.5 * wp.cw_mul(wp.vec3(1.5) - fx, wp.vec3(1.5) - fx)
    w1 = wp.vec3(0.75) - wp.cw_mul(fx - wp.vec3(1.0), fx - wp.vec3(1.0))
    w2 = 0.5 * wp.cw_mul(fx - wp.vec3(0.5), fx - wp.vec3(0.5))
    return w0, w1, w2


@wp.func
def stencil_weight(w0: wp.vec3, w1: wp.vec3, w2: wp.vec3, i: int, axis: int) -> float:
    if i == 0:
        return w0[axis]
    if i == 1:
        return w1[axis]
    return w2[axis]


@wp.kernel
def m_p2g(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
          tau: wp.array(dtype=wp.mat33), inv_dx: float, dt: float, vol: float, mass: float,
          gm: wp.array3d(dtype=float), gv: wp.array3d(dtype=wp.vec3)):
    p = wp.tid()
    base, fx = cell_of(x[p], inv_dx)
    w0, w1, w2 = quadratic_weights(fx)
    affine = (-dt * vol * 4.0 * inv_dx * inv_dx) * tau[p] + mass * C[p]
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = stencil_weight(w0, w1, w2, i, 0) * stencil_weight(w0, w1, w2, j, 1) * stencil_weight(w0, w1, w2, k, 2)
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) / inv_dx
                wp.atomic_add(gm, base[0] + i, base[1] + j, base[2] + k, w * mass)
                wp.atomic_add(gv, base[0] + i, base[1] + j, base[2] + k, w * (mass * v[p] + affine * dpos))


@wp.kernel
def m_grid(gm: wp.array3d(dtype=float), gv: wp.array3d(dtype=wp.vec3), dt: float, n: int):
    i, j, k = wp.tid()
    m = gm[i, j, k]
    if m > 0.0:
        v = gv[i, j, k] / m + dt * wp.vec3(0.0, -9.81, 0.0)
        if i < 3 and v[0] < 0.0:
            v = wp.vec3(0.0, v[1], v[2])
        if i > n - 3 and v[0] > 0.0:
            v = wp.vec3(0.0, v[1], v[2])
        if j < 3 and v[1] < 0.0:
            v = wp.vec3(v[0], 0.0, v[2])
        if j > n - 3 and v[1] > 0.0:
            v = wp.vec3(v[0], 0.0, v[2])
        if k < 3 and v[2] < 0.0:
            v = wp.vec3(v[0], v[1], 0.0)
        if k > n - 3 and v[2] > 0.0:
            v = wp.vec3(v[0], v[1], 0.0)
        gv[i, j, k] = v


@wp.kernel
def m_g2p(x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
          F: wp.array(dtype=wp.mat33), inv_dx: float, dt: float, gv: wp.array3d(dtype=wp.vec3)):
    p = wp.tid()
    base, fx = cell_of(x[p], inv_dx)
    w0, w1, w2 = quadratic_weights(fx)
    new_v = wp.vec3(0.0)
    new_C = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = stencil_weight(w0, w1, w2, i, 0) * stencil_weight(w0, w1, w2, j, 1) * stencil_weight(w0, w1, w2, k, 2)
                g = gv[base[0] + i, base[1] + j, base[2] + k]
                new_v += w * g
                new_C += (4.0 * inv_dx * w) * wp.outer(g, wp.vec3(float(i), float(j), float(k)) - fx)
    v[p] = new_v
    C[p] = new_C
    x[p] = x[p] + dt * new_v
    F[p] = (wp.identity(n=3, dtype=float) + dt * new_C) * F[p]


class MinimalMPM:
    """A minimal MLS-MPM (fixed-corotated, APIC) over the whole g³ grid, for comparison."""

    def __init__(self, x: np.ndarray, vol: float, v0: np.ndarray, C0: np.ndarray, grid_cells: int, device: str,
                 flush_denormals: bool = False):
        n = len(x)
        self.flushed = FlushedDenormals(device) if flush_denormals else contextlib.nullcontext()
        self.device, self.n, self.g = device, n, grid_cells + 1
        mu, lam = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))
        self.mu, self.lam, self.vol, self.mass = mu, lam, vol, vol * RHO
        self.inv_dx = float(grid_cells)
        with wp.ScopedDevice(device):
            self.x = wp.array(x, dtype=wp.vec3)
            self.v = wp.array(v0, dtype=wp.vec3)
            self.C = wp.array(C0, dtype=wp.mat33)
            self.F = wp.array(np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)), dtype=wp.mat33)
            self.tau = wp.zeros(n, dtype=wp.mat33)
            self.gm = wp.zeros((self.g,) * 3, dtype=float)
            self.gv = wp.zeros((self.g,) * 3, dtype=wp.vec3)
        self.kernel_times = None

    def _run(self, kernel, dim, inputs):
        t0 = time.perf_counter() if self.kernel_times is not None else 0.0
        wp.launch(kernel, dim=dim, inputs=inputs, device=self.device)
        if self.kernel_times is not None:
            wp.synchronize_device(self.device)
            self.kernel_times[kernel.key] = self.kernel_times.get(kernel.key, 0.0) + time.perf_counter() - t0

    def substep(self, dt: float) -> None:
        with self.flushed:
            self._substep(dt)

    def _substep(self, dt: float) -> None:
        g3 = (self.g,) * 3
        self._run(m_stress, self.n, [self.F, self.mu, self.lam, self.tau])
        self._run(m_clear, g3, [self.gm, self.gv])
        self._run(m_p2g, self.n, [self.x, self.v, self.C, self.tau, self.inv_dx, dt, self.vol, self.mass,
                                  self.gm, self.gv])
        self._run(m_grid, g3, [self.gm, self.gv, dt, self.g])
        self._run(m_g2p, self.n, [self.x, self.v, self.C, self.F, self.inv_dx, dt, self.gv])


# ----------------------------------------------------------------------------------------------
# The project's solver and its material update alone
# ----------------------------------------------------------------------------------------------


@wp.kernel
def material_only(ps: K.Particles, materials: wp.array(dtype=K.MaterialParams), dt: float,
                  rot: wp.array(dtype=wp.quat), Fout: wp.array(dtype=wp.mat33), tau: wp.array(dtype=wp.mat33),
                  c2: wp.array(dtype=float), offset: int):
    """g2p's material update of particles offset .. offset + dim, into scratch arrays."""
    p = wp.tid() + offset
    Cp = ps.C[p]
    Ftrial = ps.F[p] + dt * (Cp * ps.F[p])
    c2[p] = K.update_material(materials[ps.mat_id[p]], Ftrial, Cp, ps.rot[p], ps.plastic[p], dt, p, rot,
                              ps.plastic, Fout, tau)


def project_solver(x: np.ndarray, vol: float, v0: np.ndarray, C0: np.ndarray, grid_cells: int, device: str,
                   threads: int) -> MPMSolver:
    jelly = Material(name="jelly", model="fixed_corotated", E=E, nu=NU, density=RHO)
    dx = 1.0 / grid_cells
    dom = Domain(origin=np.zeros(3), dx=dx, dims=(grid_cells + 1,) * 3)
    return MPMSolver(x, np.full(len(x), vol), np.zeros(len(x), np.int64), [jelly], dom, device=device,
                     threads=threads, v0=v0, C0=C0)


def time_material(s: MPMSolver, reps: int = 3) -> float:
    """Seconds per substep of update_material over all particles (the solver's chunks, its threads)."""
    n = s.n
    with wp.ScopedDevice(s.device):
        rot = wp.clone(s.rot)
        Fout = wp.empty(n, dtype=wp.mat33)
        tau = wp.empty(n, dtype=wp.mat33)
        c2 = wp.empty(n, dtype=float)
    cmds = [wp.launch(material_only, dim=count, inputs=[s.particles, s.material_table, DT, rot, Fout, tau, c2, start],
                      device=s.device, record_cmd=True) for start, count in s._chunk_ranges]
    best = []
    for _ in range(reps):
        t0 = time.perf_counter()
        with s._flushed:  # as in a substep (fpmode)
            s._run_step(material_only, cmds, True)
        wp.synchronize_device(s.device)
        best.append(time.perf_counter() - t0)
    return float(np.median(best))


# ----------------------------------------------------------------------------------------------
# Measurements
# ----------------------------------------------------------------------------------------------


def run_steps(engine, steps: int) -> float:
    dev = engine.device
    t0 = time.perf_counter()
    for _ in range(steps):
        engine.substep(DT)
    wp.synchronize_device(dev)
    return (time.perf_counter() - t0) / steps


def measure_size(n_side: int, device: str, rounds: int, steps: int, thread_counts: list, motion: str) -> dict:
    grid_cells = SIZES.get(n_side, 2 * n_side)
    x, vol, v0, C0 = scene(n_side, grid_cells, motion)
    engines = {"minimal": MinimalMPM(x, vol, v0, C0, grid_cells, device)}
    if device == "cpu":
        engines["minimal + FTZ"] = MinimalMPM(x, vol, v0, C0, grid_cells, device, flush_denormals=True)
    for t in thread_counts:
        engines[f"project {t}t"] = project_solver(x, vol, v0, C0, grid_cells, device, t)
    names = list(engines)
    for e in engines.values():  # compile, warm caches
        run_steps(e, 2)
    times = {k: [] for k in names}
    for r in range(rounds):
        order = names[r % len(names):] + names[:r % len(names)]
        for k in order:
            times[k].append(run_steps(engines[k], steps))
        print(f"  {len(x):,} particles round {r}: " + ", ".join(f"{k} {1e3 * times[k][-1]:.1f} ms" for k in names),
              flush=True)
    mins = np.asarray(times["minimal"])
    out = {"n": len(x), "grid": grid_cells, "motion": motion, "ms": {k: 1e3 * float(np.median(v)) for k, v in times.items()},
           "ratio": {k: float(np.median(np.asarray(times[k]) / mins)) for k in names if k != "minimal"},
           "ratio_range": {k: (float(np.min(np.asarray(times[k]) / mins)), float(np.max(np.asarray(times[k]) / mins)))
                           for k in names if k != "minimal"},
           "ratio_ftz": {k: float(np.median(np.asarray(times[k]) / np.asarray(times["minimal + FTZ"])))
                         for k in names if k.startswith("project") and "minimal + FTZ" in times},
           "split": {}, "chunks": None, "layers": None}
    # per-kernel split, launches synchronised
    split_steps = max(2, steps // 2)
    for k in names:
        e = engines[k]
        e.kernel_times = {}
        run_steps(e, split_steps)
        kt = {name: 1e3 * v / split_steps for name, v in e.kernel_times.items()}
        e.kernel_times = None
        if k.startswith("project"):
            kt["update_material (alone)"] = 1e3 * time_material(e)
            out["chunks"], out["layers"] = e.chunks, e.layers
        out["split"][k] = kt
    return out


def write_section(results: list, device: str, rounds: int, steps: int, load: str) -> None:
    lines = [f"Measured {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC on {machine_description()}, "
             f"Warp device `{device}`, load average before the run {load}. Re-run: "
             "`python -m benchmarks.bench_sim_scale`.", "",
             "Scene: the jelly drop (fixed-corotated, E = 2e5 Pa, dt = 1e-4 s), a lattice cube at 8 particles per "
             "cell in a unit box, the same lattice, initial velocities and dt for both engines; “tumble”: thrown "
             "down at 1 m/s spinning at 8.8 rad/s and squeezed at 2/s (every F turns and strains), “rest”: "
             "released at rest (C ~ 1e-15 1/s: round-off). The minimal kernel is a plain MLS-MPM "
             "program in Warp written in the benchmark (one thread, atomics, whole grid cleared each substep, "
             "SVD stress); the project runs its full substep. "
             "“minimal + FTZ” is the same minimal kernel with denormals flushed to zero, as the project's "
             "substeps now run (physmotion_core/sim/fpmode.py). "
             f"Interleaved rounds ({rounds} rounds of {steps} substeps per engine); ratio = median over rounds "
             "of project / minimal time in the same round (min-max in brackets).", "",
             "| scene | particles | grid | engine | ms / substep | ns / particle-substep | / minimal | / minimal + FTZ |",
             "|---|---:|---:|---|---:|---:|---:|---:|"]
    for r in results:
        for k, ms in r["ms"].items():
            ratio = "1" if k == "minimal" else (f"{r['ratio'][k]:.2f} ({r['ratio_range'][k][0]:.2f}-"
                                                 f"{r['ratio_range'][k][1]:.2f})")
            ftz = f"{r['ratio_ftz'][k]:.2f}" if k in r["ratio_ftz"] else ("1" if k == "minimal + FTZ" else "")
            lines.append(f"| {r['motion']} | {r['n']:,} | {r['grid']}³ | {k} | {ms:.1f} | {1e6 * ms / r['n']:.0f} | {ratio} | {ftz} |")
    lines += ["", "**Per kernel** (ns per particle and substep, each launch synchronised; the project's "
              "g2p includes its material update, which is also timed alone over the same particles):", ""]
    for r in results:
        lines += [f"{r['motion']}, {r['n']:,} particles ({r['chunks']} chunks, {r['layers']} accumulator layer(s)):", "",
                  "| engine | " + " | ".join(["kernel", "ns / particle", "ms / substep"]) + " |",
                  "|---|---|---:|---:|"]
        for k, kt in r["split"].items():
            for name, ms in sorted(kt.items(), key=lambda kv: -kv[1]):
                if ms < 0.05 * max(kt.values()) and "alone" not in name:
                    continue
                lines.append(f"| {k} | {name} | {1e6 * ms / r['n']:.0f} | {ms:.1f} |")
        lines.append("")
    name, title = ("sim-scale", "on the CPU") if device == "cpu" else ("sim-scale-cuda", f"on `{device}`")
    update_section("benchmarks.md", name, f"## Large scenes {title} (issue 38)\n\n" + "\n".join(lines))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="+", default=[38, 128], help="particles per axis (38: 55 k, 128: 2.1 M)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--motion", nargs="+", default=list(MOTIONS), choices=MOTIONS)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    threads = [1] if args.device != "cpu" else args.threads
    results = []
    for motion in args.motion:
        for n in args.sizes:
            results.append(measure_size(n, args.device, args.rounds, args.steps, threads, motion))
            print(results[-1], flush=True)
    if not args.no_write and set(args.sizes) == set(SIZES):
        write_section(results, args.device, args.rounds, args.steps, load)


if __name__ == "__main__":
    main()
