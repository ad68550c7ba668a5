"""Fit Gaussians to Photo: any frame, units and centring lined up with the photo (issue 16, item 2).

The recovery cases take our own silhouette lift of a small synthetic photo, put it through a random
similarity (one of the 24 canonical frames, then up to 20° more about a random axis, a scale of
0.2-5x and an offset) and check that the fit undoes it: IoU >= 0.95 with the mask, rotation error
<= 3°, the object on the ground at the requested height.

Symmetry and the rotation error: the silhouette lift builds a solid that is mirror-symmetric about
its mid-plane z = 0. A mirror is not a rotation, so it adds no equivalent rotations, but it does make
the silhouette alone an even function of small turns about the in-plane axes (to first order the
silhouette of R_y(+θ)·S and R_y(-θ)·S are the same). The synthetic photo therefore has an
asymmetric outline (a body with an arm on the upper right and a foot on the lower left: no mirror
or rotational symmetry in the image) and asymmetric colours (horizontal and vertical gradients and
a diagonal split), which the lift carries onto the front (the back is the photo mirrored left-right),
so exactly one rotation reproduces the photo and the plain angle of R_fit · R_applied is the error.
"""

from __future__ import annotations

import math
import numpy as np
import pytest
import torch

from physmotion_core.errors import InputError
from physmotion_core.lift import silhouette_lift
from physmotion_core.lift.fit import (FitError, axis_angle_to_matrix, canonical_rotations, fit_gaussians_to_photo,
                                      rotate_sh, rotation_angle_deg, _quat_mul, _sh_basis)
from physmotion_core.render.rasterize import rasterize
from physmotion_core.types import Camera, Gaussians, rotmat_to_quat

@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """The fit renders hundreds of small images; on a machine shared with other jobs, torch's
    2-thread pool spends far longer waiting at barriers (index_add_ on a few kB: 35 ms instead of
    6 µs at a load of 9 on 2 cores) than working. One thread is also what a batch worker uses."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# The photo is 80x96: the finest level is the photo itself, the first the coarse 48 px one.
LEVELS = ((48, 24), (96, 30))


def _photo(H=96, W=80):
    yy, xx = np.mgrid[:H, :W] + 0.5
    m = (xx - 36) ** 2 / 22 ** 2 + (yy - 52) ** 2 / 30 ** 2 < 1
    m |= (np.abs(xx - 62) < 7) & (yy > 22) & (yy < 50)
    m |= (np.abs(yy - 80) < 5) & (xx > 10) & (xx < 36)
    img = np.zeros((H, W, 3), np.float32)
    img[..., 0] = 0.2 + 0.7 * xx / W
    img[..., 1] = 0.9 - 0.7 * yy / H
    img[..., 2] = np.where(xx + yy < 90, 0.8, 0.2)
    return img, m.astype(np.float32)


@pytest.fixture(scope="module")
def lifted():
    img, m = _photo()
    # Not on the ground: the lift's camera then has its principal point at the image centre, as
    # the fit assumes by default (a shift-lens photo would need principal_point).
    res = silhouette_lift(img, m, on_ground=False, max_gaussians=3000)
    assert res.camera.cx == 40 and res.camera.cy == 48
    return img, m, res


def _similarity(g: Gaussians, R: torch.Tensor, s: float, t: torch.Tensor) -> Gaussians:
    q = rotmat_to_quat(R[None])[0]
    return Gaussians(means=s * g.means @ R.T + t, quats=_quat_mul(q[None].expand(len(g), 4), g.quats),
                     scales=g.scales * s, opacities=g.opacities, sh=g.sh)


def _iou(alpha: torch.Tensor, mask) -> float:
    a, m = alpha > 0.5, torch.as_tensor(mask) > 0.5
    return float((a & m).sum() / (a | m).sum())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_a_random_canonical_frame_rotation_scale_and_offset(lifted, seed):
    img, m, lift = lifted
    gen = torch.Generator().manual_seed(100 + seed)
    R_canon = canonical_rotations(4)[int(torch.randint(0, 24, (1,), generator=gen))]
    axis = torch.nn.functional.normalize(torch.randn(3, generator=gen), dim=0)
    extra = math.radians(20.0) * float(torch.rand(1, generator=gen))
    R_applied = axis_angle_to_matrix(axis * extra) @ R_canon
    s = math.exp(float(torch.empty(1).uniform_(math.log(0.2), math.log(5.0), generator=gen)))
    t = torch.randn(3, generator=gen) * 3.0
    moved = _similarity(lift.gaussians, R_applied, s, t)

    res = fit_gaussians_to_photo(moved, img, m, object_height=0.45, levels=LEVELS, yaw_steps=4, keep=2,
                                 screen_steps=10, seed=seed)
    assert res.ok and res.iou >= 0.95, res.report()
    # The lift's camera frame is the world's (level, looking down -z), so the pose the fit found relative
    # to the camera must undo R.
    err = rotation_angle_deg(res.view_rotation @ R_applied)
    assert err <= 3.0, (err, res.report())
    # The returned pair reproduces the photo on its own (at the photo's full size).
    with torch.no_grad():
        out = rasterize(res.gaussians, res.camera)
    assert _iou(out.alpha, m) >= 0.95
    # On the ground at the requested height (every lift Gaussian is significant here).
    y = res.gaussians.means[:, 1]
    assert float(y.min()) == pytest.approx(0.0, abs=1e-6)
    assert float(y.max() - y.min()) == pytest.approx(0.45, rel=1e-5)
    # Upright: one of the input's axes (the one nearest the photo's up, within the 20° added above) is
    # the world's +y, and the camera turns by the rest (its c2w rotation times the pose = the world
    # rotation), so the render is unchanged; it stays behind the object, looking down -z.
    world_y_in_input = res.rotation.double()[1]
    assert float(world_y_in_input.abs().max()) == pytest.approx(1.0, abs=1e-5)
    assert torch.allclose(res.camera.c2w[:3, :3].double() @ res.view_rotation.double(), res.rotation.double(),
                          atol=1e-5)
    assert rotation_angle_deg(res.camera.c2w[:3, :3]) <= 20.0 * math.sqrt(2.0)
    assert float(res.camera.c2w[2, 3]) > float(res.gaussians.means[:, 2].max())
    pred = res.scale * moved.means.double() @ res.rotation.double().T + res.translation.double()
    assert torch.allclose(pred.float(), res.gaussians.means, atol=1e-5)
    cov_in = moved.covariance().double()
    R = res.rotation.double()
    expect = res.scale ** 2 * R @ cov_in @ R.T
    assert torch.allclose(res.gaussians.covariance().double(), expect, atol=1e-9, rtol=1e-4)


def test_shape_that_cannot_match_is_reported_not_passed_on():
    # A ball against a bar 4x as long as thick: no rotation or scale makes a sphere's (round)
    # silhouette a bar. (A bar against a round mask could be seen end-on, which matches.)
    g = _sphere_shell(radius=1.0, n=600)
    H, W = 64, 64
    yy, xx = np.mgrid[:H, :W] + 0.5
    bar = ((np.abs(xx - 32) < 24) & (np.abs(yy - 32) < 6)).astype(np.float32)
    img = np.full((H, W, 3), 0.5, np.float32)
    res = fit_gaussians_to_photo(g, img, bar, levels=((48, 15),), yaw_steps=1, keep=1)
    assert not res.ok and res.iou < 0.6
    assert "Could not line the Gaussians up" in res.message and f"{res.iou:.3f}" in res.message
    assert res.overlay.shape == (64, 128, 3)
    # The overlay's right half shows the mask in green where the ball does not reach.
    right = res.overlay[:, 64:]
    assert float(right[32, 9, 1]) > 0.8 and float(right[32, 9, 0]) < 0.2
    with pytest.raises(FitError) as info:
        fit_gaussians_to_photo(g, img, bar, levels=((48, 15),), yaw_steps=1, keep=1, raise_on_failure=True)
    assert info.value.result.iou == pytest.approx(res.iou) and isinstance(info.value, InputError)


def test_matching_outline_with_wrong_colours_is_reported():
    # The right shape, the wrong object: a ball coloured by height, photographed green.
    g = _sphere_shell(radius=1.0, n=600)
    cam = Camera.look_at((5.0, -2.0, 7.0), (5.0, -2.0, 1.0), width=48, height=48, fov_y_deg=40)
    with torch.no_grad():
        mask = (rasterize(g, cam).alpha > 0.5).float()
    photo = mask[..., None] * torch.tensor([0.1, 0.9, 0.1])
    kw = dict(levels=((48, 15),), yaw_steps=1, keep=1)
    res = fit_gaussians_to_photo(g, photo, mask, **kw)
    assert res.iou >= 0.9 and res.color_error > 0.3 and not res.ok
    assert "the colours do not" in res.message
    assert fit_gaussians_to_photo(g, photo, mask, max_color_error=0, **kw).ok  # 0 = not checked


def _sphere_shell(radius: float, n: int, centre=(5.0, -2.0, 1.0)) -> Gaussians:
    """Surface splats only (a hollow ball, as a .ply from a 3DGS tool is), Fibonacci-spaced,
    flattened along the normal, coloured by height."""
    k = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.acos(1 - 2 * k / n)
    theta = math.pi * (1 + 5 ** 0.5) * k
    d = torch.stack([torch.cos(theta) * torch.sin(phi), torch.cos(phi), torch.sin(theta) * torch.sin(phi)], -1)
    spacing = radius * math.sqrt(4 * math.pi / n)
    # Rotation taking z to the normal d (columns: t1, t2, d).
    up = torch.where(d[:, 1:2].abs() < 0.9, torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64),
                     torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))
    t1 = torch.nn.functional.normalize(torch.linalg.cross(up, d), dim=-1)
    t2 = torch.linalg.cross(d, t1)
    R = torch.stack([t1, t2, d], -1)
    quats = rotmat_to_quat(R.float())
    scales = torch.tensor([spacing * 0.6, spacing * 0.6, spacing * 0.05]).expand(n, 3).float().clone()
    rgb = torch.stack([0.5 + 0.4 * d[:, 1], 0.3 + 0.0 * d[:, 1], 0.7 - 0.4 * d[:, 0]], -1).float()
    means = (radius * d + torch.tensor(centre, dtype=torch.float64)).float()
    return Gaussians.from_rgb(means, rgb, scales, torch.full((n,), 0.95), quats)


def test_hollow_shell_from_a_ply_fits_and_still_fills_as_a_solid(tmp_path):
    from physmotion_core.ply import read_ply, write_ply
    from physmotion_core.sim.fill import fill_particles

    shell = _sphere_shell(radius=2.0, n=1500)
    write_ply(tmp_path / "shell.ply", shell)
    g = read_ply(tmp_path / "shell.ply")
    # The photo: the ball seen by some other camera, off-centre in the frame.
    cam = Camera.look_at((6.0, -1.0, 9.0), (5.3, -2.2, 1.0), width=72, height=64, fov_y_deg=35)
    with torch.no_grad():
        out = rasterize(g, cam)
    img, mask = out.rgb.clamp(0, 1), (out.alpha > 0.5).float()
    res = fit_gaussians_to_photo(g, img, mask, object_height=0.3, levels=((48, 25), (72, 25)), yaw_steps=4, keep=1)
    assert res.ok and res.iou >= 0.95, res.report()
    y = res.gaussians.means[:, 1]
    assert float(y.max() - y.min()) == pytest.approx(0.3, rel=1e-4)
    # The shell is filled for the physics: particles fill the ball's volume (centres' radius r,
    # plus up to about one voxel of the stamped sheet), including its centre.
    r = 0.15
    spacing = r / 12
    parts = fill_particles(res.gaussians, spacing, jitter=0.0)
    centre = res.gaussians.means.mean(0).numpy()
    assert np.linalg.norm(parts.x - centre, axis=1).min() < spacing
    ball = 4.0 / 3.0 * math.pi * r ** 3
    assert 0.95 * ball < parts.volume.sum() < 1.5 * ball, parts.volume.sum() / ball
    sheet = fill_particles(res.gaussians, spacing, jitter=0.0, fill_interior=False)
    assert sheet.volume.sum() < 0.75 * parts.volume.sum()


def test_canonical_rotations_are_the_24_cube_rotations_and_their_45_degree_turns():
    R = canonical_rotations(4)
    assert R.shape == (24, 3, 3)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(24, 3, 3), atol=1e-6)
    assert torch.allclose(torch.linalg.det(R), torch.ones(24), atol=1e-6)
    # Distinct, and closed under composition (a group): every product is again one of them.
    flat = R.reshape(24, 9).round(decimals=4)
    assert len({tuple(r.tolist()) for r in flat}) == 24
    for a in R[::5]:
        prods = (a @ R).reshape(24, 9).round(decimals=4)
        assert {tuple(p.tolist()) for p in prods} == {tuple(r.tolist()) for r in flat}
    assert canonical_rotations(8).shape == (48, 3, 3)


def test_rotated_sh_give_the_rotated_view_dependent_colour():
    R = axis_angle_to_matrix(torch.tensor([0.3, -0.7, 1.1]))
    sh = torch.randn(5, 16, 3, generator=torch.Generator().manual_seed(0))
    d = torch.nn.functional.normalize(torch.randn(40, 3, generator=torch.Generator().manual_seed(1)), dim=-1)
    new = rotate_sh(sh, R)
    # Colour along d after the rotation == colour along Rᵀ d before it, each degree on its own.
    after = torch.einsum("mk,nkc->nmc", _sh_basis(d.double(), 3).float(), new)
    before = torch.einsum("mk,nkc->nmc", _sh_basis((d @ R).double(), 3).float(), sh)
    assert torch.allclose(after, before, atol=1e-5)
    assert torch.equal(new[:, 0], sh[:, 0])
    with pytest.raises(InputError, match="degree 0-3"):
        rotate_sh(torch.zeros(2, 5, 3), R)


def test_bad_inputs_are_refused_with_what_to_change(lifted):
    img, m, lift = lifted
    g = lift.gaussians
    with pytest.raises(InputError, match="does not match the image size"):
        fit_gaussians_to_photo(g, img, m[:-1])
    with pytest.raises(InputError, match="mask has 0 pixels"):
        fit_gaussians_to_photo(g, img, np.zeros_like(m))
    with pytest.raises(InputError, match="object_height must be a positive"):
        fit_gaussians_to_photo(g, img, m, object_height=-1)
    with pytest.raises(InputError, match="iou_threshold"):
        fit_gaussians_to_photo(g, img, m, iou_threshold=1.5)
    with pytest.raises(InputError, match="principal_point"):
        fit_gaussians_to_photo(g, img, m, principal_point=(1.0,))
    with pytest.raises(InputError, match="must be Gaussians"):
        fit_gaussians_to_photo(img, img, m)


# ----------------------------------------------------------------------------------------------
# The node
# ----------------------------------------------------------------------------------------------


def _node():
    from comfy_harness import node_classes

    return node_classes()["PhysMotionFitGaussiansToPhoto"]()


def test_node_fits_with_progress_and_honours_focal_and_principal_point(lifted, monkeypatch, tmp_path):
    from fake_comfy import install_fake_comfy

    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path))
    state = install_fake_comfy(monkeypatch)
    img, m, lift = lifted
    R = canonical_rotations(4)[7]
    moved = _similarity(lift.gaussians, R, 3.0, torch.tensor([1.0, 2.0, -3.0]))
    f = float(lift.camera.fx)
    out = _node().run(moved, torch.from_numpy(img)[None], torch.from_numpy(m)[None], 0.3, 0.9, 0.15, True, 64, 0,
                      focal_px=f, principal_x=40.0, principal_y=-1.0)
    g, cam, overlay, iou, text = out["result"]
    assert isinstance(g, Gaussians) and iou >= 0.93 and f"IoU {iou:.3f}" in text
    assert cam.fx == pytest.approx(f) and cam.fy == pytest.approx(f) and (cam.cx, cam.cy) == (40.0, 48.0)
    assert overlay.shape == (1, 96, 160, 3)
    assert float(g.means[:, 1].min()) == pytest.approx(0.0, abs=1e-6)
    assert out["ui"]["images"][0]["type"] == "temp" and (tmp_path / out["ui"]["images"][0]["filename"]).exists()
    # The progress bar ran to the end, and every step checked for Cancel.
    assert state.updates and state.updates[-1][0] == state.updates[-1][1]
    assert state.checks >= len(state.updates) > 50


def test_node_stops_with_the_overlay_when_the_fit_is_poor(monkeypatch, tmp_path):
    from fake_comfy import install_fake_comfy

    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path))
    state = install_fake_comfy(monkeypatch)
    g = _sphere_shell(radius=1.0, n=400)
    bar = torch.zeros(1, 48, 48)
    bar[:, 20:28, 4:44] = 1.0
    with pytest.raises(FitError, match="Could not line the Gaussians up") as info:
        _node().run(g, torch.full((1, 48, 48, 3), 0.5), bar, 0.3, 0.85, 0.15, True, 32, 0)
    # The overlay went to the node (the progress bar's preview) and to a temp file the message names.
    name = str(info.value).split("temp file ")[1].split(")")[0]
    assert (tmp_path / name).exists()
    assert state.updates[-1] == (1, 1)


def test_node_cancel_stops_the_fit(lifted, monkeypatch):
    from fake_comfy import InterruptProcessingException, install_fake_comfy

    install_fake_comfy(monkeypatch, cancel_after_checks=5)
    img, m, lift = lifted
    with pytest.raises(InterruptProcessingException):
        _node().run(lift.gaussians, torch.from_numpy(img)[None], torch.from_numpy(m)[None], 0.3, 0.85, 0.15, True, 96, 0)


# ----------------------------------------------------------------------------------------------
# The own_splat_to_physics template's stand-in .ply (tests/comfy_harness.py: write_standin_splat)
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def standin(tmp_path_factory):
    """The stand-in .ply exactly as the template runs write it (20 000 splats of photos/coffee.png's
    silhouette lift, z-up, centimetres, off-centre), read back, with the photo, its mask and the
    lift's camera and transform."""
    from comfy_harness import ROOT, standin_splat
    from physmotion_core.image_io import load_image
    from physmotion_core.ply import read_ply, write_ply
    from physmotion_core.segment import segment

    turned, lift, (R, scale, offset) = standin_splat()
    g = read_ply(write_ply(tmp_path_factory.mktemp("standin") / "my_splat.ply", turned))
    rgb, alpha = load_image(ROOT / "photos" / "coffee.png")
    return g, rgb, segment(rgb, alpha=alpha).mask, lift.camera, R


def _frame_errors(E: torch.Tensor) -> dict:
    """How far the error rotation E = R_fit · R_applied (identity for a perfect fit) turns each
    world axis (degrees): x across the photo, y up, z towards the camera."""
    out = {}
    for k, name in enumerate("xyz"):
        e = torch.zeros(3)
        e[k] = 1.0
        out[name] = math.degrees(math.acos(max(-1.0, min(1.0, float((E @ e)[k])))))
    return out


def test_the_templates_standin_ply_fits_the_right_way_round(standin):
    """As the own_splat_to_physics template runs it (library defaults = the node's at max_render_side
    160; principal point at the image centre). The stand-in's outline is nearly its own mirror
    image, so the pose turned 180° about the up axis (seen from behind) matches the outline too (IoU
    0.94-0.97) and only the colours tell them apart; before the coarse subsets were made to cover
    the object, that pose won (colour error 0.21-0.35) and the fit was refused.

    The lift's camera has its principal point on the object's base line (row 400 of 400; a
    shift-lens camera, as the silhouette lift makes on the ground), the fit assumes the image
    centre: a shifted principal point is about a camera pitch, so the fit pitches the object (about
    the x axis, ~12° measured) and the rotation is checked per axis: x stays put, y and z within
    20° (the flipped pose would turn z and x by 180°)."""
    from physmotion_core.lift.fit import DEFAULT_MAX_COLOR_ERROR

    g, rgb, mask, cam, R_applied = standin
    res = fit_gaussians_to_photo(g, rgb, mask, object_height=0.3)
    assert res.ok and res.iou >= 0.95 and res.color_error <= DEFAULT_MAX_COLOR_ERROR, res.report()
    err = _frame_errors(res.rotation @ R_applied)
    assert err["x"] <= 3.0 and err["y"] <= 20.0 and err["z"] <= 20.0, (err, res.report())
    assert not any(c["round"] == "_retry" for c in res.info["contenders"])  # the first round found it


def test_the_standin_with_its_cameras_principal_point_recovers_the_rotation(standin):
    """Given the principal point the stand-in was lifted with, the exact similarity comes back."""
    g, rgb, mask, cam, R_applied = standin
    res = fit_gaussians_to_photo(g, rgb, mask, object_height=0.3, principal_point=(cam.cx, cam.cy),
                                 levels=((48, 30), (96, 30)))
    assert res.ok and res.iou >= 0.97 and res.color_error <= 0.05, res.report()
    assert rotation_angle_deg(res.view_rotation @ R_applied) <= 3.0, res.report()


def test_a_refused_first_round_retries_the_pose_turned_round(lifted, monkeypatch):
    """The second round: with the coarse search offered only the pose seen from behind (the
    synthetic photo's outline is not its own mirror image), the first round is refused; the retry
    turns its finalists 180° about the up axis and lines up. Without the retry the fit is refused."""
    import physmotion_core.lift.fit as fit_module

    img, m, lift = lifted
    R_applied = canonical_rotations(4)[13]
    moved = _similarity(lift.gaussians, R_applied, 2.0, torch.tensor([0.5, -1.0, 2.0]))
    flipped = fit_module._rot_y(math.pi) @ R_applied.T
    monkeypatch.setattr(fit_module, "canonical_rotations", lambda yaw_steps=8: flipped[None])
    kw = dict(object_height=0.45, levels=LEVELS, keep=1, screen_steps=10)
    res = fit_gaussians_to_photo(moved, img, m, retry=False, **kw)
    assert not res.ok and rotation_angle_deg(res.view_rotation @ R_applied) > 150.0, res.report()
    res = fit_gaussians_to_photo(moved, img, m, **kw)
    assert res.ok and res.iou >= 0.95, res.report()
    assert rotation_angle_deg(res.view_rotation @ R_applied) <= 3.0, res.report()
    assert [c["round"] for c in res.info["contenders"]] == ["", "_retry"]


def _rot_x(deg: float) -> torch.Tensor:
    c, s_ = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s_], [0.0, s_, c]])


@pytest.mark.parametrize("upright", [True, False])
def test_a_photo_from_above_stands_the_object_up_and_tilts_the_camera(lifted, upright):
    """A photo taken from 25° above: the upright lift seen by a camera pitched down is the lift turned
    25° towards the camera about the camera's x axis, seen level. Fitting the upright lift to it, the
    pose relative to the camera carries that pitch. ``upright`` stands the object up (its +y is the
    world's, so it does not topple when simulated) and pitches the camera 25° instead; without it the
    object is tilted 25° under a level camera."""
    _img, _m, lift = lifted
    c = lift.gaussians.means.mean(0)
    R_view = _rot_x(25.0)
    seen = _similarity(lift.gaussians, R_view, 1.0, c - R_view @ c)
    with torch.no_grad():
        out = rasterize(seen, lift.camera)
    photo = (out.rgb / out.alpha.clamp_min(1e-6)[..., None]).clamp(0, 1) * (out.alpha > 0.5)[..., None]
    mask = (out.alpha > 0.5).float()
    res = fit_gaussians_to_photo(lift.gaussians, photo, mask, object_height=0.45, levels=LEVELS, yaw_steps=4,
                                 keep=2, screen_steps=10, upright=upright)
    assert res.ok and res.iou >= 0.95, res.report()
    assert rotation_angle_deg(res.view_rotation @ R_view.T) <= 3.0, res.report()
    pitch = rotation_angle_deg(res.camera.c2w[:3, :3])
    # The object's +y from the world's, as atan2(|off-axis|, on-axis): acos of a float32 cosine near 1 reads one
    # ulp below 1 (a column normalised to 1 - 3e-8) as 0.02°.
    up = res.rotation.double()[:, 1]
    tilt = math.degrees(math.atan2(math.hypot(float(up[0]), float(up[2])), float(up[1])))
    if upright:
        assert tilt <= 1e-3 and pitch == pytest.approx(25.0, abs=3.0), (tilt, pitch)
        assert float(res.camera.c2w[1, 2]) > 0.3  # the camera's back axis points up: it looks down
    else:
        assert pitch == 0.0 and tilt == pytest.approx(25.0, abs=3.0), (tilt, pitch)
    # Either way the pair reproduces the photo.
    with torch.no_grad():
        again = rasterize(res.gaussians, res.camera)
    assert _iou(again.alpha, mask) >= 0.95



def test_fits_under_inference_mode_as_comfyui_runs_nodes(lifted):
    """ComfyUI runs every node under torch.inference_mode(), and its tensors are inference tensors:
    the fit (gradient descent) turns autograd on for itself and works on normal copies."""
    img, m, lift = lifted
    with torch.inference_mode():
        g = _similarity(lift.gaussians, canonical_rotations(4)[5], 1.5, torch.tensor([0.2, 0.0, -1.0]))
        photo, mask = torch.from_numpy(img), torch.from_numpy(m)
        assert g.means.is_inference() and photo.is_inference()
        res = fit_gaussians_to_photo(g, photo, mask, object_height=0.45, levels=LEVELS, yaw_steps=4, keep=2,
                                     screen_steps=10)
        assert torch.is_inference_mode_enabled()  # the caller's mode is back
    assert res.ok and res.iou >= 0.95, res.report()
    assert rotation_angle_deg(res.view_rotation @ canonical_rotations(4)[5]) <= 3.0, res.report()


def test_own_adam_takes_the_same_steps_as_torch_adam():
    """The fit's small Adam (no torch.optim: no torch._dynamo import on first use) is torch's update."""
    from physmotion_core.lift.fit import _Adam

    gen = torch.Generator().manual_seed(0)
    a0, b0 = torch.randn(3, generator=gen), torch.randn(2, generator=gen)
    ours = [a0.clone().requires_grad_(), b0.clone().requires_grad_()]
    ref = [a0.clone().requires_grad_(), b0.clone().requires_grad_()]
    opt = _Adam([{"params": [ours[0]], "lr": 0.02}, {"params": [ours[1]], "lr": 0.005}], betas=(0.8, 0.95))
    ropt = torch.optim.Adam([{"params": [ref[0]], "lr": 0.02}, {"params": [ref[1]], "lr": 0.005}], betas=(0.8, 0.95))
    for step in range(25):
        for o in (opt, ropt):
            for g in o.param_groups:  # a changing rate, as the fit's cosine schedule
                g["lr"] *= 0.97
        for (x, y), o in ((ours, opt), (ref, ropt)):
            loss = (x.sin() * 3.0).pow(2).sum() + (y - 0.3 * step).abs().sum()
            o.zero_grad(set_to_none=True)
            loss.backward()
            o.step()
    for x, y in zip(ours, ref):
        assert torch.allclose(x, y, atol=1e-6, rtol=1e-5)


def test_gradient_renders_in_longer_chunks_equal_the_rasterizer(lifted):
    """The fit's gradient renders walk the tiles GRAD_CHUNK splats at a time; image and gradients
    are the rasterizer's own (default chunks) to round-off."""
    from physmotion_core.lift import fit as fit_module
    from physmotion_core.render.rasterize import _rasterize_with_torch

    img, m, lift = lifted
    g = lift.gaussians
    prep = fit_module._prep(g, g.means.double().mean(0), float(g.means.max() - g.means.min()))
    lv = fit_module._level(torch.from_numpy(img), torch.from_numpy(m), 64, 60.0)
    outs, grads = [], []
    for chunk in (None, fit_module.GRAD_CHUNK):
        p = fit_module._Params(canonical_rotations(4)[3], math.log(60.0), (40.0, 48.0), math.log(120.0), 96.0)
        if chunk is None:  # the plain path: the rasterizer with its defaults, through the same placement
            means, cov = p.place(prep, 40.0, 48.0)
            f = float(torch.exp(p.log_f.detach()))
            cam = Camera(lv.width, lv.height, f * lv.kx, f * lv.ky, 40.0 * lv.kx, 48.0 * lv.ky, torch.eye(4),
                         near=1e-3, far=1e3)
            gg = Gaussians(means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).expand(len(g), 4),
                           scales=torch.ones(len(g), 3), opacities=prep.opacities, sh=torch.zeros(len(g), 1, 3),
                           covars=cov)
            out = _rasterize_with_torch(gg, cam, prep.rgb, prep.opacities, None, "z", 0.3)
        else:
            out = fit_module._render(prep, p, lv, 40.0, 48.0)
        loss = (out.alpha * lv.mask).sum() + out.rgb.sum()
        loss.backward()
        outs.append(out.alpha.detach())
        grads.append(torch.cat([p.omega.grad, p.log_sigma.grad[None], p.uv.grad]))
    assert float(outs[0].sum()) > 100
    assert torch.allclose(outs[0], outs[1], atol=1e-5)
    assert torch.allclose(grads[0], grads[1], rtol=1e-3, atol=1e-3 * float(grads[0].abs().max()))


@pytest.mark.parametrize("focal_free", [True, False])
def test_compiled_gradient_render_equals_the_tensor_path(lifted, monkeypatch, focal_free):
    """A refinement step's render through the compiled path (one affine placement, render/_warp_grad.py) gives
    the tensor path's image and the same gradients of a loss w.r.t. every fitted parameter (rotation, size,
    position, focal), to float32 round-off; with the focal fixed (no gradient asked of it) too."""
    from physmotion_core.lift import fit as fit_module
    from physmotion_core.render import _warp_grad

    if not _warp_grad.available():
        pytest.skip("Warp is not available")
    img, m, lift = lifted
    g = lift.gaussians
    prep = fit_module._prep(g, g.means.double().mean(0), float(g.means.max() - g.means.min()))
    lv = fit_module._level(torch.from_numpy(img), torch.from_numpy(m), 64, 60.0)
    R0 = axis_angle_to_matrix(torch.tensor([0.3, -0.2, 0.1])) @ canonical_rotations(4)[5]
    outs, grads = [], []
    for compiled in (True, False):
        monkeypatch.setattr(_warp_grad, "usable", _warp_grad.usable if compiled else (lambda *a: False))
        p = fit_module._Params(R0, math.log(55.0), (38.0, 50.0), math.log(130.0), 96.0)
        with torch.no_grad():
            p.omega += torch.tensor([0.05, 0.02, -0.03])
        p.log_f.requires_grad_(focal_free)
        out = fit_module._render(prep, p, lv, 40.0, 48.0)
        loss, _, _ = fit_module._losses(out, lv, 0.5)
        loss.backward()
        outs.append(torch.cat([out.rgb, out.alpha[..., None]], -1).detach())
        grads.append(torch.cat([p.omega.grad, p.log_sigma.grad[None], p.uv.grad]
                               + ([p.log_f.grad[None]] if focal_free else [])))
    assert outs[0].shape == outs[1].shape and float(outs[1][..., 3].sum()) > 100
    assert float((outs[0] - outs[1]).abs().max()) < 1e-4
    assert torch.allclose(grads[0], grads[1], rtol=2e-3, atol=2e-3 * float(grads[1].abs().max())), grads


def test_dropped_contenders_and_early_stops_save_steps_not_accuracy(lifted, monkeypatch):
    """Contenders far behind halfway are dropped and finer levels stop on a plateau: fewer steps,
    the same fit as running every step (the progress bar still ends full)."""
    from physmotion_core.lift import fit as fit_module

    img, m, lift = lifted
    moved = _similarity(lift.gaussians, canonical_rotations(4)[9], 2.0, torch.tensor([0.5, -1.0, 2.0]))
    kw = dict(object_height=0.45, levels=((48, 24), (72, 30), (96, 30)), yaw_steps=4, keep=3, screen_steps=10)
    runs = {}
    for name, margin, plateau in (("full", None, 0), ("cheap", fit_module.CONTENDER_MARGIN, fit_module.PLATEAU_STEPS)):
        monkeypatch.setattr(fit_module, "CONTENDER_MARGIN", margin)
        monkeypatch.setattr(fit_module, "PLATEAU_STEPS", plateau)
        calls = []
        res = fit_gaussians_to_photo(moved, img, m, progress=lambda d, t: calls.append((d, t)), **kw)
        steps = sum(len(v) for v in res.info["trace"].values())
        runs[name] = (res, steps, calls)
    full, cheap = runs["full"], runs["cheap"]
    assert full[0].ok and cheap[0].ok, (full[0].report(), cheap[0].report())
    assert cheap[0].iou >= full[0].iou - 0.01
    assert rotation_angle_deg(cheap[0].view_rotation @ full[0].view_rotation.T) <= 3.0
    assert cheap[1] < full[1]
    assert any(c["dropped"] for c in cheap[0].info["contenders"])  # 118 steps -> 77, one of 3 dropped, same IoU
    assert not any(c["dropped"] for c in full[0].info["contenders"])
    for _, _, calls in runs.values():
        assert calls[-1][0] == calls[-1][1] and all(d <= t for d, t in calls)
