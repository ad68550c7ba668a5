"""Elastic bodies survive hard hits (issue 22): a jelly cube thrown into a slip wall at 10 m/s, or
shoved by 500 N into a wall 4 cm away, must not stay crushed. Measured through ``simulate()`` from
the particles' det F (their elastic volume ratio) and from the positions' bounding box, after the
impact is over. Before the fixed-corotated model got its log-barrier volumetric term, both runs
ended as sheets with det F ~ 0 (docs/materials.md)."""

import numpy as np

from physmotion_core.types.material import material_preset
from physmotion_core.sim.simulate import simulate
from physmotion_core.types import Conditions, Force, Ground, InitialVelocity, SimSettings, Walls
from physmotion_core.validate.stress import _check_completed, gaussian_box

VOLUME_TOL = 0.05


def _cube():
    return gaussian_box((-0.05, 0.02, -0.05), (0.05, 0.12, 0.05), (10, 10, 10))


def _check_volume(res, first_frame):
    """After the impact: no particle inverted, the mean det F of every frame within 12 % of 1 (the
    undamped jelly still rings) and its average over those frames, the volume it rings about,
    within 5 % (the issue's tolerance); the body's core (10th-90th percentile extent) never thinner than
    half its size. The ringing bound was 8 % until the uniform fill of issue 22 gave the cube its true
    volume, about 9 % less mass than before, so the same 500 N shoves it harder: one frame dips to 0.895
    (0.942 with the old fill's mass; measured)."""
    J = np.linalg.det(res.F.numpy().astype(np.float64))
    mean_j = J[first_frame:].mean(axis=1)
    assert J.min() > 0.0
    assert np.all(np.abs(mean_j - 1.0) < 0.12), mean_j
    assert abs(mean_j.mean() - 1.0) < VOLUME_TOL, mean_j
    x = res.x.numpy()[first_frame:]
    core = np.percentile(x, 90, axis=1) - np.percentile(x, 10, axis=1)
    assert core.min() > 0.5 * 0.08, core  # the rest core is 0.08 m across
    ok, why, _ = _check_completed(res)
    assert ok, why


def _run(conds, frames, margin):
    s = SimSettings(frames=frames, fps=24.0, grid_res=12, particles_per_cell=1, domain_margin=margin,
                    device="cpu", rest_speed=0.0)
    return simulate(_cube(), material_preset("jelly"), conds, s, record_all=True)


def test_jelly_thrown_into_a_slip_wall_keeps_its_volume():
    res = _run(Conditions([Ground(0.0, "slip"), Walls("slip"), InitialVelocity((10.0, -10.0, 0.0))]), 16, 0.5)
    _check_volume(res, 6)


def test_jelly_shoved_into_a_wall_recovers_its_volume():
    # 500 N for 0.2 s towards the +x wall 4 cm away (domain_margin 0.4 of the 10 cm cube).
    conds = Conditions([Ground(0.0, "slip"), Walls("slip"), Force((500.0, 0.0, 0.0), t_start=0.0, t_end=0.2)])
    res = _run(conds, 16, 0.4)
    _check_volume(res, 8)  # the push ends at frame 4.8


def test_stability_check_flags_a_crushed_body():
    res = _run(Conditions([Ground(0.0, "slip"), InitialVelocity((0.0, -1.0, 0.0))]), 2, 0.5)
    assert _check_completed(res)[0]
    res.F[-1] = res.F[-1] * 0.1  # det F = 1e-3: a sheet
    ok, why = _check_completed(res)[:2]
    assert not ok and "volume" in why
    res.F[-1, 0] = -res.F[-1, 0]
    ok, why = _check_completed(res)[:2]
    assert not ok and "det F" in why


def test_rubber_thrown_at_1000_m_per_s_is_never_inverted_and_recovers():
    """Rubber (neo-Hookean) thrown at 1e3 m/s into the domain's walls (the stress matrix's case): the impact
    inverted particles (det F = -150 in frame 1) before a crushed particle was reset to MIN_J of its volume
    with its rotation kept. Now no particle's det F is ever <= 0, the body ends with its mean det F within
    [1/2, 2] (the stress matrix's rule), and the energy never exceeds its start (``_check_completed``)."""
    from physmotion_core.validate.stress import _cube as stress_cube, _settings

    res = simulate(stress_cube(), material_preset("rubber"),
                   Conditions([Ground(0.0, "slip"), InitialVelocity((1e3, -1e3, 0.0))]), _settings(), record_all=True)
    J = np.linalg.det(res.F.numpy().astype(np.float64))
    assert J.min() > 0.0
    assert 0.5 <= J[-1].mean() <= 2.0, J[-1].mean()
    ok, why, _ = _check_completed(res)
    assert ok, why
