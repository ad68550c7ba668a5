"""The simulation box holds the camera's view (simulate.view_domain).

Why: the box was the object's size around it on every side (``domain_margin``), and its walls stop what reaches
them. A small object in a wide photo met a wall in mid-frame: the thrown_ball photo's 64 mm ball, rigid, rolled
along the ground from 0.5 m/s and stopped dead 77 mm on, in view; its rubber ball bounced back off the wall (the
template's ball went back towards where it was thrown from). Now, given the camera, the box reaches past what the
camera sees at the object's depths by VIEW_ROOM object sizes, within VIEW_MAX_NODES nodes.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest
import torch

S = importlib.import_module("physmotion_core.sim.simulate")
from physmotion_core.sim.mpm import Domain
from physmotion_core.types import Camera, Ground


def _camera(width=640, height=480, fov=40.0, eye=(0.0, 0.1, 1.5), target=(0.0, 0.1, 0.0)):
    return Camera.look_at(eye, target, width=width, height=height, fov_y_deg=fov)


def _object(size=0.06):
    """Points filling a cube ``size`` wide standing on y = 0 at the origin."""
    g = np.linspace(-size / 2, size / 2, 7)
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x[:, 1] += size / 2
    return x


def test_the_box_holds_the_cameras_view_at_the_objects_depths_plus_room():
    x, cam, ground, dx = _object(), _camera(), Ground(0.0, "friction", 0.5), 0.004
    margin = Domain.around(x.min(0), x.max(0), dx, 1.0, ground)
    dom = S.view_domain(margin, x, cam)
    size = float(np.max(x.max(0) - x.min(0)))
    # the frame's corners at the nearest and farthest depth of the object, computed here from the pinhole model
    _, z = cam.project(torch.as_tensor(x, dtype=torch.float32))
    for depth in (float(z.min()), float(z.max())):
        half_w = depth * (cam.width / 2) / cam.fx
        half_h = depth * (cam.height / 2) / cam.fy
        centre_y = 0.1  # the camera looks level at y = 0.1
        assert dom.lo[0] <= -half_w - size + dx and dom.hi[0] >= half_w + size - dx
        assert dom.hi[1] >= centre_y + half_h + size - dx
    # and not much more than that, at the farthest depth (the grid snaps to whole cells)
    assert dom.hi[0] <= half_w + size + 4 * dx and dom.hi[1] <= centre_y + half_h + size + 4 * dx
    assert dom.lo[1] == pytest.approx(0.0)  # the floor stays the ground
    assert np.all(dom.lo <= margin.lo + 1e-9) and np.all(dom.hi >= margin.hi - 1e-9)  # never less than the margin
    assert dom.ground_node == margin.ground_node and dom.dx == margin.dx
    # the ground still lies on a node, and the grid under the object is the margin box's (whole cells added)
    assert dom.origin[1] + dom.ground_node * dom.dx == pytest.approx(0.0, abs=1e-12)
    shift = (margin.origin - dom.origin) / dx
    assert np.allclose(shift, np.round(shift), atol=1e-6) and shift.min() >= 0


def test_the_view_room_stays_within_the_node_budget_and_a_view_behind_the_camera_changes_nothing(monkeypatch):
    x, cam, ground, dx = _object(), _camera(fov=90.0, eye=(0.0, 0.1, 6.0)), Ground(0.0, "friction", 0.5), 0.004
    margin = Domain.around(x.min(0), x.max(0), dx, 1.0, ground)
    full = S.view_domain(margin, x, cam)
    monkeypatch.setattr(S, "VIEW_MAX_NODES", 400_000)
    capped = S.view_domain(margin, x, cam)
    n = int(np.prod(capped.dims))
    assert int(np.prod(margin.dims)) < n <= 400_000 < int(np.prod(full.dims))
    assert np.all(capped.lo <= margin.lo + 1e-9) and np.all(capped.hi >= margin.hi - 1e-9)
    assert np.all(capped.lo >= full.lo - 1e-9) and np.all(capped.hi <= full.hi + 1e-9)
    # a budget under the margin box keeps the margin box
    monkeypatch.setattr(S, "VIEW_MAX_NODES", 10)
    _same(S.view_domain(margin, x, cam), margin)
    # the object behind the camera: no view to hold
    behind = _camera(eye=(0.0, 0.1, -1.5), target=(0.0, 0.1, -3.0))
    _same(S.view_domain(margin, x, behind), margin)


def _same(a, b):
    assert a.dims == b.dims and a.ground_node == b.ground_node and a.dx == b.dx
    assert np.allclose(a.origin, b.origin, rtol=0, atol=1e-12)


def _throw_ball(material: str, camera: bool, v=(0.5, 0.0, 0.0), spin=(0.0, 0.0, -15.6), frames=13):
    from PIL import Image

    from physmotion_core.lift.silhouette import silhouette_lift
    from physmotion_core.types import Conditions, InitialVelocity, SimSettings
    from physmotion_core.types.material import material_preset

    rgba = np.asarray(Image.open(Path(__file__).resolve().parents[1] / "photos" / "throw_ball.png").convert("RGBA"))
    lift = silhouette_lift(rgba[..., :3].astype(np.float32) / 255, (rgba[..., 3] > 127).astype(np.float32),
                           object_height=0.064, fit_colors=False)
    assert lift.info["ball"]
    res = S.simulate(lift.gaussians, material_preset(material),
                     S.Conditions([Ground(0.0, "friction", 0.4), InitialVelocity(v, spin)]),
                     SimSettings(frames=frames, fps=24, device="cpu", quality="draft"), record_all=True,
                     camera=lift.camera if camera else None)
    return res.x.numpy().astype(np.float64).mean(1), lift.camera


def test_a_small_ball_rolling_across_a_wide_photo_does_not_stop_at_an_invisible_wall():
    """The 64 mm ball rolling (0.5 m/s, spin v/r) along μ = 0.4: a rolling ball keeps its speed, 0.25 m in 0.5 s.
    Without the camera the box's wall stops it about 77 mm on (measured), in view; with it, it rolls on:
    measured 198 mm at 0.5 s (draft), still at 0.3 m/s at the end."""
    c, cam = _throw_ball("rigid", camera=True)
    travel = c[-1] - c[0]
    assert travel[0] > 0.15, travel
    assert (c[-1, 0] - c[-4, 0]) / (3 / 24) > 0.25  # still rolling at the end
    uv, _ = cam.project(torch.as_tensor(c[-1:], dtype=torch.float32))
    assert 0 <= float(uv[0, 0]) <= cam.width  # in view, where a wall would have been seen
    c0, _ = _throw_ball("rigid", camera=False)
    assert c0[-1, 0] - c0[0, 0] < 0.1  # the margin box alone: the wall
