"""A soft body leans before it tips, a tall soft one cannot stand, and a body that slides does not tip
(feedback.lean / tipping / stand_line; issue 33, item 5: what a push will roughly do).

The beam model is checked against closed forms (Timoshenko's cantilever under an even load, Greenhill's
self-weight buckling of a column); the forecast's words against the simulation (quality draft, the
silhouette lift of a drawn bar or box on a plain photo, as a user's photo is lifted): a 0.3 m jelly bar
at E = 20 kPa falls over with no push and the forecast says it cannot stand, at E = 100 kPa it stands;
a push between the soft body's and the rigid body's tipping force tips it and the forecast says it may;
a rigid block wider than μ times its height pushed past friction slides and does not tip, as forecast.
The wider comparison (cup, disc and bar; jelly, stiffer jelly, rigid) is benchmarks/bench_forecast.py.
"""

import math

import numpy as np
import pytest
import torch

from physmotion_core.feedback import (BASE_BAND, STAND_WARN, BodyFacts, body_facts, forecast, lean, stand_line,
                                      tipping)
from physmotion_core.types import Conditions, Force, Ground, Material, SimSettings


def block(a=0.08, t=0.06, L=0.4, s=0.005, rho=1000.0):
    """Particles on a lattice of spacing ``s`` filling an a (x) by L (y) by t (z) block standing at y = 0."""
    gx, gy, gz = (np.arange(int(round(d / s))) * s + s / 2 for d in (a, L, t))
    x = np.stack(np.meshgrid(gx, gy, gz, indexing="ij"), -1).reshape(-1, 3)
    return x, np.full(len(x), rho * s ** 3)


def _beam_part(x, s):
    """The share of the particles above the base band and the length of the beam they make."""
    y = x[:, 1]
    up = y > y.min() + BASE_BAND * np.ptp(y)
    n = int(np.floor((y[up].max() - y[up].min()) / s)) + 1
    return up.mean(), n * s


def test_lean_of_a_uniform_block_is_timoshenkos_cantilever_under_an_even_load():
    a, t, s = 0.08, 0.06, 0.005
    x, m = block(a=a, t=t, s=s)
    mat = Material.preset("jelly")
    got = lean(x, m, mat, np.array([1.0, 0.0]), m / m.sum(), g=0.0)
    f, L = _beam_part(x, s)
    I, A = t * a ** 3 / 12, a * t
    # mean deflection of a cantilever under an even load F: F·L³/(20·E·I) bending + F·L/(3·κ·G·A) shear;
    # the load on the beam and the mass averaged over are both the share f above the base band
    want = f * f * (L ** 3 / (20 * mat.E * I) + L / (3 * 5 / 6 * mat.mu * A))
    assert got.buckling == 0.0
    assert got.compliance == pytest.approx(want, rel=0.06)
    # across the thin side (I smaller by (a/t)²) it gives more, as the closed form does
    across = lean(x, m, mat, np.array([0.0, 1.0]), m / m.sum(), g=0.0).compliance
    I2 = a * t ** 3 / 12
    assert across == pytest.approx(f * f * (L ** 3 / (20 * mat.E * I2) + L / (3 * 5 / 6 * mat.mu * A)), rel=0.06)


def test_a_uniform_column_buckles_under_its_weight_at_greenhills_height():
    a, t, s = 0.05, 0.05, 0.005
    x, m = block(a=a, t=t, L=0.4, s=s)
    _, L = _beam_part(x, s)
    I, A = t * a ** 3 / 12, a * t
    for E in (2e4, 5e4, 1e5):
        mat = Material.preset("jelly", E=E)
        got = lean(x, m, mat, np.array([1.0, 0.0]), m / m.sum(), g=9.81)
        Lc = (7.837 * E * I / (mat.density * 9.81 * A)) ** (1 / 3)  # Greenhill (1881)
        assert got.buckling == pytest.approx((L / Lc) ** 3, rel=0.08), E
        if got.buckling < 1:
            # the weight's sway adds to the lean: more than without gravity, by about 1/(1 - ratio)
            free = lean(x, m, mat, np.array([1.0, 0.0]), m / m.sum(), g=0.0).compliance
            assert free < got.compliance < 1.3 * free / (1 - got.buckling)
        else:
            assert math.isinf(got.compliance)


def test_the_stiffness_the_stability_line_asks_for_makes_the_body_stand():
    x, m = block(a=0.05, t=0.05, L=0.4, s=0.005)
    facts = BodyFacts(x, m, dx=0.01)
    soft = Material.preset("jelly", E=2e4)
    text = stand_line(soft, facts, 9.81)
    assert "cannot hold up" in text and "without any push" in text
    E_ok = float(text.split("E above about ")[1].split(" Pa")[0])
    stiff = Material.preset("jelly", E=E_ok)
    ratio = lean(x, m, stiff, np.array([1.0, 0.0]), m / m.sum()).buckling
    assert ratio == pytest.approx(STAND_WARN, rel=0.05)  # (its text rounds E to 2 digits)
    assert stand_line(Material.preset("jelly", E=4 * E_ok), facts, 9.81) == ""
    assert stand_line(Material.preset("rigid"), facts, 9.81) == ""  # a rigid body has no lean
    assert stand_line(Material.preset("honey"), facts, 9.81) == ""  # a liquid: the flow line speaks


# -- through the simulation --------------------------------------------------------------------------


def _photo(kind):
    from benchmarks.bench_forecast import synthetic

    im, mask = synthetic(kind)
    return im, torch.from_numpy(mask)


def _run(kind, material, force=0.0):
    """(forecast text, largest tilt from upright in degrees) of the drawn object pushed sideways for 0.25 s;
    ``force`` in newtons, or a function of the rigid body's tipping force."""
    from physmotion_core.pipeline import prepare
    from physmotion_core.sim.simulate import simulate

    im, mask = _photo(kind)
    settings = SimSettings(frames=40, fps=24.0, quality="draft")
    prep = prepare(im, mask=mask, material=material, settings=settings, report=lambda s: None, _weigh=False)
    facts = body_facts(prep.gaussians, material, settings, prep.conditions.ground())
    if callable(force):
        force = force(tipping(facts, np.array([1.0, 0.0]), np.ones(len(facts.x), bool), 9.81, 0.25).need)
    conds = Conditions(([Force((force, 0.0, 0.0), t_start=0.0, t_end=0.25)] if force else [])
                       + list(prep.conditions))
    text = " ".join(forecast(conds, facts, material, clip_s=39 / 24, camera=prep.camera))
    x = simulate(prep.gaussians, material, conds, settings, camera=prep.camera).x.numpy().astype(np.float64)
    a = x[0] - x[0].mean(0)
    tilt = 0.0
    for xt in x:
        u, _, vt = np.linalg.svd(a.T @ (xt - xt.mean(0)))
        r = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
        tilt = max(tilt, math.degrees(math.acos(min(1.0, max(-1.0, r[1, 1])))))
    return text, tilt


def test_a_tall_jelly_bar_cannot_stand_and_falls_with_no_push_and_a_stiffer_one_stands():
    text, tilt = _run("bar", Material.preset("jelly", E=2e4))
    assert "cannot hold up a body" in text
    assert tilt > 60.0  # it bends over and falls with no force at all
    text, tilt = _run("bar", Material.preset("jelly", E=1e5))
    assert "cannot hold up" not in text and "only just holds up" in text
    assert tilt < 15.0


def test_a_push_between_the_soft_and_the_rigid_tipping_force_tips_a_jelly_as_forecast():
    mat = Material.preset("jelly", E=1e5)
    # in proportion to the rigid body's tipping force (4.6 N on the draft lattice; the leaning jelly's 2.1 N)
    text, tilt = _run("bar", mat, force=lambda rigid: 0.52 * rigid)
    assert "may tip over" in text and "leans about" in text
    assert tilt > 60.0
    text, tilt = _run("bar", mat, force=lambda rigid: 0.25 * rigid)
    assert "rocks but does not tip" in text and "a rigid body would need" in text
    assert tilt < 19.0  # its tipping angle, atan(b/h)


def test_a_wide_rigid_block_pushed_past_friction_slides_and_does_not_tip():
    mat = Material.preset("rigid")
    # wider than μ times its height (b/h = 2 > 0.5): pushed at 1.3 times F·h = m·g·b, friction cannot turn it
    text, tilt = _run("box", mat, force=lambda need: 1.3 * need)
    assert "slides rather than tips" in text and "can tip over" not in text
    assert tilt < 5.0


def test_a_held_body_is_not_told_it_cannot_stand():
    x, m = block(a=0.05, t=0.05, L=0.4, s=0.005)
    facts = BodyFacts(x, m, dx=0.01)
    soft = Material.preset("jelly", E=2e4)
    on_ground = Conditions([Ground(0.0, "friction", 0.5)])
    assert any("cannot hold up" in s for s in forecast(on_ground, facts, soft, clip_s=2.0))
    # held where the photo's edge cuts it off, or without a ground, no column stands on anything
    assert not any("cannot hold up" in s for s in forecast(on_ground, facts, soft, clip_s=2.0, held=True))
    assert not any("cannot hold up" in s for s in forecast(Conditions([]), facts, soft, clip_s=2.0))


# -- balance: the centre of mass over what the body stands on --------------------------------------------


def _table(leg_at):
    """A 0.4 x 0.05 x 0.1 m slab on one leg 0.04 x 0.2 x 0.1 m, under the slab at ``leg_at`` (m from its left)."""
    s = 0.005
    slab, m1 = block(a=0.4, t=0.1, L=0.05, s=s)
    slab[:, 1] += 0.2
    leg, m2 = block(a=0.04, t=0.1, L=0.2, s=s)
    leg[:, 0] += leg_at
    return BodyFacts(np.concatenate([slab, leg]), np.concatenate([m1, m2]), dx=2 * s)


def test_a_body_whose_centre_of_mass_is_off_its_base_is_told_it_tips_over_and_a_balanced_one_is_not():
    from physmotion_core.feedback import balance, balance_line

    off, _ = balance(_table(0.0))  # the leg at the left end (x 0..0.04 m): the centre of mass is far right of it
    assert off == pytest.approx(_table(0.0).com[0] - 0.04, abs=0.001)
    assert "tips over under its own weight" in balance_line(_table(0.0))
    assert balance(_table(0.18))[0] == 0.0  # the leg under the middle: balanced
    assert balance_line(_table(0.18)) == ""
    mat = Material.preset("rigid")
    ground = Conditions([Force((1.0, 0.0, 0.0), t_start=0.0, t_end=0.25), Ground(0.0, "friction", 0.5)])
    text = " ".join(forecast(ground, _table(0.0), mat, clip_s=2.0))
    assert "balance:" in text and "tips over with or without the push" in text and "rocks" not in text
    # held at the frame's edge, it hangs from the hold: nothing to say about balance
    assert "balance:" not in " ".join(forecast(ground, _table(0.0), mat, clip_s=2.0, held=True))


def test_a_drawn_table_on_a_leg_at_its_end_tips_over_with_no_push_and_on_a_middle_leg_stands():
    from physmotion_core.pipeline import prepare
    from physmotion_core.sim.simulate import simulate

    mat = Material.preset("rigid")
    for leg_x, falls in ((130, True), (300, False)):
        im, _ = _photo("plain")
        yy, xx = np.mgrid[:427, :640]
        mask = ((xx >= 120) & (xx < 520) & (yy >= 150) & (yy < 220)) | ((xx >= leg_x) & (xx < leg_x + 40) & (yy >= 150)
                                                                        & (yy < 400))
        im[mask] = (40, 90, 170)
        settings = SimSettings(frames=24, fps=24.0, quality="draft")
        lines = []
        prep = prepare(im, mask=torch.from_numpy(mask.astype(np.float32)), material=mat, settings=settings,
                       report=lines.append)
        said = any(s.startswith("balance:") for s in lines)
        y = simulate(prep.gaussians, mat, prep.conditions, settings, camera=prep.camera).x.numpy()[:, :, 1]
        drop = float(y[0].mean() - y[-1].mean())  # the centre of mass comes down as it tips
        assert said == falls, lines
        assert (drop > 0.02) == falls, drop


def test_a_load_on_the_top_bends_the_top_as_timoshenkos_cantilever():
    """``lean(...).at_load``: where the load itself moves, per newton. A load on the top slice of a uniform block
    clamped at its base band moves it by the cantilever's tip deflection L³/(3·E·I) + L/(κ·G·A)."""
    a, t, s = 0.08, 0.06, 0.005
    x, m = block(a=a, t=t, s=s)
    mat = Material.preset("jelly")
    top = x[:, 1] >= x[:, 1].max() - 0.5 * s
    load = m * top
    got = lean(x, m, mat, np.array([1.0, 0.0]), load / load.sum(), g=0.0)
    _, L = _beam_part(x, s)
    I, A = t * a ** 3 / 12, a * t
    want = L ** 3 / (3 * mat.E * I) + L / (5 / 6 * mat.mu * A)
    assert got.at_load == pytest.approx(want, rel=0.08)
    # the load's own point moves more than the centre of mass does
    assert got.at_load > 2 * got.compliance


def test_a_held_soft_body_pushed_at_its_top_is_told_how_far_it_bends_and_when_it_folds_over():
    """A body the frame's bottom edge holds (a bust), pushed sideways at its top: a small push is told its bend
    (the beam's bend at the load times the swing of a sudden push), a large one that it folds over; a push
    straight down, a body held at the top, or sand are told nothing of the sort."""
    from physmotion_core.feedback import FOLD_FRACTION, bend_note, dynamic_factor

    x, m = block(a=0.08, t=0.06, L=0.3, s=0.005)
    body = BodyFacts(x, m, 0.01)
    mat = Material.preset("jelly", E=2e5)  # stands under its own weight (Greenhill's height 0.44 m)
    top = x[:, 1] >= x[:, 1].max() - 0.03
    give = lean(x, m, mat, np.array([1.0, 0.0]), (m * top) / (m * top).sum(), 9.81)
    per_n = dynamic_factor(body.total_mass, give.compliance, 0.25) * give.at_load
    height = float(x[top, 1].mean() - x[:, 1].min())
    small = 0.2 * FOLD_FRACTION * height / per_n
    note = bend_note(np.array([small, 0.0, 0.0]), small, 0.25, body, top, mat, 9.81)
    assert "springs back" in note and f"{100 * per_n * small:.2g} cm" in note
    big = 3 * FOLD_FRACTION * height / per_n
    assert "folds over" in bend_note(np.array([big, 0.0, 0.0]), big, 0.25, body, top, mat, 9.81)
    assert bend_note(np.array([0.0, -big, 0.0]), big, 0.25, body, top, mat, 9.81) == ""
    assert bend_note(np.array([big, 0.0, 0.0]), big, 0.25, body, top, Material.preset("sand"), 9.81) == ""
    # too soft to hold itself up on its base (Greenhill's height 0.26 m at 20 kPa): it folds over anyway
    assert "with or without the push" in bend_note(np.array([small, 0.0, 0.0]), small, 0.25, body, top,
                                                   Material.preset("jelly", E=2e4), 9.81)
    conds = Conditions([Force((big, 0.0, 0.0))])
    held_below = forecast(conds, body, mat, clip_s=1.0, held=True, held_edges=("bottom", "right"))
    assert any("folds over" in line for line in held_below if line.startswith("force 1"))
    held_above = forecast(conds, body, mat, clip_s=1.0, held=True, held_edges=("top",))
    assert not any("folds over" in line or "bends about" in line for line in held_above)
