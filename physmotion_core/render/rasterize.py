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
from typing import Optional

import torch

from ..errors import InputError
from ..types.camera import Camera
from ..types.gaussians import Gaussians
from ._torch_raster import rasterize_torch

log = logging.getLogger(__name__)

BACKENDS = ("auto", "torch", "gsplat")
DEPTH_MODES = ("z", "distance")
ALPHA_EPS = 1e-6


@dataclass
class RenderOutput:
    """What a rasterization returns. All tensors are on the Gaussians' device and dtype.

    rgb (H,W,3) premultiplied colour Σ c_i w_i; alpha (H,W) Σ w_i; depth (H,W) expected depth
    Σ d_i w_i / alpha (0 where alpha <= 1e-6); extra (H,W,C) premultiplied extra features if
    requested. ``backend`` names the rasterizer that produced it ("torch" or "gsplat").
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
        backend: "auto" (gsplat for CUDA tensors when it imports, else torch), "torch", "gsplat".

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
    depth = torch.where(has, depth_ref + depth_acc / torch.where(has, alpha, torch.ones_like(alpha)),
                        torch.zeros_like(alpha))
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, extra=extra, backend=backend)


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
