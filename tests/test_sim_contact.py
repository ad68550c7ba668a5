"""Contact between objects (issue 37): each object on its own grid velocity field, Coulomb contact
between the fields (Bardenhagen et al. 2000), through simulate().

Tolerances: an elastic body without damping bounces back with e → 1 as the grid refines; at 10
cells a ball the transfers' numerical dissipation and the contact's fill check leave 0.86-0.91 for
two balls (docs/accuracy.md; 0.861 for the jelly pair here), the issue's bound is e ≥ 0.85. Momentum: the contact's corrections cancel exactly in pairs, so the total stays at
float32 round-off of the particle sums (1e-6 of one ball's momentum measured; 1e-4 asserted).
Sliding contact between objects: Coulomb's stopping distance v0² / (2 μ g), within 15 % (the
spread over where the interface falls in a cell, docs/accuracy.md, "Contact between objects").
"""

import numpy as np
import pytest
import torch

from physmotion_core.errors import InputError
from physmotion_core.sim import simulate
from physmotion_core.sim.mpm import MPMSolver
from physmotion_core.types import Conditions, Gaussians, Gravity, InitialVelocity, Material, Region, SimSettings
from physmotion_core.types.conditions import Ground, ObjectContact
from physmotion_core.types.material import material_preset


def _gaussians(points, ids):
    x = torch.cat(points)
    g = Gaussians.from_rgb(x, torch.rand(len(x), 3), torch.full((len(x), 3), 0.004), torch.full((len(x),), 0.9))
    g.object_ids = torch.cat([torch.full((len(p),), i, dtype=torch.long) for i, p in enumerate(ids)])
    return g


def _ball(c, r=0.05, n=10):
    a = torch.linspace(-r, r, n)
    g = torch.stack(torch.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)
    return g[g.norm(dim=1) <= r] + torch.tensor(c)


def _com_x(res, k):
    obj = res.particle_object.numpy()
    return res.x.numpy()[:, obj == k, 0].astype(np.float64).mean(1)


def test_two_elastic_balls_bounce_apart_and_keep_momentum():
    b1, b2 = _ball((-0.07, 0.2, 0.0)), _ball((0.07, 0.2, 0.0))
    g = _gaussians([b1, b2], [b1, b2])
    v = 0.4  # each: a closing speed of 0.8 m/s
    conds = Conditions([Gravity((0.0, 0.0, 0.0)), InitialVelocity((v, 0, 0), region=Region(object_id=0)),
                        InitialVelocity((-v, 0, 0), region=Region(object_id=1))])
    fps = 50.0
    res = simulate(g, Material.preset("jelly"), conds,
                   SimSettings(frames=20, fps=fps, grid_res=24, device="cpu", rest_speed=0.0), record_all=True)
    v1 = np.gradient(_com_x(res, 0), 1 / fps)[-3:].mean()
    v2 = np.gradient(_com_x(res, 1), 1 / fps)[-3:].mean()
    e = (v2 - v1) / (2 * v)
    assert e >= 0.85, e
    assert abs(v1 + v2) <= 1e-4 * v  # equal masses (same fill): Σ m v / m
    assert v1 < 0 < v2  # they came apart


def test_fields_follow_objects_and_settings():
    x = np.array([[0.0, 0.1, 0.0], [0.2, 0.1, 0.0]], np.float32)
    from physmotion_core.sim.mpm import Domain

    dom = Domain.around(x.min(0), x.max(0), 0.02, 1.0, None)
    mats = [Material.preset("jelly"), Material.preset("jelly")]
    vol = np.full(2, 1e-6)
    assert MPMSolver(x, vol, np.array([0, 1]), mats, dom).fields == 2
    assert MPMSolver(x, vol, np.array([0, 1]), mats, dom, object_contact=ObjectContact("shared")).fields == 1
    assert MPMSolver(x, vol, np.array([0, 0]), mats[:1], dom).fields == 1
    # Anchors work on one shared field.
    assert MPMSolver(x, vol, np.array([0, 1]), mats, dom, anchored=np.array([True, False])).fields == 1
    with pytest.raises(InputError):
        MPMSolver(x, vol, np.array([0, 1]), mats, dom).set_anchors(np.array([True, False]), np.zeros((2, 3)))
    with pytest.raises(InputError):
        ObjectContact("glue")


def test_ground_node_sets_object_contact_only_when_asked():
    # The Ground & Walls node's optional object_contact / object_friction: left at their defaults
    # (what a scene gets without an ObjectContact) they add nothing, so existing workflows and chains
    # that already hold an ObjectContact keep working; set, they add one ObjectContact.
    from comfy_harness import node_classes

    from physmotion_core.types import ObjectContact as Exported

    assert Exported is ObjectContact
    ground = node_classes()["PhysMotionGround"]
    spec = ground.INPUT_TYPES()["optional"]
    from physmotion_core.types.conditions import OBJECT_CONTACTS

    assert tuple(spec["object_contact"][0]) == OBJECT_CONTACTS
    assert spec["object_contact"][1]["default"] == "friction" and spec["object_friction"][1]["default"] == 0.3
    (plain,) = ground().run("friction", 0.5, 0.0)
    assert plain.of(ObjectContact) == [] and plain.object_contact() == ObjectContact()
    (sticky,) = ground().run("friction", 0.5, 0.0, object_contact="sticky")
    assert sticky.object_contact() == ObjectContact("sticky", 0.3)
    (shared,) = ground().run("slip", 0.0, 0.0, conditions=plain, object_contact="shared", object_friction=0.0)
    assert shared.object_contact() == ObjectContact("shared", 0.0)


@pytest.mark.parametrize("contact, least", [("friction", 0.85), ("slip", 0.9)])
def test_elastic_ball_bounces_off_the_ground(contact, least):
    # Issue 37: a ball on the ground bounces as two balls do. A stiff jelly ball (E = 2e5 Pa, r = 5 cm,
    # 12 cells across) thrown at the ground at 0.8 m/s without gravity (with it, the ~30 ms contact
    # would mix g t into the rebound), on Coulomb ground (μ = 0.5) and on slip ground; e = the centre
    # of mass's rebound speed over 0.8. Measured 0.898 (friction) and 0.963 (slip); friction ground
    # costs bounce because its contact layer moves by PIC (what holds bodies on a slope, kernels.p2g).
    # Bounds: the e ≥ 0.85; slip ground's 0.9 (no PIC layer: the lattice balls of the
    # validate case bounce 0.93-0.95 there).
    r = 0.05
    b = _ball((0.0, r + 0.003, 0.0), r, 16)
    speed, fps = 0.8, 100.0
    conds = Conditions([Gravity((0.0, 0.0, 0.0)), Ground(0.0, contact, 0.5), InitialVelocity((0.0, -speed, 0.0))])
    res = simulate(_gaussians([b], [b]), material_preset("jelly", E=2.0e5), conds,
                   SimSettings(frames=8, fps=fps, grid_res=12, device="cpu", rest_speed=0.0), record_all=True)
    y = res.x.numpy()[:, :, 1].astype(np.float64).mean(1)
    e = float(np.gradient(y, 1 / fps)[-3:].mean()) / speed
    assert least <= e <= 1.0, e


def _blocks(v0, contact, mu, frames=13):
    """A jelly block (E = 2e5 Pa, 0.1 x 0.03 x 0.05 m) launched at v0 along x over a wider jelly block
    (0.3 x 0.04 x 0.07 m) resting on sticky ground, each an object of its own, 24 cells across the
    scene (the CPU's default). Returns the times, the top block's travel along x and the rise of its
    centre of mass."""
    def box(lo, hi, n, obj):
        axes = [torch.linspace(a, b, k) for a, b, k in zip(lo, hi, n)]
        p = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        return p, torch.full((len(p),), obj, dtype=torch.long)

    (pb, ob), (pt, ot) = (box((-0.145, 0.005, -0.035), (0.145, 0.035, 0.035), (30, 4, 8), 0),
                          box((-0.115, 0.045, -0.025), (-0.025, 0.075, 0.025), (10, 4, 6), 1))
    x = torch.cat([pb, pt])
    g = Gaussians.from_rgb(x, torch.rand(len(x), 3), torch.full((len(x), 3), 0.005), torch.full((len(x),), 0.9))
    g.object_ids = torch.cat([ob, ot])
    conds = Conditions([Ground(0.0, "sticky"), InitialVelocity((v0, 0.0, 0.0), region=Region(object_id=1)),
                        ObjectContact(contact, mu)])
    res = simulate(g, material_preset("jelly", E=2.0e5), conds,
                   SimSettings(frames=frames, fps=50, grid_res=24, device="cpu", rest_speed=0.0), record_all=True)
    top = res.particle_object.numpy() == 1
    x = res.x.numpy()[:, top].astype(np.float64)
    return res.times.numpy(), x[:, :, 0].mean(1) - x[0, :, 0].mean(), x[:, :, 1].mean(1) - x[0, :, 1].mean()


def test_block_sliding_over_a_block_stops_at_coulombs_distance():
    # Issue 37. Friction between objects decelerates a sliding block at μ g, so from 0.5 m/s at μ = 0.5
    # it stops after v0² / (2 μ g) = 25.5 mm (in 0.10 s; run 0.24 s). The contact acts only where the
    # two bodies' material fills a node (kernels.update_node_fields' fill check): before it, every node
    # both stencils reached took part and the block stopped after 4-12 mm. Measured over five offsets
    # of the interface within a cell: 22.3-25.0 mm (−12 … −2 %); 15 % covers that spread (what is
    # left: the block pitches onto its leading edge, where the contact normal tilts).
    v0, mu = 0.5, 0.5
    t, travel, rise = _blocks(v0, "friction", mu)
    expected = v0 ** 2 / (2 * mu * 9.81)
    assert travel[-1] == pytest.approx(expected, rel=0.15), travel
    assert abs(travel[-1] - travel[-3]) < 0.05 * expected  # it has stopped
    assert abs(rise[-1]) < 2e-3  # it neither sank into the lower block nor lifted off it


def test_block_sliding_over_a_block_keeps_its_speed_on_slip_contact():
    # Without friction the block slides on at v0: measured 115.6 mm in 0.24 s against 120 (−4 %: the
    # corners of its leading face, where the normal tilts, take a little); it slowed at ~1.6 m/s² and
    # rose 5 mm before the fill check. Bound 8 % of the distance.
    v0 = 0.5
    t, travel, rise = _blocks(v0, "slip", 0.0)
    assert travel[-1] == pytest.approx(v0 * t[-1], rel=0.08), travel
    assert abs(rise[-1]) < 2e-3
