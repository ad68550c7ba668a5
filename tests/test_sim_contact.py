"""Contact between objects (issue 37): each object on its own grid velocity field, Coulomb contact
between the fields (Bardenhagen et al. 2000), through simulate().

Tolerances: an elastic body without damping bounces back with e → 1 as the grid refines; at 10
cells a ball the transfers' numerical dissipation leaves 0.87-0.95 (docs/accuracy.md), the issue's
bound is e ≥ 0.85. Momentum: the contact's corrections cancel exactly in pairs, so the total stays at
float32 round-off of the particle sums (1e-6 of one ball's momentum measured; 1e-4 asserted).
Sliding contact between objects is not tested against Coulomb's distance: it is over-dissipative
(docs/accuracy.md, "Contact between objects").
"""

import numpy as np
import pytest
import torch

from physmotion_core.errors import InputError
from physmotion_core.sim import simulate
from physmotion_core.sim.mpm import MPMSolver
from physmotion_core.types import Conditions, Gaussians, Gravity, InitialVelocity, Material, Region, SimSettings
from physmotion_core.types.conditions import ObjectContact


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
