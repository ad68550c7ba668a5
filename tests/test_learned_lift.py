"""The learned lift (ImageDream + LGM): recentring, the input camera, LGM's frame → our world, the
generated views for refinement, end to end with tiny random-weight models, and the nodes."""

import math

import numpy as np
import pytest
import torch

from physmotion_core.errors import InputError, Interrupted, MissingModelError
from physmotion_core.lift.imagedream import generate_views, load_imagedream, views_for_lgm
from physmotion_core.lift.learned import (LearnedLiftResult, input_camera, learned_lift, lgm_gaussians_to_world,
                                          recenter, views_for_refine)
from physmotion_core.lift.lgm import IMAGENET_MEAN, IMAGENET_STD, LGMNet, load_lgm, orbit_pose
from physmotion_core.lift.silhouette import LiftResult
from physmotion_core.refine import RefineView
from physmotion_core.render.rasterize import rasterize
from physmotion_core.types import Camera

from tiny_models import IMAGEDREAM_NAME, LGM_INPUT_SIZE, LGM_NAME, write_tiny_imagedream, write_tiny_lgm

H, W = 120, 160


def _photo():
    """A 160x120 grey photo with a reddish ellipse off-centre (lower left), and its mask."""
    yy, xx = np.mgrid[:H, :W].astype(np.float32)
    mask = (((xx + 0.5 - 52) / 24) ** 2 + ((yy + 0.5 - 70) / 34) ** 2 < 1).astype(np.float32)
    img = np.full((H, W, 3), 0.45, np.float32)
    img[mask > 0] = np.stack([0.75 + 0.1 * np.sin(xx / 5), 0.25 + 0.1 * np.cos(yy / 7), 0.15 + 0 * xx], -1)[mask > 0]
    return img, mask


@pytest.fixture(scope="module")
def models_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    write_tiny_imagedream(root)
    write_tiny_lgm(root)
    return root


@pytest.fixture(scope="module")
def pipe(models_root):
    return load_imagedream(str(models_root / "physmotion" / "imagedream" / IMAGEDREAM_NAME), device="cpu")


@pytest.fixture(scope="module")
def lgm(models_root):
    return load_lgm(LGM_NAME, root=models_root, input_size=LGM_INPUT_SIZE, device="cpu")


@pytest.fixture(scope="module")
def lifted(pipe, lgm):
    img, mask = _photo()
    return learned_lift(img, mask, lgm=lgm, imagedream=pipe, steps=2, seed=3, object_height=0.3)


# ----------------------------------------------------------------------------------------------
# recentring and the input camera (exact geometry)
# ----------------------------------------------------------------------------------------------

def test_recenter_places_the_object_like_lgm():
    img, mask = _photo()
    canvas, cmask, rmap = recenter(img, mask, border_ratio=0.2, size=64)
    assert canvas.shape == (64, 64, 3) and cmask.shape == (64, 64)
    ys, xs = np.nonzero(cmask > 0.5)
    # the longer side (the 68 px tall box) fills int(64 * 0.8) = 51 px, centred
    assert ys.max() - ys.min() + 1 == pytest.approx(51, abs=1)
    assert (ys.min() + ys.max() + 1) / 2 == pytest.approx(32, abs=1)
    assert (xs.min() + xs.max() + 1) / 2 == pytest.approx(32, abs=1)
    assert rmap.scale_y == pytest.approx(51 / 68) and rmap.scale_x == pytest.approx(round(48 * 51 / 68) / 48)
    # white outside the object, the photo's colours inside; the map sends box corners to the canvas box
    assert np.all(canvas[cmask == 0] == 1.0)
    inside = cmask > 0.99
    assert np.abs(canvas[inside] - np.array([0.75, 0.25, 0.15])).max() < 0.12
    corners = rmap.to_canvas(torch.tensor([[rmap.photo_x0, rmap.photo_y0], [rmap.photo_x0 + 48, rmap.photo_y0 + 68]]))
    torch.testing.assert_close(corners, torch.tensor([[rmap.canvas_x0, rmap.canvas_y0],
                                                      [rmap.canvas_x0 + 36, rmap.canvas_y0 + 51]]))
    pts = torch.rand(5, 2) * 100
    torch.testing.assert_close(rmap.to_photo(rmap.to_canvas(pts)), pts, atol=1e-4, rtol=0)


@pytest.mark.parametrize("border, match", [(0.95, "border_ratio"), (-0.1, "border_ratio")])
def test_recenter_rejects_bad_borders(border, match):
    img, mask = _photo()
    with pytest.raises(InputError, match=match):
        recenter(img, mask, border_ratio=border)
    with pytest.raises(InputError, match="mask has 0 pixels"):
        recenter(img, np.zeros((H, W), np.float32))


def test_input_camera_sees_the_photo_as_lgm_sees_the_canvas():
    """A point's pixel in the photo through the returned camera is exactly its pixel in LGM's
    azimuth-0 view of the canvas, mapped back through the recentring (any world similarity)."""
    img, mask = _photo()
    _, _, rmap = recenter(img, mask, size=256)
    s, shift = 0.23, torch.tensor([0.0, 0.11, 0.0])
    cam = input_camera(rmap, s, shift)
    canvas_cam = Camera.from_fov(256, 256, 49.1, orbit_pose(0, 0, 1.5))
    pts = torch.rand(200, 3) * 1.6 - 0.8                                  # LGM's frame
    uv_canvas, z_canvas = canvas_cam.project(pts)
    uv_photo, z_photo = cam.project(pts * s + shift)
    torch.testing.assert_close(uv_photo, rmap.to_photo(uv_canvas), atol=2e-3, rtol=0)
    torch.testing.assert_close(z_photo, z_canvas * s, atol=1e-5, rtol=1e-5)
    # the camera follows docs/lift.md ("Frames and conventions"): on +z, level, looking down -z
    torch.testing.assert_close(cam.c2w[:3, :3], torch.eye(3))
    assert float(cam.c2w[0, 3]) == 0.0 and float(cam.c2w[2, 3]) == pytest.approx(1.5 * s)
    assert (cam.width, cam.height) == (W, H)


def test_world_transform_scales_to_height_and_ground():
    g = torch.zeros(50, 14)
    g[:, 0:3] = torch.rand(50, 3) * 1.2 - 0.6
    g[:, 3] = 0.8
    g[:, 4:7] = 0.01 + 0.02 * torch.rand(50, 3)
    g[:, 7:11] = torch.nn.functional.normalize(torch.randn(50, 4), dim=-1)
    g[:, 11:] = 0.5
    y = g[:, 1]
    out, s, shift = lgm_gaussians_to_world(g, rotation_dim=-1, object_height=2.0, on_ground=True, ground_height=0.5)
    assert s == pytest.approx(2.0 / float(y.max() - y.min()))
    assert float(out.means[:, 1].min()) == pytest.approx(0.5, abs=1e-6)
    assert float(out.means[:, 1].max() - out.means[:, 1].min()) == pytest.approx(2.0, rel=1e-6)
    torch.testing.assert_close(out.means[:, [0, 2]], g[:, [0, 2]] * s)           # no rotation, no x/z shift
    torch.testing.assert_close(out.scales, g[:, 4:7] * s)
    torch.testing.assert_close(out.quats, g[:, 7:11])
    centred, _, _ = lgm_gaussians_to_world(g, rotation_dim=-1, object_height=2.0, on_ground=False)
    assert float(centred.means[:, 1].min() + centred.means[:, 1].max()) == pytest.approx(0.0, abs=1e-5)


def test_rotation_quirk_keeps_the_covariance_the_original_rasterizer_drew():
    """dim-1 weights: the covariance is R(q) S² R(q)ᵀ with the raw (non-unit) q, as the CUDA
    rasterizer computed it; re-normalising q would give the Gaussians arbitrary orientations."""
    n = 400
    g = torch.zeros(n, 14)
    g[:, 0:3] = torch.rand(n, 3) - 0.5
    g[:, 3] = 0.9
    g[:, 4:7] = 0.005 + 0.05 * torch.rand(n, 3)
    g[:, 7:11] = torch.nn.functional.normalize(torch.randn(n, 4), dim=0)     # the quirk: unit columns
    g[:, 11:] = 0.3
    out, s, _ = lgm_gaussians_to_world(g, rotation_dim=1, object_height=1.0)
    from physmotion_core.lift.lgm import raw_rotation_matrix

    R = raw_rotation_matrix(g[:, 7:11].double())
    S = g[:, 4:7].double() * s
    want = R @ torch.diag_embed(S ** 2) @ R.transpose(1, 2)
    torch.testing.assert_close(out.covariance().double(), want, atol=1e-9, rtol=1e-4)
    torch.testing.assert_close(out.quats.norm(dim=-1), torch.ones(n))
    # ... which is nearly axis-aligned (|q| ~ 2/sqrt(N)): far from the re-normalised orientations
    naive = torch.nn.functional.normalize(g[:, 7:11], dim=-1)
    from physmotion_core.types import quat_to_rotmat

    Rn = quat_to_rotmat(naive).double()
    naive_cov = Rn @ torch.diag_embed(S ** 2) @ Rn.transpose(1, 2)
    assert float((want - torch.diag_embed(torch.diagonal(want, dim1=1, dim2=2))).abs().max()) < 0.05 * float(S.max() ** 2)
    assert float((naive_cov - want).abs().max()) > 0.2 * float(S.max() ** 2)


# ----------------------------------------------------------------------------------------------
# a perfect LGM: the render lands on the input mask
# ----------------------------------------------------------------------------------------------

class OracleLGM(LGMNet):
    """What a perfect LGM returns for its front view: one opaque Gaussian per splat pixel where the
    azimuth-0 view is not white, on that pixel's ray at the plane z = 0, coloured like the view;
    every Gaussian of the other views transparent. (Pre-activation values, so LGM's head runs.)"""

    def forward_raw(self, images):
        b, v, c, s, _ = images.shape
        rgb = images[:, 0, :3] * torch.tensor(IMAGENET_STD).view(1, 3, 1, 1) + torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        n = self.cfg.splat_size
        rgb = torch.nn.functional.adaptive_avg_pool2d(rgb, n)[0]                     # [3, n, n]
        on = (1 - rgb).amax(0) > 0.4                 # at least about half of the splat pixel is object
        f = 0.5 * n / math.tan(math.radians(self.cfg.fovy) / 2)
        px = (torch.arange(n) + 0.5 - n / 2) / f
        yy, xx = torch.meshgrid(px, px, indexing="ij")
        raw = torch.zeros(b, v, n, n, 14)
        raw[0, 0, ..., 0] = self.cfg.cam_radius * xx                                 # ray ∩ plane z = 0
        raw[0, 0, ..., 1] = -self.cfg.cam_radius * yy
        raw[..., 3] = -9.0
        raw[0, 0, ..., 3] = torch.where(on, 9.0, -9.0)
        sigma = 0.5 * self.cfg.cam_radius / f                                        # half a splat pixel
        raw[..., 4:7] = math.log(math.expm1(sigma / 0.1))
        raw[..., 7] = 1.0
        raw[0, 0, ..., 11:14] = torch.atanh((2 * rgb - 1).clamp(-0.99, 0.99)).permute(1, 2, 0)
        return raw.reshape(b, v * n * n, 14)


def test_a_perfect_lgm_lands_on_the_input_mask(lgm):
    img, mask = _photo()
    canvas, _, _ = recenter(img, mask, size=64)
    views = torch.ones(4, 64, 64, 3)
    views[0] = torch.from_numpy(canvas)
    oracle = OracleLGM(lgm.cfg)
    res = learned_lift(img, mask, lgm=oracle, views=views, object_height=0.3)
    assert res.info["n_kept"] < res.info["n_lgm"] / 4                # the transparent ones were pruned
    r = rasterize(res.gaussians, res.camera)
    drawn, want = r.alpha.numpy() > 0.5, mask > 0.5
    iou = (drawn & want).sum() / (drawn | want).sum()
    # Tolerance: the oracle samples the object on LGM's 32² splat grid, 2.7 photo pixels per splat,
    # so the outline is quantised by about ±1.4 px and the splats' Gaussian fall-off moves the 0.5
    # alpha contour by a fraction of a splat; on this 48x68 px ellipse that band is ~5-7 % of its
    # area (measured IoU 0.936). The centroids must agree to 1 px, and a camera whose principal
    # point is off by 4 px already fails the IoU check (below).
    assert iou > 0.9, iou
    cy, cx = [float(np.mean(a)) for a in np.nonzero(drawn)]
    wy, wx = [float(np.mean(a)) for a in np.nonzero(want)]
    assert abs(cx - wx) < 1.0 and abs(cy - wy) < 1.0
    import dataclasses

    off = rasterize(res.gaussians, dataclasses.replace(res.camera, cx=res.camera.cx + 4)).alpha.numpy() > 0.5
    assert (off & want).sum() / (off | want).sum() < 0.9
    # colours come through as well
    assert np.abs(r.rgb.numpy()[want & drawn] - img[want & drawn]).mean() < 0.08
    assert float(res.gaussians.means[:, 1].min()) == pytest.approx(0.0, abs=1e-6)


# ----------------------------------------------------------------------------------------------
# end to end with tiny random-weight ImageDream + LGM (real loaders, official folder layout)
# ----------------------------------------------------------------------------------------------

def test_end_to_end_frame_and_views(lifted, lgm):
    res = lifted
    assert isinstance(res, LiftResult) and isinstance(res, LearnedLiftResult)
    g = res.gaussians
    assert res.info["n_lgm"] == 4 * 32 * 32 and len(g) == res.info["n_kept"] <= 4096
    g.validate()
    y = g.means[:, 1]
    assert float(y.max() - y.min()) == pytest.approx(0.3, rel=1e-5)
    assert float(y.min()) == pytest.approx(0.0, abs=1e-6)
    D = 1.5 * res.scale
    cam = res.camera
    torch.testing.assert_close(cam.c2w[:3, :3], torch.eye(3))
    torch.testing.assert_close(cam.position, torch.tensor([0.0, float(res.shift[1]), D]))
    assert bool((g.means[:, 2] < cam.position[2]).all())               # everything in front of the camera
    assert res.mask.shape == (H, W) and torch.equal(res.mask, torch.from_numpy(_photo()[1]))
    # the four generated views, at LGM's azimuths round the object's axis, looking at it
    assert res.view_images.shape == (4, 64, 64, 3)
    assert [v.name for v in res.views] == ["imagedream_az000", "imagedream_az090", "imagedream_az180",
                                           "imagedream_az270"]
    target = torch.tensor([0.0, float(res.shift[1]), 0.0])
    for v, az in zip(res.views, (0, 90, 180, 270)):
        assert isinstance(v, RefineView) and not v.colour and v.depth is None
        a = math.radians(az)
        torch.testing.assert_close(v.camera.position, target + D * torch.tensor([math.sin(a), 0.0, math.cos(a)]),
                                   atol=1e-6, rtol=0)
        torch.testing.assert_close(v.camera.c2w[:3, 2], (v.camera.position - target) / D, atol=1e-6, rtol=0)
        assert v.camera.fov_y_deg == pytest.approx(49.1)
        assert v.image.shape == (64, 64, 3) and v.mask.shape == (64, 64)
        torch.testing.assert_close(v.image, res.view_images[[0, 90, 180, 270].index(az)] * v.mask[..., None])
    assert [v.name for v in views_for_refine(res.views)] == ["imagedream_az090", "imagedream_az180",
                                                            "imagedream_az270"]
    assert len(views_for_refine(res.views, include_front=True)) == 4
    blank = RefineView(camera=res.views[1].camera, image=torch.zeros(64, 64, 3), mask=torch.zeros(64, 64),
                       name="imagedream_az090")
    assert views_for_refine([blank]) == []                              # nothing to compare against


def test_end_to_end_is_deterministic_and_seeded(lifted, pipe, lgm):
    img, mask = _photo()
    again = learned_lift(img, mask, lgm=lgm, imagedream=pipe, steps=2, seed=3, object_height=0.3)
    assert torch.equal(again.gaussians.means, lifted.gaussians.means)
    assert torch.equal(again.view_images, lifted.view_images)
    other = learned_lift(img, mask, lgm=lgm, imagedream=pipe, steps=2, seed=4, object_height=0.3)
    assert float((other.view_images - lifted.view_images).abs().max()) > 1e-3
    # the same views given directly give the same Gaussians (ImageDream is then not needed)
    direct = learned_lift(img, mask, lgm=lgm, views=lifted.view_images, object_height=0.3)
    assert torch.equal(direct.gaussians.means, lifted.gaussians.means)


def test_the_views_are_imagedream_of_the_recentred_photo_in_lgm_order(lifted, pipe):
    img, mask = _photo()
    canvas, _, _ = recenter(img, mask, size=pipe.image_size)
    want = views_for_lgm(generate_views(pipe, canvas, num_inference_steps=2, seed=3))
    assert torch.equal(lifted.view_images, want)
    torch.testing.assert_close(lifted.canvas, torch.from_numpy(canvas))


def test_pruning_and_cap(lifted, lgm):
    img, mask = _photo()
    op = lifted.lgm_gaussians[:, 3]
    thr = float(op.median())
    pruned = learned_lift(img, mask, lgm=lgm, views=lifted.view_images, prune_opacity=thr)
    assert len(pruned.gaussians) == int((op >= thr).sum())
    assert float(pruned.gaussians.opacities.min()) >= thr - 1e-6
    capped = learned_lift(img, mask, lgm=lgm, views=lifted.view_images, max_gaussians=100)
    assert len(capped.gaussians) == 100
    assert float(capped.gaussians.opacities.min()) >= float(torch.topk(op, 100).values.min()) - 1e-6
    with pytest.raises(InputError, match="below the opacity threshold"):
        learned_lift(img, mask, lgm=lgm, views=lifted.view_images, prune_opacity=0.999999)


def test_progress_and_cancel(pipe, lgm):
    img, mask = _photo()
    calls = []
    learned_lift(img, mask, lgm=lgm, imagedream=pipe, steps=2, progress=lambda d, t: calls.append((d, t)))
    assert calls[-1] == (3, 3) and [c[1] for c in calls] == [3] * len(calls) and len(calls) == 3

    def cancel():
        raise Interrupted("stop")

    with pytest.raises(Interrupted):
        learned_lift(img, mask, lgm=lgm, imagedream=pipe, steps=2, cancel=cancel)


@pytest.mark.parametrize("kwargs, match", [(dict(object_height=0), "object_height"),
                                           (dict(prune_opacity=1.5), "prune_opacity"),
                                           (dict(max_gaussians=-1), "max_gaussians"),
                                           (dict(views=torch.ones(3, 64, 64, 3)), "4 square RGB")])
def test_bad_inputs(lgm, kwargs, match):
    img, mask = _photo()
    kw = dict(views=torch.ones(4, 64, 64, 3))
    kw.update(kwargs)
    with pytest.raises(InputError, match=match):
        learned_lift(img, mask, lgm=lgm, **kw)
    with pytest.raises(InputError, match="ImageDream pipeline"):
        learned_lift(img, mask, lgm=lgm)


# ----------------------------------------------------------------------------------------------
# nodes, in-process
# ----------------------------------------------------------------------------------------------

@pytest.fixture
def nodes(models_root, monkeypatch, tmp_path):
    from comfy_harness import node_classes

    monkeypatch.setenv("PHYSMOTION_MODELS", str(models_root))
    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))             # previews land there
    return node_classes()


def test_loader_nodes_list_and_load(nodes):
    lgm_spec = nodes["PhysMotionLGMLoader"].INPUT_TYPES()["required"]
    assert lgm_spec["lgm_name"][0] == [LGM_NAME]
    net, = nodes["PhysMotionLGMLoader"]().run(LGM_NAME, "auto", LGM_INPUT_SIZE)
    assert isinstance(net, LGMNet) and net.rotation_dim == -1 and net.cfg.input_size == LGM_INPUT_SIZE
    assert net.device.type == "cpu"
    id_spec = nodes["PhysMotionImageDreamLoader"].INPUT_TYPES()["required"]
    assert id_spec["model_name"][0] == [IMAGEDREAM_NAME]
    pipe, = nodes["PhysMotionImageDreamLoader"]().run(IMAGEDREAM_NAME)
    assert pipe.image_size == 64 and pipe.device.type == "cpu"
    with pytest.raises(MissingModelError, match="physmotion/lgm"):
        nodes["PhysMotionLGMLoader"]().run("model_fp16.safetensors", "auto", 256)


def test_lift_nodes_feed_hard_depth_refine(nodes, pipe, lgm, tmp_path):
    img, mask = _photo()
    image, m = torch.from_numpy(img)[None], torch.from_numpy(mask)[None]
    out = nodes["PhysMotionMultiViewGenerate"]().run(pipe, image, m, seed=3, steps=2, guidance=5.0,
                                                     border_ratio=0.2)
    views, = out["result"]
    assert views.shape == (4, 64, 64, 3)
    # the node shows the 4 views as one 2x2 grid
    import cv2

    (shown,) = out["ui"]["images"]
    grid = cv2.imread(str(tmp_path / ".previews" / shown["filename"]))[..., ::-1] / 255.0
    assert grid.shape == (128, 128, 3)
    assert abs(grid[64:, :64] - views[2].numpy()).max() < 1.5 / 255  # bottom-left: the back view (180°)
    lift = nodes["PhysMotionLGMLift"]()
    common = dict(object_height=0.3, on_ground=True, prune_opacity=0.005, max_gaussians=0, seed=3, steps=2,
                  guidance=5.0, border_ratio=0.2)
    g, cam, pm_views, images = lift.run(lgm, image, m, imagedream=pipe, **common)["result"]
    assert torch.equal(images, views)                                   # the node generated the same views
    g2, _, _, _ = lift.run(lgm, image, m, views=views, **common)["result"]
    assert torch.equal(g.means, g2.means)
    assert isinstance(cam, Camera) and (cam.width, cam.height) == (W, H)
    assert len(pm_views) == 3 and all(isinstance(v, RefineView) for v in pm_views)
    with pytest.raises(ValueError, match="connect an ImageDream"):
        lift.run(lgm, image, m, **common)
    out = nodes["PhysMotionHardDepthRefine"]().run(
        g, cam, image, m, iterations=2, hard_depth_every=1, learning_rate=1e-3, prune_floaters=False,
        max_render_side=64, time_limit_s=0.0, seed=0, views=pm_views, filename_prefix="")
    refined, preview = out["result"][:2] if isinstance(out, dict) else out[:2]
    assert len(refined) == len(g) and preview.shape[0] == 1
