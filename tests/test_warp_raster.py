"""The compiled CPU compositing (``render._warp_raster``) against the PyTorch tensor path and a float64 brute force.

``rasterize`` uses it for CPU float32 renders that ask no gradient (every video render); the tensor path keeps the
gradients. Both composite the same projected splats in the same order, so they agree to float round-off.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from physmotion_core.errors import InputError
from physmotion_core.render import rasterize
from physmotion_core.render import _warp_raster as WR
from physmotion_core.render._torch_raster import composite_tiles, project_gaussians
from physmotion_core.render.rasterize import probe

from test_render import EPS2D, camera, gaussians, random_gaussians, reference_render


def _projected(g, cam):
    w2c = cam.w2c_opencv()
    with torch.no_grad():
        return project_gaussians(g.means, g.covariance(), g.opacities, w2c, cam.fx, cam.fy, cam.cx, cam.cy,
                                 cam.width, cam.height, cam.near, cam.far, EPS2D)


def _features(g, proj, mc, extra: int, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    parts = [g.rgb[proj.index], mc[proj.index][:, 2:3] - 4.0]
    if extra:
        parts.append(torch.randn(len(proj.index), extra, generator=gen))
    return torch.cat(parts, 1).contiguous()


@pytest.mark.parametrize("extra", [0, 9])  # colour + depth (4 channels), and with the flow's 9 (13)
@pytest.mark.parametrize("opacity", [(0.05, 0.3), (0.2, 0.95), (0.9, 1.0)])
def test_compositing_matches_the_tensor_path(extra, opacity):
    """Faint splats (pixels never saturate), mixed ones and nearly opaque ones (most pixels stop early, at the
    0.99 clamp) on a 160x120 frame with odd tiles at the borders: every channel within float32 round-off of the
    tensor path, at every pixel."""
    cam = camera(163, 121)
    g = random_gaussians(1500, seed=3, spread=0.7, size=0.06, opacity=opacity)
    proj, mc = _projected(g, cam)
    feats = _features(g, proj, mc, extra)
    ref = composite_tiles(proj, feats, cam.width, cam.height)
    got = WR.composite_warp(proj, feats, cam.width, cam.height)
    assert got.shape == ref.shape == (cam.height, cam.width, feats.shape[1] + 1)
    scale = float(feats.abs().max())
    torch.testing.assert_close(got, ref, atol=2e-5 * scale, rtol=1e-5)
    if opacity[0] >= 0.9:
        assert float(got[..., -1].max()) > 0.999  # saturated pixels: the early termination was exercised


def test_one_splat_is_the_alpha_formula_at_every_pixel():
    """One tilted, stretched splat over a frame: every pixel's alpha is min(0.99, o exp(-½ dᵀ conic d)) of the
    projected splat, computed in float64, within the float32 evaluation's round-off (4e-6 relative, 1.5e-6 measured;
    the compiled row loop's polynomial exp with its r² coefficient 0.2 % off gave 1.7e-4), 0 exactly wherever the
    formula is below 1/255,
    and drawn wherever it is above (pixels within 1e-4 of the threshold may go either way). Features (C = 1 and
    C = 13, the row loop's two layouts) are alpha times the splat's values; ``split`` hands the same numbers back
    unjoined."""
    cam = camera(150, 110)
    g = gaussians([[0.05, -0.03, 0.0]], [0.35, 0.12, 0.05], 0.93, rgb=[[0.2, 0.5, 0.9]],
                  quats=torch.nn.functional.normalize(torch.tensor([[0.9, 0.1, 0.3, 0.2]]), dim=1))
    proj, _ = _projected(g, cam)
    assert len(proj.index) == 1
    u, v = proj.uv[0].double()
    a, b, c = proj.conic[0].double()
    ys, xs = torch.meshgrid(torch.arange(cam.height, dtype=torch.float64) + 0.5,
                            torch.arange(cam.width, dtype=torch.float64) + 0.5, indexing="ij")
    dx, dy = xs - u, ys - v
    power = float(proj.log_opacity[0]) - 0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy)
    want = power.exp().clamp(max=0.99)
    want = torch.where(want > 1 / 255, want, torch.zeros_like(want))
    for C in (1, 13):
        feats = torch.linspace(-2.0, 3.0, C)[None, :]
        got = WR.composite_warp(proj, feats, cam.width, cam.height)
        alpha = got[..., -1].double()
        clear = ((want - 1 / 255).abs() > 1e-4) | (want == 0)
        assert int((want > 0).sum()) > 1000 and bool(((alpha > 0) == (want > 0))[clear].all())
        drawn = (want > 0) & (alpha > 0)
        assert float(((alpha - want).abs() / want)[drawn].max()) < 4e-6
        torch.testing.assert_close(got[..., :C].double(), alpha[..., None] * feats.double(), atol=1e-6, rtol=1e-6)
        fimg, split_alpha = WR.composite_warp(proj, feats, cam.width, cam.height, split=True)
        assert fimg.shape == (cam.height, cam.width, 4 * -(-C // 4))
        assert torch.equal(fimg[..., :C], got[..., :C]) and torch.equal(split_alpha, got[..., -1])
        assert not bool(fimg[..., C:].any())  # the padding channels


def test_compiled_projection_matches_project_gaussians():
    """``project_warp`` (the projection of every CPU render without gradients) against the tensor path on splats
    that take every culling branch: behind the camera, past far, too faint, NaN and infinite means, degenerate
    covariances, splats wholly off the frame or on its borders, far beyond the frustum (the Jacobian's clamp),
    and ordinary ones with ties in depth (the sort is stable). The same splats survive, in the same order, with
    the same pixel boxes; positions bit-equal, log opacities to an ulp; conics within float32 round-off amplified by the
    determinant's cancellation (relative to the conic's size)."""
    cam = camera(163, 121)
    g = random_gaussians(3000, seed=11, spread=1.6, size=0.05, opacity=(0.0, 1.0))
    means, cov, opac = g.means.clone(), g.covariance().clone(), g.opacities.clone()
    means[:40, 2] = 6.0  # behind the camera (at z = 4 looking at -z)
    means[40:60, 2] = -500.0  # past far
    opac[60:80] = 0.5 / 255  # fainter than 1/255, on the optical axis (a pixel centre: the box alone keeps them)
    means[60:80, :2] = 0.0
    means[80, 0], means[81, 1], means[82, 2] = float("nan"), float("inf"), float("-inf")
    cov[90:100] = 0.0  # a point: only eps2d keeps it
    cov[100:110] = torch.diag(torch.tensor([1e-3, 0.0, 0.0]))  # a needle
    means[110:130, 0] = 40.0  # far off to the side
    # Large splats centred beyond 1.3 half-fields of view whose boxes still reach the frame: the Jacobian's clamp.
    tan_x = 0.5 * cam.width / cam.fx
    means[170:190] = torch.tensor([2.0 * 4.0 * tan_x, 0.0, 0.0])
    cov[170:190] = torch.eye(3) * torch.linspace(1.0, 4.0, 20)[:, None, None]
    means[130:150] = means[150:170]  # exact ties in depth
    w2c = cam.w2c_opencv()
    args = (means, cov, opac, w2c, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, cam.near, cam.far, EPS2D)
    with torch.no_grad():
        ref, mc_ref = project_gaussians(*args)
        got, mc = WR.project_warp(*args)
    assert 1000 < len(ref.index) < 2900  # many culled, many kept
    assert torch.equal(got.index, ref.index)
    kept = set(ref.index.tolist())
    assert not kept & set(range(60, 80)) and set(range(170, 190)) <= kept
    assert torch.equal(got.pix_lo, ref.pix_lo) and torch.equal(got.pix_hi, ref.pix_hi)
    assert torch.equal(got.uv, ref.uv)
    torch.testing.assert_close(got.log_opacity, ref.log_opacity, atol=1e-7, rtol=1e-6)  # two logf's: an ulp
    fin = torch.isfinite(mc_ref).all(1)
    assert torch.equal(mc[fin], mc_ref[fin])
    size = ref.conic.abs().amax(1, keepdim=True)
    assert float(((got.conic - ref.conic).abs() / size).max()) < 1e-4
    assert float(((got.conic - ref.conic).abs() / size).median()) < 1e-6
    empty, _ = WR.project_warp(means[:0], cov[:0], opac[:0], *args[3:])
    assert empty.index.numel() == 0 and empty.pix_lo.shape == (0, 2)


@pytest.mark.parametrize("C", [3, 5, 7])  # K = 4, 5 and 7: the row loop's vectors
def test_vector_lanes_past_a_span_add_nothing(C):
    """The row loop composites eight pixels at a time; its lanes past a span's end (pixels the splat does not reach,
    the next tile's, the next row's) must add nothing: the render equals the tensor path. With one splat's first
    channel infinite (0 x inf is nan), the frame takes the scalar loop: the infinity stays in the pixels that splat
    reaches, and every other pixel and channel is finite and equals the vector loop's render with that channel
    finite (to the round-off of their exps: the vector loop evaluates the polynomial in another order)."""
    cam = camera(163, 121)
    g = random_gaussians(400, seed=5, spread=0.7, size=0.05, opacity=(0.2, 0.9))
    proj, mc = _projected(g, cam)
    feats = _features(g, proj, mc, max(C - 4, 0))[:, :C].contiguous()
    ok = WR.composite_warp(proj, feats, cam.width, cam.height)
    torch.testing.assert_close(ok, composite_tiles(proj, feats, cam.width, cam.height), atol=2e-5, rtol=1e-5)
    j = 0  # the front splat: nothing hides it, so every pixel it reaches takes its infinity
    bad = feats.clone()
    bad[j, 0] = float("inf")
    got = WR.composite_warp(proj, bad, cam.width, cam.height)
    alone = dataclasses.replace(proj, index=proj.index[j:j + 1], uv=proj.uv[j:j + 1], conic=proj.conic[j:j + 1],
                                log_opacity=proj.log_opacity[j:j + 1], pix_lo=proj.pix_lo[j:j + 1],
                                pix_hi=proj.pix_hi[j:j + 1])
    reach = WR.composite_warp(alone, torch.ones(1, 1), cam.width, cam.height)[..., -1] > 0
    assert int(reach.sum()) > 10 and bool(torch.isinf(got[..., 0][reach]).all())
    assert bool(torch.isfinite(got[..., 0][~reach]).all()) and bool(torch.isfinite(got[..., 1:]).all())
    torch.testing.assert_close(got[..., 0][~reach], ok[..., 0][~reach], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(got[..., 1:], ok[..., 1:], atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("n", [0, 1, 7, 1000, 50000])
def test_depth_order_is_the_stable_argsort(n):
    """``depth_order`` (Warp's radix sort) against torch's stable argsort of the finite keys: ties (kept in index
    order), negative keys, -0 and +0 (equal), culled splats (+inf, dropped)."""
    import math

    gen = torch.Generator().manual_seed(n)
    key = torch.randn(n, generator=gen) * 10
    for value, share in ((math.inf, 0.1), (0.5, 0.2), (-0.0, 0.05), (0.0, 0.05)):
        key[torch.rand(n, generator=gen) < share] = value
    ok = (key < math.inf).nonzero().squeeze(1)
    want = ok.index_select(0, torch.argsort(key.index_select(0, ok), stable=True))
    assert torch.equal(WR.depth_order(key), want)


def test_tile_size_changes_nothing():
    """A pixel visits the same splats in the same order whatever the tile: bit-identical results."""
    cam = camera(97, 70)
    g = random_gaussians(800, seed=5, spread=0.7, size=0.1)
    proj, mc = _projected(g, cam)
    feats = _features(g, proj, mc, 2)
    base = WR.composite_warp(proj, feats, cam.width, cam.height, tile_size=8)
    for ts in (4, 16, 32, 64):
        assert torch.equal(WR.composite_warp(proj, feats, cam.width, cam.height, tile_size=ts), base), ts


def test_rasterize_uses_it_without_gradients_and_matches_brute_force():
    cam = camera()
    g = random_gaussians(120, seed=2, opacity=(0.3, 1.0))
    with torch.no_grad():
        out = rasterize(g, cam)
        tensor_path = rasterize(g, cam, backend="torch")
    assert out.backend == "warp" and tensor_path.backend == "torch"
    rgb, alpha, depth = reference_render(g, cam)
    torch.testing.assert_close(out.rgb.double(), rgb, atol=2e-5, rtol=0)
    torch.testing.assert_close(out.alpha.double(), alpha, atol=2e-5, rtol=0)
    m = alpha > 0.05
    torch.testing.assert_close(out.depth.double()[m], depth[m], atol=1e-4, rtol=0)
    for a, b in ((out.rgb, tensor_path.rgb), (out.alpha, tensor_path.alpha), (out.depth, tensor_path.depth)):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=1e-5)


def test_opaque_stack_shows_the_front_splat_only():
    """Two opaque splats on the same axis: with the 0.99 clamp the second brings T to 1e-4, so it is not counted
    (the termination rule), and the front colour shows alone."""
    cam = camera()
    g = gaussians([[0, 0, 0.5], [0, 0, 0]], [0.3, 0.3, 0.3], 1.0, rgb=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    out = rasterize(g, cam)
    assert out.backend == "warp"
    c = out.rgb[24, 32]
    assert float(c[0]) == pytest.approx(0.99, abs=1e-6) and float(c[1]) == 0.0
    assert float(out.alpha[24, 32]) == pytest.approx(0.99, abs=1e-6)


def test_gradients_and_other_dtypes_take_the_tensor_path():
    cam = camera()
    g = random_gaussians(40, seed=4)
    means = g.means.clone().requires_grad_()
    out = rasterize(dataclasses.replace(g, means=means), cam)
    assert out.backend == "torch"
    out.alpha.sum().backward()
    assert means.grad is not None and float(means.grad.abs().sum()) > 0
    with torch.no_grad():  # the same inputs, no gradient asked: compiled
        assert rasterize(dataclasses.replace(g, means=means), cam).backend == "warp"
        assert rasterize(random_gaussians(40, seed=4, dtype=torch.float64), cam).backend == "torch"
    assert not WR.usable("cpu", torch.float64)
    assert not WR.usable("meta", torch.float32)


def test_asked_pixels_only_and_probe():
    cam = camera(120, 90)
    g = random_gaussians(600, seed=6, spread=0.6, size=0.07)
    proj, mc = _projected(g, cam)
    feats = _features(g, proj, mc, 0)
    full = WR.composite_warp(proj, feats, cam.width, cam.height, tile_size=8)
    asked = torch.rand(cam.height, cam.width, generator=torch.Generator().manual_seed(1)) < 0.05
    part = WR.composite_warp(proj, feats, cam.width, cam.height, tile_size=8, pixels=asked)
    assert torch.equal(part[asked], full[asked])  # the same loop for each asked pixel
    assert float(part[~asked].abs().max()) == 0.0
    # probe (the tracks' visibility) composites the same way: the frame's alpha and depth at the asked pixels.
    with torch.no_grad():
        frame = rasterize(g, cam)
        p = probe(g, cam, asked)
    torch.testing.assert_close(p.alpha[asked], frame.alpha[asked], atol=2e-6, rtol=1e-5)
    torch.testing.assert_close(p.depth[asked], frame.depth[asked], atol=2e-5, rtol=1e-5)


def test_too_many_intersections_is_a_clear_error(monkeypatch):
    cam = camera()
    g = random_gaussians(200, seed=7)
    proj, mc = _projected(g, cam)
    feats = _features(g, proj, mc, 0)
    # The limits are patched in the modules these functions run in (other tests reload the render modules).
    monkeypatch.setitem(WR.composite_warp.__globals__, "MAX_INTERSECTIONS", 10)
    with pytest.raises(InputError, match="Lower the resolution"):
        WR.composite_warp(proj, feats, cam.width, cam.height)
    monkeypatch.setitem(composite_tiles.__globals__, "MAX_INTERSECTIONS", 10)  # the tensor path: the same check
    with pytest.raises(InputError, match="splat-tile intersections"):
        composite_tiles(proj, feats, cam.width, cam.height)


def test_empty_frame():
    cam = camera()
    g = gaussians([[0, 0, 10.0]], [0.1, 0.1, 0.1], 0.5)  # behind the camera (it sits at z = 4 looking at -z)
    with torch.no_grad():
        out = rasterize(g, cam)
    assert out.backend == "warp" and float(out.alpha.abs().max()) == 0.0 and float(out.depth.abs().max()) == 0.0


def test_a_failing_compiled_path_falls_back_once(monkeypatch, caplog):
    """A kernel that fails to build or launch (a broken Warp install) costs no render: the tensor path draws it,
    with one warning, and the compiled path is not tried again."""
    calls = []

    def broken(*args, **kwargs):
        calls.append(1)
        raise RuntimeError("clang: cannot compile")

    monkeypatch.setattr(WR, "composite_warp", broken)
    monkeypatch.setattr(WR, "_failed", False)
    cam = camera()
    g = random_gaussians(50, seed=8)
    with caplog.at_level("WARNING", logger=WR.__name__), torch.no_grad():
        first = rasterize(g, cam)
        second = rasterize(g, cam)
        asked = torch.zeros(cam.height, cam.width, dtype=torch.bool)
        asked[20:25, 30:35] = True
        p = probe(g, cam, asked)
    assert first.backend == second.backend == "torch" and len(calls) == 1
    torch.testing.assert_close(first.rgb, rasterize(g, cam, backend="torch").rgb)
    torch.testing.assert_close(p.alpha[asked], first.alpha[asked], atol=2e-6, rtol=1e-5)
    assert sum("compiled CPU compositing failed" in r.getMessage() for r in caplog.records) == 1
