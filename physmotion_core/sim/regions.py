"""Which particles a Region selects."""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..errors import InputError
from ..types.camera import Camera
from ..types.conditions import Region


def select(region: Region, x: np.ndarray, object_id: np.ndarray, camera: Optional[Camera] = None,
           what: str = "condition") -> np.ndarray:
    """Boolean mask (P,) of the particles (rest positions ``x``) in ``region``."""
    if region.kind == "all":
        sel = np.ones(x.shape[0], dtype=bool)
    elif region.kind == "box":
        lo, hi = np.asarray(region.lo), np.asarray(region.hi)
        sel = np.all((x >= lo) & (x <= hi), axis=1)
    elif region.kind == "sphere":
        sel = np.linalg.norm(x - np.asarray(region.center), axis=1) <= region.radius
    elif region.kind == "image":
        if camera is None:
            raise InputError(f"The {what} uses an image-space region, which needs the input camera; "
                             "pass the camera from the lift stage")
        uv, z = camera.project(torch.from_numpy(x.astype(np.float32)))
        uv, z = uv.numpy(), z.numpy()
        sel = np.zeros(x.shape[0], dtype=bool)
        if region.points:
            pts = np.asarray(region.points, dtype=np.float32)
            d2 = ((uv[:, None, :] - pts[None, :, :]) ** 2).sum(-1).min(axis=1)
            sel |= d2 <= region.radius_px ** 2
        if region.mask is not None:
            m = np.asarray(region.mask)
            if m.ndim != 2:
                raise InputError(f"The {what}'s region mask must be 2-D (H, W); got shape {m.shape}")
            # The mask may be at another resolution than the camera: scale the pixel coordinates.
            su, sv = m.shape[1] / camera.width, m.shape[0] / camera.height
            iu = np.floor(uv[:, 0] * su).astype(np.int64)
            iv = np.floor(uv[:, 1] * sv).astype(np.int64)
            ok = (iu >= 0) & (iu < m.shape[1]) & (iv >= 0) & (iv < m.shape[0])
            sel[ok] |= m[iv[ok], iu[ok]] > 0.5
        sel &= z > 0
    else:  # pragma: no cover - Region validates its kind
        raise InputError(f"unknown region kind {region.kind}")
    if region.object_id is not None:
        sel &= object_id == region.object_id
    if not sel.any():
        where = {
            "image": f"image point(s) {list(region.points)} (radius {region.radius_px}px)",
            "box": f"box {region.lo}..{region.hi}",
            "sphere": f"sphere at {region.center} r={region.radius}",
            "all": f"object {region.object_id}",
        }[region.kind]
        raise InputError(f"The {what}'s region ({where}) contains no part of the object. "
                         "Place it on the object (e.g. click inside the object's mask) or enlarge it.")
    return sel


REGION_MODES = ("whole object", "image point", "mask")


def region_from_ui(mode: str, u: float = 0.0, v: float = 0.0, radius_px: float = 25.0, mask=None,
                   object_id: int = -1) -> Region:
    """A Region from the simple choices a node offers: the whole object, the part under an image
    point (through the whole depth), or the part under a painted mask; optionally one object only."""
    obj = None if object_id is None or object_id < 0 else int(object_id)
    if mode == "whole object":
        return Region(kind="all", object_id=obj)
    if mode == "image point":
        return Region(kind="image", points=((float(u), float(v)),), radius_px=float(radius_px), object_id=obj)
    if mode == "mask":
        if mask is None:
            raise InputError("region is 'mask' but no mask is connected: connect a MASK (paint it in the mask editor)")
        m = np.asarray(mask.detach().cpu() if hasattr(mask, "detach") else mask, dtype=np.float32)
        if m.ndim == 3:
            if m.shape[0] == 0:
                raise InputError(f"the region mask is an empty MASK batch (shape {m.shape}): the node upstream "
                                 "produced no mask; connect a painted mask")
            m = m[0]
        if m.ndim != 2 or m.size == 0:
            raise InputError(f"the region mask must be a MASK [H,W] with pixels; got shape {m.shape}")
        if not (m > 0.5).any():
            raise InputError("the region mask is empty: paint the part of the object the condition acts on")
        return Region(kind="image", mask=m, object_id=obj)
    raise InputError(f"region must be one of {REGION_MODES}; got '{mode}'")
