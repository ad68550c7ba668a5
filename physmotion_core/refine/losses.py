"""Losses of the refinement: colour (L1 + λ·D-SSIM) and DNGaussian's patch-normalised depth.

Depth normalisation (DNGaussian, Li et al., CVPR 2024: its global-local depth normalisation; the
refinement is measured in docs/accuracy.md, "Refinement"): the map is cut into non-overlapping
p×p patches (p drawn from 5..17 each step). Each patch is normalised as (x − mean_patch) / (s + ε) with

* local term:  s = the patch's own standard deviation;
* global term: s = the standard deviation of the whole map (detached), so relative depth *between*
  patches matters too;

and ε = 0.01 · std(whole map). Only differences whose magnitude exceeds the error tolerance
(0.2 in DNGaussian's configs) are penalised (squared). Total = 0.1·local + 1.0·global.

Our object-only views add a mask: statistics are taken over the object's pixels of each patch, and
patches less than half covered by the object are skipped (their few pixels give no stable std).
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

LOCAL_WEIGHT = 0.1
GLOBAL_WEIGHT = 1.0
ERROR_TOLERANCE = 0.2
PATCH_RANGE = (5, 17)
MIN_PATCH_COVERAGE = 0.5


def patchify(x: torch.Tensor, p: int) -> torch.Tensor:
    """(H,W) → (n_patches, p·p): non-overlapping patches from the top-left corner (a partial last
    row/column of patches is dropped, as ``F.unfold`` with stride p does)."""
    return F.unfold(x[None, None], kernel_size=p, stride=p)[0].T


def normalise_patches(patches: torch.Tensor, weights: torch.Tensor, whole: torch.Tensor, whole_w: torch.Tensor,
                      use_global_std: bool) -> torch.Tensor:
    """(x − patch mean) / (s + 0.01·std(map)), statistics weighted by ``weights`` (mask)."""
    wsum = weights.sum(1, keepdim=True).clamp(min=1e-8)
    mean = (patches * weights).sum(1, keepdim=True) / wsum
    ww = whole_w.sum().clamp(min=2.0)
    wmean = (whole * whole_w).sum() / ww
    # Unbiased (n−1) standard deviations, as torch.std.
    wstd = torch.sqrt(((whole - wmean) ** 2 * whole_w).sum() / (ww - 1)).clamp(min=0)
    if use_global_std:
        s = wstd.detach()
    else:
        var = ((patches - mean) ** 2 * weights).sum(1, keepdim=True) / (wsum - 1).clamp(min=1e-8)
        s = torch.sqrt(var.clamp(min=0))
    return (patches - mean) / (s + 0.01 * wstd)


def margin_l2(a: torch.Tensor, b: torch.Tensor, margin: float, weights: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Mean of (a−b)² over the entries where |a−b| > margin (and weight > 0); 0 if there are none."""
    diff = a - b
    sel = diff.abs() > margin
    if weights is not None:
        sel = sel & (weights > 0)
    if not bool(sel.any()):
        return diff.sum() * 0.0
    return (diff[sel] ** 2).mean()


def patch_depth_loss(pred: torch.Tensor, target: torch.Tensor, mask: Optional[torch.Tensor], patch: int, *,
                     tolerance: float = ERROR_TOLERANCE, use_global_std: bool = False) -> torch.Tensor:
    """One of DNGaussian's two terms for (H,W) depth maps ``pred`` (rendered) and ``target`` (monocular
    pseudo-depth); ``mask`` (H,W) selects the object's pixels."""
    m = torch.ones_like(pred) if mask is None else (mask > 0.5).to(pred.dtype)
    pp, tp, mp = patchify(pred, patch), patchify(target, patch), patchify(m, patch)
    keep = mp.mean(1) >= MIN_PATCH_COVERAGE
    if not bool(keep.any()):
        return pred.sum() * 0.0
    pp, tp, mp = pp[keep], tp[keep], mp[keep]
    a = normalise_patches(pp, mp, pred, m, use_global_std)
    b = normalise_patches(tp, mp, target, m, use_global_std)
    return margin_l2(a, b, tolerance, mp)


def hard_depth_loss(pred: torch.Tensor, target: torch.Tensor, mask: Optional[torch.Tensor], patch: int,
                    tolerance: float = ERROR_TOLERANCE) -> torch.Tensor:
    """0.1 · local + 1.0 · global patch-normalised depth loss (DNGaussian's weighting)."""
    return (LOCAL_WEIGHT * patch_depth_loss(pred, target, mask, patch, tolerance=tolerance)
            + GLOBAL_WEIGHT * patch_depth_loss(pred, target, mask, patch, tolerance=tolerance, use_global_std=True))


def _gauss_window(size: int = 11, sigma: float = 1.5, dtype=torch.float32, device=None) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-x ** 2 / (2 * sigma ** 2))
    g = g / g.sum()
    return (g[:, None] * g[None, :])[None, None]


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of two (H,W,C) images in 0..1 (Gaussian 11×11 window, σ 1.5, C1=0.01², C2=0.03²)."""
    x = a.permute(2, 0, 1)[:, None]
    y = b.permute(2, 0, 1)[:, None]
    w = _gauss_window(window, sigma, a.dtype, a.device)
    pad = window // 2
    mx = F.conv2d(x, w, padding=pad)
    my = F.conv2d(y, w, padding=pad)
    sxx = F.conv2d(x * x, w, padding=pad) - mx ** 2
    syy = F.conv2d(y * y, w, padding=pad) - my ** 2
    sxy = F.conv2d(x * y, w, padding=pad) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx ** 2 + my ** 2 + c1) * (sxx + syy + c2))
    return s.mean()


def colour_loss(pred: torch.Tensor, target: torch.Tensor, lam: float = 0.2) -> torch.Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM), 3DGS's photometric loss (λ = 0.2)."""
    return (1.0 - lam) * (pred - target).abs().mean() + lam * (1.0 - ssim(pred, target))
