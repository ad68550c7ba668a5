"""Tall elastic blocks on a Coulomb slope at 0.9 μ (issue 37): how far they travel in 1 s with the ground
friction's memory (MPMSolver ``friction_memory``, kernels.static_friction) and without it (0, the law
before), against an independent 1D column.

The solver runs: a jelly block (E = 2e5 Pa, ν = 0.3, ρ = 1000) 14 x H x 10 cells, on a lattice of dx/2,
released at rest (or at ``--kick`` m/s downhill) at 24.2° on μ = 0.5 (tan θ = 0.9 μ), the slope made by
tilting gravity; the travel of its centre of mass and of its bottom layer of particles after 1 s.

The 1D column (``column_travel``, plain NumPy, no MPM): the normal force on the base comes from a bar of
modulus E on a fixed base released stress-free (a quarter-wave column: it swings between 0 and twice
the weight), the tangential motion from a shear column of modulus G whose base node sticks while the
force that stops it is within μ N(t), else slides under μ N; optional stiffness-proportional damping of
ratio ζ at the bar's fundamental. It is what an ideal elastic body does when released stress-free.

With ``--preload`` each block also runs started in equilibrium under gravity (MPMSolver.preload, the
default of simulate()); ``--user X HEIGHT Z E`` runs a jelly block of that size through simulate() at
grid_res 24, without and with the preload (``user_block_travel``).

Numbers are in docs/accuracy.md, "Friction on a slope", "Tall bodies", "Starting in equilibrium". Usage:
    .venv/bin/python -m benchmarks.bench_slope [--dx 0.01] [--heights 5 7 10 15 20] [--kick 0.05] [--preload]
    .venv/bin/python -m benchmarks.bench_slope --user 0.3 0.3 0.15 2e5 [--frac 0.9]
    .venv/bin/python -m benchmarks.bench_slope --column 0.05 0.1 0.2 [--zeta 0.05]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

G = 9.81


def block_travel(cells_tall: int, dx: float = 0.01, memory: float = 1.0, kick: float = 0.0, mu: float = 0.5,
                 frac: float = 0.9, E: float = 2e5, t_end: float = 1.0, preload: bool = False) -> dict:
    """A 14 x H x 10-cell jelly block on the slope through MPMSolver; travel (m) of its centre of mass and base."""
    from physmotion_core.sim.mpm import MPMSolver
    from physmotion_core.types.conditions import Ground
    from physmotion_core.validate.cases import FRAME_DT, MIN_SUBSTEPS, _elastic
    from physmotion_core.validate.harness import box_domain, lattice, run_sampled

    w, h, d = 14 * dx, cells_tall * dx, 10 * dx
    x, vol = lattice((-w / 2, 0.0, -d / 2), (w / 2, h, d / 2), dx / 2)
    ground = Ground(0.0, "friction", mu)
    th = math.atan(frac * mu)
    dom = box_domain((-w / 2 - 0.1, 0.0, -d / 2 - 0.05), (w / 2 + 0.15 + kick * t_end, h + 0.1, d / 2 + 0.05), dx,
                     ground=ground)
    s = MPMSolver(x, vol, np.zeros(len(x), np.int64), [_elastic(E)], dom, ground=ground,
                  gravity=(G * math.sin(th), -G * math.cos(th), 0.0), friction_memory=memory,
                  v0=np.tile([kick, 0.0, 0.0], (len(x), 1)) if kick else None)
    pre = s.preload(h, math.sqrt(E / (2 * 1.3) / 1000.0)) if preload else None
    m = s.mass_np.astype(np.float64)
    base = x[:, 1] < dx / 2
    t0 = time.perf_counter()
    (p,) = run_sampled(s, [t_end], lambda s: s.positions().astype(np.float64), max_dt=FRAME_DT / MIN_SUBSTEPS)
    return {"com": float(((p[:, 0] - x[:, 0]) * m).sum() / m.sum()), "base": float((p[base, 0] - x[base, 0]).mean()),
            "particles": len(x), "seconds": time.perf_counter() - t0, "preload": pre}


def user_block_travel(size=(0.3, 0.3, 0.15), E: float = 2e5, frac: float = 0.9, preload: bool = True,
                      grid_res: int = 24, mu: float = 0.5, t_end: float = 1.0, fps: float = 10.0,
                      points: int = 13, margin: float = 2.0) -> dict:
    """A jelly block (the preset with this E) at the user's scale through simulate(): Gaussians on a lattice
    filling size (x × height × z, m), released at rest on the slope (tilted gravity, Coulomb μ) at tan θ =
    frac μ, grid_res cells across its largest extent. Travel (m) of its particles' mean and of its bottom
    layer's after t_end, the top's drop over the run, and the run's stats (substeps, preload)."""
    import torch

    from physmotion_core.sim import simulate
    from physmotion_core.types import Conditions, Gaussians, Gravity, Ground, SimSettings
    from physmotion_core.types.material import material_preset

    n = [max(2, round(points * a / max(size))) for a in size]
    axes = [torch.linspace(-a / 2 if i != 1 else 0.0, a / 2 if i != 1 else a, k) for i, (a, k) in enumerate(zip(size, n))]
    p = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    sigma = 0.5 * min(a / (k - 1) for a, k in zip(size, n))
    gen = torch.Generator().manual_seed(0)
    gs = Gaussians.from_rgb(p, torch.rand(len(p), 3, generator=gen), torch.full((len(p), 3), sigma),
                            torch.full((len(p),), 0.9))
    th = math.atan(frac * mu)
    frames = int(round(t_end * fps)) + 1
    t0 = time.perf_counter()
    res = simulate(gs, material_preset("jelly", E=E),
                   Conditions([Gravity((G * math.sin(th), -G * math.cos(th), 0.0)), Ground(0.0, "friction", mu)]),
                   SimSettings(frames=frames, fps=fps, grid_res=grid_res, domain_margin=margin, rest_speed=0.0,
                               device="cpu", preload=preload), record_all=True)
    x = res.x.numpy().astype(np.float64)
    base = x[0][:, 1] < x[0][:, 1].min() + 0.5 * res.stats["particle_spacing"]
    top = x[0][:, 1] > x[0][:, 1].max() - 0.5 * res.stats["particle_spacing"]
    return {"com": float(x[-1, :, 0].mean() - x[0, :, 0].mean()),
            "base": float(x[-1, base, 0].mean() - x[0, base, 0].mean()),
            "top_drop": float(x[0, top, 1].mean() - x[:, top, 1].mean(1).min()),
            "frame0_exact": bool(np.array_equal(x[0], res.rest_particles.numpy().astype(np.float64))),
            "dx": res.stats["dx"], "substeps": res.stats["substeps"], "preload": res.stats.get("preload"),
            "seconds": time.perf_counter() - t0, "particles": res.stats["particles"]}


def column_travel(H: float, zeta: float = 0.0, kick: float = 0.0, static: bool = False, E: float = 2e5,
                  nu: float = 0.3, rho: float = 1000.0, mu: float = 0.5, frac: float = 0.9, t_end: float = 1.0,
                  n: int = 50) -> tuple[float, float]:
    """The 1D column (module docstring), n segments: (travel of its centre of mass, of its base) in m.
    ``static``: start from the equilibrium under gravity instead of stress-free."""
    Gs = E / (2 * (1 + nu))
    th = math.atan(frac * mu)
    gn, gt = G * math.cos(th), G * math.sin(th)
    h = H / n
    m = np.full(n + 1, rho * h)  # per unit area
    m[0] *= 0.5
    m[-1] *= 0.5
    kn, kt = E / h, Gs / h
    dt = 0.5 * h / math.sqrt(E / rho)
    beta = 2 * zeta / (math.pi / (2 * H) * math.sqrt(E / rho))
    if beta > 0:
        dt = min(dt, 0.4 / (beta * kn / (rho * h)))
    y = np.linspace(0.0, H, n + 1)
    un, vn = np.zeros(n + 1), np.zeros(n + 1)
    rest_t = rho * gt / Gs * (H * y - 0.5 * y * y)
    ut, vt = (rest_t.copy() if static else np.zeros(n + 1)), np.full(n + 1, kick)
    if static:
        un = -rho * gn / E * (H * y - 0.5 * y * y)
    for _ in range(int(round(t_end / dt))):
        fn = np.zeros(n + 1)
        sn = kn * (np.diff(un) + beta * np.diff(vn))
        fn[:-1] += sn
        fn[1:] -= sn
        fn -= m * gn
        N = max(-fn[0], 0.0)  # what holds the base node up
        vn[1:] += dt * fn[1:] / m[1:]
        un[1:] += dt * vn[1:]
        ft = np.zeros(n + 1)
        st = kt * (np.diff(ut) + beta * np.diff(vt))
        ft[:-1] += st
        ft[1:] -= st
        ft += m * gt
        need = -(ft[0] + m[0] * vt[0] / dt)  # the friction that stops the base node in this step
        ft[0] += need if abs(need) <= mu * N else math.copysign(mu * N, need)
        vt += dt * ft / m
        ut += dt * vt
    moved = ut - (rest_t if static else 0.0)
    return float((m * moved).sum() / m.sum()), float(moved[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dx", type=float, default=0.01)
    ap.add_argument("--heights", type=int, nargs="+", default=[5, 7, 10, 15, 20])
    ap.add_argument("--kick", type=float, default=0.0, help="initial speed downhill (m/s)")
    ap.add_argument("--column", type=float, nargs="*", help="run the 1D column for these heights (m) instead")
    ap.add_argument("--zeta", type=float, default=0.0)
    ap.add_argument("--preload", action="store_true", help="also run each block with the gravity preload")
    ap.add_argument("--user", type=float, nargs=4, metavar=("X", "HEIGHT", "Z", "E"),
                    help="instead: a block this size (m) and E (Pa) through simulate() at grid_res 24, "
                         "without and with the preload")
    ap.add_argument("--frac", type=float, default=0.9, help="tan θ as a fraction of μ (--user)")
    args = ap.parse_args(argv)
    if args.user:
        for pre in (False, True):
            r = user_block_travel(tuple(args.user[:3]), args.user[3], args.frac, pre)
            print(f"block {args.user[:3]} E {args.user[3]:g} at {args.frac:g} μ, preload {pre}: COM {r['com'] * 1e3:.2f} mm, "
                  f"base {r['base'] * 1e3:.2f} mm, top drop {r['top_drop'] * 1e3:.2f} mm, dx {r['dx']:.4g}, "
                  f"{r['particles']} particles, {r['substeps']} substeps, {r['seconds']:.1f} s, frame 0 exact "
                  f"{r['frame0_exact']}, preload {r['preload']}", flush=True)
        return 0
    if args.column:
        for H in args.column:
            com, base = column_travel(H, args.zeta, args.kick)
            print(f"1D column H = {H:g} m, ζ = {args.zeta:g}, kick {args.kick:g} m/s: centre of mass "
                  f"{com * 1e3:.2f} mm, base {base * 1e3:.2f} mm in 1 s")
        return 0
    print(f"| H (cells) | memory | centre of mass (mm) | base (mm) | particles | s |  (dx = {args.dx:g} m, "
          f"kick {args.kick:g} m/s)")
    print("|---:|---:|---:|---:|---:|---:|")
    for cells in args.heights:
        for memory, pre in ((0.0, False), (1.0, False)) + (((1.0, True),) if args.preload else ()):
            r = block_travel(cells, args.dx, memory, args.kick, preload=pre)
            print(f"| {cells} | {memory:g}{' + preload' if pre else ''} | {r['com'] * 1e3:.2f} | {r['base'] * 1e3:.2f} | {r['particles']} | "
                  f"{r['seconds']:.1f} |" + (f" preload {r['preload']}" if pre else ""), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
