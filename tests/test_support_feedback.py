"""What holds a cut-off object (support.py) and what the user is told before and after the wait
(feedback.py): issue 33, items 4 and 5.

The hold is checked through ``simulate()``: a leaning oval cut off by the frame's bottom edge (a head
filling the frame, leaning right) stays within 1 % of its height for 1 s under gravity when held at
that edge, and, as a control, sags and topples when it is stood on the cut instead. The material is
rubber (E = 1 MPa, ρ = 1100 kg/m³): its static sag under its own weight, ρ·g·h²/(2E) = 0.5 mm for a
0.3 m body, is 0.16 % of its height, so the 1 % bound is about the hold, not the elasticity.
"""

from types import SimpleNamespace

import math

import numpy as np
import pytest
import torch

from physmotion_core.feedback import BodyFacts, after_run, forecast
from physmotion_core.support import edge_band, edge_contact, plan_support, touched_edges
from physmotion_core.types import Conditions, Force, Ground, InitialVelocity, Material, SimSettings
from physmotion_core.types.camera import Camera


def disc(h=120, w=160, cx=80, cy=60, r=30):
    yy, xx = np.mgrid[:h, :w]
    return ((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r).astype(np.float32)


def oval(h=120, w=160, lean=0.0):
    """A head-like oval filling the frame's height, cut off by the bottom edge (its neck). With
    ``lean`` (pixels right per pixel up) its centre of mass lies right of the cut, so stood on the
    cut it topples."""
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    cx = 80 + lean * (h - yy) - lean * 60
    return ((((xx - cx) / 34.0) ** 2 + ((yy - 66) / 60.0) ** 2) <= 1.0).astype(np.float32)


# -- which edges cut the object ----------------------------------------------------------------


def test_an_object_inside_the_frame_touches_no_edge():
    assert touched_edges(disc()) == ()


def test_the_edges_that_cut_an_object_are_found():
    m = disc(cx=80, cy=110, r=30)  # cut by the bottom edge
    assert touched_edges(m) == ("bottom",)
    m = disc(cx=5, cy=5, r=40)  # a corner: top and left
    assert touched_edges(m) == ("top", "left")
    assert set(edge_contact(m)) == {"top", "left"}


def test_a_stray_border_pixel_is_not_a_cut():
    m = disc()
    m[0, 80] = 1.0  # one pixel of the top row
    assert touched_edges(m) == ()


def test_the_band_is_the_object_next_to_the_cut_edge():
    m = disc(cx=80, cy=110, r=30)
    band = edge_band(m, ("bottom",), band_px=5)
    assert band.sum() > 0 and np.all(band <= m)
    assert np.all(band[:-5] == 0)  # only the last 5 rows
    assert np.array_equal(band[-5:] > 0, m[-5:] > 0)


# -- the support plan ----------------------------------------------------------------------------


def test_plan_holds_a_cut_object_and_moves_the_ground_out_of_the_way():
    plan = plan_support(disc(cx=80, cy=110, r=30), ground=Ground(0.0, "friction", 0.5), object_height=0.3)
    assert plan.hold and plan.anchor is not None and plan.edges == ("bottom",)
    assert plan.ground.height == pytest.approx(-0.3)
    text = " ".join(plan.lines)
    assert "bottom" in text and "held" in text and "--no-hold-edges" in text
    assert "0.3 m (assumed)" in text and "--object-height" in text


def test_plan_puts_the_ground_under_an_object_inside_the_frame():
    plan = plan_support(disc(), ground=Ground(0.0, "friction", 0.5), object_height=0.5, height_given=True)
    assert not plan.hold and plan.anchor is None and plan.ground.height == 0.0 and plan.ground_under_object
    assert "under the object's lowest visible point" in " ".join(plan.lines)
    assert "0.5 m (given)" in " ".join(plan.lines)


def test_plan_with_the_hold_off_holds_nothing_and_says_so():
    plan = plan_support(disc(cx=80, cy=110, r=30), ground=Ground(0.0, "friction", 0.5), object_height=0.3,
                        hold_edges=False)
    assert plan.anchor is None and not plan.hold
    assert "holding it there is off" in " ".join(plan.lines)


def _cut_off_run(hold: bool, lean: float = 0.0):
    from physmotion_core.lift import silhouette_lift
    from physmotion_core.sim import simulate

    mask = oval(lean=lean)
    assert touched_edges(mask) == ("bottom",)
    img = np.full(mask.shape + (3,), 0.6, np.float32)
    height = 0.3
    ground = Ground(0.0, "friction", 0.5)
    plan = plan_support(mask, ground=ground, object_height=height, hold_edges=hold)
    lift = silhouette_lift(img, mask, object_height=height, max_gaussians=3000, fit_colors=False)
    conds = Conditions([plan.ground] + ([plan.anchor] if plan.anchor is not None else []))
    res = simulate(lift.gaussians, Material.preset("rubber"), conds,
                   SimSettings(frames=25, fps=24.0, grid_res=10, device="cpu"), camera=lift.camera, record_all=True)
    x = res.x.numpy().astype(np.float64)
    return float(np.linalg.norm(x - x[0], axis=2).max()), height


def test_a_cut_off_object_held_at_the_frame_edge_stays_put_for_a_second():
    motion, height = _cut_off_run(hold=True)
    assert motion < 0.01 * height, f"held object moved {motion:.4f} m (> 1 % of {height} m)"


def test_a_leaning_cut_off_object_is_held_where_stood_on_its_cut_it_topples():
    held, height = _cut_off_run(hold=True, lean=0.4)
    free, _ = _cut_off_run(hold=False, lean=0.4)
    assert free > 0.1 * height, f"unheld leaning object moved only {free:.4f} m"
    assert held < 0.3 * free, (held, free)


# -- the forecast before the wait ------------------------------------------------------------------


def slab(size=(0.5, 0.1, 0.5), mass=25.0, n=10):
    """Particles of a box on the ground (y from 0), total ``mass`` kg."""
    g = [np.linspace(-s / 2, s / 2, n) for s in size]
    x = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    x[:, 1] += size[1] / 2
    return BodyFacts(x, np.full(len(x), mass / len(x)))


def _lines(facts, force, ground=Ground(0.0, "friction", 0.5), clip_s=2.0, held=False):
    mat = Material.preset("rigid")
    conds = Conditions([Force(force, t_start=0.0, t_end=0.25), ground])
    return " ".join(forecast(conds, facts, mat, clip_s=clip_s, held=held))


def test_forecast_says_a_weak_push_will_not_beat_static_friction():
    text = _lines(slab(), (40.0, 0.0, 0.0))
    assert "25 kg" in text
    assert "will not slide" in text and "123 N" in text  # μ m g = 0.5 · 25 · 9.81 = 122.6 N
    assert "Δv ≈ 0.4 m/s" in text  # 40 N · 0.25 s / 25 kg


def test_forecast_says_a_strong_push_slides():
    text = _lines(slab(), (300.0, 0.0, 0.0))
    assert "beats static friction" in text and "will not slide" not in text


def test_forecast_on_a_frictionless_ground_says_it_slides_and_sticky_says_it_does_not():
    assert "slides" in _lines(slab(), (1.0, 0.0, 0.0), ground=Ground(0.0, "slip"))
    assert "sticky: it will not slide" in _lines(slab(), (1000.0, 0.0, 0.0), ground=Ground(0.0, "sticky"))


def test_forecast_tipping_for_a_tall_thin_block_and_not_for_a_flat_slab():
    tall = slab(size=(0.1, 0.6, 0.1), mass=2.0)  # a whole-body push acts at the centre: h = 0.3, b = 0.05
    # F·h > m·g·b  <=>  F > 2 · 9.81 · 0.05 / 0.3 = 3.27 N; friction μ m g = 9.81 N
    assert "can tip over" in _lines(tall, (5.0, 0.0, 0.0))
    assert "can tip over" not in _lines(slab(), (100.0, 0.0, 0.0))


def test_forecast_for_a_held_object_says_the_push_bends_it():
    text = _lines(slab(), (40.0, 0.0, 0.0), held=True)
    assert "held" in text and "will not slide" not in text


def test_a_soft_body_held_on_its_base_by_the_frame_is_told_it_folds_over():
    """A figure cut off by the frame's bottom edge is a column clamped at its base: the stability line that a body
    standing on the ground gets applies (until 2026-12-06 a held body got none, and a held jelly astronaut swayed
    with no push and no word). Held at the top (hanging) or at a side, the column's buckling does not describe it."""
    s = 0.01  # a 10 cm square column 0.4 m tall on a 1 cm lattice, 1000 kg/m³: jelly of 20 kPa buckles
    x = np.stack(np.meshgrid(*[np.arange(n) * s + s / 2 for n in (10, 40, 10)], indexing="ij"), -1).reshape(-1, 3)
    column = BodyFacts(x, np.full(len(x), 1000.0 * s**3), dx=2 * s)
    conds = Conditions([Ground(-0.3, "friction", 0.5)])
    jelly = Material.preset("jelly")

    def said(**kw):
        return " ".join(forecast(conds, column, jelly, clip_s=1.0, **kw))

    assert "folds over from the first frame without any push" in said(held=True, held_edges=("bottom",))
    assert "on the base the frame's bottom edge holds" in said(held=True, held_edges=("bottom",))
    for edges in (("top",), ("left",), ("bottom", "left")):
        assert "stability:" not in said(held=True, held_edges=edges), edges
    stiff = " ".join(forecast(conds, column, Material.preset("jelly", E=1e7), clip_s=1.0, held=True,
                              held_edges=("bottom",)))
    assert "stability:" not in stiff


def test_forecast_warns_when_the_push_throws_it_off_screen():
    facts = slab(size=(0.1, 0.1, 0.1), mass=0.1)
    cam = Camera.from_fov(160, 120, 40.0, c2w=torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0.05], [0, 0, 1, 1.0],
                                                             [0, 0, 0, 1]]))
    conds = Conditions([Force((30.0, 0.0, 0.0), t_start=0.0, t_end=0.25), Ground(0.0, "friction", 0.5)])
    text = " ".join(forecast(conds, facts, Material.preset("jelly"), clip_s=2.0, camera=cam))
    assert "may leave the frame" in text
    conds = Conditions([Force((0.6, 0.0, 0.0), t_start=0.0, t_end=0.25), Ground(0.0, "friction", 0.5)])
    assert "may leave the frame" not in " ".join(forecast(conds, facts, Material.preset("jelly"), clip_s=2.0,
                                                          camera=cam))


def test_forecast_reports_a_throw_and_a_torque():
    from physmotion_core.types import Torque

    facts = slab(size=(0.2, 0.2, 0.2), mass=8.0)
    conds = Conditions([Torque((0.0, 1.0, 0.0), t_start=0.0, t_end=0.5), InitialVelocity((1.0, 0.0, 0.0))])
    text = " ".join(forecast(conds, facts, Material.preset("rigid"), clip_s=1.0))
    # I = m (a² + a²) / 12 = 8 · 0.08 / 12 = 0.0533 for a cube of side 0.2 (particles on a grid: a bit more)
    inertia = float((facts.mass * (facts.x[:, 0] ** 2 + facts.x[:, 2] ** 2)).sum())
    assert f"{0.5 / inertia:.3g} rad/s" in text
    assert "throw 1: starts at 1 m/s" in text


# -- after the run -----------------------------------------------------------------------------------


def _fake_sim(offsets):
    x0 = np.stack(np.meshgrid(np.linspace(-0.05, 0.05, 4), np.linspace(0.0, 0.1, 4), np.linspace(-0.05, 0.05, 4),
                              indexing="ij"), -1).reshape(-1, 3)
    x = np.stack([x0 + np.asarray(o) for o in offsets]).astype(np.float32)
    return SimpleNamespace(x=torch.from_numpy(x), times=torch.arange(len(offsets)) / 24.0)


CAM = Camera.from_fov(160, 120, 40.0, c2w=torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0.05], [0, 0, 1, 1.0],
                                                         [0, 0, 0, 1]]))


def test_nothing_moved_warns_only_when_nothing_moved():
    still = after_run(_fake_sim([(0, 0, 0)] * 10), CAM)
    assert still.max_motion_px < 1.0 and any("nothing moved" in w for w in still.warnings)
    px_per_m = CAM.fy / 1.0  # at 1 m from the camera
    moved = after_run(_fake_sim([(0, 0, 0)] + [(5.0 / px_per_m, 0, 0)] * 9), CAM)  # 5 px to the right
    assert moved.max_motion_px == pytest.approx(5.0, rel=0.1)
    assert not moved.warnings


def test_leaving_the_frame_warns_with_the_frame():
    half_width = 80 / CAM.fx  # metres from the centre to the frame's edge at 1 m
    offs = [(k * half_width * 0.4, 0, 0) for k in range(8)]  # inside up to frame 2, outside from frame 3
    rep = after_run(_fake_sim(offs), CAM)
    assert rep.left_frame_at == 3
    assert any("left the frame" in w and "frame 3" in w for w in rep.warnings)
    assert after_run(_fake_sim([(0.01 * k, 0, 0) for k in range(8)]), CAM).left_frame_at is None


def test_the_node_path_finds_the_same_cut_edges_as_the_mask():
    """MPM Simulate decides the hold from a render of the Gaussians (it has no mask): an object that
    stops a few pixels short of the frame is not cut (the splats' footprints reach past the outline),
    one that runs off the frame is."""
    from physmotion_core.lift import silhouette_lift
    from physmotion_core.support import edge_hold

    img = np.full((120, 160, 3), 0.6, np.float32)
    short = disc(cx=80, cy=85, r=30)  # ends 5 px above the bottom edge
    cut = oval()  # runs off the bottom edge
    for m, want in ((short, ()), (cut, ("bottom",))):
        assert touched_edges(m) == want
        lift = silhouette_lift(img, m, max_gaussians=3000, fit_colors=False)
        anchor, edges, line = edge_hold(lift.gaussians, lift.camera)
        assert edges == want, (edges, want)
        assert (anchor is not None) == bool(want)
        assert ("it is held there" in line) == bool(want)


def test_a_hold_on_nothing_is_skipped_but_a_users_anchor_on_nothing_is_refused():
    from physmotion_core.errors import InputError
    from physmotion_core.sim import simulate
    from physmotion_core.types import Anchor, Region
    from physmotion_core.validate.stress import gaussian_box

    g = gaussian_box((-0.05, 0.0, -0.05), (0.05, 0.1, 0.05), (5, 5, 5))
    nowhere = Region("box", lo=(1.0, 1.0, 1.0), hi=(2.0, 2.0, 2.0))
    settings = SimSettings(frames=2, fps=24.0, grid_res=6, device="cpu")
    res = simulate(g, Material.preset("rubber"), Conditions([Anchor(nowhere, optional=True)]), settings)
    assert res.x.shape[0] == 2
    with pytest.raises(InputError, match="contains no part of the object"):
        simulate(g, Material.preset("rubber"), Conditions([Anchor(nowhere)]), settings)


# -- a mask in separate pieces -------------------------------------------------------------------------

S = 0.01  # particle spacing (m); the grid cell is two spacings, as the simulator's 8 particles a cell


def lattice_block(lo, hi, seed=0, jitter=0.1):
    """Particles as ``sim.fill`` puts them: voxel centres of spacing S over [lo, hi), jittered by 0.1 S."""
    g = [np.arange(a + S / 2, b - 1e-9, S) for a, b in zip(lo, hi)]
    x = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3)
    return x + np.random.default_rng(seed).uniform(-jitter * S, jitter * S, x.shape)


def facts_of(*blocks, density=1000.0):
    x = np.concatenate(blocks)
    return BodyFacts(x, np.full(len(x), density * S ** 3), 2 * S)


def test_piece_labels_part_bodies_one_empty_voxel_apart_and_only_those():
    from physmotion_core.feedback import piece_labels

    a = lattice_block((0, 0, 0), (0.1, 0.1, 0.1))
    gap = lattice_block((0.11, 0, 0), (0.2, 0.1, 0.1), seed=1)  # one empty voxel (1 S) between them
    touch = lattice_block((0.1, 0, 0), (0.2, 0.1, 0.1), seed=2)  # the next voxel: one body
    lab = piece_labels(np.concatenate([a, gap]), 2 * S)
    assert set(lab[:len(a)]) == {0} and set(lab[len(a):]) == {1}  # the larger first (1000 against 900)
    assert set(piece_labels(np.concatenate([a, touch]), 2 * S)) == {0}
    corner = lattice_block((0.1, 0.1, 0.1), (0.15, 0.15, 0.15), seed=3)  # meets the cube at one corner only
    assert set(piece_labels(np.concatenate([a, corner]), 2 * S)) == {0}
    assert not piece_labels(np.concatenate([a, gap]), 0.0).any()  # dx 0: looked at as one


def test_pieces_held_standing_resting_or_loose():
    from physmotion_core.feedback import pieces
    from physmotion_core.types import Anchor, Region

    base = lattice_block((-0.1, 0, -0.05), (0.1, 0.1, 0.05))  # on the ground (y = 0)
    on_top = lattice_block((-0.03, 0.12, -0.03), (0.03, 0.18, 0.03), seed=1)  # 2 cm above the base: lies on it
    floating = lattice_block((0.3, 0.3, -0.03), (0.36, 0.36, 0.03), seed=2)  # over nothing
    facts = facts_of(base, on_top, floating)
    ground = Ground(0.0, "friction", 0.5)
    got = pieces(facts, Conditions([ground]))
    assert [len(p.sel.nonzero()[0]) for p in got] == [len(base), len(on_top), len(floating)]
    assert (got[0].grounded, got[1].resting, got[2].supported) == (True, True, False)
    assert got[2].share == pytest.approx(len(floating) / len(facts.x))
    # held by an anchor on its particles: supported; without the ground the base falls, and what lies on it
    hold = Anchor(Region(kind="box", lo=(0.29, 0.29, -0.1), hi=(0.4, 0.4, 0.1)))
    got = pieces(facts, Conditions([hold]))
    assert (got[0].supported, got[1].supported, got[2].held) == (False, False, True)


def test_forecast_pushes_the_piece_it_touches_and_names_the_loose_ones():
    from physmotion_core.types import Region

    base = lattice_block((-0.1, 0, -0.05), (0.1, 0.1, 0.05))
    floating = lattice_block((0.3, 0.3, -0.03), (0.36, 0.36, 0.03), seed=2)
    facts = facts_of(base, floating)
    m_small = len(floating) * 1000.0 * S ** 3  # 0.216 kg
    push = Force((10.0, 0.0, 0.0), t_start=0.0, t_end=0.25,
                 region=Region(kind="box", lo=(0.29, 0.29, -0.1), hi=(0.4, 0.4, 0.1)))
    lines = forecast(Conditions([push, Ground(0.0, "friction", 0.5)]), facts, Material.preset("jelly"), clip_s=1.0)
    text = " ".join(lines)
    assert "2 separate pieces" in text and "neither held nor standing on anything: it falls" in text
    assert f"Δv ≈ {10 * 0.25 / m_small:.3g} m/s" in text and "the piece it pushes" in text
    assert "nothing holds that piece up" in text and "static friction" not in text
    # a push on the whole object, or the same object looked at as one (dx 0): the whole mass, no pieces
    whole = forecast(Conditions([Force((10.0, 0.0, 0.0), t_start=0.0, t_end=0.25), Ground(0.0, "friction", 0.5)]),
                     facts, Material.preset("jelly"), clip_s=1.0)
    m = facts.total_mass
    assert f"Δv ≈ {10 * 0.25 / m:.3g} m/s" in " ".join(whole)
    one = forecast(Conditions([push, Ground(0.0, "friction", 0.5)]), BodyFacts(facts.x, facts.mass, 0.0),
                   Material.preset("jelly"), clip_s=1.0)
    assert "pieces" not in " ".join(one) and f"Δv ≈ {10 * 0.25 / m:.3g} m/s" in " ".join(one)


def test_a_piece_that_leaves_the_frame_is_warned_about_and_one_that_stays_is_not():
    half_width = 80 / CAM.fx
    sim = _fake_sim([(0, 0, 0)] * 8)
    n = sim.x.shape[1]
    piece = torch.zeros(n, dtype=torch.long)
    piece[: n // 4] = 1  # a quarter of the particles: a separate piece
    x = sim.x.clone()
    for k in range(8):
        x[k, : n // 4, 0] += k * half_width * 0.4  # out of the frame from frame 3
    rep = after_run(SimpleNamespace(x=x, times=sim.times, particle_piece=piece), CAM)
    assert rep.left_frame_at is None  # most of the object stayed
    (w,) = [w for w in rep.warnings if "separate piece" in w]
    assert "25%" in w and "frame 3" in w
    still = after_run(SimpleNamespace(x=sim.x, times=sim.times, particle_piece=piece), CAM)
    assert not [w for w in still.warnings if "separate piece" in w]
    assert not [w for w in after_run(SimpleNamespace(x=x, times=sim.times), CAM).warnings if "separate piece" in w]


def test_a_slender_object_is_told_how_few_cells_it_is_across_and_the_grid_that_resolves_it():
    from physmotion_core.feedback import thin_line

    rod = lattice_block((0, 0, 0), (0.03, 0.6, 0.04), jitter=0.0)  # 3 cm wide, 60 cm tall: 0.03 / 0.02 = 1.5 cells
    line = thin_line(facts_of(rod))
    assert "1.5 grid cells across its narrowest side (its width)" in line and "bends too easily" in line
    # 3 cells across need dx = 0.01: the 0.6 m height then spans 60 cells, 2x the 30 it spans now
    assert "grid resolution of 60 cells" in line and "about 8x the particles and 16x the run time" in line
    text = " ".join(forecast(Conditions([Ground(0.0, "friction", 0.5)]), facts_of(rod), Material.preset("metal"),
                             clip_s=1.0))
    assert "resolution:" in text
    assert thin_line(facts_of(lattice_block((0, 0, 0), (0.05, 0.6, 0.05)))) == ""  # 2.5 cells: within 5 %
    assert thin_line(BodyFacts(rod, np.ones(len(rod)))) == ""  # no grid known: nothing said


def test_a_throw_is_forecast_to_leave_the_frame_up_or_sideways_only_when_it_does():
    """Apex v_y²/2g against the room above; sideways: v_x over the flight 2·v_y/g, then sliding v_x²/2μg."""
    facts = slab(size=(0.1, 0.1, 0.1), mass=1.0)  # y 0..0.1, x -0.05..0.05, 1 m in front of CAM
    ground = Ground(0.0, "friction", 0.5)
    g = 9.81

    def said(v):
        return " ".join(forecast(Conditions([InitialVelocity(v), ground]), facts, Material.preset("rubber"),
                                 clip_s=2.0, camera=CAM))

    uv, z = CAM.project(torch.tensor([[0.05, 0.1, 0.05]]))  # the slab's top right front corner
    top_room = float(uv[0, 1]) * float(z[0]) / CAM.fx  # metres at the object's depth (its centre, 1 m)
    assert 2.0 ** 2 / (2 * g) < top_room < 3.0 ** 2 / (2 * g)  # the two throws below straddle it
    assert "past the frame's top" not in said((0.0, 2.0, 0.0))
    assert f"it rises about {3.0 ** 2 / (2 * g):.2g} m, past the frame's top" in said((0.0, 3.0, 0.0))
    slow, fast = said((1.0, 1.0, 0.0)), said((2.0, 1.0, 0.0))
    travel = 2.0 * (2 * 1.0 / g) + 2.0 ** 2 / (2 * 0.5 * g)  # 0.41 m in the air + 0.41 m sliding
    assert "sideways" not in slow and f"it travels about {travel:.2g} m sideways" in fast
    assert "on the right" in fast and "a slower throw keeps it in" in fast


def test_leaving_the_frame_says_whether_it_came_back():
    half_width = 80 / CAM.fx
    out_and_back = [(0, 0, 0), (0, 0, 0), (0, 0, 0), (half_width * 1.5, 0, 0), (half_width * 1.5, 0, 0),
                    (half_width * 1.5, 0, 0), (0.02, 0, 0), (0.02, 0, 0)]
    rep = after_run(_fake_sim(out_and_back), CAM)
    assert (rep.left_frame_at, rep.back_in_frame_at) == (3, 6)
    assert any("from frame 3" in w and "back in from frame 6" in w for w in rep.warnings)
    rep = after_run(_fake_sim(out_and_back[:6]), CAM)
    assert rep.back_in_frame_at is None and any("does not come back" in w for w in rep.warnings)


def _column(name, height, cells=10):
    """An upright cylinder twice as tall as wide of preset ``name`` on rough ground: what the forecast says of
    it, and its top's height (fraction of ``height``) simulated at 0.75 and 3 times √(2h/g)."""
    from physmotion_core.feedback import flow_line
    from physmotion_core.validate.cases import FRAME_DT, MIN_SUBSTEPS, _solver, box_domain, lattice
    from physmotion_core.validate.harness import run_sampled

    mat = Material.preset(name)
    dx = height / cells
    x, vol = lattice((-height / 2, 0.0, -height / 2), (height / 2, height, height / 2), dx / 2)
    keep = np.hypot(x[:, 0], x[:, 2]) <= height / 2
    x, vol = x[keep], vol[keep]
    said = flow_line(mat, BodyFacts(x, vol * mat.density, dx), 9.81)
    ground = Ground(0.0, "friction", 0.5)
    dom = box_domain((-1.5 * height, 0.0, -1.5 * height), (1.5 * height, height + 0.05, 1.5 * height), dx,
                     ground=ground)
    s = _solver(x, vol, mat, dom, ground=ground)
    t_fall = math.sqrt(2 * height / 9.81)
    tops = run_sampled(s, [0.75 * t_fall, 3 * t_fall], lambda s: float(np.percentile(s.positions()[:, 1], 99)),
                       max_dt=FRAME_DT / MIN_SUBSTEPS)
    return said, [(t + dx / 4) / height for t in tops]


def test_the_flow_forecast_agrees_with_the_simulated_slump():
    """What the forecast says a liquid or a paste does under its own weight, against the solver: honey 0.3 m tall
    is at about half its height when the forecast says (0.75·√(2h/g)); honey 3 cm tall, which it says its
    viscosity slows, is well above half then; toothpaste at ρ·g·h = 1.2 σ_y, which it says keeps its shape, sags
    under 2 %; at 6 σ_y, which it says flows, falls below 60 %."""
    said, tops = _column("honey", 0.3)
    assert "flows under its own weight" in said and f"half its height in about {0.75 * math.sqrt(0.6 / 9.81):.2g} s" \
        in said
    assert 0.4 < tops[0] < 0.6, tops
    said, tops = _column("honey", 0.03)
    assert "its viscosity (10 Pa·s) slows it" in said and tops[0] > 0.65, tops
    paste = Material.preset("toothpaste")
    h_c = paste.yield_stress / (paste.density * 9.81)  # 1.57 cm
    said, tops = _column("toothpaste", 1.2 * h_c)
    assert "keeps its shape" in said and tops[1] > 0.98, tops
    said, tops = _column("toothpaste", 6 * h_c)
    assert "flows under its own weight" in said and tops[1] < 0.6, tops


def test_a_rigid_ball_thrown_is_forecast_to_roll_on_and_a_block_to_slide_to_a_stop():
    """``rolls_along``: a body round about the axis across the throw (a ball, a wheel face-on) is not stopped by
    friction: rigid, it rolls on at 5/7 of v_x (found: scikit-image's logo disc, rigid, at 0.4 m/s, was forecast
    to slide 16 mm and rolled out of the frame). A block, or a ball of a material that does not roll in the
    simulation yet (rubber: docs/accuracy.md, "Rolling"), slides v_x²/2μg as before."""
    from physmotion_core.feedback import rolls_along

    n = 14
    g1 = np.linspace(-0.05, 0.05, n)
    x = np.stack(np.meshgrid(g1, g1, g1, indexing="ij"), -1).reshape(-1, 3)
    x = x[np.linalg.norm(x, axis=1) <= 0.05]
    x[:, 1] += 0.05
    ball = BodyFacts(x, np.full(len(x), 1.0 / len(x)))
    block = slab(size=(0.1, 0.1, 0.1), mass=1.0)
    assert rolls_along(ball, np.array([1.0, 0, 0])) and rolls_along(ball, np.array([0.0, 0, 1.0]))
    assert not rolls_along(block, np.array([1.0, 0, 0]))
    assert not rolls_along(ball, np.array([0.0, 1.0, 0]))  # straight up: nothing to roll along
    ground, v = Ground(0.0, "friction", 0.5), (0.5, 0.0, 0.0)

    def said(facts, name):
        return " ".join(forecast(Conditions([InitialVelocity(v), ground]), facts, Material.preset(name), clip_s=2.0,
                                 camera=CAM))

    assert f"it rolls about {5 / 7 * 0.5 * 2.0:.2g} m sideways" in said(ball, "rigid")  # 0.71 m: out of the frame
    assert "sideways" not in said(ball, "rubber") and "sideways" not in said(block, "rigid")  # 25 mm of sliding
