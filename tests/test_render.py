"""Tests of the Gaussian-splat rasterizer against analytic answers and a brute-force reference.

CPU only and fast; the gsplat comparison runs only where CUDA and gsplat are both present.
"""

from __future__ import annotations

import dataclasses
import importlib
import math

import pytest
import torch

from physmotion_core.errors import InputError
from physmotion_core.render import RenderOutput, gsplat_available, rasterize
from physmotion_core.render.rasterize import _rasterize_with_torch
from physmotion_core.types import SH_C0, Camera, Gaussians


@pytest.fixture(autouse=True)
def one_thread():
    """These scenes are tiny, and the gradient checks render them hundreds of times; on a shared,
    busy machine two OpenMP threads stall on every small op, so this module runs single-threaded."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


W, H = 65, 49  # odd sizes: the principal point (W/2, H/2) is the centre of pixel (24, 32)
EPS2D = 0.3


def camera(width: int = W, height: int = H, **kw) -> Camera:
    return Camera.look_at((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), width=width, height=height, fov_y_deg=40.0, **kw)


def gaussians(means, scales, opacities, rgb=None, quats=None, dtype=torch.float32) -> Gaussians:
    means = torch.as_tensor(means, dtype=dtype).reshape(-1, 3)
    n = means.shape[0]
    scales = torch.as_tensor(scales, dtype=dtype).reshape(-1, 3).expand(n, 3).clone()
    opacities = torch.as_tensor(opacities, dtype=dtype).reshape(-1).expand(n).clone()
    if rgb is None:
        rgb = torch.full((n, 3), 0.5, dtype=dtype)
    rgb = torch.as_tensor(rgb, dtype=dtype).reshape(n, 3)
    if quats is not None:
        quats = torch.as_tensor(quats, dtype=dtype).reshape(n, 4)
    return Gaussians.from_rgb(means, rgb, scales, opacities, quats=quats)


def random_gaussians(n: int, seed: int = 0, spread: float = 0.5, size: float = 0.08,
                     opacity=(0.2, 0.95), dtype=torch.float32) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=gen) * 2 - 1) * spread
    scales = size * (0.3 + torch.rand(n, 3, generator=gen))
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1)
    opac = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=gen)
    rgb = torch.rand(n, 3, generator=gen)
    g = Gaussians(means=means, quats=quats, scales=scales, opacities=opac, sh=((rgb - 0.5) / SH_C0)[:, None])
    return g._map(lambda t: t.to(dtype))


def pixel_grid(h: int, w: int, dtype=torch.float64):
    ys, xs = torch.meshgrid(torch.arange(h, dtype=dtype) + 0.5, torch.arange(w, dtype=dtype) + 0.5,
                            indexing="ij")
    return xs, ys


def moments(img: torch.Tensor):
    """Intensity-weighted centroid (u, v) and second central moments (σu², σv², σuv) of an image."""
    img = img.double()
    xs, ys = pixel_grid(*img.shape)
    s = img.sum()
    mu, mv = (img * xs).sum() / s, (img * ys).sum() / s
    return (float(mu), float(mv), float((img * (xs - mu) ** 2).sum() / s),
            float((img * (ys - mv) ** 2).sum() / s), float((img * (xs - mu) * (ys - mv)).sum() / s))


def truncation_factor(opacity: float) -> float:
    """E[x²]/σ² of a 2D Gaussian cut off where o·exp(-m²/2) < 1/255 (m = Mahalanobis radius)."""
    s = math.log(255.0 * opacity)  # m²/2 at the cut-off
    return 1.0 - s * math.exp(-s) / (1.0 - math.exp(-s))


def reference_render(g: Gaussians, cam: Camera, colors=None, opacities=None, eps2d: float = EPS2D,
                     depth_mode: str = "z"):
    """Brute force in float64: every Gaussian against every pixel, one Gaussian at a time."""
    w2c = cam.w2c_opencv().double()
    R, t = w2c[:3, :3], w2c[:3, 3]
    means = g.means.double()
    cov = g.covariance().double()
    colors = (g.rgb if colors is None else colors).double()
    opac = (g.opacities if opacities is None else opacities).double()
    mc = means @ R.T + t
    xs, ys = pixel_grid(cam.height, cam.width)
    T = torch.ones(cam.height, cam.width, dtype=torch.float64)
    done = torch.zeros(cam.height, cam.width, dtype=torch.bool)
    rgb = torch.zeros(cam.height, cam.width, 3, dtype=torch.float64)
    acc_d = torch.zeros(cam.height, cam.width, dtype=torch.float64)
    lim_x = 1.3 * 0.5 * cam.width / cam.fx
    lim_y = 1.3 * 0.5 * cam.height / cam.fy
    for i in torch.argsort(mc[:, 2]).tolist():
        x, y, z = mc[i].tolist()
        if not (cam.near < z < cam.far) or opac[i] < 1 / 255:
            continue
        tx, ty = z * min(max(x / z, -lim_x), lim_x), z * min(max(y / z, -lim_y), lim_y)
        J = torch.tensor([[cam.fx / z, 0, -cam.fx * tx / z**2], [0, cam.fy / z, -cam.fy * ty / z**2]],
                         dtype=torch.float64)
        cov2 = J @ R @ cov[i] @ R.T @ J.T + eps2d * torch.eye(2, dtype=torch.float64)
        con = torch.linalg.inv(cov2)
        dx, dy = cam.fx * x / z + cam.cx - xs, cam.fy * y / z + cam.cy - ys
        power = 0.5 * (con[0, 0] * dx * dx + 2 * con[0, 1] * dx * dy + con[1, 1] * dy * dy)
        alpha = torch.clamp(opac[i] * torch.exp(-power), max=0.99)
        alpha = torch.where(alpha < 1 / 255, 0.0, alpha)
        next_t = T * (1 - alpha)
        stop = (alpha > 0) & (next_t <= 1e-4) & ~done
        use = (alpha > 0) & ~done & ~stop
        w = torch.where(use, alpha * T, 0.0)
        rgb += w[..., None] * colors[i]
        acc_d += w * (z if depth_mode == "z" else float(mc[i].norm()))
        T = torch.where(use, next_t, T)
        done |= stop
    alpha = 1 - T
    depth = torch.where(alpha > 1e-6, acc_d / alpha.clamp_min(1e-12), 0.0)
    return rgb, alpha, depth


# ----------------------------------------------------------------------------------------------
# Geometry of single splats
# ----------------------------------------------------------------------------------------------


def test_single_isotropic_gaussian_position_and_size():
    cam = camera()
    sigma, opacity, z = 0.3, 0.5, 4.0
    out = rasterize(gaussians([0, 0, 0], [sigma] * 3, opacity), cam)
    assert isinstance(out, RenderOutput) and out.backend == "warp"  # CPU, float32, no gradient asked
    assert out.rgb.shape == (H, W, 3) and out.alpha.shape == (H, W) and out.depth.shape == (H, W)
    # The peak is at the projected centre, (cx, cy) = (32.5, 24.5): the centre of pixel (24, 32).
    assert tuple((out.alpha == out.alpha.max()).nonzero()[0].tolist()) == (24, 32)
    assert float(out.alpha.max()) == pytest.approx(opacity, rel=1e-5)
    mu, mv, suu, svv, suv = moments(out.alpha)
    assert mu == pytest.approx(cam.cx, abs=1e-3) and mv == pytest.approx(cam.cy, abs=1e-3)
    # Footprint: σ_px² = (f σ / z)² + eps2d, measured from the second moment of the alpha image
    # (corrected for the cut-off below alpha = 1/255, which trims the tails).
    expected = math.sqrt((cam.fx * sigma / z) ** 2 + EPS2D)
    c = truncation_factor(opacity)
    assert math.sqrt(suu / c) == pytest.approx(expected, rel=0.01)
    assert math.sqrt(svv / c) == pytest.approx(expected, rel=0.01)
    assert abs(suv) < 1e-3 * suu
    # Without the dilation the footprint is exactly f σ / z.
    out0 = rasterize(gaussians([0, 0, 0], [sigma] * 3, opacity), cam, eps2d=0.0)
    assert math.sqrt(moments(out0.alpha)[2] / c) == pytest.approx(cam.fx * sigma / z, rel=0.01)


def test_off_centre_gaussian_lands_at_its_projection():
    # Off-centre principal point and non-square pixels, to catch any cx/cy or fx/fy mix-up.
    c2w = Camera.look_at((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), width=W, height=H).c2w
    cam = Camera(W, H, fx=70.0, fy=60.0, cx=28.3, cy=27.1, c2w=c2w)
    mean = torch.tensor([[0.6, -0.45, 0.3]])
    out = rasterize(gaussians(mean, [0.12] * 3, 0.6), cam)
    uv, _ = cam.project(mean)
    mu, mv, *_ = moments(out.alpha)
    assert mu == pytest.approx(float(uv[0, 0]), abs=0.02)
    assert mv == pytest.approx(float(uv[0, 1]), abs=0.02)
    # +y world is up, so a point above the axis lands in the upper half of the image (smaller v).
    up = rasterize(gaussians([0, 0.5, 0], [0.1] * 3, 0.6), cam)
    assert moments(up.alpha)[1] < cam.cy - 5


def test_anisotropic_gaussian_elongation_and_covars_path():
    cam = camera()
    su, sv, z, opacity = 0.4, 0.15, 4.0, 0.5
    out = rasterize(gaussians([0, 0, 0], [su, sv, 0.15], opacity), cam)
    _, _, suu, svv, suv = moments(out.alpha)
    expected_ratio = math.sqrt(((cam.fx * su / z) ** 2 + EPS2D) / ((cam.fy * sv / z) ** 2 + EPS2D))
    # The alpha cut-off is an ellipse aligned with the splat: it scales both moments alike.
    assert math.sqrt(suu / svv) == pytest.approx(expected_ratio, rel=0.01)
    assert abs(suv) < 1e-3 * suu
    # Elongated along world y instead: elongated along v.
    out_y = rasterize(gaussians([0, 0, 0], [sv, su, 0.15], opacity), cam)
    _, _, suu_y, svv_y, _ = moments(out_y.alpha)
    assert math.sqrt(svv_y / suu_y) == pytest.approx(expected_ratio, rel=0.01)

    # General covariances (as the simulator produces) render exactly like rotation + scale.
    g = random_gaussians(40, seed=3)
    ref = rasterize(g, cam)
    cov = dataclasses.replace(g, covars=g.covariance())
    got = rasterize(cov, cam)
    for a, b in ((got.rgb, ref.rgb), (got.alpha, ref.alpha), (got.depth, ref.depth)):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    # A sheared covariance F Σ Fᵀ is honoured (not silently replaced by quats/scales).
    F = torch.tensor([[1.0, 0.8, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    one = gaussians([0, 0, 0], [0.15, 0.4, 0.15], 0.5)
    sheared = dataclasses.replace(one, covars=F @ one.covariance() @ F.T)
    *_, suv_sheared = moments(rasterize(sheared, cam).alpha)
    assert suv_sheared < -1.0  # x grows with y; image v points down, so the u-v correlation is negative


# ----------------------------------------------------------------------------------------------
# Compositing
# ----------------------------------------------------------------------------------------------


def two_layers(a_front: float, a_back: float, front_first: bool):
    front = ([0, 0, 1.0], [0.08] * 3, a_front, [1.0, 0.2, 0.0])  # z_cam = 3, red-ish
    back = ([0, 0, -1.0], [0.13] * 3, a_back, [0.0, 0.3, 1.0])  # z_cam = 5, blue-ish, same size on screen
    layers = [front, back] if front_first else [back, front]
    return gaussians([l[0] for l in layers], [l[1] for l in layers], [l[2] for l in layers],
                     [l[3] for l in layers])


@pytest.mark.parametrize("front_first", [True, False])
def test_front_splat_wins_regardless_of_input_order(front_first):
    cam = camera()
    out = rasterize(two_layers(1.0, 1.0, front_first), cam)
    centre = out.rgb[24, 32]
    # alpha clamps at 0.99; the back layer would bring T to 1e-4, so it is not counted at all.
    torch.testing.assert_close(centre, torch.tensor([0.99, 0.99 * 0.2, 0.0]), atol=1e-5, rtol=0)
    assert float(out.alpha[24, 32]) == pytest.approx(0.99, abs=1e-6)
    assert float(out.depth[24, 32]) == pytest.approx(3.0, abs=1e-5)


@pytest.mark.parametrize("front_first", [True, False])
def test_two_partial_layers_match_analytic_formula(front_first):
    cam = camera()
    a1, a2 = 0.6, 0.5
    out = rasterize(two_layers(a1, a2, front_first), cam)
    c1, c2 = torch.tensor([1.0, 0.2, 0.0]), torch.tensor([0.0, 0.3, 1.0])
    torch.testing.assert_close(out.rgb[24, 32], c1 * a1 + c2 * a2 * (1 - a1), atol=1e-6, rtol=0)
    assert float(out.alpha[24, 32]) == pytest.approx(a1 + a2 * (1 - a1), abs=1e-6)
    expected_depth = (3.0 * a1 + 5.0 * a2 * (1 - a1)) / (a1 + a2 * (1 - a1))
    assert float(out.depth[24, 32]) == pytest.approx(expected_depth, abs=1e-5)


def test_depth_of_opaque_splat_z_and_distance():
    cam = camera()
    g = gaussians([0.4, -0.3, 0.5], [0.1] * 3, 1.0)
    out = rasterize(g, cam)
    seen = out.alpha > 1e-6
    assert int(seen.sum()) > 20
    # One splat: its depth everywhere it is seen, 0 elsewhere.
    torch.testing.assert_close(out.depth[seen], torch.full_like(out.depth[seen], 3.5), atol=1e-5, rtol=0)
    assert float(out.depth[~seen].abs().max()) == 0.0
    dist = float(torch.linalg.vector_norm(torch.tensor([0.4, -0.3, 0.5]) - cam.position))
    out_d = rasterize(g, cam, depth_mode="distance")
    torch.testing.assert_close(out_d.depth[seen], torch.full_like(out_d.depth[seen], dist), atol=1e-5, rtol=0)


def test_matches_brute_force_reference():
    cam = camera(41, 33)
    g = random_gaussians(60, seed=1, spread=0.7, size=0.1, opacity=(0.3, 1.0))
    # Some splats partly behind the near plane / outside the view, and a NaN one, are culled.
    g.means[0] = torch.tensor([0.0, 0.0, 3.995])
    g.means[1] = torch.tensor([3.0, 0.0, 0.0])
    g.means[2] = torch.tensor([float("nan"), 0.0, 0.0])
    g64 = g._map(lambda t: t.double())
    ref_rgb, ref_alpha, ref_depth = reference_render(g64, cam)
    for gg, tol in ((g64, 1e-9), (g, 3e-5)):
        out = rasterize(gg, cam)
        assert torch.isfinite(out.rgb).all()
        torch.testing.assert_close(out.rgb.double(), ref_rgb, atol=tol, rtol=0)
        torch.testing.assert_close(out.alpha.double(), ref_alpha, atol=tol, rtol=0)
        # Expected depth divides by alpha: compare where alpha is not tiny.
        m = ref_alpha > 0.05
        torch.testing.assert_close(out.depth.double()[m], ref_depth[m], atol=tol * 100, rtol=0)
    out_d = rasterize(g64, cam, depth_mode="distance")
    _, _, ref_dist = reference_render(g64, cam, depth_mode="distance")
    torch.testing.assert_close(out_d.depth[ref_alpha > 0.05], ref_dist[ref_alpha > 0.05], atol=1e-8, rtol=0)


# ----------------------------------------------------------------------------------------------
# Early termination and chunking
# ----------------------------------------------------------------------------------------------


def test_early_termination_stops_after_front_layers():
    cam = camera(33, 25)
    # Two huge splats cover the image almost uniformly: alpha 0.99 (clamped) then 0.98999, so
    # T = 0.01 * 0.01001 = 1.001e-4 after them. Any further Gaussian with alpha >= 1/255 would bring
    # T to <= 1e-4, so it is not counted, nor anything after it: the 200 splats behind vanish.
    front = gaussians([[0, 0, 1.0], [0, 0, 0.9]], [500.0] * 3, [1.0, 0.98999], rgb=[[1, 0, 0], [0, 1, 0]])
    hidden = random_gaussians(200, seed=2, spread=0.6, size=0.1, opacity=(0.05, 1.0))
    third = gaussians([0, 0, 0.7], [500.0] * 3, 0.95, rgb=[[1, 1, 1]])
    only_front = rasterize(front, cam)
    for behind in (hidden, third, Gaussians.cat([third, hidden])):
        everything = rasterize(Gaussians.cat([behind, front]), cam)
        # One hidden contribution would be at least (1/255) * 1e-4 = 3.9e-7.
        torch.testing.assert_close(everything.rgb, only_front.rgb, atol=1e-7, rtol=0)
        torch.testing.assert_close(everything.alpha, only_front.alpha, atol=1e-7, rtol=0)
        torch.testing.assert_close(everything.depth, only_front.depth, atol=0, rtol=1e-6)
    torch.testing.assert_close(only_front.rgb[12, 16], torch.tensor([0.99, 0.01 * 0.98999, 0.0]),
                               atol=1e-6, rtol=0)
    torch.testing.assert_close(only_front.alpha, torch.full((25, 33), 1 - 1.001e-4), atol=1e-6, rtol=0)
    # Without the front layers the hidden splats are of course visible.
    assert float(rasterize(hidden, cam).alpha.max()) > 0.5


@pytest.mark.parametrize("tile_size,chunk,max_elements", [(4, 1, 1 << 22), (8, 3, 2000), (16, 7, 1 << 22),
                                                          (8, 64, 1 << 22), (5, 2, 100)])
def test_chunked_equals_unchunked(tile_size, chunk, max_elements):
    cam = camera(47, 37)
    # Dense enough that many pixels saturate (early termination inside chunks and across them).
    g = random_gaussians(300, seed=4, spread=0.5, size=0.12, opacity=(0.5, 1.0), dtype=torch.float64)
    colors, extra = g.rgb, torch.randn(300, 2, dtype=torch.float64)

    def render(**tiling):
        return _rasterize_with_torch(g, cam, colors, g.opacities, extra, "z", EPS2D, **tiling)

    # Reference: one 64x64 tile at a time, each tile's whole list (<= 300 Gaussians) in one chunk.
    ref = render(tile_size=64, chunk=300, max_elements=300 * 64 * 64)
    assert float((ref.alpha > 0.9998).double().mean()) > 0.05
    got = render(tile_size=tile_size, chunk=chunk, max_elements=max_elements)
    for a, b in ((got.rgb, ref.rgb), (got.alpha, ref.alpha), (got.extra, ref.extra), (got.depth, ref.depth)):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=0)


def _thin_splats(n: int, seed: int, dtype=torch.float64) -> Gaussians:
    """Needles and discs at every orientation, opacities from just above 1/255 to 1: the tile lists of
    their bounding boxes hold many tiles only a box corner reaches."""
    g = random_gaussians(n, seed=seed, spread=0.6, size=0.1, opacity=(0.005, 1.0), dtype=dtype)
    gen = torch.Generator().manual_seed(seed + 1)
    squash = torch.ones(n, 3, dtype=dtype)
    squash[torch.arange(n), torch.randint(0, 3, (n,), generator=gen)] = 0.05
    squash[torch.arange(0, n, 3), torch.randint(0, 3, (len(range(0, n, 3)),), generator=gen)] = 0.1
    return dataclasses.replace(g, scales=g.scales * squash * 1.5)


def test_culled_tile_lists_drop_only_entries_below_the_alpha_threshold():
    from physmotion_core.render._torch_raster import _tile_runs, project_gaussians

    cam = camera(97, 71)
    g = _thin_splats(400, seed=7)
    w2c = cam.w2c_opencv().double()
    proj, _ = project_gaussians(g.means, g.covariance(), g.opacities, w2c, cam.fx, cam.fy, cam.cx, cam.cy,
                                cam.width, cam.height, cam.near, cam.far, EPS2D)
    ts = 8

    def pairs(cull):
        gi, ty, lo, hi = _tile_runs(proj, ts, cull)
        return {(int(a), int(y), x) for a, y, l, h in zip(gi, ty, lo, hi) for x in range(int(l), int(h) + 1)}

    box, kept = pairs(False), pairs(True)
    assert kept <= box
    # Brute force, float64: the pairs in which alpha reaches 1/255 at some pixel centre of the tile.
    allp = sorted(box)
    gi = torch.tensor([d[0] for d in allp])
    ty = torch.tensor([d[1] for d in allp], dtype=torch.float64)
    tx = torch.tensor([d[2] for d in allp], dtype=torch.float64)
    off = torch.arange(ts, dtype=torch.float64) + 0.5
    dx = (tx[:, None, None] * ts + off[None, None, :]) - proj.uv[gi, 0, None, None]
    dy = (ty[:, None, None] * ts + off[None, :, None]) - proj.uv[gi, 1, None, None]
    a, b, c = (proj.conic[gi, k, None, None] for k in range(3))
    alpha = proj.log_opacity[gi, None, None].exp() * torch.exp(-0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy))
    inside = ((tx[:, None, None] * ts + off[None, None, :]) < cam.width) & \
        ((ty[:, None, None] * ts + off[None, :, None]) < cam.height)
    reach = ((alpha >= 1 / 255) & inside).flatten(1).any(1)
    needed = {p for p, r in zip(allp, reach.tolist()) if r}
    assert needed <= kept  # nothing that contributes is dropped
    # and the lists are tight: the culled ones hold few pairs beyond those (the box ones hold many).
    assert len(box - needed) > 0.1 * len(needed), (len(box), len(needed))
    assert len(kept - needed) < 0.1 * len(box - needed), (len(kept), len(needed), len(box))


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6)])
def test_culled_tile_lists_render_the_same(dtype, tol):
    cam = camera(97, 71)
    g = _thin_splats(400, seed=8, dtype=dtype)
    extra = torch.randn(400, 2, dtype=dtype, generator=torch.Generator().manual_seed(3))
    for tiling in ({}, {"tile_size": 4, "chunk": 3}, {"tile_size": 16, "chunk": 7, "max_elements": 3000}):
        a = _rasterize_with_torch(g, cam, g.rgb, g.opacities, extra, "z", EPS2D, cull=True, **tiling)
        b = _rasterize_with_torch(g, cam, g.rgb, g.opacities, extra, "z", EPS2D, cull=False, **tiling)
        for x, y in ((a.rgb, b.rgb), (a.alpha, b.alpha), (a.extra, b.extra), (a.depth, b.depth)):
            torch.testing.assert_close(x, y, atol=tol, rtol=0)
    # With gradients (Fit and Refine): the same gradients too.
    grads = []
    for cull in (True, False):
        means = g.means.clone().requires_grad_()
        gg = dataclasses.replace(g, means=means)
        out = _rasterize_with_torch(gg, cam, g.rgb, g.opacities, extra, "z", EPS2D, cull=cull)
        (out.rgb.sum() + out.depth.sum() + (out.extra * 0.3).sum()).backward()
        grads.append(means.grad)
    torch.testing.assert_close(grads[0], grads[1], atol=tol * 100, rtol=tol * 100)


# ----------------------------------------------------------------------------------------------
# Gradients
# ----------------------------------------------------------------------------------------------


def _loss_fn(cam, weights, use_covars=False, tile_size=4, chunk=2):
    def loss(means, scales, quats, opac, colors, extra):
        g = Gaussians(means=means, quats=quats, scales=scales, opacities=opac,
                      sh=torch.zeros(means.shape[0], 1, 3, dtype=means.dtype))
        if use_covars:
            g = dataclasses.replace(g, covars=g.covariance())
        out = _rasterize_with_torch(g, cam, colors, opac, extra, "z", EPS2D, tile_size=tile_size, chunk=chunk)
        return ((out.rgb * weights[0]).sum() + (out.alpha * weights[1]).sum()
                + (out.depth * weights[2]).sum() + (out.extra * weights[3]).sum())
    return loss


@pytest.mark.parametrize("use_covars", [False, True])
def test_gradients_match_finite_differences(use_covars):
    cam = camera(23, 19)
    gen = torch.Generator().manual_seed(5)
    n = 6
    means = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 0.25
    scales = 0.06 + 0.06 * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen, dtype=torch.float64), dim=-1)
    opac = 0.3 + 0.6 * torch.rand(n, generator=gen, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    extra = torch.rand(n, 2, generator=gen, dtype=torch.float64)
    weights = [torch.randn(19, 23, 3, generator=gen, dtype=torch.float64),
               torch.randn(19, 23, generator=gen, dtype=torch.float64),
               torch.randn(19, 23, generator=gen, dtype=torch.float64),
               torch.randn(19, 23, 2, generator=gen, dtype=torch.float64)]
    inputs = [t.clone().requires_grad_() for t in (means, scales, quats, opac, colors, extra)]
    loss = _loss_fn(cam, weights, use_covars)
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradients_with_saturated_pixels():
    """Early termination inside and across chunks: gradients still match finite differences."""
    cam = camera(23, 19)
    gen = torch.Generator().manual_seed(1)
    n = 14
    means = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 0.08
    means[:, 2] = torch.linspace(0.5, -0.5, n, dtype=torch.float64)
    scales = 0.1 + 0.05 * torch.rand(n, 3, generator=gen, dtype=torch.float64)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen, dtype=torch.float64), dim=-1)
    opac = 0.93 + 0.06 * torch.rand(n, generator=gen, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    extra = torch.rand(n, 1, generator=gen, dtype=torch.float64)
    weights = [torch.randn(19, 23, 3, generator=gen, dtype=torch.float64),
               torch.randn(19, 23, generator=gen, dtype=torch.float64),
               torch.randn(19, 23, generator=gen, dtype=torch.float64),
               torch.randn(19, 23, 1, generator=gen, dtype=torch.float64)]
    loss = _loss_fn(cam, weights, tile_size=8, chunk=3)
    with torch.no_grad():
        g = Gaussians(means=means, quats=quats, scales=scales, opacities=opac, sh=torch.zeros(n, 1, 3))
        assert int((rasterize(g, cam).alpha > 0.9998).sum()) >= 3
    inputs = [t.clone().requires_grad_() for t in (means, scales, quats, opac, colors, extra)]
    assert torch.autograd.gradcheck(loss, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradients_reach_sh_and_float32_backward_runs():
    cam = camera(40, 30)
    g = random_gaussians(100, seed=6)
    g = Gaussians(means=g.means.requires_grad_(), quats=g.quats.requires_grad_(),
                  scales=g.scales.requires_grad_(), opacities=g.opacities.requires_grad_(),
                  sh=g.sh.requires_grad_())
    out = rasterize(g, cam)
    (out.rgb.sum() + out.alpha.sum() + out.depth.sum()).backward()
    for t in (g.means, g.quats, g.scales, g.opacities, g.sh):
        assert t.grad is not None and torch.isfinite(t.grad).all() and float(t.grad.abs().sum()) > 0


# ----------------------------------------------------------------------------------------------
# Options and edge cases
# ----------------------------------------------------------------------------------------------


def test_opacity_override_and_opacities_argument():
    cam = camera()
    g = random_gaussians(50, seed=7)
    a = rasterize(g, cam, opacity_override=0.7)
    b = rasterize(g, cam, opacities=torch.full((50,), 0.7))
    c = rasterize(dataclasses.replace(g, opacities=torch.full((50,), 0.7)), cam)
    for x, y, z in ((a.rgb, b.rgb, c.rgb), (a.alpha, b.alpha, c.alpha), (a.depth, b.depth, c.depth)):
        torch.testing.assert_close(x, y)
        torch.testing.assert_close(x, z)
    # Hard depth: with opacity ~1 the front surface hides everything behind it.
    hard = rasterize(two_layers(0.3, 0.3, False), cam, opacity_override=0.9999)
    assert float(hard.depth[24, 32]) == pytest.approx(3.0, abs=1e-5)


def test_colors_override_and_extra_features():
    cam = camera()
    g = random_gaussians(50, seed=8)
    colors = torch.rand(50, 3)
    out = rasterize(g, cam, colors=colors, extra_features=torch.cat([colors, torch.ones(50, 1), -colors], 1))
    assert out.extra.shape == (H, W, 7)
    torch.testing.assert_close(out.extra[..., :3], out.rgb)
    torch.testing.assert_close(out.extra[..., 3], out.alpha)  # a constant 1 composites to alpha
    torch.testing.assert_close(out.extra[..., 4:], -out.rgb)  # colours are not clamped
    assert rasterize(g, cam).extra is None
    # The default colour is the SH DC colour, not clamped.
    bright = dataclasses.replace(g, sh=g.sh + 5.0)
    assert float(rasterize(bright, cam).rgb.max()) > 1.0


def test_nothing_visible_gives_zeros_and_backward_works():
    cam = camera()
    g = gaussians([[0, 0, 5.0], [0, 0, 10.0]], [0.1] * 3, 0.8)  # both behind the camera
    g.means.requires_grad_()
    out = rasterize(g, cam)
    assert float(out.alpha.detach().abs().sum()) == 0.0 and float(out.depth.detach().abs().sum()) == 0.0
    out.rgb.sum().backward()
    assert g.means.grad is not None and float(g.means.grad.abs().sum()) == 0.0
    empty = gaussians(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0))
    assert float(rasterize(empty, cam).alpha.sum()) == 0.0


def test_huge_and_tiny_splats_are_safe():
    cam = camera()
    g = gaussians([[0, 0, 3.9], [0, 0, 0], [0.2, 0, 0]], [[5.0] * 3, [1e-6] * 3, [0.1] * 3], 0.5)
    out = rasterize(g, cam)  # a splat filling the view, a sub-pixel one (dilated by eps2d), a normal one
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    assert float(out.alpha.min()) > 0.4


def test_invalid_arguments_raise_input_error():
    cam = camera()
    g = random_gaussians(5)
    with pytest.raises(InputError, match="backend"):
        rasterize(g, cam, backend="vulkan")
    with pytest.raises(InputError, match="depth_mode"):
        rasterize(g, cam, depth_mode="disparity")
    with pytest.raises(InputError, match="colors"):
        rasterize(g, cam, colors=torch.zeros(4, 3))
    with pytest.raises(InputError, match="opacities"):
        rasterize(g, cam, opacities=torch.zeros(5, 1))
    with pytest.raises(InputError, match="opacity_override"):
        rasterize(g, cam, opacity_override=1.5)
    with pytest.raises(InputError, match="extra_features"):
        rasterize(g, cam, extra_features=torch.zeros(5))
    with pytest.raises(InputError, match="eps2d"):
        rasterize(g, cam, eps2d=-1.0)


def test_gsplat_backend_falls_back_without_cuda():
    cam = camera()
    g = random_gaussians(20)
    out = rasterize(g, cam, backend="gsplat")  # CPU tensors: gsplat cannot run them
    assert out.backend == "warp"  # our rasterizer, as "auto" picks it for CPU tensors without gradients
    torch.testing.assert_close(out.rgb, rasterize(g, cam, backend="torch").rgb)
    assert isinstance(gsplat_available(), bool)


# ----------------------------------------------------------------------------------------------
# The gsplat wrapper's plumbing, with a stand-in for gsplat (runs everywhere)
# ----------------------------------------------------------------------------------------------


def raster_module():
    # ``physmotion_core.render.rasterize`` the attribute is the function (re-exported by the
    # package); the module itself is in sys.modules.
    return importlib.import_module("physmotion_core.render.rasterize")


class FakeGsplat:
    """Implements gsplat 1.x's ``rasterization`` contract with our own renderer, to check how the
    wrapper packs inputs (features, depth channel, covars) and unpacks outputs, or to fail."""

    def __init__(self, fail: bool = False):
        self.fail = fail
        self.calls = []

    def rasterization(self, means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                      near_plane=0.01, far_plane=1e10, radius_clip=0.0, eps2d=0.3, sh_degree=None,
                      packed=True, tile_size=16, backgrounds=None, render_mode="RGB", covars=None):
        self.calls.append(dict(colors=colors.shape, render_mode=render_mode, covars=covars is not None))
        if self.fail:
            raise RuntimeError("Error building extension 'gsplat_cuda': nvcc not found")
        from physmotion_core.render._torch_raster import rasterize_torch

        cov = covars if covars is not None else Gaussians(
            means=means, quats=quats, scales=scales, opacities=opacities,
            sh=torch.zeros(means.shape[0], 1, 3)).covariance()
        K = Ks[0]
        img, ref = rasterize_torch(means, cov, opacities, colors, viewmats[0], fx=float(K[0, 0]),
                                   fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]), width=width,
                                   height=height, near=near_plane, far=far_plane, eps2d=eps2d,
                                   depth_mode="z")
        d = colors.shape[1]
        return img[None, ..., :d], img[None, ..., d + 1:], {}


@pytest.fixture
def fake_gsplat(monkeypatch):
    R = raster_module()

    def install(fail=False):
        fake = FakeGsplat(fail)
        monkeypatch.setattr(R, "_gsplat_module", fake)
        monkeypatch.setattr(R, "_gsplat_checked", True)
        monkeypatch.setattr(R, "_gsplat_failed", False)
        monkeypatch.setattr(R, "_covars_kw", None)
        monkeypatch.setattr(R, "_warned", set())
        return fake
    return install


@pytest.mark.parametrize("use_covars", [False, True])
def test_gsplat_wrapper_packs_and_unpacks_like_torch_path(fake_gsplat, use_covars):
    from physmotion_core.render.rasterize import _rasterize_gsplat

    fake = fake_gsplat()
    cam = camera()
    g = random_gaussians(80, seed=12)
    if use_covars:
        g = dataclasses.replace(g, covars=g.covariance())
    extra = torch.randn(80, 2)
    for depth_mode in ("z", "distance"):
        got = _rasterize_gsplat(g, cam, g.rgb, g.opacities, extra, depth_mode, EPS2D)
        ref = rasterize(g, cam, extra_features=extra, depth_mode=depth_mode, backend="torch")
        assert got.backend == "gsplat"
        for a, b in ((got.rgb, ref.rgb), (got.alpha, ref.alpha), (got.extra, ref.extra)):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=0)
        m = ref.alpha > 0.05
        torch.testing.assert_close(got.depth[m], ref.depth[m], atol=1e-4, rtol=0)
    assert fake.calls[0] == dict(colors=(80, 3 + 1 + 2), render_mode="RGB", covars=use_covars)


def test_gsplat_failure_falls_back_to_torch_once(fake_gsplat, monkeypatch, caplog):
    R = raster_module()

    fake = fake_gsplat(fail=True)
    monkeypatch.setattr(R, "_use_gsplat", lambda device, dtype, backend: not R._gsplat_failed)
    cam = camera()
    g = random_gaussians(30, seed=13)
    with caplog.at_level("WARNING", logger=R.__name__):
        first = rasterize(g, cam)
        second = rasterize(g, cam)
    assert first.backend == second.backend == "warp"  # our rasterizer's CPU path
    assert len(fake.calls) == 1  # not retried after the failure
    warnings = [r for r in caplog.records if "gsplat rasterization failed" in r.getMessage()]
    assert len(warnings) == 1 and "nvcc not found" in warnings[0].getMessage()
    torch.testing.assert_close(first.rgb, rasterize(g, cam, backend="torch").rgb)


# ----------------------------------------------------------------------------------------------
# CUDA: the torch path on GPU tensors, and gsplat against it
# ----------------------------------------------------------------------------------------------

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@needs_cuda
def test_torch_path_on_cuda_matches_cpu():
    cam = camera()
    g = random_gaussians(200, seed=9)
    cpu = rasterize(g, cam, backend="torch")
    gpu = rasterize(g.to("cuda"), cam, backend="torch")
    for a, b in ((gpu.rgb, cpu.rgb), (gpu.alpha, cpu.alpha), (gpu.depth, cpu.depth)):
        torch.testing.assert_close(a.cpu(), b, atol=1e-4, rtol=1e-4)


@needs_cuda
@pytest.mark.skipif(not gsplat_available(), reason="needs gsplat")
@pytest.mark.parametrize("use_covars", [False, True])
def test_gsplat_matches_torch(use_covars):
    from physmotion_core.render.rasterize import _rasterize_gsplat

    cam = camera(128, 96)
    # Opacities below 0.99: gsplat clamps alpha at 0.999, we (like 3DGS) at 0.99.
    g = random_gaussians(500, seed=10, spread=0.6, size=0.05, opacity=(0.1, 0.95)).to("cuda")
    if use_covars:
        g = dataclasses.replace(g, covars=g.covariance())
    extra = torch.randn(500, 2, device="cuda")
    results = {}
    for name in ("torch", "gsplat"):
        means = g.means.clone().requires_grad_()
        opac = g.opacities.clone().requires_grad_()
        colors = g.rgb.clone().requires_grad_()
        gg = dataclasses.replace(g, means=means, opacities=opac)
        if name == "gsplat":
            out = _rasterize_gsplat(gg, cam, colors, opac, extra, "distance", EPS2D)
        else:
            out = rasterize(gg, cam, colors=colors, opacities=opac, extra_features=extra,
                            depth_mode="distance", backend="torch")
        assert out.backend == name
        (out.rgb.sum() + out.alpha.sum() + (out.depth * out.alpha).sum() + out.extra.sum()).backward()
        results[name] = (out, means.grad, opac.grad, colors.grad)
    (t, tm, to, tc), (s, sm, so, sc) = results["torch"], results["gsplat"]
    for a, b in ((s.rgb, t.rgb), (s.alpha, t.alpha), (s.extra, t.extra)):
        torch.testing.assert_close(a, b, atol=2e-3, rtol=1e-3)
    m = t.alpha > 0.1
    torch.testing.assert_close(s.depth[m], t.depth[m], atol=2e-3, rtol=1e-3)
    for a, b in ((sm, tm), (so, to), (sc, tc)):
        torch.testing.assert_close(a, b, atol=2e-2 * float(b.abs().max()), rtol=0)
    # "auto" picks gsplat on CUDA.
    assert rasterize(g, cam).backend == "gsplat"


def test_half_precision_gaussians_render_like_float32():
    cam = camera()
    g = random_gaussians(60, seed=11)
    ref = rasterize(g, cam)
    half = rasterize(g._map(lambda t: t.half()), cam)
    assert half.rgb.dtype == torch.float16 and half.depth.dtype == torch.float16
    # fp16 inputs are rounded (~1e-3 relative), which can flip a pixel across the 1/255 cut-off.
    torch.testing.assert_close(half.alpha.float(), ref.alpha, atol=1e-2, rtol=0)
    torch.testing.assert_close(half.rgb.float(), ref.rgb, atol=1e-2, rtol=0)
    assert float((half.alpha.float() - ref.alpha).abs().mean()) < 1e-3


@pytest.mark.parametrize("shape", [(3, 700, 64), (200, 12, 64)])
def test_cumprod_both_ways_match_float64(shape):
    """_cumprod_ takes cumprod_ for few tiles and a long chunk and loops over the chunk otherwise; either way
    the transmittances are the float64 products to float32 round-off (relative 1e-5 over 700 factors)."""
    from physmotion_core.render._torch_raster import CUMPROD_LOOP_MIN, _cumprod_

    T, K, P = shape
    assert (T * P < CUMPROD_LOOP_MIN) == (shape[0] == 3)  # one shape per branch
    g = torch.Generator().manual_seed(0)
    x = 1.0 - 0.01 * torch.rand(shape, generator=g)  # 700 factors down to ~3e-2, no underflow
    ref = x.double().cumprod(1)
    got = _cumprod_(x.clone())
    assert torch.allclose(got.double(), ref, rtol=1e-5, atol=0.0)
