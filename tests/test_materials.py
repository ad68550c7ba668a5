"""One behavioural test per material and per condition of the MPM engine, checked numerically.

Each scene is small (a few thousand particles, coarse grid) so the file runs in about a minute on
two CPU cores; every tolerance says why it is what it is. Test materials use the presets' models
with stiffnesses lowered where that only shortens the run (the behaviour class is what is tested).
"""

import math

import numpy as np
import pytest
import torch
import warp as wp

from physmotion_core.errors import InputError
from physmotion_core.sim import kernels as K
from physmotion_core.sim import simulate
from physmotion_core.sim.materials import kernel_params
from physmotion_core.types.material import material_preset
from physmotion_core.types import (Anchor, Conditions, Force, Gaussians, Gravity, Ground, InitialVelocity,
                                   Material, Region, SimSettings, Torque)

NO_GRAVITY = Gravity((0.0, 0.0, 0.0))


def lattice(lo, hi, n, object_id=None):
    """Gaussians on an n-point lattice filling the box lo..hi (metres)."""
    axes = [torch.linspace(a, b, k) for a, b, k in zip(lo, hi, n)]
    p = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    sigma = 0.5 * min((b - a) / max(k - 1, 1) for a, b, k in zip(lo, hi, n))
    g = Gaussians.from_rgb(p, torch.rand(len(p), 3), torch.full((len(p), 3), sigma), torch.full((len(p),), 0.9))
    if object_id is not None:
        g.object_ids = torch.full((len(p),), object_id, dtype=torch.int64)
    return g


def box(lo, hi):
    return Region(kind="box", lo=lo, hi=hi)


def components(x: np.ndarray, spacing: float) -> list[int]:
    """Sizes of the connected pieces of a particle cloud (neighbours within 1.5 spacings)."""
    cell = 1.5 * spacing
    keys = np.floor(x / cell).astype(np.int64)
    occupied = {tuple(k) for k in keys}
    seen, sizes = set(), []
    counts = {}
    for k in map(tuple, keys):
        counts[k] = counts.get(k, 0) + 1
    for start in occupied:
        if start in seen:
            continue
        stack, size = [start], 0
        seen.add(start)
        while stack:
            c = stack.pop()
            size += counts[c]
            for d in np.ndindex(3, 3, 3):
                nb = (c[0] + d[0] - 1, c[1] + d[1] - 1, c[2] + d[2] - 1)
                if nb in occupied and nb not in seen:
                    seen.add(nb)
                    stack.append(nb)
        sizes.append(size)
    return sorted(sizes, reverse=True)


def test_metal_stays_bent_after_the_load_is_removed():
    # A cantilever clamped at x < 0.03 m, pushed down at its tip for 0.2 s, then released; mass-
    # proportional damping lets it settle within the run. Yield strain 0.4 %: the push yields the
    # root, so the bar keeps most of its bend; the same bar with no yield springs back.
    bar = lattice((0.0, -0.03, -0.03), (0.3, 0.03, 0.03), (16, 4, 4))
    conds = Conditions([NO_GRAVITY, Anchor(box((-1, -1, -1), (0.03, 1, 1))),
                        Force((0, -4.0, 0), box((0.26, -1, -1), (1, 1, 1)), 0.0, 0.2)])
    s = SimSettings(frames=17, fps=40, grid_res=15, domain_margin=0.5)

    def tip(material):
        res = simulate(bar, material, conds, s, record_all=True)
        x = res.x.numpy()
        sel = x[0][:, 0] > 0.27
        y = x[:, sel, 1].mean(1) - x[0, sel, 1].mean()
        return y, res

    metal, res = tip(Material(name="metal", model="von_mises", E=5e5, nu=0.3, density=1000, yield_stress=2e3,
                              damping=10.0))
    elastic, _ = tip(Material(name="elastic", model="von_mises", E=5e5, nu=0.3, density=1000, yield_stress=1e9,
                              damping=10.0))
    assert float(res.plastic.max()) > 0.01, "the root must yield"
    # Plastic: at the end (0.2 s after release) it keeps > 60 % of its largest bend.
    assert metal[-1] < 0.6 * metal.min() < 0
    # Elastic control: it springs back to within 25 % of its largest bend.
    assert abs(elastic[-1]) < 0.25 * abs(elastic.min())


def _slope_deg(x: np.ndarray, spacing: float) -> float:
    """Mean surface slope of a heap: top-surface height against radius, fitted between 20 % and
    80 % of the heap's height (excludes the rounded summit and the thin toe)."""
    c = x[:, [0, 2]].mean(0)
    r = np.linalg.norm(x[:, [0, 2]] - c, axis=1)
    edges = np.arange(0.0, r.max() + spacing, 1.5 * spacing)
    prof = [((a + b) / 2, np.percentile(x[(r >= a) & (r < b), 1], 95))
            for a, b in zip(edges[:-1], edges[1:]) if ((r >= a) & (r < b)).sum() > 3]
    prof = np.array(prof)
    top = prof[:, 1].max()
    use = (prof[:, 1] > 0.2 * top) & (prof[:, 1] < 0.8 * top)
    return float(np.degrees(np.arctan(-np.polyfit(prof[use, 0], prof[use, 1], 1)[0])))


def _cone(radius=0.08, angle_deg=60.0, n=16, bottom=0.01):
    h = radius * math.tan(math.radians(angle_deg))
    a = torch.linspace(-radius, radius, n)
    p = torch.stack(torch.meshgrid(a, torch.linspace(0, h, n), a, indexing="ij"), -1).reshape(-1, 3)
    p = p[p[:, 1] <= h * (1 - torch.sqrt(p[:, 0] ** 2 + p[:, 2] ** 2) / radius)]
    p[:, 1] += bottom
    return Gaussians.from_rgb(p, torch.rand(len(p), 3), torch.full((len(p), 3), radius / n),
                              torch.full((len(p),), 0.9))


def test_sand_heap_slumps_to_a_slope_set_by_its_friction_angle():
    # A 60° cone of dry sand is steeper than any friction angle below 60°: it slumps until its
    # slope can stand. The Drucker-Prager cone is fitted to Mohr-Coulomb in triaxial compression,
    # and a slumping heap is partly in weaker stress states and still moving when it stops, so its
    # final slope sits several degrees below φ (measured after 1 s: 14° for φ = 20°, 28.6° for
    # φ = 40° at grid_res 12, 29.4° at 14): we require φ - 14° < slope < φ, and a steeper heap for the
    # larger angle. grid_res 12, not 10: with the uniform fill of issue 22 (the cone filled to its true
    # volume, flat-faced) the φ = 40° heap at grid_res 10 still stood at 49-56° after 1 s over three
    # seeds (30-37° with the old fill); at 12 and 14 both fills slump as above, so it is the coarsest grid
    # that no longer resolves the slump, which was not investigated further.
    s = SimSettings(frames=21, fps=20, grid_res=12, domain_margin=1.0)
    slopes = {}
    for phi in (20.0, 40.0):
        res = simulate(_cone(), Material.preset("sand", friction_angle=phi), Conditions([Ground(0, "friction", 0.6)]),
                       s, record_all=True)
        slopes[phi] = _slope_deg(res.x[-1].numpy(), res.stats["particle_spacing"])
        assert phi - 14.0 < slopes[phi] < phi, (phi, slopes[phi])
    assert slopes[40.0] > slopes[20.0] + 10.0


def test_snow_compacts_under_load_and_stays_compacted():
    # A 0.1 m block pressed by 150 N (15 kPa, several times snow's elastic limit E θc ≈ 3.5 kPa)
    # for 0.15 s, then released (0.1 s more). Snow densifies plastically (Jp < 1) and keeps most of the height it
    # lost; an elastic block of the same stiffness recovers.
    blk = lattice((-0.05, 0.01, -0.05), (0.05, 0.11, 0.05), (8, 8, 8))
    press = Force((0, -150.0, 0), box((-1, 0.09, -1), (1, 1, 1)), 0.0, 0.15)
    s = SimSettings(frames=11, fps=40, grid_res=6, domain_margin=0.5)

    def heights(mat):
        res = simulate(blk, mat, Conditions([Ground(0, "sticky"), press, NO_GRAVITY]), s, record_all=True)
        y = res.x[:, :, 1].numpy()
        return np.percentile(y, 98, axis=1) - y.min(axis=1), res

    snow_h, res = heights(Material.preset("snow", damping=10.0))
    elastic_h, _ = heights(Material(name="elastic", model="fixed_corotated", E=1.4e5, nu=0.2, density=400,
                                    damping=10.0))
    jp = res.plastic[-1].numpy()
    assert float(np.median(jp)) < 0.97, "the pressed snow must have densified (plastic J < 1)"
    assert snow_h[-1] < 0.93 * snow_h[0], "snow keeps a compacted height"
    assert elastic_h[-1] > 0.97 * elastic_h[0], "an elastic block recovers its height"


def test_water_column_spreads_flat():
    # A dam break: a 0.1 m column of water in a 0.25 m wide box. After 1 s the free surface is
    # flat: its height varies by no more than ~2 particle layers (residual sloshing), and the peak
    # is far below the column's. Damping 3/s (a settled tank, not viscosity) shortens the wait, and
    # a 10x softer bulk modulus (sound speed 12 m/s, still 5x the flow speed) a 3x longer step.
    col = lattice((-0.025, 0.01, -0.025), (0.025, 0.11, 0.025), (5, 10, 5))
    s = SimSettings(frames=21, fps=20, grid_res=10, domain_margin=1.0)
    res = simulate(col, Material.preset("water", damping=3.0, bulk_modulus=2e4), Conditions([Ground(0, "slip")]), s,
                   record_all=True)
    x = res.x[-1].numpy()
    spacing = res.stats["particle_spacing"]
    h0 = float(res.x[0, :, 1].max() - res.x[0, :, 1].min())
    edges = np.arange(x[:, 0].min(), x[:, 0].max() + 1e-9, 2 * spacing)
    tops = [np.percentile(x[(x[:, 0] >= a) & (x[:, 0] < b), 1], 95)
            for a, b in zip(edges[:-1], edges[1:]) if ((x[:, 0] >= a) & (x[:, 0] < b)).sum() > 5]
    assert max(tops) - min(tops) < 2.5 * spacing
    assert float(x[:, 1].max() - x[:, 1].min()) < 0.35 * h0
    assert float(np.ptp(x[:, 0])) > 3 * 0.05, "it spread sideways"


def test_rigid_cube_keeps_its_shape_and_follows_newton_euler():
    # No gravity, a 0.1 m rigid cube pushed by 2 N and twisted by 0.01 N·m for 0.25 s.
    # Expected: COM displacement ½ (F/M) t², rotation ½ (τ/I) t² about z (a cube's inertia is
    # isotropic, so the axis stays fixed). Tolerance 2 %: the symplectic-Euler drift is dt/t with
    # dt = frame/8, i.e. 1.25 % at t = 0.25 s; I is computed here from the particles as a solid
    # (point masses plus each particle's cube), independently of the solver's own.
    cube = lattice((-0.05, 0.2, -0.05), (0.05, 0.3, 0.05), (8, 8, 8))
    F, tau = np.array([2.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.01])
    res = simulate(cube, Material.preset("rigid"), Conditions([NO_GRAVITY, Force(tuple(F)), Torque(tuple(tau))]),
                   SimSettings(frames=11, fps=40, grid_res=10), record_all=True)
    x = res.x.numpy().astype(np.float64)
    M = res.stats["mass_kg"]
    m = M / x.shape[1]
    s = res.stats["particle_spacing"]
    r0 = x[0] - x[0].mean(0)
    inertia = np.eye(3) * (m * (r0**2).sum(1)).sum() - (r0.T * m) @ r0 + np.eye(3) * M * s * s / 6
    alpha = np.linalg.solve(inertia, tau)
    t = float(res.times[-1])
    disp = x[-1].mean(0) - x[0].mean(0)
    assert disp[0] == pytest.approx(0.5 * F[0] / M * t**2, rel=0.02)
    assert abs(disp[1]) < 1e-6 and abs(disp[2]) < 1e-6
    r1 = x[-1] - x[-1].mean(0)
    U, _, Vt = np.linalg.svd(r0.T @ r1)
    R = Vt.T @ U.T
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(0.5 * alpha[2] * t**2, rel=0.02)
    # Rigid: pairwise distances of a sample of particles change by < 0.1 %.
    idx = np.random.default_rng(0).choice(x.shape[1], 300, replace=False)
    d0 = np.linalg.norm(x[0][idx, None] - x[0][None, idx], axis=-1)
    d1 = np.linalg.norm(x[-1][idx, None] - x[-1][None, idx], axis=-1)
    off = d0 > 0
    assert float((np.abs(d1 - d0)[off] / d0[off]).max()) < 1e-3


def test_rigid_block_lands_and_rests_without_creeping():
    cube = lattice((-0.05, 0.03, -0.05), (0.05, 0.13, 0.05), (8, 8, 8))
    res = simulate(cube, Material.preset("rigid"), Conditions([Ground(0.0, "friction", 0.5)]),
                   SimSettings(frames=13, fps=24, grid_res=10), record_all=True)
    x = res.x.numpy()
    spacing = res.stats["particle_spacing"]
    # It fell onto the ground (lowest particle within half a spacing of y = 0, not below it by more)
    assert abs(float(x[-1][:, 1].min()) - 0.5 * spacing) < 0.6 * spacing
    # and rests flat: no creep or spin from the contact resolution (0.5 mm over the run), and it
    # has come to a stop (the last frames are the same).
    assert np.allclose(x[-1][:, [0, 2]].mean(0), x[0][:, [0, 2]].mean(0), atol=5e-4)
    assert np.allclose(x[-1] - x[-1].mean(0), x[0] - x[0].mean(0), atol=5e-4)
    assert np.allclose(x[-1], x[-3], atol=1e-5)


def test_fracture_splits_one_body_into_pieces():
    # A bread loaf pulled apart by 40 N on each end for 0.3 s (no gravity). Bread tears once
    # stretched 12 %: it ends as at least two separate pieces, each a sizeable part of the loaf.
    # The same pull on an elastic body of the same stiffness only stretches it: one piece.
    loaf = lattice((-0.1, 0.05, -0.03), (0.1, 0.11, 0.03), (12, 4, 4))
    pull = [Force((-40.0, 0, 0), box((-1, -1, -1), (-0.06, 1, 1))), Force((40.0, 0, 0), box((0.06, -1, -1), (1, 1, 1)))]
    s = SimSettings(frames=11, fps=40, grid_res=12, domain_margin=1.5)
    torn = simulate(loaf, Material.preset("bread"), Conditions([NO_GRAVITY, *pull]), s, record_all=True)
    pieces = components(torn.x[-1].numpy(), torn.stats["particle_spacing"])
    assert len(pieces) >= 2 and pieces[1] > 0.2 * sum(pieces), pieces
    assert float(torn.plastic[-1].max()) == 1.0  # some particles are marked torn
    whole = simulate(loaf, Material(name="elastic", model="fixed_corotated", E=5e4, nu=0.2, density=250),
                     Conditions([NO_GRAVITY, *[Force(f.vector, f.region, 0.0, 0.05) for f in pull]]), s,
                     record_all=True)
    assert len(components(whole.x[-1].numpy(), whole.stats["particle_spacing"])) == 1


def test_block_on_sticky_ground_stops_at_once():
    # (Slip and Coulomb friction are checked in test_sim.py: keeps going / stops after v0²/(2μg).)
    blk = lattice((-0.05, 0.01, -0.05), (0.05, 0.06, 0.05), (8, 4, 8))
    res = simulate(blk, Material.preset("jelly", E=1e5),
                   Conditions([Ground(0.0, "sticky"), InitialVelocity(velocity=(1.0, 0.0, 0.0))]),
                   SimSettings(frames=7, fps=24, grid_res=10, domain_margin=2.0), record_all=True)
    x = res.x.numpy()
    bottom = x[0][:, 1] < x[0][:, 1].min() + res.stats["particle_spacing"]
    # The bottom layer is glued: it moves less than half a grid cell, although the block's top
    # lurches forward elastically.
    assert float(np.abs(x[-1][bottom, 0] - x[0][bottom, 0]).max()) < 0.5 * res.stats["dx"]


def test_torque_with_zero_net_force_leaves_the_centre_of_mass_still():
    # A jelly block twisted about y by 0.02 N·m for 0.3 s, no gravity: it spins up, yet its centre
    # of mass must stay put (Σf = 0 exactly); 0.1 mm is float32 round-off over the run.
    blk = lattice((-0.05, 0.2, -0.05), (0.05, 0.3, 0.05), (8, 8, 8))
    res = simulate(blk, Material.preset("jelly", E=1e5), Conditions([NO_GRAVITY, Torque((0.0, 0.02, 0.0))]),
                   SimSettings(frames=13, fps=40, grid_res=10), record_all=True)
    x = res.x.numpy().astype(np.float64)
    com = x.mean(1)
    assert float(np.abs(com - com[0]).max()) < 1e-4
    r0, r1 = x[0] - com[0], x[-1] - com[-1]
    a, b = r0[:, [2, 0]], r1[:, [2, 0]]  # (z, x): rotation about +y
    angle = np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], (a * b).sum(1))
    assert float(np.median(angle)) > 0.1, "the torque must have turned the block"


def test_two_objects_of_different_materials_collide_and_conserve_momentum():
    # A rubber ball-ish block and a jelly block approach at ±1 m/s with no gravity or walls in
    # reach. They meet, bounce and separate: total momentum is conserved by the shared grid
    # (tolerance 1 %, float32 accumulation over ~1000 substeps), and they never pass through
    # each other.
    a = lattice((-0.16, 0.2, -0.04), (-0.08, 0.28, 0.04), (6, 6, 6), object_id=0)
    b = lattice((0.08, 0.2, -0.04), (0.16, 0.28, 0.04), (6, 6, 6), object_id=1)
    g = Gaussians.cat([a, b])
    conds = Conditions([NO_GRAVITY, InitialVelocity((1.0, 0, 0), region=Region(object_id=0)),
                        InitialVelocity((-1.0, 0, 0), region=Region(object_id=1))])
    res = simulate(g, [Material.preset("rubber", E=2e5), Material.preset("jelly", density=500.0)], conds,
                   SimSettings(frames=13, fps=40, grid_res=16, domain_margin=1.0), record_all=True)
    assert res.stats["objects"] == 2
    obj = res.particle_object.numpy()
    x = res.x.numpy().astype(np.float64)
    mass = np.where(obj == 0, 1100.0, 500.0)  # equal particle volumes: mass ∝ density
    v = np.gradient(x, res.times.numpy(), axis=0)
    p = (v * mass[None, :, None]).sum(1)
    scale = np.abs((v[1] * mass[:, None])).sum(0)[0]
    assert np.abs(p[:, 0] - p[1, 0]).max() < 0.01 * scale
    ca, cb = x[:, obj == 0, 0].mean(1), x[:, obj == 1, 0].mean(1)
    assert np.all(ca < cb)
    assert float(x[:, obj == 0, 0].max(1).max()) > -0.08 + 0.02  # they did reach each other
    assert ca[-1] < ca[6] or cb[-1] > cb[6]  # and came apart again


def test_anchors_hold_still_or_move_at_their_velocity_then_release():
    # A jelly bar held fixed at its left end while its right end is pulled at 0.1 m/s for 0.2 s,
    # then released. The held particles move exactly as prescribed (to float32 precision); after
    # the release the right end recoils back towards the bar.
    bar = lattice((-0.1, 0.2, -0.02), (0.1, 0.24, 0.02), (12, 3, 3))
    left, right = box((-1, -1, -1), (-0.08, 1, 1)), box((0.08, -1, -1), (1, 1, 1))
    conds = Conditions([NO_GRAVITY, Anchor(left), Anchor(right, velocity=(0.1, 0.0, 0.0), t_end=0.2)])
    res = simulate(bar, Material.preset("jelly", E=5e4), conds, SimSettings(frames=13, fps=40, grid_res=12),
                   record_all=True)
    x = res.x.numpy().astype(np.float64)
    t = res.times.numpy()
    held_l = x[0][:, 0] < -0.08
    held_r = x[0][:, 0] > 0.08
    assert np.abs(x[:, held_l] - x[0, held_l]).max() < 1e-6
    k = int(np.argmin(np.abs(t - 0.2)))  # frame 8 = 0.2 s: end of the pull
    assert np.allclose(x[k, held_r, 0] - x[0, held_r, 0], 0.1 * t[k], atol=1e-5)
    assert np.allclose(x[k, held_r, 1:], x[0, held_r, 1:], atol=1e-6)
    assert x[-1, held_r, 0].mean() < x[k, held_r, 0].mean() - 1e-3  # released: it springs back


def test_every_preset_is_documented_and_valid():
    from pathlib import Path

    from physmotion_core.types.material import PRESETS

    doc = (Path(__file__).resolve().parent.parent / "docs" / "materials.md").read_text()
    for name in PRESETS:
        m = Material.preset(name)
        assert f"| {name} | {m.model} |" in doc, f"docs/materials.md lacks the '{name}' preset"
        assert m.wave_speed() >= 0


def test_a_rigid_body_spinning_in_place_is_not_at_rest():
    # Regression: rest detection looked at a rigid body's linear velocity only, so a cube spun by
    # a torque stopped being simulated (and froze) three frames after the torque ended.
    blk = lattice((-0.05, 0.2, -0.05), (0.05, 0.3, 0.05), (6, 6, 6))
    res = simulate(blk, Material.preset("rigid"), Conditions([NO_GRAVITY, Torque((0.0, 0.01, 0.0), t_end=0.1)]),
                   SimSettings(frames=16, fps=24, grid_res=8), record_all=True)
    assert res.stats["rest_from_frame"] is None
    x = res.x.numpy().astype(np.float64)
    r = [x[k] - x[k].mean(0) for k in (-3, -2, -1)]
    def cross2(a, b):  # the z of the 2-D cross product (np.cross on 2-D vectors is deprecated in NumPy 2)
        return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]

    turn = [np.arctan2(cross2(r[i][:, [2, 0]], r[i + 1][:, [2, 0]]), (r[i][:, [2, 0]] * r[i + 1][:, [2, 0]]).sum(1))
            for i in range(2)]
    # Still turning at a steady rate in the last frames (no torque, no friction: ω is constant);
    # ω = τ t / I ≈ 0.2 rad/s for this ~2 kg filled cube, 0.0083 rad per frame.
    assert float(np.median(turn[0])) > 0.005
    assert float(np.median(turn[1])) == pytest.approx(float(np.median(turn[0])), rel=0.02)


@pytest.mark.parametrize("b", [0.03, 0.08])  # the SVD-free route (small stretch) and the SVD route
def test_plane_strain_cone_meets_mohr_coulomb_in_plane_strain(b):
    # Sand's Drucker–Prager cone with yield_surface="plane_strain": a plane-strain trial strain
    # (Hencky strains a + b, a, a − b, so the out-of-plane deviator is zero) sheared far past yield
    # is returned to the cone; the stress there has σ2 = (σ1 + σ3)/2 and its Mohr circle touches
    # Mohr–Coulomb's line at the friction angle: (σ1 − σ3) / −(σ1 + σ3) = sin φ (to float32,
    # 1e-4). The triaxial cone (the preset's default) mobilises more than φ in plane strain:
    # sin φ_ps = 3α/√2 with its α, here 1.40× sin φ.
    a = -0.01
    rng = np.random.default_rng(1)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    F = Q @ np.diag(np.exp([a + b, a, a - b])) @ Q.T
    sin_phi = {}
    for surface in ("plane_strain", "triaxial"):
        mat = material_preset("sand", yield_surface=surface)
        out = _map_one(kernel_params(mat), F)
        s = np.linalg.eigvalsh(out.astype(np.float64))  # ascending: σ3 (most compressive) .. σ1
        assert s[1] == pytest.approx(0.5 * (s[0] + s[2]), abs=1e-4 * abs(s).max())
        sin_phi[surface] = (s[2] - s[0]) / -(s[2] + s[0])
    phi = math.sin(math.radians(material_preset("sand").friction_angle))
    assert sin_phi["plane_strain"] == pytest.approx(phi, rel=1e-4)
    t = math.sqrt(2 / 3) * 2 * phi / (3 - phi)
    assert sin_phi["triaxial"] == pytest.approx(3 * t / math.sqrt(2), rel=1e-4)
    with pytest.raises(InputError, match="yield_surface must be"):
        material_preset("sand", yield_surface="cone")
    from physmotion_core.types.material import parse_overrides  # the node's key=value overrides
    assert parse_overrides("yield_surface=plane_strain, friction_angle=30") == {
        "yield_surface": "plane_strain", "friction_angle": 30.0}



@wp.kernel
def _map_kernel(F: wp.array(dtype=wp.mat33), mat: K.MaterialParams, rot: wp.array(dtype=wp.quat),
                plastic: wp.array(dtype=float), Fout: wp.array(dtype=wp.mat33), tau: wp.array(dtype=wp.mat33)):
    K.update_material(mat, F[0], wp.mat33(0.0), rot[0], 0.0, 1.0e-4, 0, rot, plastic, Fout, tau)


def _map_one(params, F):
    """update_material on one deformation gradient (C = 0, state 0): the Kirchhoff stress."""
    dev = "cpu"
    Fw = wp.array(np.asarray(F, np.float32).reshape(1, 3, 3), dtype=wp.mat33, device=dev)
    rot = wp.array(np.array([[0, 0, 0, 1]], np.float32), dtype=wp.quat, device=dev)
    plastic = wp.zeros(1, dtype=float, device=dev)
    Fout = wp.zeros(1, dtype=wp.mat33, device=dev)
    tau = wp.zeros(1, dtype=wp.mat33, device=dev)
    wp.launch(_map_kernel, dim=1, inputs=[Fw, params, rot, plastic, Fout, tau], device=dev)
    return tau.numpy()[0]


@pytest.mark.parametrize("model", ["viscoplastic", "fluid"])
def test_sheared_layer_on_sticky_ground_slows_at_its_stated_viscosity(model):
    # Issue 37. A layer of thickness H slides at U over a sticky ground (no gravity; its top is
    # free): its velocity decays as a sum of modes sin((2n+1) π y / 2H), the slowest at the rate of
    # the mode k² = (π/2H)²: η k²/ρ for a Newtonian liquid (the fluid model, η = 10 Pa·s), the slow
    # root of s² + s μ/η + μ k²/ρ = 0 for honey (a Maxwell liquid, relaxation time η/μ; yield stress
    # lowered to 1e-3 Pa). Measured on the middle third of a slab six times longer than thick (its
    # free ends shear only the layer near them), fitted from 0.04 s (the next mode decays 9x faster).
    # Tolerance 12 %: the layer is 4.5 cells thick, the sticky wall sits on the ground node and the
    # free top is known to half a particle spacing (5 % of H); measured +5.4 % (honey), +1.9 %
    # (fluid), and -3 %, -4 % at twice the resolution. Before the fix honey slowed at half the rate.
    from physmotion_core.validate.cases import maxwell_decay_rate
    if model == "fluid":
        mat = Material(name="liquid", model="fluid", E=1.0, nu=0.0, density=1400.0, bulk_modulus=5000.0, gamma=7.0,
                       viscosity=10.0)
    else:
        mat = material_preset("honey", yield_stress=1e-3)
    L, h = 0.24, 0.04
    slab = lattice((-L / 2, 0.0, -0.01), (L / 2, h, 0.01), (61, 11, 6))
    res = simulate(slab, mat, Conditions([NO_GRAVITY, Ground(0.0, "sticky"), InitialVelocity(velocity=(0.05, 0, 0))]),
                   SimSettings(frames=26, fps=100, grid_res=24, domain_margin=0.3, rest_speed=0.0), record_all=True)
    x = res.x.numpy().astype(np.float64)
    H = float(x[0][:, 1].max()) + 0.5 * res.stats["particle_spacing"]
    mid = np.abs(x[0][:, 0]) < L / 6
    t = res.times.numpy()
    v = (x[2:, mid, 0].mean(1) - x[:-2, mid, 0].mean(1)) / (t[2:] - t[:-2])
    sel = t[1:-1] >= 0.04
    rate = -float(np.polyfit(t[1:-1][sel], np.log(v[sel]), 1)[0])
    k2 = (math.pi / (2 * H)) ** 2
    expected = maxwell_decay_rate(mat.viscosity, mat.mu if model == "viscoplastic" else math.inf, mat.density, k2)
    assert rate == pytest.approx(expected, rel=0.12)


@pytest.mark.parametrize("degrees", [24.2, 30.0])
def test_rigid_block_on_a_coulomb_slope_holds_below_mu_and_slides_at_the_right_rate_above(degrees):
    # Issue 37. The slope is gravity tilted by θ about z (downhill +x), the ground Coulomb μ = 0.5,
    # which holds up to tan θ = μ (26.6°). At 24.2° (0.9 μ) the block must travel under half a cell
    # in 1 s (measured 0.12 cell, MPMSolver; the rest of the grid's settling); at 30° it slides with
    # a = g (sin θ − μ cos θ) = 0.657 m/s², so travels a t²/2 from rest: 5 % covers the first frame,
    # where it settles onto the ground (measured 0.03 % by the validate case's fit).
    th = math.radians(degrees)
    cube = lattice((-0.05, 0.0, -0.05), (0.05, 0.05, 0.05), (9, 5, 9))
    g = Gravity((9.81 * math.sin(th), -9.81 * math.cos(th), 0.0))
    res = simulate(cube, Material.preset("rigid"), Conditions([g, Ground(0.0, "friction", 0.5)]),
                   SimSettings(frames=11, fps=10, grid_res=10, domain_margin=4.0, rest_speed=0.0), record_all=True)
    x = res.x.numpy().astype(np.float64)
    travel = x[:, :, 0].mean(1) - x[0, :, 0].mean()
    if degrees < 26.0:
        assert abs(travel[-1]) < 0.5 * res.stats["dx"]
    else:
        t = res.times.numpy()
        a = 9.81 * (math.sin(th) - 0.5 * math.cos(th))
        assert travel[-1] == pytest.approx(0.5 * a * t[-1] ** 2, rel=0.05)


@pytest.mark.parametrize("degrees", [24.2, 30.0])
def test_stiff_jelly_block_on_a_coulomb_slope_holds_below_mu_and_slides_at_the_right_rate_above(degrees):
    # Issue 37. As the rigid block above, for a jelly of E = 2e5 Pa (ν as the preset), which crept
    # ~50 mm/s at 24.2° (0.9 μ; 5 cells in 1 s), hopping at ~11 Hz, until the contact layer's
    # transfer dropped APIC's affine part (kernels.p2g). Hold: under half a cell in 1 s, the issue's
    # bound (measured 0.26 cell by the validate case: the block settles in its first ~0.3 s, then
    # stands still). Slide: a t²/2 within 5 % (the validate case's fit: +1.3 % at 30°; the start,
    # where the block settles onto the ground, and its ringing).
    th = math.radians(degrees)
    cube = lattice((-0.05, 0.0, -0.05), (0.05, 0.05, 0.05), (9, 5, 9))
    g = Gravity((9.81 * math.sin(th), -9.81 * math.cos(th), 0.0))
    res = simulate(cube, material_preset("jelly", E=2.0e5), Conditions([g, Ground(0.0, "friction", 0.5)]),
                   SimSettings(frames=11, fps=10, grid_res=10, domain_margin=4.0, rest_speed=0.0), record_all=True)
    x = res.x.numpy().astype(np.float64)
    travel = x[:, :, 0].mean(1) - x[0, :, 0].mean()
    if degrees < 26.0:
        assert abs(travel[-1]) < 0.5 * res.stats["dx"], (travel[-1], res.stats["dx"])
    else:
        t = res.times.numpy()
        a = 9.81 * (math.sin(th) - 0.5 * math.cos(th))
        assert travel[-1] == pytest.approx(0.5 * a * t[-1] ** 2, rel=0.05)


@pytest.mark.parametrize("v0", [0.0, 0.05])
def test_tall_stiff_jelly_block_holds_on_a_coulomb_slope_at_0_9_mu(v0):
    # Issue 37, tall bodies: a 0.15 x 0.1 x 0.05 m jelly block (E = 2e5 Pa), 10 cells tall at grid_res 15, on
    # a μ = 0.5 slope at 24.2° (0.9 μ). Before the ground's friction kept the budget a column left unused
    # (kernels.static_friction) it crept without end, its vertical ringing kept up by the friction: 60 mm in
    # 1 s released at rest (measured), 63 mm given 0.05 m/s, still sliding at 1 s; now 1.5 mm, and 11.1 mm
    # (where a rigid block stops after v0² / (2 g (μ cos θ − sin θ)) = 2.8 mm: the tall body's ringing still
    # costs it friction while it slides, docs/accuracy.md "Friction on a slope"). Released at rest it must
    # travel under half a cell in 1 s, the bound (the elastic shear of a 10-cell block under its
    # own weight moves its centre of mass by ~0.2 mm). Kicked it must come to rest: the last 0.3 s move it
    # by under a tenth of a cell (0.01 mm measured; the creep moved it 6 mm every 0.1 s), after at least
    # the rigid block's distance and under two cells (a guard on the measured 11.1 mm, not Coulomb's answer).
    th = math.radians(24.2)
    blk = lattice((-0.075, 0.0, -0.025), (0.075, 0.1, 0.025), (13, 9, 5))
    conds = [Gravity((9.81 * math.sin(th), -9.81 * math.cos(th), 0.0)), Ground(0.0, "friction", 0.5)]
    if v0:
        conds.append(InitialVelocity((v0, 0.0, 0.0)))
    res = simulate(blk, material_preset("jelly", E=2.0e5), Conditions(conds),
                   SimSettings(frames=11, fps=10, grid_res=15, domain_margin=2.0, rest_speed=0.0), record_all=True)
    x = res.x.numpy().astype(np.float64)
    travel = x[:, :, 0].mean(1) - x[0, :, 0].mean()
    dx = res.stats["dx"]
    assert round(0.1 / dx) == 10
    if v0 == 0.0:
        assert abs(travel[-1]) < 0.5 * dx, (travel[-1], dx)
    else:
        stop = v0 ** 2 / (2 * 9.81 * (0.5 * math.cos(th) - math.sin(th)))
        assert stop < travel[-1] < 2.0 * dx, (travel[-1], stop)
        assert abs(travel[-1] - travel[-4]) < 0.1 * dx, travel


def test_block_resting_on_coulomb_ground_starts_sliding_when_pushed_past_friction():
    # The price of the ground friction's memory (kernels.static_friction): a column at rest banks the budget
    # it leaves unused, up to τ μ N with τ = 4 H / c (12.5 ms for this 5 cm jelly block, c ≈ 16 m/s), so a
    # push past friction may start the slide up to τ late. A jelly block resting 0.3 s on flat ground
    # (μ = 0.5), then pushed at F ≈ 2 μ M g, slides with a = F / M − μ g: over the next 0.2 s it covers
    # a t²/2 less at most 2 τ / t (12.5 %) for that delay. Measured −4.5 % (+2.4 % without the memory:
    # the grid's settling).
    blk = lattice((-0.05, 0.0, -0.05), (0.05, 0.05, 0.05), (9, 5, 9))
    mu, g = 0.5, 9.81
    F = 2.0 * mu * g * 0.6  # the block's mass is ~0.6-0.7 kg; the test uses the one simulate() reports
    conds = Conditions([Ground(0.0, "friction", mu), Force((F, 0.0, 0.0), t_start=0.3)])
    res = simulate(blk, material_preset("jelly", E=2.0e5), conds,
                   SimSettings(frames=11, fps=20, grid_res=10, domain_margin=4.0, rest_speed=0.0), record_all=True)
    x = res.x.numpy().astype(np.float64)
    com = x[:, :, 0].mean(1)
    t = res.times.numpy()
    i0 = int(np.argmin(abs(t - 0.3)))
    assert abs(com[i0] - com[0]) < 0.5 * res.stats["dx"]  # it rested until the push
    a = F / res.stats["mass_kg"] - mu * g
    expected = 0.5 * a * (t[-1] - t[i0]) ** 2
    assert expected * (1 - 0.125) < com[-1] - com[i0] < expected * 1.05, (com[-1] - com[i0], expected)
