"""Photo-textured rendering (physmotion_core/render/photo_texture.py): frame 0 is the photo inside the object,
a rigid translation carries the photo by exactly that much, a tear shows the splats' own colours on the faces
the photo never saw, and the seen test keeps the back out."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from physmotion_core import controls as C
from physmotion_core.blend import composite
from physmotion_core.render.frames import render_frames
from physmotion_core.render.photo_texture import make_photo_texture, seen_weights
from physmotion_core.types import Camera, Gaussians, Material, SimResult

SEG_DATA = "benchmarks/data/segment"


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def psnr(a: torch.Tensor, b: torch.Tensor, where: torch.Tensor) -> float:
    mse = float(((a - b) ** 2)[where].mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def sim_from_positions(rest: Gaussians, positions: list) -> SimResult:
    """Each Gaussian its own particle, moved to the given (N,3) positions per frame, undeformed."""
    X = rest.means.double()
    n = X.shape[0]
    x = torch.stack([torch.as_tensor(p, dtype=torch.float64) for p in positions]).float()
    F = torch.eye(3).expand(len(positions), n, 3, 3).contiguous()
    return SimResult(rest=rest, times=torch.arange(len(positions), dtype=torch.float64) / 24.0, x=x, F=F,
                     binding=torch.arange(n), rest_particles=X.float(), material=Material(),
                     stats={"particle_spacing": 0.005})


# ----------------------------------------------------------------------------------------------
# An analytic slab: a flat sheet of splats facing the camera at exactly 1 m
# ----------------------------------------------------------------------------------------------

W, H = 160, 120


def slab_camera() -> Camera:
    return Camera.look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), width=W, height=H, fov_y_deg=40)


def texture_image() -> torch.Tensor:
    """A detailed photo: the astronaut, scaled to the frame (fine detail everywhere)."""
    from skimage import data

    img = cv2.resize(data.astronaut(), (W, H), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(img).float() / 255.0


def slab(cam: Camera, photo: torch.Tensor, half=(0.36, 0.26), spacing=0.006, z=0.0, rgb=None) -> Gaussians:
    xs = torch.arange(-half[0], half[0] + 1e-9, spacing)
    ys = torch.arange(-half[1], half[1] + 1e-9, spacing)
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    means = torch.stack([xx.flatten(), yy.flatten(), torch.full_like(xx.flatten(), z)], 1)
    if rgb is None:  # the photo's colour under each splat, as a lift gives it
        uv, _ = cam.project(means)
        iu = uv[:, 0].long().clamp(0, W - 1)
        iv = uv[:, 1].long().clamp(0, H - 1)
        rgb = photo[iv, iu]
    else:
        rgb = torch.as_tensor(rgb, dtype=torch.float32).expand(means.shape[0], 3)
    scales = torch.tensor([0.6 * spacing, 0.6 * spacing, 0.1 * spacing]).expand(means.shape[0], 3)
    return Gaussians.from_rgb(means, rgb.contiguous(), scales.contiguous(), torch.full((means.shape[0],), 0.97))


def test_rigid_translation_moves_the_photo_by_exactly_that_much():
    cam = slab_camera()
    photo = texture_image()
    g = slab(cam, photo)
    shift_px = 7
    dx = shift_px * 1.0 / cam.fx  # at 1 m depth: exactly 7 px to the right
    sim = sim_from_positions(g, [g.means, g.means + torch.tensor([dx, 0.0, 0.0])])
    rest = render_frames(sim, cam)  # the splat render
    matte = (rest.alpha[0] > 0.5).float()
    bg = torch.full((H, W, 3), 0.5)
    tex = make_photo_texture(photo, matte, cam, background=bg)
    inner = torch.from_numpy(cv2.erode(matte.numpy().astype(np.uint8), np.ones((9, 9), np.uint8)) > 0)
    for one_map in (True, False):  # the rigid fast path and the 10 composited channels agree
        before = C.ONE_MAP_FLOW
        C.ONE_MAP_FLOW = one_map
        try:
            fr = render_frames(sim, cam, photo=tex)
        finally:
            C.ONE_MAP_FLOW = before
        out = composite(fr.rgb, fr.alpha, bg)
        # Frame 0 is the photo inside the object; frame 1 is the photo moved 7 px to the right.
        assert psnr(out[0], photo, matte > 0.5) > 60.0
        moved = torch.zeros_like(inner)
        moved[:, shift_px:] = inner[:, :-shift_px]
        expect = torch.zeros_like(photo)
        expect[:, shift_px:] = photo[:, :-shift_px]
        err = (out[1] - expect).abs()[moved]
        assert float(err.max()) < 2e-3, (one_map, float(err.max()))
    # The splat render of the same motion is visibly blurrier than the photo: the test can tell them apart.
    splat = composite(render_frames(sim, cam).rgb, rest.alpha, bg)
    assert psnr(splat[1], expect, moved) < 35.0


def test_torn_faces_show_splat_colours_and_old_faces_the_photo():
    cam = slab_camera()
    photo = texture_image()
    front = slab(cam, photo)
    green = (0.0, 1.0, 0.0)
    inside = slab(cam, photo, half=(0.45, 0.33), z=-0.05, rgb=green)  # the inside, behind the front: never photographed
    g = Gaussians.cat([front, inside])
    nf = front.means.shape[0]
    shift_px = 30
    dx = shift_px / cam.fx
    moved = g.means.clone()
    right = torch.zeros(g.means.shape[0], dtype=torch.bool)
    right[:nf] = front.means[:, 0] > 0.0
    moved[right, 0] += dx  # the front's right half slides away: a crack opens onto the inside
    sim = sim_from_positions(g, [g.means, moved])
    rest = render_frames(sim, cam)
    matte = (rest.alpha[0] > 0.5).float()
    seen = seen_weights(sim.gaussians_at(0), cam)
    assert float(seen[:nf][(front.means[:, :2].abs() < 0.2).all(1)].min()) > 0.99  # the front is seen
    assert float(seen[nf:][(inside.means[:, :2].abs() < 0.25).all(1)].max()) < 0.01  # the inside behind it is not
    bg = torch.zeros(H, W, 3)
    tex = make_photo_texture(photo, matte, cam, background=bg)
    out = composite(*(lambda f: (f.rgb, f.alpha))(render_frames(sim, cam, photo=tex)), bg)[1]
    cx = int(round(cam.cx))
    # The crack: pixels just right of the centre line, now showing the inside: its own (green) colour.
    crack = torch.zeros(H, W, dtype=torch.bool)
    crack[25:95, cx + 5:cx + shift_px - 5] = True
    assert float((out[crack] - torch.tensor(green)).abs().max()) < 0.05
    # The old faces: the left half where it was, the right half 30 px on; both the photo.
    left = torch.zeros(H, W, dtype=torch.bool)
    left[25:95, 28:cx - 5] = True
    assert psnr(out, photo, left) > 40.0
    shifted = torch.zeros_like(photo)
    shifted[:, shift_px:] = photo[:, :-shift_px]
    right_px = torch.zeros(H, W, dtype=torch.bool)
    right_px[25:95, cx + shift_px + 5:W - 4] = True
    right_px &= torch.roll(matte > 0.5, shift_px, 1)
    right_px[:, :shift_px] = False
    assert psnr(out, shifted, right_px) > 40.0


# ----------------------------------------------------------------------------------------------
# Real photos through the silhouette lift: frame 0 >= 40 dB inside the object
# ----------------------------------------------------------------------------------------------


def _photo_and_mask(name: str, max_side: int = 200):
    if name == "coffee":
        img = cv2.cvtColor(cv2.imread("photos/coffee.png"), cv2.COLOR_BGR2RGB)
    else:
        from skimage import data

        img = getattr(data, name)()
    mask = cv2.imread(f"{SEG_DATA}/{name}.png", cv2.IMREAD_GRAYSCALE)
    s = max_side / max(img.shape[:2])
    size = (round(img.shape[1] * s), round(img.shape[0] * s))
    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    soft = cv2.resize(mask.astype(np.float32) / 255.0, size, interpolation=cv2.INTER_AREA)  # a soft matte
    return torch.from_numpy(img).float() / 255.0, torch.from_numpy(soft)


@pytest.mark.parametrize("name", ["coffee", "astronaut", "rocket"])
def test_frame_zero_is_the_photo_inside_the_object(name):
    from physmotion_core.lift.silhouette import silhouette_lift
    from physmotion_core.segment.classic import inpaint_background

    img, soft = _photo_and_mask(name)
    hard = soft > 0.5
    lift = silhouette_lift(img, hard.float(), max_gaussians=20000)
    g = lift.gaussians
    sim = sim_from_positions(g, [g.means])
    hole = np.maximum(hard.numpy(), soft.numpy() > 1 / 255).astype(np.float32)
    bg = inpaint_background(img.numpy(), hole)
    splat = render_frames(sim, lift.camera)
    tex = make_photo_texture(img, soft, lift.camera, background=bg)
    fr = render_frames(sim, lift.camera, photo=tex)
    out = composite(fr.rgb, fr.alpha, bg)[0]
    before = psnr(composite(splat.rgb, splat.alpha, bg)[0], img, hard)
    after = psnr(out, img, hard)
    assert after >= 40.0, (name, before, after)
    assert after > before + 3.0
    # No seam at the matte's edge: the ring just around it matches the photo as well as the inpainted
    # background there does (the band where the object's own edge pixels blend with what was behind it).
    ring = torch.from_numpy(cv2.dilate(hard.numpy().astype(np.uint8), np.ones((5, 5), np.uint8)) > 0) & ~hard
    assert psnr(out, img, ring) >= psnr(bg, img, ring) - 0.5


def test_render_node_takes_the_photo_as_an_optional_input(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    from comfy_harness import load_pack

    node = load_pack().NODE_CLASS_MAPPINGS["PhysMotionRender"]()
    cam = slab_camera()
    photo = texture_image()
    g = slab(cam, photo)
    dx = 5.0 / cam.fx
    sim = sim_from_positions(g, [g.means, g.means + torch.tensor([dx, 0.0, 0.0])])
    plain = node.run(sim, cam, 0, 0)["result"]  # an existing graph: no photo, the splat render as before
    ref = render_frames(sim, cam)
    assert torch.equal(plain[0], ref.rgb)
    mask = (ref.alpha[:1] > 0.5).float()
    bg = torch.full((1, H, W, 3), 0.5)
    rgb, alpha, _ = node.run(sim, cam, 0, 0, photo=photo[None], mask=mask, background=bg)["result"]
    out = composite(rgb, alpha, bg[0])
    inner = torch.from_numpy(cv2.erode(mask[0].numpy().astype(np.uint8), np.ones((5, 5), np.uint8)) > 0)
    assert psnr(out[0], photo, inner) > 50.0
    # Without the mask the rest render's coverage stands in for it: still the photo well inside the object.
    rgb2, alpha2, _ = node.run(sim, cam, 0, 0, photo=photo[None])["result"]
    assert psnr(composite(rgb2, alpha2, bg[0])[0], photo, inner) > 40.0
    # texture="splat" keeps the splats' colours even with the photo connected.
    rgb3, _, _ = node.run(sim, cam, 0, 0, photo=photo[None], texture="splat")["result"]
    assert torch.equal(rgb3, ref.rgb)


@pytest.mark.parametrize("extra", [1, 3, 4, 5])
def test_compiled_compositing_of_a_few_extra_channels_matches_the_tensor_path(extra):
    """The compiled compositor's vectorised path for 5-8 channels (colour, depth and up to 4 more: the photo
    texture's) against the PyTorch rasterizer, and its general path just past it."""
    from physmotion_core.render.rasterize import rasterize

    cam = slab_camera()
    g = slab(cam, texture_image(), spacing=0.012)
    f = torch.rand(g.means.shape[0], extra, generator=torch.Generator().manual_seed(extra))
    a = rasterize(g, cam, extra_features=f, backend="warp")
    b = rasterize(g, cam, extra_features=f, backend="torch")
    assert a.backend == "warp"
    for x, y in ((a.rgb, b.rgb), (a.alpha, b.alpha), (a.extra, b.extra)):
        assert float((x - y).abs().max()) < 1e-5


def test_a_face_the_photo_saw_edge_on_keeps_its_own_colour_when_turned_to_the_camera():
    """A side face lies along the viewing ray at rest: the photo holds a one-pixel sliver of it. Turned 90° to
    face the camera, stretching that sliver over the face would smear it; the face shows its splats' colour."""
    cam = slab_camera()
    photo = texture_image()
    sp = 0.006
    ys = torch.arange(-0.1, 0.1 + 1e-9, sp)
    zs = torch.arange(-0.2, 0.0 + 1e-9, sp)
    yy, zz = torch.meshgrid(ys, zs, indexing="ij")
    means = torch.stack([torch.full_like(yy.flatten(), 0.05), yy.flatten(), zz.flatten()], 1)
    n = means.shape[0]
    green = torch.tensor([0.0, 1.0, 0.0])
    g = Gaussians.from_rgb(means, green.expand(n, 3).contiguous(),
                           torch.tensor([0.1 * sp, 0.6 * sp, 0.6 * sp]).expand(n, 3).contiguous(), torch.full((n,), 0.97))
    centre = torch.tensor([0.05, 0.0, -0.1])
    rot = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # 90° about y: the face turns to +z
    turned = (means - centre) @ rot.T + centre
    sim = sim_from_positions(g, [means, turned])
    sim.F[1] = rot  # the splats turn with it
    rest = render_frames(sim, cam)
    assert float(rest.alpha[0].sum()) > 20  # the photo sees a sliver of it
    tex = make_photo_texture(photo, (rest.alpha[0] > 0.5).float(), cam, background=torch.zeros(H, W, 3))
    fr = render_frames(sim, cam, photo=tex)
    face = render_frames(sim, cam).alpha[1] > 0.9
    face = torch.from_numpy(cv2.erode(face.numpy().astype(np.uint8), np.ones((5, 5), np.uint8)) > 0)
    assert int(face.sum()) > 200
    out = composite(fr.rgb, fr.alpha, torch.zeros(H, W, 3))[1]
    assert float((out[face] - green).abs().max()) < 0.05


@pytest.mark.parametrize("one_map", [True, False])
def test_compiled_shading_matches_the_tensor_path(one_map, monkeypatch):
    """The photo texture's per-pixel passes compiled (``_warp_shade``) against their tensor twin, on a slab the
    photo saw turned 70° away, turned to face the camera (the photo stretched by about 2.9 across it: partly faded,
    PHOTO_STRETCH) and moved by a fraction of a pixel: both photo-coordinate paths (one rigid map; each splat's
    displacement), the stretch fade, bicubic sampling between pixels and the coverage floor."""
    from physmotion_core.render import _warp_shade
    from physmotion_core.render.photo_texture import TexturedPoser, shade
    from physmotion_core.render.rasterize import rasterize

    assert _warp_shade.available()
    cam = slab_camera()
    photo = texture_image()
    flat = slab(cam, photo, half=(0.2, 0.2), spacing=0.005)
    ang = math.radians(70.0)
    rot = torch.tensor([[math.cos(ang), 0.0, math.sin(ang)], [0.0, 1.0, 0.0], [-math.sin(ang), 0.0, math.cos(ang)]])
    quat = torch.tensor([math.cos(ang / 2), 0.0, math.sin(ang / 2), 0.0]).expand(flat.means.shape[0], 4)
    g = Gaussians.from_rgb(flat.means @ rot.T, flat.rgb, flat.scales, flat.opacities, quats=quat.contiguous())
    turned = flat.means + torch.tensor([0.3 / cam.fx, 0.45 / cam.fy, 0.0])
    sim = sim_from_positions(g, [g.means, turned])
    sim.F[1] = rot.T
    if not one_map:  # a slight per-particle spread in F: no single map, each splat's displacement channel
        gen = torch.Generator().manual_seed(0)
        sim.F[1] = sim.F[1] * (1.0 + 0.01 * torch.rand(sim.F.shape[1], 1, 1, generator=gen))
    rest = render_frames(sim, cam)
    tex = make_photo_texture(photo, rest.alpha[0].clamp(0, 1), cam, background=torch.full((H, W, 3), 0.3))
    poser = TexturedPoser(sim, cam, tex)
    feats, one = poser.features(1, sim.gaussians_at(1))
    assert (one is not None) == one_map
    out = rasterize(sim.gaussians_at(1), cam, extra_features=feats)
    a_rgb, a_a = shade(tex, cam, out.rgb, out.alpha, out.depth, out.extra, one, compiled=True)
    b_rgb, b_a = shade(tex, cam, out.rgb, out.alpha, out.depth, out.extra, one, compiled=False)
    assert float((a_rgb - b_rgb).abs().max()) < 1e-5
    assert float((a_a - b_a).abs().max()) < 1e-5
    # The photo is really sampled in this frame (the test can tell the paths from the splat render), and the
    # stretch fade is partial over the face (the magnification 1 / cos 70° = 2.9 lies within PHOTO_STRETCH).
    photo_share = (a_rgb - out.rgb).abs().sum(-1) > 1e-3
    assert int(photo_share.sum()) > 1000
    from physmotion_core.render import photo_texture as P

    monkeypatch.setattr(P, "PHOTO_STRETCH", (1e6, 2e6))  # no stretch fade
    c_rgb, _ = shade(tex, cam, out.rgb, out.alpha, out.depth, out.extra, one, compiled=False)
    faded = (c_rgb - b_rgb).abs().sum(-1) > 0.02
    assert int(faded.sum()) > 500


def test_compiled_texture_features_match_the_tensor_path():
    """The per-splat channels of a deforming frame (s·Δ, s), computed in one compiled loop, against their tensor
    twin: equal to float32 round-off (both in float64, the sums in another order), with shifts of several pixels."""
    from physmotion_core.render.photo_texture import TexturedPoser

    cam = slab_camera()
    photo = texture_image()
    g = slab(cam, photo, half=(0.2, 0.15), spacing=0.01)
    gen = torch.Generator().manual_seed(1)
    moved = g.means + torch.tensor([0.02, -0.01, 0.05]) + 0.004 * torch.randn(g.means.shape, generator=gen)
    sim = sim_from_positions(g, [g.means, moved])
    sim.F[1] = torch.eye(3) * (1.0 + 0.02 * torch.rand(sim.F.shape[1], 1, 1, generator=gen))  # no single map
    tex = make_photo_texture(photo, torch.ones(H, W), cam)
    poser = TexturedPoser(sim, cam, tex)
    assert poser._compiled()
    got, one = poser.features(1, sim.gaussians_at(1))
    poser._use_compiled = False
    want, one_t = poser.features(1, sim.gaussians_at(1))
    assert one is None and one_t is None and got.shape == want.shape == (g.means.shape[0], 3)
    assert float(want[:, :2].abs().max()) > 3.0 and float(want[:, 2].min()) > 0.5  # seen, and shifted by pixels
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-6)


def test_unseen_splats_show_their_colours_low_passed():
    """The splats the photo never saw show their colours averaged over a box of cells: a colour ramp along x
    (linear) is kept inside the grid (a box filter is exact on linear functions), a per-splat checkerboard (the
    streaks of a lift's colour drawn out along depth) averages to its mean; the seen splats keep their colours."""
    from physmotion_core.render.photo_texture import TexturedPoser, smoothed_colours

    sp = 0.01
    xs = torch.arange(0.0, 0.2 + 1e-9, sp)
    g = torch.stack(torch.meshgrid(xs, xs, xs, indexing="ij"), -1).reshape(-1, 3)
    ramp = torch.stack([g[:, 0] * 4.0, torch.full_like(g[:, 0], 0.5), 1.0 - g[:, 0]], 1)
    out = smoothed_colours(g, ramp, sp, 1)
    inner = ((g > 1.5 * sp) & (g < 0.2 - 1.5 * sp)).all(1)
    assert float((out[inner] - ramp[inner]).abs().max()) < 1e-5
    ijk = torch.round(g / sp).long()
    checker = ((ijk.sum(1) % 2).float())[:, None].expand(-1, 3)
    out = smoothed_colours(g, checker, sp, 1)
    assert float((out[inner] - 0.5).abs().max()) < 0.05  # 13 of 27 or 14 of 27 ones
    # Through the texture: the torn slab's inside (unseen, green) striped with red per splat column.
    cam = slab_camera()
    photo = texture_image()
    front = slab(cam, photo)
    inside = slab(cam, photo, half=(0.45, 0.33), z=-0.05, rgb=(0.0, 1.0, 0.0))
    stripes = (torch.round(inside.means[:, 0] / 0.006).long() % 2 == 0)
    rgb = inside.rgb.clone()
    rgb[stripes] = torch.tensor([1.0, 0.0, 0.0])
    inside = Gaussians.from_rgb(inside.means, rgb, inside.scales, inside.opacities)
    gs = Gaussians.cat([front, inside])
    sim = sim_from_positions(gs, [gs.means])
    sim.stats["particle_spacing"] = 0.006
    tex = make_photo_texture(photo, (render_frames(sim, cam).alpha[0] > 0.5).float(), cam)
    poser = TexturedPoser(sim, cam, tex)
    nf = front.means.shape[0]
    seen = poser.seen
    sure = seen >= 1.0
    assert int(sure.sum()) > 1000 and torch.equal(poser.colors[sure], gs.rgb[sure].float())
    hidden = torch.zeros(gs.means.shape[0], dtype=torch.bool)
    hidden[nf:] = (inside.means[:, :2].abs() < 0.3).all(1) & (seen[nf:] < 0.01)
    assert int(hidden.sum()) > 1000
    c = poser.colors[hidden]
    # Stripes one cell wide through a 3-cell box: 1/3 or 2/3 red instead of 0 or 1 (the std down by 3).
    assert float(c[:, 0].std()) < 0.4 * float(gs.rgb[hidden][:, 0].std())
    assert abs(float(c[:, 0].mean()) - float(gs.rgb[hidden][:, 0].mean())) < 0.05


def test_a_notch_narrower_than_the_splats_stays_open_at_rest_and_in_motion(monkeypatch):
    """scikit-image's horse silhouette through the silhouette lift: the splats' footprints fill the gap under its
    jaw, between its legs and under its belly (a splat render's coverage, and before OUTSIDE_PX the photo
    texture's coverage floor, spread several px past the outline there). With the photo texture frame 0 matches
    the photo outside the object too (more than 3 px from it: 44 dB against 23 dB with the floor everywhere), and
    moved to the right, the open gap under the jaw moves with it."""
    from skimage import data

    from physmotion_core.lift.silhouette import silhouette_lift
    from physmotion_core.render import photo_texture as PT
    from physmotion_core.segment.classic import inpaint_background

    horse = ~data.horse()  # True on the horse
    img = np.where(horse[..., None], 0.05, 0.97).astype(np.float32) * np.ones(3, np.float32)
    size = (200, round(200 * horse.shape[0] / horse.shape[1]))
    img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    soft = cv2.resize(horse.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    img_t, soft_t = torch.from_numpy(img), torch.from_numpy(soft)
    hard = soft_t > 0.5
    lift = silhouette_lift(img_t, hard.float(), max_gaussians=20000)
    g = lift.gaussians
    shift_px = 6
    bg = inpaint_background(img, np.maximum(hard.numpy(), soft > 1 / 255).astype(np.float32))
    far = torch.from_numpy(cv2.dilate(hard.numpy().astype(np.uint8), np.ones((7, 7), np.uint8)) == 0)
    results = {}
    for name, outside in (("floor everywhere", (1e9, 2e9)), ("now", PT.OUTSIDE_PX)):
        monkeypatch.setattr(PT, "OUTSIDE_PX", outside)
        sim = sim_from_positions(g, [g.means])
        tex = make_photo_texture(img_t, soft_t, lift.camera, background=bg)
        fr = render_frames(sim, lift.camera, photo=tex)
        results[name] = psnr(composite(fr.rgb, fr.alpha, bg)[0], img_t, far)
    assert results["now"] >= 40.0 and results["floor everywhere"] < 30.0, results
    # The splat render alone covers the gap under the jaw (so the test has something to catch).
    jaw = far.clone()
    jaw[:, : int(0.8 * size[0])] = False  # the head's end of the photo
    jaw[: int(0.15 * size[1])] = False
    jaw[int(0.5 * size[1]):] = False
    rest = render_frames(sim_from_positions(g, [g.means]), lift.camera)
    assert float(rest.alpha[0][jaw].max()) > 0.5
    # Moved 6 px to the right (a translation of the splats at their depth), the gap moves with them.
    cam = lift.camera
    z = float(cam.project(g.means)[1].mean())
    right = cam.c2w[:3, 0]  # the camera's right in world axes
    sim = sim_from_positions(g, [g.means, g.means + right * (shift_px * z / cam.fx)])
    tex = make_photo_texture(img_t, soft_t, cam, background=bg)
    fr = render_frames(sim, cam, photo=tex)
    moved_jaw = torch.zeros_like(jaw)
    moved_jaw[:, shift_px:] = jaw[:, :-shift_px]
    moved_jaw &= jaw  # still in the gap at both positions: away from the edges that move into it
    assert int(moved_jaw.sum()) > 20
    # (with the floor everywhere: up to 1.0, 74 pixels over 0.05; the faint rest is the jaw's underside, splats
    # the photo did not see, in their own colour and coverage)
    gap = fr.alpha[1][moved_jaw]
    assert float(gap.max()) < 0.2 and float(gap.mean()) < 0.01, (float(gap.max()), float(gap.mean()))
