"""Geometry-aware refinement of lifted Gaussians (PhysMotion §3.2, with DNGaussian's hard depth).

Each iteration renders the input view and takes an Adam step on the colour loss
(L1 + λ·D-SSIM, λ = 0.2) over every Gaussian parameter. From ``depth_start`` on, every
``depth_every`` iterations a *hard-depth* step follows on every view that has a depth target (the
input view and the generated ones): depth is rendered with every opacity replaced by δ = 0.95, so
the nearest Gaussians dominate (D_hard = Σ ||x_n − o|| δ(1−δ)^(n−1) G_n), compared with the
monocular pseudo-depth through DNGaussian's patch normalisation, and only the positions move
(scales, rotations, opacities and colours are detached).

The paper's schedule is 3000 iterations, learning rates in [1e-4, 1e-3] multiplied by 0.1 after
1500, hard depth every 10 iterations after 500. ``RefineSettings`` keeps those proportions for any
iteration count (decay at 1/2, depth from 1/6). Position learning rates are in units of the object's
height per step, so the same settings work for a 3 cm and a 3 m object.

Floater pruning (optional): a Gaussian whose centre projects outside the (dilated) object mask of
any view that has a mask is not part of the object seen from that side, so it is removed.
"""

from __future__ import annotations

import logging
import math
import random
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import cv2
import numpy as np
import torch

from ..autograd import with_autograd
from ..errors import InputError
from ..progress import ProgressFn, report
from ..render.rasterize import rasterize
from ..types.camera import Camera
from ..types.gaussians import Gaussians
from .losses import ERROR_TOLERANCE, PATCH_RANGE, colour_loss, hard_depth_loss

log = logging.getLogger(__name__)

HARD_DEPTH_OPACITY = 0.95  # δ of DNGaussian's render_for_depth


@dataclass
class RefineView:
    """One view of the object: its camera, target image (H,W,3, the object over black), object mask
    (H,W) and, optionally, a monocular pseudo-depth (H,W; larger = farther). ``colour`` marks the
    view(s) whose colours are trusted (the real input photo); generated views give depth only."""

    camera: Camera
    image: Optional[torch.Tensor] = None
    mask: Optional[torch.Tensor] = None
    depth: Optional[torch.Tensor] = None
    colour: bool = False
    name: str = "view"


@dataclass
class RefineSettings:
    iterations: int = 3000
    lr_position: float = 1e-3  # object heights per step
    lr_colour: float = 1e-3
    lr_opacity: float = 1e-3
    lr_scale: float = 1e-3
    lr_rotation: float = 1e-3
    lr_depth_position: float = 0.01  # object heights moved by the Gaussian with the largest gradient per hard-depth step
    decay_at: float = 0.5  # fraction of the iterations after which learning rates are × decay
    decay: float = 0.1
    depth_start: float = 500 / 3000  # fraction of the iterations before the first hard-depth step
    depth_every: int = 10
    hard_depth: bool = True
    depth_optimizer: str = "scaled"  # "scaled": step ∝ gradient, the largest = lr | "adam" (as the paper)
    ssim_lambda: float = 0.2
    tolerance: float = ERROR_TOLERANCE
    patch_range: tuple = PATCH_RANGE
    max_render_side: int = 512  # views are rendered (and compared) at most this large
    prune_floaters: bool = False
    prune_dilate: float = 0.02  # mask dilation for pruning, fraction of the mask's size
    seed: int = 0
    max_seconds: float = 0.0  # 0 = no limit; otherwise stop (with a log line) after this long

    def validate(self) -> None:
        if int(self.iterations) < 0:
            raise InputError(f"iterations must be >= 0; got {self.iterations}")
        for name in ("lr_position", "lr_colour", "lr_opacity", "lr_scale", "lr_rotation", "lr_depth_position"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v <= 1.0):
                raise InputError(f"{name} must be in [0, 1]; got {v}")
        if not (0 < self.decay <= 1 and 0 <= self.decay_at <= 1 and 0 <= self.depth_start <= 1):
            raise InputError("decay must be in (0, 1], decay_at and depth_start in [0, 1] (fractions of the run)")
        if int(self.depth_every) < 1:
            raise InputError(f"depth_every must be >= 1; got {self.depth_every}")
        lo, hi = self.patch_range
        if not (2 <= lo <= hi <= 64):
            raise InputError(f"patch_range must satisfy 2 <= min <= max <= 64; got {self.patch_range}")
        if int(self.max_render_side) < 16:
            raise InputError(f"max_render_side must be >= 16; got {self.max_render_side}")


@dataclass
class RefineResult:
    gaussians: Gaussians
    history: list = field(default_factory=list)  # dicts: iteration, colour, depth (per logged step)
    iterations_done: int = 0
    seconds: float = 0.0
    pruned: int = 0
    notes: list = field(default_factory=list)

    @property
    def iterations_per_second(self) -> float:
        return self.iterations_done / self.seconds if self.seconds > 0 else float("nan")


def _fit_view(view: RefineView, max_side: int) -> RefineView:
    """The view resized so its long side is at most ``max_side`` (camera intrinsics scaled)."""
    cam = view.camera
    s = min(1.0, max_side / max(cam.width, cam.height))
    if s >= 1.0:
        return view
    W, H = max(1, round(cam.width * s)), max(1, round(cam.height * s))

    def rs(t, mode):
        if t is None:
            return None
        a = t.detach().float().cpu().numpy()
        return torch.from_numpy(cv2.resize(a, (W, H), interpolation=mode))

    return RefineView(camera=cam.resized(W, H), image=rs(view.image, cv2.INTER_AREA),
                      mask=rs(view.mask, cv2.INTER_AREA), depth=rs(view.depth, cv2.INTER_AREA),
                      colour=view.colour, name=view.name)


def _check_views(views: Sequence[RefineView]) -> None:
    if not views:
        raise InputError("refine_gaussians needs at least one view (the input camera and photo)")
    for v in views:
        H, W = v.camera.height, v.camera.width
        for what, t, shape in (("image", v.image, (H, W, 3)), ("mask", v.mask, (H, W)), ("depth", v.depth, (H, W))):
            if t is not None and tuple(t.shape) != shape:
                raise InputError(f"view '{v.name}': {what} has shape {tuple(t.shape)} but its camera is {W}x{H}; "
                                 f"expected {shape}")
            if t is not None and not bool(torch.isfinite(t).all()):
                raise InputError(f"view '{v.name}': {what} has NaN or Inf values")
        if v.colour and v.image is None:
            raise InputError(f"view '{v.name}' is marked for the colour loss but has no image")


def _object_height(g: Gaussians) -> float:
    lo, hi = g.bounds()
    ext = (hi - lo).abs()
    return float(max(float(ext[1]), 1e-3 * float(ext.max()), 1e-9))


def prune_floaters(gaussians: Gaussians, views: Sequence[RefineView], dilate: float = 0.02) -> torch.Tensor:
    """Boolean keep-mask: False for Gaussians whose centre projects outside the dilated mask of any
    view with a mask (or behind that view's camera)."""
    keep = torch.ones(len(gaussians), dtype=torch.bool)
    means = gaussians.means.detach().float().cpu()
    for v in views:
        if v.mask is None:
            continue
        m = (v.mask.detach().float().cpu().numpy() > 0.5).astype(np.uint8)
        ys, xs = np.nonzero(m)
        if len(ys) == 0:
            continue
        r = max(1, int(round(dilate * max(np.ptp(ys) + 1, np.ptp(xs) + 1))))
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
        cam = v.camera
        uv, z = cam.project(means)
        u = torch.floor(uv[:, 0]).long()
        vv = torch.floor(uv[:, 1]).long()
        inside = (z > 0) & (u >= 0) & (u < cam.width) & (vv >= 0) & (vv < cam.height)
        on = torch.zeros_like(inside)
        mt = torch.from_numpy(m.astype(bool))
        on[inside] = mt[vv[inside], u[inside]]
        keep &= on
    return keep


@with_autograd
def refine_gaussians(gaussians: Gaussians, views: Sequence[RefineView], settings: Optional[RefineSettings] = None,
                     *, progress: Optional[ProgressFn] = None,
                     preview: Optional[Callable[[int, torch.Tensor], None]] = None,
                     monitor: Optional[Callable[[int, Gaussians], None]] = None, monitor_every: int = 50) -> RefineResult:
    """Refine ``gaussians`` against ``views`` (see the module docstring); returns new Gaussians.

    ``progress(done, total)`` is called every iteration (it may raise to cancel: the Gaussians of
    the last finished iteration are then lost, the input is never modified). ``preview(it, image)``
    gets the current input-view render beside its target every 50 iterations. ``monitor(it, g)``
    gets a detached copy of the current Gaussians before iteration 0 and after every
    ``monitor_every`` iterations (benchmarks use it to trace error against iterations).
    """
    st = settings or RefineSettings()
    st.validate()
    _check_views(views)
    gaussians.validate("refine_gaussians input")
    views = [_fit_view(v, int(st.max_render_side)) for v in views]
    dev = gaussians.means.device
    dtype = torch.float32
    g0 = gaussians.with_covariance_as_rotscale().to(dev)
    size = _object_height(g0)
    rng = random.Random(st.seed)
    notes = []

    colour_views = [v for v in views if v.colour]
    depth_views = [v for v in views if v.depth is not None]
    if st.hard_depth and not depth_views:
        notes.append("no depth targets: colour loss only")
        log.info("refine: no view has a depth target; running the colour loss only")
    if not colour_views:
        notes.append("no colour view: positions refined by depth only")

    means = g0.means.detach().to(dtype).clone().requires_grad_(True)
    sh = g0.sh.detach().to(dtype).clone().requires_grad_(True)
    op = g0.opacities.detach().to(dtype).clamp(1e-4, 1 - 1e-4)
    op_logit = torch.log(op / (1 - op)).clone().requires_grad_(True)
    log_scales = torch.log(g0.scales.detach().to(dtype).clamp(min=1e-9)).clone().requires_grad_(True)
    quats = g0.quats.detach().to(dtype).clone().requires_grad_(True)

    def current(detach_shape: bool = False) -> Gaussians:
        q = quats / quats.norm(dim=1, keepdim=True).clamp(min=1e-12)
        sc = torch.exp(log_scales)
        o = torch.sigmoid(op_logit)
        if detach_shape:
            q, sc, o = q.detach(), sc.detach(), o.detach()
            s = sh.detach()
        else:
            s = sh
        return Gaussians(means=means, quats=q, scales=sc, opacities=o, sh=s)

    groups = [
        {"params": [means], "lr": st.lr_position * size, "name": "means"},
        {"params": [sh], "lr": st.lr_colour, "name": "sh"},
        {"params": [op_logit], "lr": st.lr_opacity, "name": "opacity"},
        {"params": [log_scales], "lr": st.lr_scale, "name": "scales"},
        {"params": [quats], "lr": st.lr_rotation, "name": "quats"},
    ]
    opt = torch.optim.Adam(groups, eps=1e-15)
    depth_opt = torch.optim.Adam([means], lr=st.lr_depth_position * size, eps=1e-15)
    base_lrs = [g["lr"] for g in opt.param_groups]
    base_depth_lr = depth_opt.param_groups[0]["lr"]

    targets = {}
    for v in colour_views:
        m = v.mask.to(dev, dtype) if v.mask is not None else torch.ones(v.camera.height, v.camera.width,
                                                                        device=dev, dtype=dtype)
        targets[id(v)] = (v.image.to(dev, dtype) * m[..., None], m)

    n_it = int(st.iterations)
    decay_it = int(round(st.decay_at * n_it))
    depth_from = int(round(st.depth_start * n_it))
    history = []
    t0 = time.perf_counter()
    done = 0
    def snapshot() -> Gaussians:
        with torch.no_grad():
            c = current(detach_shape=True)
            return Gaussians(means=c.means.detach().clone(), quats=c.quats.clone(), scales=c.scales.clone(),
                             opacities=c.opacities.clone(), sh=c.sh.clone())

    if monitor is not None:
        monitor(0, snapshot())
    for it in range(n_it):
        if it == decay_it:
            for g, lr in zip(opt.param_groups, base_lrs):
                g["lr"] = lr * st.decay
            depth_opt.param_groups[0]["lr"] = base_depth_lr * st.decay
        rec = {"iteration": it}
        if colour_views:
            opt.zero_grad(set_to_none=True)
            g = current()
            loss = 0.0
            for v in colour_views:
                out = rasterize(g, v.camera)
                tgt, m = targets[id(v)]
                loss = loss + colour_loss(out.rgb, tgt, st.ssim_lambda) + (out.alpha - m).abs().mean()
                if preview is not None and it % 50 == 0 and v is colour_views[0]:
                    preview(it, torch.cat([out.rgb.detach().clamp(0, 1), tgt], dim=1).cpu())
            loss.backward()
            opt.step()
            rec["colour"] = float(loss.detach())
        if st.hard_depth and depth_views and it >= depth_from and (it - depth_from) % int(st.depth_every) == 0:
            depth_opt.zero_grad(set_to_none=True)
            g = current(detach_shape=True)
            patch = rng.randint(int(st.patch_range[0]), int(st.patch_range[1]))
            dl = 0.0
            for v in depth_views:
                out = rasterize(g, v.camera, opacity_override=HARD_DEPTH_OPACITY, depth_mode="distance")
                m = v.mask.to(dev, dtype) if v.mask is not None else (out.alpha.detach() > 0.5).to(dtype)
                dl = dl + hard_depth_loss(out.depth, v.depth.to(dev, dtype), m, patch, st.tolerance)
                report(progress, it, n_it)  # a depth step renders every view: let Cancel act between them
            dl.backward()
            if st.depth_optimizer == "scaled":
                with torch.no_grad():
                    gm = means.grad
                    norm = gm.norm(dim=1).max().clamp(min=1e-20)
                    means -= depth_opt.param_groups[0]["lr"] * gm / norm
            else:
                depth_opt.step()
            rec["depth"] = float(dl.detach())
        history.append(rec)
        done = it + 1
        if monitor is not None and done % int(monitor_every) == 0:
            monitor(done, snapshot())
        report(progress, done, n_it)
        if st.max_seconds and time.perf_counter() - t0 > st.max_seconds:
            notes.append(f"stopped after {done} of {n_it} iterations (time limit {st.max_seconds:g} s)")
            log.info("refine: %s", notes[-1])
            break
    seconds = time.perf_counter() - t0
    with torch.no_grad():
        out = current(detach_shape=True)
        result = Gaussians(means=out.means.detach().clone(), quats=out.quats.clone(), scales=out.scales.clone(),
                           opacities=out.opacities.clone(), sh=out.sh.clone(), object_ids=g0.object_ids)
    if not bool(torch.isfinite(result.means).all()):
        raise InputError("Refinement diverged (non-finite positions); lower the learning rates")
    pruned = 0
    if st.prune_floaters:
        keep = prune_floaters(result, views, st.prune_dilate).to(result.means.device)
        pruned = int((~keep).sum())
        if pruned == len(result):
            notes.append("pruning would remove every Gaussian: skipped (check the masks and cameras)")
            pruned = 0
        elif pruned:
            result = result.subset(keep)
    return RefineResult(gaussians=result, history=history, iterations_done=done, seconds=seconds, pruned=pruned,
                        notes=notes)


def build_views(camera: Camera, image, mask, extra_views: Sequence[RefineView] = (), depth_model=None,
                progress: Optional[ProgressFn] = None) -> list[RefineView]:
    """The input view (colour + depth) and any generated views (depth only), with monocular depth
    from ``depth_model`` when one is given (``physmotion_core.depth.DepthModel``)."""
    from ..segment.classic import as_image_array, as_mask_array

    img = torch.from_numpy(as_image_array(image))
    H, W = img.shape[:2]
    if (camera.width, camera.height) != (W, H):
        camera = camera.resized(W, H)
    m = torch.from_numpy(as_mask_array(mask, (H, W))).float() if mask is not None else None
    views = [RefineView(camera=camera, image=img, mask=m, colour=True, name="input")]
    for v in extra_views:
        views.append(RefineView(camera=v.camera, image=v.image, mask=v.mask, depth=v.depth, colour=False,
                                name=v.name))
    if depth_model is not None:
        from ..depth import estimate_depth

        for k, v in enumerate(views):
            if v.image is not None and v.depth is None:
                v.depth = estimate_depth(depth_model, v.image).pseudo_depth()
            report(progress, k + 1, len(views))
    return views
