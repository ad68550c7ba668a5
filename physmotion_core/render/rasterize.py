"""Differentiable Gaussian-splat rasterization: gsplat on CUDA, our own PyTorch rasterizer elsewhere.

Both backends implement the same image-formation model (3D Gaussian Splatting, EWA splatting):

* each Gaussian is projected with the Jacobian of the pinhole projection at its mean,
  ``Σ₂ᴰ = J W Σ Wᵀ Jᵀ + eps2d·I`` (eps2d px² of screen-space dilation, 0.3 as gsplat);
* pixel (i, j) is sampled at its centre (j + 0.5, i + 0.5);
* ``alpha_i = min(0.99, o_i exp(-½ dᵀ Σ₂ᴰ⁻¹ d))``; contributions below 1/255 are skipped;
* Gaussians are composited front to back by camera-space z of their means:
  ``w_i = alpha_i Π_{j<i} (1 - alpha_j)``;
* early termination as gsplat's and 3DGS's kernels: the Gaussian that would bring the
  transmittance to 1e-4 or below is *not* counted, nor any after it. (So a pixel's alpha never
  exceeds 1 - 1e-4, and a stack of opaque splats shows exactly the front one: with the 0.99 clamp
  the second opaque layer would hit T = 1e-4 and is dropped. This makes "hard depth" renders with
  ``opacity_override`` close to 1 the depth of the front surface.)

The outputs are premultiplied: ``rgb = Σ c_i w_i``, ``alpha = Σ w_i``, ``depth = Σ d_i w_i / alpha``
(0 where alpha <= 1e-6). Colours are not clamped so gradients reach them everywhere.

Without gradients, on the CPU, in float32 (every video render), the PyTorch rasterizer's splats are composited
by a compiled loop (``_warp_raster``, Warp) instead of dense tensor blocks: the same rule, the same splats in the
same order, equal to float round-off, 1.1-2x faster. ``backend`` names it "warp"; "torch" keeps the tensor path.

Known difference between backends: gsplat clamps alpha at 0.999 instead of 0.99, so where a pixel
is covered by a fully opaque splat gsplat's alpha is 0.999 and ours 0.99. Elsewhere they agree to
float32 round-off (gsplat also evaluates whole 16x16 tiles, which only adds contributions below the
1/255 threshold that both skip).
"""

from __future__ import annotations

import inspect
import logging
import math
from dataclasses import dataclass
from functools import partial
from typing import Optional

import torch

from ..errors import InputError
from ..types.camera import Camera
from ..types.gaussians import Gaussians
from ._torch_raster import MAX_EXTENT, Projected, composite_tiles, project_gaussians, rasterize_torch

log = logging.getLogger(__name__)

BACKENDS = ("auto", "torch", "warp", "gsplat")
DEPTH_MODES = ("z", "distance")
ALPHA_EPS = 1e-6


@dataclass
class RenderOutput:
    """What a rasterization returns. All tensors are on the Gaussians' device and dtype.

    rgb (H,W,3) premultiplied colour Σ c_i w_i; alpha (H,W) Σ w_i; depth (H,W) expected depth
    Σ d_i w_i / alpha (0 where alpha <= 1e-6); extra (H,W,C) premultiplied extra features if
    requested. ``backend`` names the rasterizer that produced it ("torch", "warp" (the PyTorch
    rasterizer's projection with the compiled compositing) or "gsplat").
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    extra: Optional[torch.Tensor] = None
    backend: str = "torch"


# ----------------------------------------------------------------------------------------------
# gsplat detection
# ----------------------------------------------------------------------------------------------

_gsplat_module = None
_gsplat_checked = False
_gsplat_failed = False  # set once a call failed (e.g. its CUDA JIT build); then never retried


def gsplat_available() -> bool:
    """Whether ``import gsplat`` works (its CUDA kernels may still fail to build at first use)."""
    global _gsplat_module, _gsplat_checked
    if not _gsplat_checked:
        _gsplat_checked = True
        try:
            import gsplat  # noqa: F401

            _gsplat_module = gsplat
        except Exception as exc:  # ImportError, or a broken install raising anything else
            log.debug("gsplat not available: %s", exc)
            _gsplat_module = None
    return _gsplat_module is not None


def _use_gsplat(device: torch.device, dtype: torch.dtype, backend: str) -> bool:
    if backend == "torch":
        return False
    usable = device.type == "cuda" and gsplat_available() and not _gsplat_failed
    if backend == "gsplat" and not usable:
        why = ("it is not installed" if not gsplat_available() else
               "it failed earlier in this session" if _gsplat_failed else
               "the Gaussians are not on a CUDA device (gsplat has no CPU path)")
        _warn_once(f"backend='gsplat' requested but {why}; using the PyTorch rasterizer instead.")
        return False
    # float64 stays on the exact-precision torch path unless gsplat is asked for by name.
    return usable and (backend == "gsplat" or dtype != torch.float64)


_warned: set[str] = set()


def _warn_once(message: str) -> None:
    if message not in _warned:
        _warned.add(message)
        log.warning(message)


# ----------------------------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------------------------


def rasterize(gaussians: Gaussians, camera: Camera, *, colors: Optional[torch.Tensor] = None,
              opacities: Optional[torch.Tensor] = None, opacity_override: Optional[float] = None,
              depth_mode: str = "z", extra_features: Optional[torch.Tensor] = None,
              eps2d: float = 0.3, backend: str = "auto") -> RenderOutput:
    """Render Gaussians through a pinhole camera: premultiplied RGB, alpha and expected depth.

    Args:
        gaussians: the splats; their shape is ``gaussians.covariance()`` (``covars`` when set).
        camera: intrinsics in pixels and pose (``camera.w2c_opencv()``); near/far cull by z.
        colors: (N,3) colours overriding ``gaussians.rgb`` (the SH DC colour). Not clamped.
        opacities: (N,) opacities overriding ``gaussians.opacities``.
        opacity_override: if given, every opacity is this value (e.g. 0.999 for a hard-depth
            render in which the front surface hides everything behind it).
        depth_mode: "z" (camera-space z of each mean) or "distance" (distance of each mean to the
            camera centre); composited as expected depth.
        extra_features: (N,C) extra per-Gaussian features, composited like colour (premultiplied).
        eps2d: screen-space dilation added to the 2D covariance diagonal, px².
        backend: "auto" (gsplat for CUDA tensors when it imports; else "warp" where it applies: CPU, float32,
            no gradient asked; else "torch"), "torch" (the tensor path always), "warp", "gsplat". A backend
            asked for by name that cannot run these inputs falls back to "torch", with a warning.

    Everything is differentiable w.r.t. means, quats/scales or covars, opacities, colours and
    extra features. See the module docstring for the exact compositing rule.
    """
    if backend not in BACKENDS:
        raise InputError(f"rasterize: backend must be one of {BACKENDS}; got '{backend}'")
    if depth_mode not in DEPTH_MODES:
        raise InputError(f"rasterize: depth_mode must be one of {DEPTH_MODES}; got '{depth_mode}'")
    if not (math.isfinite(eps2d) and eps2d >= 0):
        raise InputError(f"rasterize: eps2d must be a finite number of px² >= 0; got {eps2d}")
    means = gaussians.means
    n = means.shape[0]
    device, dtype = means.device, means.dtype
    if not dtype.is_floating_point:
        raise InputError(f"rasterize: Gaussian means must be floating point; got {dtype}")

    if colors is None:
        colors = gaussians.rgb
    if tuple(colors.shape) != (n, 3):
        raise InputError(f"rasterize: colors must have shape ({n}, 3); got {tuple(colors.shape)}")
    if opacity_override is not None:
        if not (0.0 <= float(opacity_override) <= 1.0):
            raise InputError(f"rasterize: opacity_override must be in [0, 1]; got {opacity_override}")
        opac = torch.full((n,), float(opacity_override), device=device, dtype=dtype)
    else:
        opac = gaussians.opacities if opacities is None else opacities
        if tuple(opac.shape) != (n,):
            raise InputError(f"rasterize: opacities must have shape ({n},); got {tuple(opac.shape)}")
    if extra_features is not None:
        if extra_features.ndim != 2 or extra_features.shape[0] != n:
            raise InputError(f"rasterize: extra_features must have shape ({n}, C); "
                             f"got {tuple(extra_features.shape)}")
    # Half-precision Gaussians (e.g. straight from an fp16 network) are rendered in float32:
    # transmittance products need the range. Outputs come back in the input dtype.
    work = dtype if dtype in (torch.float32, torch.float64) else torch.float32
    if work != dtype:
        gaussians = gaussians._map(lambda t: t.to(work) if t.is_floating_point() else t)
    colors = colors.to(device=device, dtype=work)
    opac = opac.to(device=device, dtype=work)
    extra = None if extra_features is None else extra_features.to(device=device, dtype=work)

    out = None
    if _use_gsplat(device, work, backend):
        try:
            out = _rasterize_gsplat(gaussians, camera, colors, opac, extra, depth_mode, eps2d)
        except Exception as exc:  # a failed JIT build, an old/broken gsplat, an OOM in its kernels
            global _gsplat_failed
            _gsplat_failed = True
            _warn_once(f"gsplat rasterization failed ({type(exc).__name__}: {exc}); falling back "
                       "to the PyTorch rasterizer for the rest of this session.")
    if out is None and backend != "torch":  # (gsplat asked for but unusable falls back here too)
        from . import _warp_raster

        if _warp_raster.usable(device, work, gaussians.means, gaussians.covars, gaussians.quats, gaussians.scales,
                               colors, opac, extra):
            # A failed kernel build or launch: the tensor path, from now on.
            out = _warp_raster.attempt(_rasterize_with_torch, gaussians, camera, colors, opac, extra, depth_mode,
                                       eps2d, compositor=partial(_warp_raster.composite_warp, split=True),
                                       projector=_warp_raster.project_warp)
            if out is not None:
                out.backend = "warp"
        elif backend == "warp":
            _warn_once("backend='warp' renders CPU float32 tensors without gradients; these are not, so the "
                       "PyTorch rasterizer renders them.")
    if out is None:
        out = _rasterize_with_torch(gaussians, camera, colors, opac, extra, depth_mode, eps2d)
    if work != dtype:
        out = RenderOutput(rgb=out.rgb.to(dtype), alpha=out.alpha.to(dtype), depth=out.depth.to(dtype),
                           extra=None if out.extra is None else out.extra.to(dtype), backend=out.backend)
    return out


def _rasterize_with_torch(gaussians: Gaussians, camera: Camera, colors: torch.Tensor, opac: torch.Tensor,
                          extra: Optional[torch.Tensor], depth_mode: str, eps2d: float,
                          **tiling) -> RenderOutput:
    means = gaussians.means
    w2c = camera.w2c_opencv().to(means.device, means.dtype)
    feats = colors if extra is None else torch.cat([colors, extra], 1)
    img, depth_ref = rasterize_torch(
        means, gaussians.covariance().to(means.dtype), opac, feats, w2c,
        fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy, width=camera.width,
        height=camera.height, near=camera.near, far=camera.far, eps2d=eps2d, depth_mode=depth_mode,
        **tiling)
    c = feats.shape[1]
    if isinstance(img, tuple):  # the Warp compositor's own buffers (``composite_warp(split=True)``): no joining copy
        fimg, alpha = img
        return _finish(fimg[..., :3].contiguous(), alpha, fimg[..., c],
                       None if extra is None else fimg[..., 3:c].contiguous(), backend="torch", anchor=means,
                       depth_ref=depth_ref)
    return _finish(img[..., :3].contiguous(), img[..., c + 1].contiguous(), img[..., c],
                   None if extra is None else img[..., 3:c].contiguous(), backend="torch",
                   anchor=means, depth_ref=depth_ref)


def _finish(rgb, alpha, depth_acc, extra, *, backend: str, anchor: torch.Tensor,
            depth_ref: float = 0.0) -> RenderOutput:
    """Expected depth = depth_ref + depth_acc / alpha where alpha > 1e-6, else 0."""
    if torch.is_grad_enabled() and anchor.requires_grad and not alpha.requires_grad:
        # Nothing visible: keep the (zero) outputs attached to the graph so backward() still works.
        zero = anchor.sum() * 0
        rgb, alpha, depth_acc = rgb + zero, alpha + zero, depth_acc + zero
        extra = None if extra is None else extra + zero
    has = alpha > ALPHA_EPS
    if alpha.requires_grad or depth_acc.requires_grad:
        # Divide only where defined, so no NaN/inf enters the backward pass.
        depth = torch.where(has, depth_ref + depth_acc / torch.where(has, alpha, torch.ones_like(alpha)),
                            torch.zeros_like(alpha))
    else:  # the same values in place, with one frame-sized allocation instead of four
        depth = (depth_acc / alpha).add_(depth_ref).masked_fill_(~has, 0.0)
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, extra=extra, backend=backend)


# ----------------------------------------------------------------------------------------------
# Probing a few pixels
# ----------------------------------------------------------------------------------------------


#: Splats per compositing step in ``probe`` (a whole frame uses 16).
PROBE_CHUNK = 64


@dataclass
class Probe:
    """What ``probe`` returns (H,W each): ``alpha`` and ``depth`` as ``rasterize`` renders them at the asked
    pixels (0 at the others), and ``footprint``: the pixels of the 8x8 tiles that a bound on some splat's box
    reaches, a superset of the pixels where any splat reaches alpha 1/255 (so a whole render's alpha is exactly 0
    outside it)."""

    alpha: torch.Tensor
    depth: torch.Tensor
    footprint: torch.Tensor


def probe(gaussians: Gaussians, camera: Camera, pixels: torch.Tensor, *, depth_mode: str = "z",
          eps2d: float = 0.3) -> Probe:
    """Alpha and expected depth at a few pixels (``pixels``: (H,W) bool), without rendering the frame.

    The PyTorch rasterizer's own projection, culling, depth order and compositing, run only over the
    8x8 tiles that hold an asked pixel and the splats whose boxes reach them, for the asked pixels: each
    is composited as in a whole-frame render (the same splats in the same order, the same early
    termination; on the CPU the compiled compositing that ``rasterize`` uses there, ``_warp_raster``), so the
    values equal ``rasterize``'s to float round-off. Splats are culled before the projection by a bound on their
    boxes, whose union (to whole 8x8 tiles) is returned as the frame's footprint. Not differentiable (visibility
    tests need no gradients); any device.
    """
    if depth_mode not in DEPTH_MODES:
        raise InputError(f"probe: depth_mode must be one of {DEPTH_MODES}; got '{depth_mode}'")
    H, W = int(camera.height), int(camera.width)
    if tuple(pixels.shape) != (H, W):
        raise InputError(f"probe: pixels must be a ({H}, {W}) mask for this camera; got {tuple(pixels.shape)}")
    means = gaussians.means
    work = means.dtype if means.dtype in (torch.float32, torch.float64) else torch.float32
    device = means.device
    ts = 8  # composite_tiles' default tile
    TY, TX = -(-H // ts), -(-W // ts)
    with torch.no_grad():
        means = means.to(work)
        w2c = camera.w2c_opencv().to(device, work)
        cov, opac = gaussians.covariance().to(work), gaussians.opacities.to(work)
        # The tiles holding an asked pixel, and a summed-area table of them: a box reaches one when its sum > 0.
        tiles = torch.zeros(TY, TX, dtype=torch.bool, device=device)
        py, px = pixels.to(device).nonzero(as_tuple=True)
        tiles[py // ts, px // ts] = True
        sat = torch.zeros(TY + 1, TX + 1, dtype=torch.int32, device=device)
        sat[1:, 1:] = tiles.int().cumsum(0).cumsum(1)

        def reaches(x0, y0, x1, y1):  # pixel boxes (inclusive, inside the frame) that overlap an asked tile
            tx0, ty0 = torch.div(x0, ts, rounding_mode="floor"), torch.div(y0, ts, rounding_mode="floor")
            tx1, ty1 = torch.div(x1, ts, rounding_mode="floor") + 1, torch.div(y1, ts, rounding_mode="floor") + 1
            return (sat[ty1, tx1] - sat[ty0, tx1] - sat[ty1, tx0] + sat[ty0, tx0]) > 0

        # Splats that cannot reach an asked tile are dropped before the projection, by a bound on their boxes:
        # the half-width is extent·√(Σ₂ᴰ₀₀ + eps2d) ≤ MAX_EXTENT·√(‖J‖²_F tr Σ + eps2d) (‖J R‖₂ ≤ ‖J‖_F and
        # λmax ≤ tr Σ), J the projection's Jacobian at the same clamped x/z, y/z as project_gaussians'; plus 2 px.
        mc = torch.addmm(w2c[:3, 3], means, w2c[:3, :3].T)
        x, y, z = mc.unbind(-1)
        front = z > camera.near
        rz = 1.0 / torch.where(front, z, torch.ones_like(z))
        tan_x, tan_y = 0.5 * W / camera.fx, 0.5 * H / camera.fy
        qx = (x * rz).clamp(-(camera.cx / camera.fx + 0.3 * tan_x), (W - camera.cx) / camera.fx + 0.3 * tan_x)
        qy = (y * rz).clamp(-(camera.cy / camera.fy + 0.3 * tan_y), (H - camera.cy) / camera.fy + 0.3 * tan_y)
        j2 = (camera.fx ** 2 * (1 + qx * qx) + camera.fy ** 2 * (1 + qy * qy)) * rz * rz
        r = MAX_EXTENT * torch.sqrt(j2 * cov.diagonal(dim1=-2, dim2=-1).sum(-1).clamp_min(0) + eps2d) + 2.0
        u, v = camera.fx * x * rz + camera.cx, camera.fy * y * rz + camera.cy
        big = float(4 * max(W, H))
        x0, x1 = torch.floor((u - r).clamp(-big, big)).long(), torch.floor((u + r).clamp(-big, big)).long()
        y0, y1 = torch.floor((v - r).clamp(-big, big)).long(), torch.floor((v + r).clamp(-big, big)).long()
        on = front & torch.isfinite(r) & torch.isfinite(u) & torch.isfinite(v) & (x1 >= 0) & (y1 >= 0)
        on &= (x0 <= W - 1) & (y0 <= H - 1)
        # Footprint: the tiles those (larger) boxes of every splat reach, by a 2D difference array over tiles (a
        # pixel-exact one costs two cumulative sums over the frame, 7 ms at 832x480, more than the probe's other
        # bookkeeping), as pixels.
        b = on.nonzero().squeeze(1)
        bx0, bx1 = x0[b].clamp(0, W - 1), x1[b].clamp(0, W - 1)
        by0, by1 = y0[b].clamp(0, H - 1), y1[b].clamp(0, H - 1)
        diff = torch.zeros(TY + 1, TX + 1, dtype=torch.int32, device=device)
        one = torch.ones(b.shape[0], dtype=torch.int32, device=device)
        tx0, tx1 = torch.div(bx0, ts, rounding_mode="floor"), torch.div(bx1, ts, rounding_mode="floor") + 1
        ty0, ty1 = torch.div(by0, ts, rounding_mode="floor"), torch.div(by1, ts, rounding_mode="floor") + 1
        for ys, xs, sign in ((ty0, tx0, 1), (ty0, tx1, -1), (ty1, tx0, -1), (ty1, tx1, 1)):
            diff.index_put_((ys, xs), one * sign, accumulate=True)
        reached = diff.cumsum(0).cumsum(1)[:TY, :TX] > 0
        footprint = reached.repeat_interleave(ts, 0).repeat_interleave(ts, 1)[:H, :W]
        cand = b[reaches(bx0, by0, bx1, by1)]
        from . import _warp_raster

        compiled = _warp_raster.usable(device, work)  # as rasterize projects and composites a frame without gradients
        args = (means[cand], cov[cand], opac[cand], w2c, camera.fx, camera.fy, camera.cx, camera.cy, W, H, camera.near,
                camera.far, eps2d)
        found = _warp_raster.attempt(_warp_raster.project_warp, *args) if compiled else None
        proj, mc = found if found is not None else project_gaussians(*args)
        mcv = mc[proj.index]
        depth = mcv[:, 2] if depth_mode == "z" else torch.linalg.vector_norm(mcv, dim=-1)
        ref = float(depth.mean()) if depth.numel() else 0.0  # the reference rasterize_torch takes
        lo, hi = proj.pix_lo, proj.pix_hi  # (M,2) inclusive pixel boxes, clipped to the frame
        keep = reaches(lo[:, 0], lo[:, 1], hi[:, 0], hi[:, 1]).nonzero().squeeze(1)  # still front to back
        sub = Projected(index=proj.index[keep], uv=proj.uv[keep], conic=proj.conic[keep],
                        log_opacity=proj.log_opacity[keep], pix_lo=lo[keep], pix_hi=hi[keep])
        feats = (depth[keep] - ref)[:, None]
        img = None
        if compiled and _warp_raster.usable(device, work):
            img = _warp_raster.attempt(_warp_raster.composite_warp, sub, feats, W, H, tile_size=ts,
                                       pixels=pixels.to(device))
        if img is None:
            # Longer chunks than a whole frame's: few tiles, so the per-step overhead, not the work, dominates.
            img = composite_tiles(sub, feats, W, H, tile_size=ts, chunk=PROBE_CHUNK, pixels=pixels.to(device))
        alpha = img[..., 1].contiguous()
        has = alpha > ALPHA_EPS
        z = torch.where(has, ref + img[..., 0] / torch.where(has, alpha, torch.ones_like(alpha)),
                        torch.zeros_like(alpha))
    return Probe(alpha=alpha, depth=z, footprint=footprint)


# ----------------------------------------------------------------------------------------------
# gsplat backend
# ----------------------------------------------------------------------------------------------

_covars_kw: Optional[bool] = None


def _gsplat_takes_covars(fn) -> bool:
    global _covars_kw
    if _covars_kw is None:
        try:
            _covars_kw = "covars" in inspect.signature(fn).parameters
        except (TypeError, ValueError):
            _covars_kw = False
    return _covars_kw


def _rasterize_gsplat(gaussians: Gaussians, camera: Camera, colors: torch.Tensor, opac: torch.Tensor,
                      extra: Optional[torch.Tensor], depth_mode: str, eps2d: float) -> RenderOutput:
    """gsplat 1.x ``rasterization``; raises whatever gsplat raises (the caller falls back)."""
    if not gsplat_available():
        raise RuntimeError("gsplat is not installed")
    rasterization = _gsplat_module.rasterization
    means = gaussians.means
    device, out_dtype = means.device, means.dtype
    f32 = torch.float32
    w2c = camera.w2c_opencv().to(device, f32)
    Ks = torch.tensor([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]],
                      device=device, dtype=f32)
    means32 = means.to(f32)
    # Depth goes in as a feature channel (differentiable, and the same code for z and distance),
    # composited with the same weights as colour; "RGB" mode then returns Σ d_i w_i.
    mc = means32 @ w2c[:3, :3].T + w2c[:3, 3]
    depth = mc[:, 2] if depth_mode == "z" else torch.linalg.vector_norm(mc, dim=-1)
    parts = [colors.to(f32), depth[:, None]]
    if extra is not None:
        parts.append(extra.to(f32))
    feats = torch.cat(parts, 1).contiguous()

    quats, scales = gaussians.quats.to(f32), gaussians.scales.to(f32)
    kwargs = dict(near_plane=float(camera.near), far_plane=float(camera.far), eps2d=float(eps2d),
                  render_mode="RGB", packed=False)
    if gaussians.covars is not None:
        cov = gaussians.covars.to(f32)
        cov = 0.5 * (cov + cov.transpose(-1, -2))  # gsplat reads the upper triangle only
        if _gsplat_takes_covars(rasterization):
            kwargs["covars"] = cov.contiguous()
        else:  # gsplat < 1.4: no covars argument; go through the eigen-decomposition
            _warn_once("this gsplat version has no `covars` argument (added in 1.4); deformed "
                       "Gaussians are converted to rotation+scale (gradients pass through eigh).")
            rs = Gaussians(means=means32, quats=quats, scales=scales, opacities=opac.to(f32),
                           sh=gaussians.sh[:, :1].to(f32), covars=cov).with_covariance_as_rotscale()
            quats, scales = rs.quats, rs.scales
    render, alphas, _meta = rasterization(
        means32.contiguous(), quats.contiguous(), scales.contiguous(), opac.to(f32).contiguous(), feats,
        w2c[None].contiguous(), Ks[None].contiguous(), int(camera.width), int(camera.height), **kwargs)
    render = render[0].to(out_dtype)
    alpha = alphas[0, ..., 0].to(out_dtype).contiguous()
    return _finish(render[..., :3].contiguous(), alpha, render[..., 3],
                   None if extra is None else render[..., 4:].contiguous(), backend="gsplat", anchor=means)
