"""The compiled differentiable compositing (``render._warp_grad``, the fit's refinement renders) against the
float64 tensor path (``composite_tiles``): values, gradients w.r.t. every input, a directional derivative by
finite differences of the float64 model, and the fallback when Warp is not there.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from physmotion_core.render import _warp_grad as WG
from physmotion_core.render._torch_raster import Projected, composite_tiles, project_gaussians

from test_render import EPS2D, camera, random_gaussians

pytestmark = pytest.mark.skipif(not WG.available(), reason="Warp is not available")


def _scene(n=600, seed=1, opacity=(0.2, 0.95), size=0.07, width=61, height=45):
    """A random scene projected in float32 and in float64 (same splats, same order), with features (colour and
    a random signed channel)."""
    cam = camera(width, height)
    g = random_gaussians(n, seed=seed, spread=0.6, size=size, opacity=opacity, dtype=torch.float64)
    w2c = cam.w2c_opencv().double()
    out = []
    for dtype in (torch.float32, torch.float64):
        with torch.no_grad():
            proj, _ = project_gaussians(g.means.to(dtype), g.covariance().to(dtype), g.opacities.to(dtype),
                                        w2c.to(dtype), cam.fx, cam.fy, cam.cx, cam.cy, width, height, cam.near,
                                        cam.far, EPS2D)
        out.append(proj)
    p32, p64 = out
    assert torch.equal(p32.index, p64.index)
    gen = torch.Generator().manual_seed(seed)
    feats = torch.cat([g.rgb, torch.randn(n, 1, generator=gen, dtype=torch.float64)], 1)[p64.index]
    return cam, p32, p64, feats


def _leaves(proj, feats, dtype):
    ins = [t.detach().to(dtype).clone().requires_grad_() for t in (proj.uv, proj.conic, proj.log_opacity, feats)]
    return dataclasses.replace(proj, uv=ins[0], conic=ins[1], log_opacity=ins[2]), ins


def _render_and_grads(fn, proj, feats, dtype, weights, width, height):
    pr, ins = _leaves(proj, feats, dtype)
    img = fn(pr, ins[3], width, height)
    (img.double() * weights).sum().backward()
    return img.detach().double(), [t.grad.double() for t in ins]


@pytest.mark.parametrize("opacity", [(0.05, 0.3), (0.2, 0.95), (0.9, 1.0)])
def test_values_and_gradients_match_the_float64_tensor_path(opacity):
    """Faint splats (no pixel saturates), mixed and nearly opaque ones (pixels stop early, alphas at the 0.99
    clamp) on a frame with partial tiles at the right and bottom borders: the image and the gradients w.r.t.
    the 2D means, conics, log-opacities and features of a random weighting of every channel agree with the
    float64 tensor path to float32 round-off (scaled by each gradient's largest entry)."""
    cam, p32, p64, feats = _scene(opacity=opacity)
    gen = torch.Generator().manual_seed(7)
    weights = torch.randn(cam.height, cam.width, feats.shape[1] + 1, generator=gen, dtype=torch.float64)
    got, g_got = _render_and_grads(WG.composite, p32, feats, torch.float32, weights, cam.width, cam.height)
    ref, g_ref = _render_and_grads(composite_tiles, p64, feats, torch.float64, weights, cam.width, cam.height)
    assert got.shape == ref.shape == (cam.height, cam.width, feats.shape[1] + 1)
    torch.testing.assert_close(got, ref, atol=2e-5, rtol=1e-5)
    if opacity[0] >= 0.9:
        assert float(ref[..., -1].max()) > 0.999  # saturation (early termination) was exercised
    for name, a, b in zip(("uv", "conic", "log_opacity", "features"), g_got, g_ref):
        scale = float(b.abs().max())
        assert scale > 0, name
        err = float((a - b).abs().max())
        assert err <= 2e-5 * scale, (name, err, scale)  # measured: 0.8e-6 to 1.6e-6


def test_directional_derivative_matches_finite_differences():
    """The gradient of a loss, dotted with a random direction in (means, conics, log-opacities, features),
    equals the central difference of the float64 model along that direction, to 1e-3. The splats are wide
    and faint (every pixel inside every splat's 1/255 contour, none near the 0.99 clamp or saturated), so the
    model is smooth where it is differenced: alpha's jump at 1/255 would otherwise dominate a difference."""
    width, height, n = 37, 29, 12
    gen = torch.Generator().manual_seed(4)
    uv = torch.rand(n, 2, generator=gen, dtype=torch.float64) * torch.tensor([width, height])
    sig = 30.0 + 20.0 * torch.rand(n, 2, generator=gen, dtype=torch.float64)  # px
    rho = 0.6 * (torch.rand(n, generator=gen, dtype=torch.float64) - 0.5)
    det = (sig[:, 0] * sig[:, 1]) ** 2 * (1 - rho * rho)
    cxy = rho * sig[:, 0] * sig[:, 1]
    conic = torch.stack([sig[:, 1] ** 2 / det, -cxy / det, sig[:, 0] ** 2 / det], 1)
    logo = torch.log(0.05 + 0.25 * torch.rand(n, generator=gen, dtype=torch.float64))
    feats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    lo = torch.zeros(n, 2, dtype=torch.long)
    hi = torch.tensor([[width - 1, height - 1]] * n)
    p64 = Projected(index=torch.arange(n), uv=uv, conic=conic, log_opacity=logo, pix_lo=lo, pix_hi=hi)
    weights = torch.randn(height, width, 5, generator=gen, dtype=torch.float64)
    _, grads = _render_and_grads(WG.composite, p64, feats, torch.float32, weights, width, height)
    base = [uv, conic, logo, feats]
    dirs = [torch.randn(t.shape, generator=gen, dtype=torch.float64) * float(t.abs().mean()) for t in base]
    analytic = sum(float((g * d).sum()) for g, d in zip(grads, dirs))

    def loss(eps):
        u, c, lg, f = (t + eps * d for t, d in zip(base, dirs))
        pr = Projected(index=p64.index, uv=u, conic=c, log_opacity=lg, pix_lo=lo, pix_hi=hi)
        img = composite_tiles(pr, f, width, height)
        assert float(img[..., -1].min()) > 0.05 and float(img[..., -1].max()) < 0.95  # every splat everywhere
        return float((img * weights).sum())

    h = 1e-5
    numeric = (loss(h) - loss(-h)) / (2 * h)
    assert abs(numeric) > 1.0
    assert abs(analytic - numeric) <= 1e-3 * abs(numeric), (analytic, numeric)


def test_falls_back_to_the_tensor_path_without_warp(monkeypatch):
    """No Warp (or a failed build): the tensor path renders, with its gradients; float64 inputs always take it."""
    cam, p32, p64, feats = _scene(n=200)
    weights = torch.ones(cam.height, cam.width, feats.shape[1] + 1, dtype=torch.float64)
    monkeypatch.setattr(WG, "_failed", True)
    assert not WG.available()
    got, g_got = _render_and_grads(WG.composite, p32, feats, torch.float32, weights, cam.width, cam.height)
    ref, g_ref = _render_and_grads(composite_tiles, p32, feats, torch.float32, weights, cam.width, cam.height)
    assert torch.equal(got, ref)
    for a, b in zip(g_got, g_ref):
        assert torch.equal(a, b)
    monkeypatch.setattr(WG, "_failed", False)
    got64, _ = _render_and_grads(WG.composite, p64, feats, torch.float64, weights, cam.width, cam.height)
    ref64, _ = _render_and_grads(composite_tiles, p64, feats, torch.float64, weights, cam.width, cam.height)
    assert torch.equal(got64, ref64)


def test_tile_lists_hold_every_splat_that_reaches_a_tile_in_depth_order():
    """The compiled tile lists: every splat with alpha above 1/255 (float64, at a pixel centre) at some pixel
    of a tile is in that tile's list, lists are front to back (increasing index), and they hold no more
    entries than the tensor path's row-band lists."""
    from physmotion_core.render._torch_raster import tile_lists

    cam, p32, p64, _ = _scene(n=300, seed=2, size=0.05, width=45, height=31)
    W, H, ts = cam.width, cam.height, WG.TILE
    glist, start, count = WG.tile_lists_warp(p32, W, H)
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                            indexing="ij")
    dx = p64.uv[:, 0, None, None] - xs
    dy = p64.uv[:, 1, None, None] - ys
    a, b, c = (p64.conic[:, k, None, None] for k in range(3))
    alpha = torch.exp(p64.log_opacity[:, None, None] - 0.5 * (a * dx * dx + 2 * b * dx * dy + c * dy * dy))
    TX, TY = -(-W // ts), -(-H // ts)
    hit = torch.nn.functional.pad(alpha > 1.0 / 255.0, (0, TX * ts - W, 0, TY * ts - H))
    hit = hit.view(-1, TY, ts, TX, ts).any(4).any(2).reshape(-1, TX * TY)  # (splat, tile)
    assert int(hit.sum()) > 100
    for t in range(TX * TY):
        lst = glist[int(start[t]):int(start[t]) + int(count[t])].long()
        assert torch.all(lst[1:] > lst[:-1]), t
        need = hit[:, t].nonzero().squeeze(1)
        assert bool(torch.isin(need, lst).all()), t
    assert int(count.sum()) <= tile_lists(p32, ts, W, H)[3]


def test_affine_projection_matches_the_tensor_projection_and_its_gradient():
    """``project_affine`` (splats X, C under x -> A x + b) against ``project_gaussians`` of the placed splats in
    float64: the same splats drawn in the same order (some behind the camera, some too faint, some off the
    image are culled), 2D means and conics to float32 round-off, and the gradients of a loss w.r.t. A and b
    equal to those that autograd gives through the placement and the tensor projection."""
    cam = camera(61, 45)
    g = random_gaussians(400, seed=5, spread=1.6, size=0.07, opacity=(0.001, 0.9), dtype=torch.float64)
    X, C = g.means, g.covariance()
    gen = torch.Generator().manual_seed(3)
    A0 = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))[0] * 0.8
    b0 = torch.tensor([0.1, -0.2, 3.0], dtype=torch.float64)
    wu = torch.randn(400, 2, generator=gen, dtype=torch.float64)
    wc = torch.randn(400, 3, generator=gen, dtype=torch.float64)
    kw = dict(fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy, width=61, height=45, near=cam.near, far=cam.far,
              eps2d=EPS2D)
    res = []
    for compiled in (True, False):
        A, b = A0.clone().requires_grad_(), b0.clone().requires_grad_()
        if compiled:
            proj = WG.project_affine(X.float(), C.float(), g.opacities.float(), A, b, **kw)
        else:
            proj, _ = project_gaussians(X @ A.T + b, A @ C @ A.T, g.opacities, torch.eye(4, dtype=torch.float64),
                                        cam.fx, cam.fy, cam.cx, cam.cy, 61, 45, cam.near, cam.far, EPS2D)
        K = len(proj.index)
        loss = (proj.uv.double() * wu[:K]).sum() + (proj.conic.double() * wc[:K]).sum()
        loss.backward()
        res.append((proj, A.grad.clone(), b.grad.clone()))
    (p1, gA1, gb1), (p2, gA2, gb2) = res
    assert torch.equal(p1.index, p2.index) and 50 < len(p2.index) < 380  # some culled, most drawn
    assert torch.equal(p1.pix_lo, p2.pix_lo) and torch.equal(p1.pix_hi, p2.pix_hi)
    torch.testing.assert_close(p1.uv.double(), p2.uv, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(p1.conic.double(), p2.conic, atol=1e-6, rtol=1e-4)
    torch.testing.assert_close(p1.log_opacity.double(), p2.log_opacity, atol=1e-6, rtol=1e-6)
    for a, b in ((gA1, gA2), (gb1, gb2)):
        assert float((a - b).abs().max()) <= 1e-4 * float(b.abs().max()), (a, b)


def test_fit_falls_back_when_a_compiled_launch_fails(monkeypatch):
    """A compiled launch that fails (here: the projection raises) turns the compiled path off with one warning
    and the fit's render comes from the tensor path, the same image to round-off."""
    import math

    from physmotion_core.lift import fit as F
    from physmotion_core.types.gaussians import Gaussians

    g = random_gaussians(300, seed=6, spread=0.5, size=0.08)
    prep = F._prep(Gaussians(**{k: v for k, v in g.__dict__.items()}), torch.zeros(3, dtype=torch.float64), 1.0)
    mask = torch.zeros(40, 48)
    mask[10:30, 12:36] = 1.0
    lv = F._level(torch.rand(40, 48, 3), mask, 48, 24.0)
    p = F._Params(torch.eye(3), math.log(30.0), (24.0, 20.0), math.log(60.0), 48.0)
    with torch.no_grad():
        ref = F._render(prep, p, lv, 24.0, 20.0).alpha

    def broken(*a, **k):
        raise RuntimeError("launch failed")

    monkeypatch.setattr(WG, "project_affine", broken)
    monkeypatch.setattr(WG, "_failed", False)
    out = F._render(prep, p, lv, 24.0, 20.0)
    assert WG._failed and not WG.available()
    assert float(ref.sum()) > 10
    assert float((out.alpha.detach() - ref).abs().max()) < 1e-4
    loss, _, _ = F._losses(out, lv, 0.5)
    loss.backward()
    assert p.omega.grad is not None and torch.isfinite(p.omega.grad).all()


def test_fit_render_with_nothing_on_screen_still_backpropagates():
    """The object placed entirely off the image: the compiled render is empty and a loss on it still goes
    through backward() (zero gradients), as the tensor path's does."""
    import math

    from physmotion_core.lift import fit as F
    from physmotion_core.types.gaussians import Gaussians

    g = random_gaussians(200, seed=8, spread=0.5, size=0.05)
    prep = F._prep(Gaussians(**{k: v for k, v in g.__dict__.items()}), torch.zeros(3, dtype=torch.float64), 1.0)
    mask = torch.zeros(40, 48)
    mask[10:30, 12:36] = 1.0
    lv = F._level(torch.rand(40, 48, 3), mask, 48, 24.0)
    p = F._Params(torch.eye(3), math.log(10.0), (500.0, 20.0), math.log(60.0), 48.0)  # far right of the photo
    out = F._render(prep, p, lv, 24.0, 20.0)
    assert out.backend == "warp" and float(out.alpha.detach().abs().sum()) == 0.0
    loss, _, _ = F._losses(out, lv, 0.5)
    loss.backward()
    assert float(p.omega.grad.abs().sum()) == 0.0 and float(p.uv.grad.abs().sum()) == 0.0
