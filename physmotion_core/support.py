"""What holds the object up: the ground under it, or the frame's edge where the photo cuts it off.

A photo often shows only part of a body: a face that fills the frame, a branch entering from the
side, a statue cut at the knees. Standing such a part on the mask's lowest row (as for a cup on a
table) makes it sag and topple with no force at all, because the rest of the body, outside the
frame, is what really holds it. So by default every part of the object that the frame's edge cuts is
held there (an Anchor on the particles seen within a thin band of that edge), and the ground goes
under the object's lowest visible point only when that point is not on the frame's edge; when it is,
the ground is put one object height lower, out of the way, so the run does not invent a floor at the
frame's bottom row. ``plan_support`` makes that choice and says it in plain words.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .errors import InputError
from .types.conditions import Anchor, Ground, Region

EDGES = ("top", "bottom", "left", "right")


def _as_bool_mask(mask) -> np.ndarray:
    m = mask.detach().cpu().numpy() if hasattr(mask, "detach") else np.asarray(mask)
    if m.ndim == 3 and m.shape[0] == 1:
        m = m[0]
    if m.ndim != 2:
        raise InputError(f"the object mask must have shape (H, W); got {tuple(m.shape)}")
    return m.astype(np.float32) > 0.5


def edge_contact(mask, *, tol_px: Optional[int] = None) -> dict:
    """For each frame edge the mask touches, how many pixels of that edge it covers.

    A pixel counts as touching when the mask reaches within ``tol_px`` of the edge (default: 0.5 % of
    the short side, at least 1 px: a matte that stops a pixel short of the border is still cut by
    it). An edge counts only if the contact is at least 2 % of that edge's length or 3 px: a stray
    pixel of a wide mask on the border is not a cut.
    """
    m = _as_bool_mask(mask)
    H, W = m.shape
    if tol_px is None:
        tol_px = max(1, int(round(0.005 * min(H, W))))
    t = max(1, int(tol_px))
    runs = {"top": m[:t].any(0).sum(), "bottom": m[H - t:].any(0).sum(),
            "left": m[:, :t].any(1).sum(), "right": m[:, W - t:].any(1).sum()}
    lengths = {"top": W, "bottom": W, "left": H, "right": H}
    return {e: int(n) for e, n in runs.items() if n >= max(3, 0.02 * lengths[e])}


def touched_edges(mask, *, tol_px: Optional[int] = None) -> tuple[str, ...]:
    """The frame edges (of ``EDGES``, in that order) that cut the object (see ``edge_contact``)."""
    contact = edge_contact(mask, tol_px=tol_px)
    return tuple(e for e in EDGES if e in contact)


def edge_band(mask, edges, *, band_px: Optional[int] = None) -> np.ndarray:
    """Object pixels within ``band_px`` of the given frame edges (float32 (H, W) in {0, 1}).

    Default band: 3 % of the short side and at least 7 % of the object's extent (about 1.7 grid cells
    at the CPU preset of 24 cells across the object, so that simulation particles, two a cell along
    each axis, always fall in it), at least 3 px: thick enough to hold, thin enough that the rest of
    the object moves freely.
    """
    m = _as_bool_mask(mask)
    H, W = m.shape
    if band_px is None:
        extent = 0
        if m.any():
            ys, xs = np.nonzero(m)
            extent = max(int(ys.max() - ys.min()) + 1, int(xs.max() - xs.min()) + 1)
        band_px = max(3, int(round(0.03 * min(H, W))), int(math.ceil(0.07 * extent)))
    b = int(band_px)
    band = np.zeros_like(m)
    for e in edges:
        if e == "top":
            band[:b] = True
        elif e == "bottom":
            band[H - b:] = True
        elif e == "left":
            band[:, :b] = True
        elif e == "right":
            band[:, W - b:] = True
        else:
            raise InputError(f"unknown frame edge {e!r}; choose from {EDGES}")
    return (band & m).astype(np.float32)


@dataclass
class SupportPlan:
    """How the object is held: ``anchor`` (None when nothing is held), the ground to use (None: no
    ground), the frame edges that cut it, and the sentences that tell the user what was chosen."""

    edges: tuple[str, ...]
    hold: bool
    anchor: Optional[Anchor]
    ground: Optional[Ground]
    ground_under_object: bool
    lines: list[str] = field(default_factory=list)


def plan_support(mask, *, ground: Optional[Ground], object_height: float, hold_edges: bool = True,
                 height_given: bool = False, how_to_unhold: str = "--no-hold-edges",
                 how_to_height: str = "--object-height METRES") -> SupportPlan:
    """Choose what holds the object (see the module's text) and say it.

    ``ground`` is the ground the user asked for (None: none). The lift puts the object's lowest
    visible point at y = ``ground.height``; when that point is on the frame's bottom edge the ground
    is lowered by ``object_height`` (the body continues below the frame), so only the hold (or, with
    ``hold_edges`` off, a fall) decides what happens there.
    """
    edges = touched_edges(mask)
    lines: list[str] = []
    anchor = None
    hold = bool(hold_edges) and bool(edges)
    if hold:
        band = edge_band(mask, edges)
        anchor = Anchor(Region(kind="image", mask=band), optional=True)
        lines.append(f"support: the photo cuts the object at the {_join(edges)} edge{'s' if len(edges) > 1 else ''}; "
                     f"it is held there (the rest of the body, outside the frame, holds it). Turn this off with "
                     f"{how_to_unhold}.")
    elif edges:
        lines.append(f"support: the photo cuts the object at the {_join(edges)} edge{'s' if len(edges) > 1 else ''}, "
                     "but holding it there is off: it rests on the ground or falls.")
    on_bottom = "bottom" in edges
    out_ground = ground
    if ground is not None:
        if on_bottom:
            out_ground = dataclasses.replace(ground, height=float(ground.height) - float(object_height))
            lines.append(f"ground: the object's lowest visible point is on the frame's bottom edge, so the ground is "
                         f"not put there; it is {float(object_height):.3g} m lower, below the frame.")
        else:
            lines.append("ground: under the object's lowest visible point.")
    else:
        lines.append("ground: none.")
    lines.append(f"object height: {float(object_height):.3g} m {'(given)' if height_given else '(assumed)'} from the "
                 f"top to the bottom of what the photo shows; it sets how fast everything happens. Change it with "
                 f"{how_to_height}.")
    return SupportPlan(edges=edges, hold=hold, anchor=anchor, ground=out_ground,
                       ground_under_object=ground is not None and not on_bottom, lines=lines)


def _join(items) -> str:
    items = list(items)
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def view_mask(gaussians, camera) -> np.ndarray:
    """Where the Gaussians cover the input view (rendered alpha > 0.5): the object's mask as the camera
    sees it, for graphs that have the Gaussians and the camera but not the segmentation's mask."""
    import torch

    from .render.rasterize import rasterize

    import cv2

    with torch.no_grad():
        out = rasterize(gaussians, camera)
    m = (out.alpha.detach().float().cpu().numpy() > 0.5).astype(np.uint8)
    # The splats' footprints reach 2-4 px past the outline they came from (measured on the cup: its
    # mask ends 5 px above the frame's bottom edge, its render 1 px): shrink by 1 % of the short side
    # (at least 2 px) so only an object the frame really cuts touches an edge. OpenCV's erosion does
    # not erode from outside the image, so a part running off the frame still reaches it.
    r = max(2, int(round(0.01 * min(m.shape))))
    m = cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    return m > 0


def edge_hold(gaussians, camera, material=None) -> tuple[Optional[Anchor], tuple[str, ...], str]:
    """The MPM Simulate node's default support: an Anchor on the parts the frame's edge cuts (None when
    it cuts nothing, or the material is rigid), the edges, and a sentence saying what was chosen."""
    m = view_mask(gaussians, camera)
    edges = touched_edges(m)
    if not edges:
        return None, edges, "support: the object is inside the frame; nothing is held."
    where = f"the {_join(edges)} edge{'s' if len(edges) > 1 else ''}"
    if material is not None and getattr(material, "model", None) == "rigid":
        return None, edges, (f"support: the photo cuts the object at {where}, but a rigid object is not held there "
                             "(it could not move at all).")
    return (Anchor(Region(kind="image", mask=edge_band(m, edges)), optional=True), edges,
            f"support: the photo cuts the object at {where}; it is held there. Turn off hold_cut_edges to let it go.")


def anchor_reaches(anchor: Optional[Anchor], gaussians, camera) -> bool:
    """Whether the hold's band covers some of the lifted object (its Gaussians' centres): a learned lift
    need not fill the mask it came from to the frame's edge, and an anchor on nothing cannot hold."""
    if anchor is None:
        return False
    from .sim.regions import select

    x = gaussians.means.detach().float().cpu().numpy()
    try:
        return bool(select(anchor.region, x, np.zeros(len(x), np.int64), camera, "hold").any())
    except InputError:
        return False
