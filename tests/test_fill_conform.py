"""fill_particles(conform=True): where surface splats bound a solid, no particle sits outside the surface and
the outermost ones sit half a spacing inside it, along its normal (fill._conform).

Why: a flat splat marks a voxel-thick sheet, so the voxel lattice's outer layer stuck out of a shell of
splats by up to 0.8 spacings (its mass was right, ``_volumes``, but the particles were not where the body
is), and on a round body the outer layer made a polygon of flats: a rigid disc pushed along Coulomb ground
rocked on its bottom flat instead of rolling (docs/accuracy.md, "Rolling"). Measured here (2026-12-07):
a 0.2 m sphere of splats, outer layer's radius against R - s/2: mean +0.50 / +0.39 spacings at 12 / 24
voxels across, now -0.05 / -0.05 (sd 0.14); a slab's faces 0.6 spacings outside, now 0.4 inside; a 0.3 m disc
rolls 91 mm in 0.5 s from 0.3 m/s (a cylinder rolling without slip: 101 mm), 3 mm before. simulate() uses it for rigid bodies only (see the docs).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.bench_mass import shell, slab_shell, sphere_shell  # noqa: E402

from physmotion_core.sim.fill import fill_particles  # noqa: E402


def cylinder_shell(R: float = 0.15, T: float = 0.06, h: float = 0.004):
    """Flat splats every ``h`` over a disc R in radius and T thick, its axis along z, standing on y = 0."""
    pts, nrm = [], []
    na = int(2 * math.pi * R / h)
    a = (np.arange(na) + 0.5) * 2 * math.pi / na
    for z in -T / 2 + (np.arange(int(T / h)) + 0.5) * h:
        pts.append(np.stack([R * np.cos(a), R + R * np.sin(a), np.full(na, z)], 1))
        nrm.append(np.stack([np.cos(a), np.sin(a), 0 * a], 1))
    g1, g2 = np.meshgrid(np.arange(-R + h / 2, R, h), np.arange(-R + h / 2, R, h), indexing="ij")
    inside = g1**2 + g2**2 <= R * R
    for sgn in (-1.0, 1.0):
        p = np.stack([g1[inside], R + g2[inside], np.full(inside.sum(), sgn * T / 2)], 1)
        pts.append(p)
        nrm.append(np.tile([0.0, 0.0, sgn], (len(p), 1)))
    return shell(np.concatenate(pts), np.concatenate(nrm), h)


@pytest.mark.parametrize("across", [12, 24])
def test_a_sphere_of_splats_has_its_outer_layer_half_a_spacing_inside_its_surface(across):
    g, V, extent = sphere_shell()
    R, s = 0.1, extent / across
    dev = {}
    for conform in (False, True):
        ps = fill_particles(g, s, conform=conform)
        r = np.linalg.norm(ps.x.astype(np.float64), axis=1)
        outer = r > R - s
        dev[conform] = (r[outer] - (R - s / 2)) / s
        if conform:
            # the same mass: the solid's volume is shared by fewer particles
            assert float(ps.volume.astype(np.float64).sum()) == pytest.approx(vol_before, rel=1e-6)
            assert (R - r).min() >= 0.0  # none outside (measured 0.50 / 0.24 spacings inside at the least)
        else:
            vol_before = float(ps.volume.astype(np.float64).sum())
    assert dev[False].mean() > 0.3, dev[False].mean()  # the lattice's layer stuck out (measured +0.50 / +0.39)
    assert abs(dev[True].mean()) <= 0.1 and dev[True].std() <= 0.25, (dev[True].mean(), dev[True].std())


def test_a_slabs_faces_are_half_a_spacing_inside_and_a_box_of_volume_gaussians_is_left_on_its_lattice():
    from physmotion_core.validate.stress import gaussian_box

    g, _, extent = slab_shell(0.0)  # 0.3 x 0.2 x 0.05 m, faces on the axes
    s = extent / 24
    half = np.array([0.15, 0.1, 0.025])
    for conform, want, tol in ((False, 0.6, 0.1), (True, -0.45, 0.1)):  # measured 0.60 and -0.40 to -0.42
        x = fill_particles(g, s, conform=conform).x.astype(np.float64)
        for ax in range(3):
            for got in (x[:, ax].max(), -x[:, ax].min()):
                assert (got - half[ax]) / s == pytest.approx(want, abs=tol), (conform, ax, got)
    box = gaussian_box((-0.05, 0.0, -0.05), (0.05, 0.1, 0.05), (8, 8, 8))
    a, b = fill_particles(box, 0.01), fill_particles(box, 0.01, conform=True)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.volume, b.volume)


def test_a_rigid_disc_of_splats_pushed_along_the_ground_rolls():
    """A solid cylinder from v0 = 0.3 m/s on μ = 0.5 slips for v0 / (3 μ g) = 20 ms, then rolls at 2/3 v0:
    0.101 m in 0.5 s, turning by that over R. Lattice fill: it rocks on its bottom flat (3 mm)."""
    from physmotion_core.sim.mpm import MPMSolver
    from physmotion_core.types.conditions import Ground
    from physmotion_core.types.material import material_preset
    from physmotion_core.validate.harness import box_domain, run_sampled

    R, v0, mu, g_acc, t = 0.15, 0.3, 0.5, 9.81, 0.5
    t1 = v0 / (3 * mu * g_acc)
    want = v0 * t1 - 0.5 * mu * g_acc * t1**2 + 2 / 3 * v0 * (t - t1)
    dx = 2 * R / 16
    g = cylinder_shell(R)
    got = {}
    for conform in (False, True):
        ps = fill_particles(g, dx / 2, conform=conform, floor=0.0)
        x = ps.x.astype(np.float64)
        ground = Ground(0.0, "friction", mu)
        dom = box_domain((-0.3, 0.0, -0.1), (0.6, 0.45, 0.1), dx, ground=ground)
        sol = MPMSolver(x, ps.volume, np.zeros(len(x), np.int64), [material_preset("rigid")], dom, ground=ground,
                        v0=np.tile([v0, 0.0, 0.0], (len(x), 1)).astype(np.float32), body=np.zeros(len(x), np.int64))
        m = sol.mass_np.astype(np.float64)
        (p,) = run_sampled(sol, [t], lambda S: S.positions().astype(np.float64), max_dt=1 / 24 / 8)
        c0, c = (x * m[:, None]).sum(0) / m.sum(), (p * m[:, None]).sum(0) / m.sum()
        a, b = x[:, :2] - c0[:2], p[:, :2] - c[:2]
        turn = -math.atan2((a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum(), (a * b).sum())
        got[conform] = (c[0] - c0[0], turn * R)
    assert got[False][0] < 0.1 * want, got  # rocks on its flat (measured 3 mm)
    travel, rolled = got[True]
    assert 0.7 * want <= travel <= 1.05 * want, (travel, want)  # measured 0.091 m of 0.101
    assert rolled == pytest.approx(travel, rel=0.1), got  # it rolls: the turn matches the travel


def test_simulate_fills_rigid_bodies_to_their_surface_and_deformable_ones_on_the_lattice():
    """simulate() (and the preview's body_facts, which must weigh what it simulates) turns conform on for rigid
    bodies only: a deformable body's stress wants the lattice's equal spacing (docs/accuracy.md, "Rolling")."""
    from physmotion_core.feedback import body_facts
    from physmotion_core.sim import simulate
    from physmotion_core.types import Conditions, Ground, SimSettings
    from physmotion_core.types.material import material_preset

    g, _, _ = sphere_shell()
    g.means[:, 1] += 0.1  # resting on y = 0
    R, ground = 0.1, Ground(0.0, "friction", 0.5)
    for name, inside in (("rigid", True), ("jelly", False)):
        st = SimSettings(frames=1, device="cpu")
        res = simulate(g, material_preset(name), Conditions([ground]), st, record_all=True)
        x = res.rest_particles.numpy().astype(np.float64)
        s = float(res.stats["particle_spacing"])
        r = np.linalg.norm(x - [0.0, 0.1, 0.0], axis=1)
        assert (r.max() <= R) == inside, (name, (r.max() - R) / s)  # the lattice's layer sticks out
        facts = body_facts(g, material_preset(name), st, ground)
        assert np.array_equal(facts.x, res.rest_particles.numpy()), name


def test_the_packs_ball_photo_thrown_along_the_ground_rolls_like_a_ball():
    """photos/ball.png lifted (a ball: ``silhouette.is_ball``) and simulated rigid from 0.4 m/s on μ = 0.5: a solid
    sphere slips for 2 v0 / (7 μ g) = 23 ms, then rolls at 5/7 v0: 0.289 m in 1 s, turning that over its radius.
    Before (a pillow on the lattice) it slid 7 mm and stopped; the pillow filled to its surface rolled 141 mm and
    then fell over onto its face; measured now 254 mm."""
    from PIL import Image

    from physmotion_core.lift.silhouette import silhouette_lift
    from physmotion_core.sim import simulate
    from physmotion_core.types import Conditions, Ground, InitialVelocity, SimSettings
    from physmotion_core.types.material import material_preset

    rgba = np.asarray(Image.open(Path(__file__).resolve().parents[1] / "photos" / "ball.png").convert("RGBA"))
    lift = silhouette_lift(rgba[..., :3].astype(np.float32) / 255, (rgba[..., 3] > 127).astype(np.float32),
                           object_height=0.3, fit_colors=False)
    assert lift.info["ball"]
    v0, mu, g_acc, t = 0.4, 0.5, 9.81, 1.0
    t1 = 2 * v0 / (7 * mu * g_acc)
    want = v0 * t1 - 0.5 * mu * g_acc * t1**2 + 5 / 7 * v0 * (t - t1)
    res = simulate(lift.gaussians, material_preset("rigid"),
                   Conditions([Ground(0.0, "friction", mu), InitialVelocity((v0, 0.0, 0.0))]),
                   SimSettings(frames=25, fps=24, device="cpu"), record_all=True)
    x = res.x.numpy().astype(np.float64)
    travel = x[-1].mean(0) - x[0].mean(0)
    assert 0.75 * want <= travel[0] <= 1.05 * want, (travel, want)
    assert abs(travel[2]) < 0.1 * travel[0] and abs(travel[1]) < 0.01, travel  # along x, on the ground


def test_a_round_rigid_body_pushed_below_friction_is_told_it_rolls_and_it_rolls():
    """A ball pushed sideways through its centre rolls under any push on a ground that grips: friction turns it
    (a = 5/7·F/m) instead of holding it. The forecast said "static friction holds ... it will not slide" for a
    push under μ·m·g (bench_forecast's rigid disc, lifted as a ball, rolled). photos/ball.png, rigid, μ = 0.5,
    pushed with 0.4·μ·m·g for 0.25 s: after 0.5 s it has rolled ½·a·t1² + a·t1·(t - t1) (measured 0.109 m of 0.131)."""
    from PIL import Image

    from physmotion_core.feedback import BodyFacts, body_facts, forecast
    from physmotion_core.lift.silhouette import silhouette_lift
    from physmotion_core.sim import simulate
    from physmotion_core.types import Conditions, Force, Ground, SimSettings
    from physmotion_core.types.material import material_preset

    rgba = np.asarray(Image.open(Path(__file__).resolve().parents[1] / "photos" / "ball.png").convert("RGBA"))
    lift = silhouette_lift(rgba[..., :3].astype(np.float32) / 255, (rgba[..., 3] > 127).astype(np.float32),
                           object_height=0.3, fit_colors=False)
    mat, mu, g_acc, t1, t = material_preset("rigid"), 0.5, 9.81, 0.25, 0.5
    ground = Ground(0.0, "friction", mu)
    settings = SimSettings(frames=13, fps=24, device="cpu")
    facts = body_facts(lift.gaussians, mat, settings, ground)
    m = facts.total_mass
    F = 0.4 * mu * m * g_acc
    conds = Conditions([ground, Force((F, 0.0, 0.0), t_start=0.0, t_end=t1)])
    text = " ".join(forecast(conds, facts, mat, clip_s=t, camera=lift.camera))
    assert "it is round: it rolls rather than slides or tips" in text and "will not slide" not in text, text
    assert "skids" not in text  # 0.4·μ·m·g is under 3.5·μ·m·g
    # the same push on a block of its weight: static friction holds it
    block = BodyFacts(np.stack(np.meshgrid(*[np.linspace(-0.1, 0.1, 9)] * 3, indexing="ij"), -1).reshape(-1, 3)
                      + [0.0, 0.1, 0.0], np.full(729, m / 729), 0.025)
    assert "will not slide" in " ".join(forecast(conds, block, mat, clip_s=t))
    res = simulate(lift.gaussians, mat, conds, settings, record_all=True)
    x = res.x.numpy().astype(np.float64)
    a = 5.0 / 7.0 * F / m
    want = 0.5 * a * t1**2 + a * t1 * (t - t1)
    travel = x[-1].mean(0) - x[0].mean(0)
    assert 0.7 * want <= travel[0] <= 1.1 * want, (travel, want)
