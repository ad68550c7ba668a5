"""Issue 22, fill: a Gaussian cube is filled uniformly, through ``simulate()`` (the path users run).

What "uniform" means here. ``gaussian_box(lo, hi, (n, n, n))`` puts Gaussians on a lattice of step
h = (hi - lo) / (n - 1) with σ = h/2. The solid they describe is the n³ cells they stand for: along
each axis [lo - h/2, hi + h/2] (where their summed density falls to half its interior value), of
volume V = (n h)³. With s the particle spacing simulate() picks (default settings on the CPU):

* layers: along each axis, the particles binned into the layers of the particle lattice (bins
  centred on the lattice, found from the positions' phase, so the ±s/4 jitter never moves a particle
  into the next bin) all hold as many particles as the median layer, within LAYER_TOL. This is the
  issue's figure ("the emptiest fill layer has 0.86 of the particles of a full one");
* slabs: along each axis, K slabs of equal thickness cut from the TRUE extent [lo - h/2, hi + h/2]
  hold particle volume (each particle's volume spread over its voxel [c - s/2, c + s/2] along the
  axis) equal to the slab's volume within SLAB_TOL. The spreading itself can misplace up to half a
  voxel of a face voxel's volume across the face, about s/2 of a slab some 12 s thick (2 %);
* total: the particles' volume (the run's mass over the density) equals V within TOTAL_TOL.

Measured on 16 random cubes before the change (docs/accuracy.md): layers 0.10 of the median at worst,
slabs 0.90-1.07, total 0.92-1.11; after: layers 1.000, slabs 0.983-1.016, total 0.999-1.001.
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from physmotion_core.sim import simulate
from physmotion_core.types import Material, SimSettings
from physmotion_core.validate.stress import gaussian_box

LAYER_TOL = 0.02
SLAB_TOL = 0.03
TOTAL_TOL = 0.02
K = 4  # slabs per axis

# (seed): random offset in ±5 cm, edge 0.1-0.5 m, 8-16 Gaussians a side.
CASES = [3, 11, 29]


def _cube(seed):
    rng = np.random.default_rng(seed)
    off = rng.uniform(-0.05, 0.05, 3)
    size = float(rng.uniform(0.1, 0.5))
    n = int(rng.integers(8, 17))
    g = gaussian_box(tuple(off), tuple(off + size), (n, n, n))
    h = size / (n - 1)
    return g, off - h / 2, n * h  # the Gaussians, the solid's lower corner, its edge


def _snap(x, s):
    """The particle-lattice coordinate of each position (the lattice phase from the circular mean)."""
    phase = np.angle(np.mean(np.exp(2j * np.pi * x / s))) * s / (2 * np.pi)
    return phase + np.round((x - phase) / s) * s


@pytest.mark.parametrize("seed", CASES)
def test_gaussian_cube_fill_is_uniform_through_simulate(seed, monkeypatch):
    sim_module = importlib.import_module("physmotion_core.sim.simulate")
    filled = []

    def spy(*args, **kwargs):
        filled.append(sim_module_fill(*args, **kwargs))
        return filled[-1]

    sim_module_fill = sim_module.fill_objects
    monkeypatch.setattr(sim_module, "fill_objects", spy)

    g, corner, edge = _cube(seed)
    mat = Material.preset("jelly")
    res = simulate(g, mat, settings=SimSettings(frames=1, device="cpu"), record_all=True)
    parts = filled[0]
    x = res.rest_particles.numpy().astype(np.float64)
    assert np.array_equal(x, parts.x.astype(np.float64))  # the particles the run used
    s = float(res.stats["particle_spacing"])
    vol = parts.volume.astype(np.float64)
    assert res.stats["mass_kg"] == pytest.approx(vol.sum() * mat.density, rel=1e-5)

    V = edge**3
    total = res.stats["mass_kg"] / mat.density / V
    assert abs(total - 1.0) <= TOTAL_TOL, f"total particle volume {total:.4f} of the cube's"

    thick = edge / K
    for ax in range(3):
        c = _snap(x[:, ax], s)
        layers = np.bincount(np.round((c - c.min()) / s).astype(np.int64))
        worst = layers.min() / np.median(layers)
        assert worst >= 1.0 - LAYER_TOL, f"axis {ax}: emptiest layer {worst:.3f} of the median ({layers.tolist()})"
        a = c - s / 2 - corner[ax]
        b = c + s / 2 - corner[ax]
        for k in range(K):
            share = np.clip(np.minimum(b, (k + 1) * thick) - np.maximum(a, k * thick), 0.0, None) / s
            ratio = float((vol * share).sum() / (edge**2 * thick))
            assert abs(ratio - 1.0) <= SLAB_TOL, f"axis {ax} slab {k}: volume {ratio:.4f} of the slab's"


def test_a_mix_of_round_and_flat_gaussians_fills():
    """Round Gaussians take their box axes from their neighbours, whose indices count every Gaussian: with
    flat splats among them (a lifted shell over a solid core, as the learned front end gives) the round
    ones' neighbours were looked up in the round ones only, out of bounds (IndexError in the pipeline).
    The mixed set fills, and its round core's particles match the core filled alone."""
    import torch

    from physmotion_core.sim.fill import fill_particles
    from physmotion_core.types.gaussians import Gaussians
    from physmotion_core.validate.stress import gaussian_box

    core = gaussian_box((-0.05, 0.0, -0.05), (0.05, 0.1, 0.05), (6, 6, 6))
    n = 40
    ang = torch.linspace(0, 6.283, n)
    flat_means = torch.stack([0.2 + 0.02 * torch.cos(ang), 0.05 + 0.0 * ang, 0.02 * torch.sin(ang)], 1)
    flat = Gaussians.from_rgb(flat_means, torch.rand(n, 3), torch.tensor([[0.004, 0.004, 0.0002]]).repeat(n, 1),
                              torch.full((n,), 0.9))
    # The flat splats first, so that every round Gaussian's index is past the round ones' count.
    both = Gaussians.from_rgb(torch.cat([flat.means, core.means]), torch.rand(len(core.means) + n, 3),
                              torch.cat([flat.scales, core.scales]), torch.cat([flat.opacities, core.opacities]),
                              quats=torch.cat([flat.quats, core.quats]))
    s = 0.01
    mixed = fill_particles(both, s)
    alone = fill_particles(core, s)
    in_core = np.all(np.abs(mixed.x - np.array([0.0, 0.05, 0.0])) < 0.08, axis=1)
    assert in_core.sum() == len(alone.x)


# -- a shell of surface splats (the silhouette lift, LGM) weighs what it encloses -----------------------------------


@pytest.mark.parametrize("shape", ["sphere", "slab 0", "slab 30", "slab 45"])
def test_a_shell_of_surface_splats_weighs_what_it_encloses_at_every_spacing(shape):
    """A flat splat marks a voxel-thick sheet (its ellipsoid widened by half a voxel), but the solid ends at its
    plane: the particles share the volume inside the surface. Before (2026-12-06), they shared the widened sheet's,
    and a body weighed more the coarser its grid: a 0.2 m sphere 1.40 / 1.22 / 1.09 times its volume at 12 / 24 / 48
    voxels across, a 5 cm slab turned 20° 2.28 / 1.57 / 1.27 times; now within 6 % at 12 and 2 % from 24
    (docs/accuracy.md, "Mass of a filled object")."""
    from benchmarks.bench_mass import slab_shell, sphere_shell
    from physmotion_core.sim.fill import fill_particles

    g, V, extent = sphere_shell() if shape == "sphere" else slab_shell(float(shape.split()[1]))
    for across, tol in ((12, 0.06), (24, 0.02), (48, 0.02)):
        got = float(fill_particles(g, extent / across).volume.astype(np.float64).sum())
        assert got == pytest.approx(V, rel=tol), f"{across} voxels across: {got / V:.3f} of its volume"


def test_a_lifted_photo_weighs_about_the_same_at_every_quality():
    """scikit-image's horse, lifted from its silhouette, weighed at draft, standard and high quality: before the
    fill cut a surface splat's solid at its plane (2026-12-06), draft weighed 1.31 times high, and the stability
    verdict moved with it; now 1.12 times (2.63 against 2.36 kg; docs/accuracy.md)."""
    from benchmarks.bench_mass import photo_masses

    m = {q: kg for q, (kg, _) in photo_masses("horse").items()}
    assert m["draft"] >= m["standard"] >= m["high"] >= m["fine"]  # (what excess is left shrinks with the grid)
    assert m["draft"] / m["high"] < 1.16, m


def test_flat_splats_that_enclose_nothing_still_weigh_something():
    """Surface splats cut their voxels at their planes; a cloud of them that encloses nothing (thin discs stacked
    apart, as a sparse or open cloud from a user's file can be) would then weigh nothing, and a simulation of it
    divides by zero. Every solid voxel stands for MIN_VOXEL_SHARE of itself at least, on average."""
    import torch

    from physmotion_core.sim.fill import MIN_VOXEL_SHARE, fill_particles
    from physmotion_core.validate.stress import gaussian_box

    g = gaussian_box((-0.05, 0.05, -0.05), (0.05, 0.15, 0.05), (4, 4, 4))
    g.scales = torch.tensor([0.01, 0.01, 0.002]).expand(len(g), 3).clone()  # discs 3.3 cm apart, facing z
    s = 0.1 / 12
    ps = fill_particles(g, s)
    assert float(ps.volume.astype(np.float64).sum()) >= MIN_VOXEL_SHARE * len(ps.x) * s**3 * 0.999
    assert np.all(ps.volume > 0)
