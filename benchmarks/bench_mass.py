"""The mass of a filled object against the grid it is filled on: quality should change accuracy, not weight.

    python -m benchmarks.bench_mass              # writes the "fill-mass" section of docs/accuracy.md
    python -m benchmarks.bench_mass --no-write   # print only

The simulator fills an object's Gaussians with particles on a voxel lattice (``sim.fill``) and gives them the
solid's volume times the density. Shells of flat surface splats (what the silhouette lift and LGM make) are
measured here: two with a known volume (a 0.2 m sphere; a 0.3 x 0.2 x 0.05 m slab turned 30° about the vertical)
filled at 12 to 96 voxels across, and two photos lifted as a run lifts them (the bundled example cup with the demo's
box; scikit-image's horse silhouette), weighed as ``generate --preview`` weighs them at each quality and at a fine
grid (``grid_res`` 96 on the CPU's particles-per-cell, about the limit the masses converge to).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ACROSS = (12, 16, 24, 36, 48, 96)  # voxels across the shapes of known volume
QUALITIES = ("draft", "standard", "high")
FINE_GRID = 96  # grid cells across a photo's object for the "fine" column


def _quats_from_z(normals: np.ndarray) -> np.ndarray:
    """(w, x, y, z) unit quaternions turning +z onto each unit normal."""
    z = np.array([0.0, 0.0, 1.0])
    c = np.cross(z, normals)
    w = 1.0 + normals @ z
    q = np.concatenate([w[:, None], c], 1)
    q[w < 1e-9] = [0.0, 1.0, 0.0, 0.0]  # -z: half a turn about x
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def shell(points: np.ndarray, normals: np.ndarray, h: float):
    """Flat splats (σ = h/2 in the surface, h/14 across it, like the silhouette lift's) at ``points`` facing
    ``normals``."""
    import torch

    from physmotion_core.types.gaussians import Gaussians

    n = len(points)
    gen = torch.Generator().manual_seed(0)
    return Gaussians.from_rgb(torch.tensor(points, dtype=torch.float32), torch.rand(n, 3, generator=gen),
                              torch.tensor([[h / 2, h / 2, h / 14]], dtype=torch.float32).repeat(n, 1),
                              torch.full((n,), 0.9), quats=torch.tensor(_quats_from_z(normals), dtype=torch.float32))


def sphere_shell(R: float = 0.1, h: float = 0.003):
    """(Gaussians, volume, extent): splats every ``h`` over a sphere (a Fibonacci lattice)."""
    n = int(4 * np.pi * R * R / h / h)
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5 ** 0.5) * i
    u = np.stack([np.cos(th) * np.sin(phi), np.cos(phi), np.sin(th) * np.sin(phi)], 1)
    return shell(R * u, u, h), 4 / 3 * np.pi * R**3, 2 * R


def slab_shell(tilt_deg: float, size=(0.3, 0.2, 0.05), h: float = 0.003):
    """(Gaussians, volume, extent): splats every ``h`` over the six faces of a box turned ``tilt_deg`` about y."""
    a = np.asarray(size, float) / 2
    pts, nrm = [], []
    for ax in range(3):
        o = [k for k in range(3) if k != ax]
        g1, g2 = np.meshgrid(np.arange(-a[o[0]] + h / 2, a[o[0]], h), np.arange(-a[o[1]] + h / 2, a[o[1]], h),
                             indexing="ij")
        for sign in (-1.0, 1.0):
            p = np.zeros((g1.size, 3))
            p[:, o[0]], p[:, o[1]], p[:, ax] = g1.ravel(), g2.ravel(), sign * a[ax]
            nn = np.zeros_like(p)
            nn[:, ax] = sign
            pts.append(p)
            nrm.append(nn)
    t = np.radians(tilt_deg)
    rot = np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])
    p, nn = np.concatenate(pts) @ rot.T, np.concatenate(nrm) @ rot.T
    return shell(p, nn, h), float(np.prod(size)), float(np.ptp(p, axis=0).max())


def horse_photo():
    """scikit-image's horse silhouette as a photo (a dark horse on a light ground) and its mask."""
    import torch
    from skimage import data

    fg = ~data.horse()
    img = np.where(fg[..., None], 60, 230).astype(np.uint8).repeat(3, axis=2)
    return img, torch.from_numpy(fg.astype(np.float32))


def photo_masses(name: str) -> dict:
    """{quality: (kg, particles)} of a photo lifted as ``generate`` lifts it, and "fine" at FINE_GRID."""
    from physmotion_core.feedback import body_facts
    from physmotion_core.pipeline import prepare

    if name == "horse":
        img, mask = horse_photo()
        prep = prepare(img, material="jelly", mask=mask, report=lambda s: None, _weigh=False)
    else:
        prep = prepare(str(ROOT / "photos" / "coffee.png"), material="jelly", box=(55, 6, 498, 395),
                       report=lambda s: None, _weigh=False)
    out = {}
    for q in QUALITIES + ("fine",):
        s = (dataclasses.replace(prep.settings, quality=q) if q != "fine"
             else dataclasses.replace(prep.settings, grid_res=FINE_GRID, max_particles=5_000_000))
        f = body_facts(prep.gaussians, prep.material, s, prep.conditions.ground())
        out[q] = (f.total_mass, len(f.x))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    args = ap.parse_args(argv)
    from physmotion_core.report import machine_description, update_section
    from physmotion_core.sim.fill import fill_particles

    t0 = time.perf_counter()
    md = [f"Measured by `python -m benchmarks.bench_mass` on {machine_description()}.", "",
          "Shells of flat splats (3 mm apart) around a known volume V, filled by `fill_particles` at a spacing of "
          "the shape's extent over N; the particles' total volume over V:", "",
          "| shape | " + " | ".join(f"N = {n}" for n in ACROSS) + " |",
          "| --- | " + " | ".join("---:" for _ in ACROSS) + " |"]
    for label, build in (("sphere, 0.2 m", sphere_shell), ("slab, 30°", lambda: slab_shell(30.0)),
                         ("slab, 45°", lambda: slab_shell(45.0))):
        g, V, extent = build()
        cells = [float(fill_particles(g, extent / n, max_particles=5_000_000).volume.astype(np.float64).sum()) / V
                 for n in ACROSS]
        md.append(f"| {label} | " + " | ".join(f"{c:.3f}" for c in cells) + " |")
        print(md[-1])
    md += ["", f"Photos lifted as `generate` lifts them (jelly, 1000 kg/m³), weighed as `--preview` weighs them; "
           f"fine: grid_res {FINE_GRID}:", "",
           "| photo | " + " | ".join(QUALITIES) + " | fine | draft / fine | standard / fine |",
           "| --- | " + " | ".join("---:" for _ in QUALITIES) + " | ---: | ---: | ---: |"]
    for name in ("cup", "horse"):
        m = photo_masses(name)
        fine = m["fine"][0]
        md.append(f"| {name} | " + " | ".join(f"{m[q][0]:.3g} kg ({m[q][1]:,})" for q in QUALITIES)
                  + f" | {fine:.3g} kg ({m['fine'][1]:,}) | {m['draft'][0] / fine:.3f} | {m['standard'][0] / fine:.3f} |")
        print(md[-1])
    md += ["", f"({(time.perf_counter() - t0) / 60:.1f} min in all.)"]
    text = "\n".join(md)
    if not args.no_write:
        print("written to", update_section("accuracy.md", "fill-mass", text))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
