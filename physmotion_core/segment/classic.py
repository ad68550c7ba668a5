"""Model-free segmentation: alpha channel, a given mask, or GrabCut seeded by an automatic box.

This is the path that needs no weights (README.md, "Where weights go": with an alpha channel or a
mask no segmentation model is used; without SAM, GrabCut). It produces what every later stage
consumes: the object mask, the foreground, and the background with the object's region inpainted,
so the simulated object can be composited back over an empty scene.

Everything here is OpenCV main-module code (no contrib) on numpy arrays; tensors go in and out.
"""

from __future__ import annotations

import logging
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Optional, Sequence

import cv2
import numpy as np
import torch

from ..errors import InputError
from ..progress import report, scaled

log = logging.getLogger(__name__)

METHODS = ("auto", "alpha", "mask", "grabcut")

# GrabCut runs at most at this long side; the mask is upsampled after (smoothly, so the outline
# stays within a pixel or two of a full-size cut). GrabCut costs ~1 s per 600x400 image at 5
# iterations on one core and grows with the pixel count. At 640 px (tried) a 3 % downscale of the
# grey cell photo turned a box result of IoU 1.00 into 0.56: GrabCut's colour models are that
# sensitive on low-contrast photos, so photos up to 1024 px are cut at full size (above COARSE_TRIGGER
# coarse to fine: the full-size pass decides a band around a COARSE_SIDE outline; the cell at 1024 px
# keeps its 0.98).
GRABCUT_MAX_SIDE = 1024
# GrabCut's colour models start from k-means with OpenCV's global random generator: seeded before
# every call so the same image and prompts always give the same mask.
GRABCUT_SEED = 12345
# The inpainting runs at most at this long side and only the inpainted region is upsampled, so a
# 4k photo costs about what a 1k photo does.
INPAINT_MAX_SIDE = 1024

# Each thread's "one GrabCut iteration is done" hook (``_ticking``): the calling thread's reports
# progress and raises to cancel; a click's second thread's only stops when the first one was cancelled.
_TICK = threading.local()


class _Cancelled(Exception):
    """A click's second thread stops: the first thread was cancelled or failed."""


@contextmanager
def _ticking(fn):
    """Run the block with ``fn()`` called between this thread's GrabCut iterations."""
    before = getattr(_TICK, "fn", None)
    _TICK.fn = fn
    try:
        yield
    finally:
        _TICK.fn = before


#: Which GrabCut iterates: "graph" (``gridflow.GrabCutGraph``: OpenCV's colour models and graph, the max-flow kept
#: from iteration to iteration; the same labels and models as OpenCV; five iterations at 640 px 1.4-2.9x faster) or "opencv"
#: (``cv2.grabCut``, which builds the graph and pushes all of its flow again every iteration). OpenCV also does
#: the first colour models (its k-means) either way, and is the fallback when Warp cannot build the kernels.
GRABCUT_ENGINE = "graph"
_engine_failed: list = []


def _new_graph(bgr: np.ndarray):
    """A ``GrabCutGraph`` for ``bgr``, or None (OpenCV iterates) when the engine is "opencv" or Warp failed."""
    if GRABCUT_ENGINE != "graph" or _engine_failed or bgr.shape[0] * bgr.shape[1] * 8 >= 2 ** 31:
        return None  # (the kernels index the graph's links with 32-bit integers)
    try:
        from .gridflow import GrabCutGraph

        return GrabCutGraph(bgr)
    except Exception as exc:  # a broken Warp install: OpenCV's own GrabCut, the same labels, slower
        _engine_failed.append(exc)
        log.warning("GrabCut's compiled max-flow is not available (%s); using OpenCV's", exc)
        return None


def _grabcut_run(bgr: np.ndarray, gc: np.ndarray, rect, bgd: np.ndarray, fgd: np.ndarray, iters: int,
                 mode: int, until=None, graph=None):
    """GrabCut, ``iters`` iterations, seeded (``GRABCUT_SEED``), with this thread's hook (``_ticking``)
    before each: a long cut reports progress and can be cancelled between iterations (a 1024 px cut's
    iteration takes up to a second or two). The colour models carry over in ``bgd``/``fgd`` and the labels in
    ``gc``, so the labels and models are the same bit for bit as one ``cv2.grabCut`` call with ``iters``
    (checked on every GrabCut of the benchmark photos' clicks, boxes and automatic picks). OpenCV makes the
    first colour models (k-means, from ``rect`` or the labels); the iterations run on ``graph``
    (``gridflow.GrabCutGraph`` of ``bgr``; a new one when None, and on OpenCV when GRABCUT_ENGINE says so),
    which keeps its max-flow from one iteration to the next: pass the returned graph back to continue on the
    same image (the box-tightness rounds). ``until(gc, i)``, when given, is asked after each iteration ``i``
    but the last whether the labels already answer its caller's question; True stops the cut there
    (``_grown_click``). Returns the graph (None on OpenCV)."""
    cv2.setRNGSeed(GRABCUT_SEED)
    if graph is None and int(iters) > 0:
        graph = _new_graph(bgr)
    if graph is not None and int(iters) > 0 and mode in (cv2.GC_INIT_WITH_RECT, cv2.GC_INIT_WITH_MASK):
        cv2.grabCut(bgr, gc, rect, bgd, fgd, 0, mode)  # OpenCV's k-means: the first colour models, no iteration
    for i in range(int(iters)):
        fn = getattr(_TICK, "fn", None)
        if fn is not None:
            fn()  # just before the iteration: after a Cancel no iteration starts
        if graph is None:
            cv2.grabCut(bgr, gc, rect if i == 0 else None, bgd, fgd, 1, mode if i == 0 else cv2.GC_EVAL)
        else:
            graph.iterate(gc, bgd, fgd)
        if until is not None and i + 1 < int(iters) and until(gc, i):
            break
    return graph


class _CutProgress:
    """The calling thread's GrabCut iterations as ``progress(done, total)`` against an estimate of
    how many there will be: called before each iteration (so a cancelling callback stops the cut before
    more work), it never reports the end; the caller does once the result is there."""

    def __init__(self, progress, total: int):
        self.progress, self.total, self.done = progress, max(2, int(total)), 0

    def __call__(self) -> None:
        report(self.progress, self.done, self.total)
        self.done = min(self.done + 1, self.total - 1)


@dataclass
class Segmentation:
    """The object cut out of an image.

    ``box`` is (x0, y0, x1, y1) in pixels with x1, y1 exclusive (slice convention), the tight
    bounding box of ``mask``.
    """

    image: torch.Tensor  # (H,W,3) float32 0..1
    mask: torch.Tensor  # (H,W) float32 in {0,1}
    foreground: torch.Tensor  # (H,W,3) image * mask
    background: torch.Tensor  # (H,W,3) image with the object's (dilated) region inpainted
    box: tuple[int, int, int, int]
    method: str  # "alpha" | "mask" | "grabcut"


# ----------------------------------------------------------------------------------------------
# Input normalisation
# ----------------------------------------------------------------------------------------------


def _to_numpy(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def as_image_array(image, name: str = "image") -> np.ndarray:
    """(H,W,3) or (1,H,W,3), float 0..1 or uint8, torch or numpy → contiguous float32 (H,W,3)."""
    if image is None:
        raise InputError(f"{name} is missing: give an (H, W, 3) RGB image")
    arr = _to_numpy(image)
    if arr.ndim == 4 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 3 or arr.shape[2] != 3:
        hint = " (a batch of images: pass one image at a time)" if arr.ndim == 4 else ""
        hint = hint or (" (RGBA: pass the alpha channel as alpha=)" if arr.ndim == 3 and arr.shape[2] == 4 else "")
        raise InputError(f"{name} must have shape (H, W, 3) (RGB); got {tuple(arr.shape)}{hint}")
    if arr.shape[0] < 2 or arr.shape[1] < 2:
        raise InputError(f"{name} is too small to segment: {arr.shape[1]}x{arr.shape[0]} pixels")
    if arr.dtype == np.uint8:
        arr = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16:
        arr = arr.astype(np.float32) / 65535.0
    else:
        arr = arr.astype(np.float32, copy=False)
    if not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or Inf values")
    return np.ascontiguousarray(arr)


def as_mask_array(mask, shape: tuple[int, int], name: str = "mask") -> np.ndarray:
    """(H,W), (1,H,W) or (H,W,1), any dtype → float32 (H,W) (not yet thresholded)."""
    arr = _to_numpy(mask)
    if arr.ndim == 3 and arr.shape[0] == 1:
        arr = arr[0]
    elif arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim != 2:
        raise InputError(f"{name} must have shape (H, W); got {tuple(arr.shape)}")
    if tuple(arr.shape) != tuple(shape):
        raise InputError(f"{name} size {arr.shape[1]}x{arr.shape[0]} does not match the image size "
                         f"{shape[1]}x{shape[0]}; resize the {name} to the image (or the image to the {name})")
    if arr.dtype == np.bool_:
        return arr.astype(np.float32)
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / 255.0
    arr = arr.astype(np.float32)
    if not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or Inf values")
    return arr


def mask_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """Tight (x0, y0, x1, y1) of a boolean mask, x1/y1 exclusive."""
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        raise InputError("The mask is empty: no object pixels")
    return int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1


def _ellipse(radius: int) -> np.ndarray:
    k = 2 * int(radius) + 1
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))


def _to_u8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _resize_to_max_side(img: np.ndarray, max_side: int) -> tuple[np.ndarray, float]:
    h, w = img.shape[:2]
    scale = min(1.0, max_side / float(max(h, w)))
    if scale >= 1.0:
        return img, 1.0
    size = (max(2, int(round(w * scale))), max(2, int(round(h * scale))))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA), scale


# ----------------------------------------------------------------------------------------------
# Mask clean-up
# ----------------------------------------------------------------------------------------------


def clean_mask(mask, *, min_component_fraction: float = 0.2, max_hole_fraction: float = 0.1,
               smooth_px: Optional[int] = None) -> torch.Tensor:
    """Tidy a binary object mask: smooth, keep the object's components, fill holes, drop specks.

    - Light morphological smoothing: an opening then a closing with a disk of ``smooth_px``
      (default: 1 px per 300 px of the short image side, at least 1) removes one-pixel spurs and
      notches without moving the outline.
    - Connected components (8-connected): the largest is kept, plus any other at least
      ``min_component_fraction`` of its area (several parts of one object); smaller ones are specks.
    - Holes (background regions not connected to the image border) up to ``max_hole_fraction`` of
      the object's area are filled; bigger ones are real openings (a ring, a handle) and stay.

    Returns a float32 (H,W) tensor in {0, 1}; an empty input gives an empty mask.
    """
    m = _to_numpy(mask)
    if m.ndim == 3 and m.shape[0] == 1:
        m = m[0]
    if m.ndim != 2:
        raise InputError(f"clean_mask: mask must have shape (H, W); got {tuple(m.shape)}")
    m = (m.astype(np.float32) > 0.5).astype(np.uint8)
    h, w = m.shape
    if smooth_px is None:
        smooth_px = max(1, int(round(min(h, w) / 300.0)))
    if smooth_px > 0 and m.any():
        k = _ellipse(smooth_px)
        opened = cv2.morphologyEx(m, cv2.MORPH_OPEN, k)
        if opened.any():  # a thin object must not vanish under the opening
            m = opened
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, k, borderType=cv2.BORDER_REPLICATE)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return torch.from_numpy(m.astype(np.float32))
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.zeros(n, dtype=bool)
    keep[1:] = areas >= min_component_fraction * areas.max()
    m = keep[labels].astype(np.uint8)
    # Holes: background components (4-connected, the dual of 8-connected foreground) that do not
    # touch the image border.
    inv = (1 - m).astype(np.uint8)
    nb, blabels, bstats, _ = cv2.connectedComponentsWithStats(inv, connectivity=4)
    if nb > 1:
        border = np.unique(np.concatenate([blabels[0], blabels[-1], blabels[:, 0], blabels[:, -1]]))
        area = float(m.sum())
        fill = np.zeros(nb, dtype=bool)
        fill[1:] = bstats[1:, cv2.CC_STAT_AREA] <= max_hole_fraction * area
        fill[border] = False
        fill[0] = False
        m[fill[blabels]] = 1
    return torch.from_numpy(m.astype(np.float32))


# ----------------------------------------------------------------------------------------------
# Automatic box and GrabCut
# ----------------------------------------------------------------------------------------------


def _central_box(w: int, h: int, frac: float = 0.8) -> tuple[int, int, int, int]:
    mx, my = int(round(w * (1 - frac) / 2)), int(round(h * (1 - frac) / 2))
    return mx, my, w - mx, h - my


def auto_box(image, *, margin: float = 0.03, max_side: int = 512) -> tuple[int, int, int, int]:
    """A box (x0, y0, x1, y1), x1/y1 exclusive, around the salient object near the image centre.

    The background's colours are learned from a thin band along the image border (k-means in
    CIE Lab, ignoring clusters that cover under 5% of the band, which are usually the object
    itself touching the border). Each pixel's distance to the nearest background colour is a
    saliency map; Otsu's threshold splits it; a closing joins the object's fragments (its
    highlights and shadows differ from each other as much as from the table). The component that
    best overlaps the central half of the image is the object; components at least a quarter of
    its size that also reach the centre join it. The box is their bounding box grown by ``margin``
    of the image size and clipped to the image. When nothing plausible is found the central 80%
    of the image is returned.
    """
    img = as_image_array(image)
    H, W = img.shape[:2]
    small, scale = _resize_to_max_side(img, max_side)
    h, w = small.shape[:2]
    fallback = _central_box(W, H)
    if min(h, w) < 8:
        return fallback
    lab = cv2.cvtColor(small, cv2.COLOR_RGB2LAB)  # float32 input: L in 0..100, a/b about ±127
    lab = cv2.GaussianBlur(lab, (0, 0), 1.0)
    band = max(2, int(round(0.02 * min(h, w))))
    border = np.concatenate([lab[:band].reshape(-1, 3), lab[-band:].reshape(-1, 3),
                             lab[band:-band, :band].reshape(-1, 3), lab[band:-band, -band:].reshape(-1, 3)])
    k = int(min(5, max(1, border.shape[0] // 50)))
    cv2.setRNGSeed(12345)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.5)
    _, labels, centres = cv2.kmeans(border.astype(np.float32), k, None, criteria, 3, cv2.KMEANS_PP_CENTERS)
    share = np.bincount(labels.ravel(), minlength=k) / float(labels.size)
    centres = centres[share >= 0.05] if (share >= 0.05).any() else centres
    flat = lab.reshape(-1, 1, 3)
    dist = np.sqrt(((flat - centres[None]) ** 2).sum(-1)).min(1).reshape(h, w)
    top = float(np.percentile(dist, 99))
    if top <= 1e-6:
        return fallback  # a flat image: nothing stands out
    d8 = np.clip(dist / top * 255.0, 0, 255).astype(np.uint8)
    _, fg = cv2.threshold(d8, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    close_r = max(1, int(round(0.02 * min(h, w))))
    fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, _ellipse(close_r))
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, _ellipse(max(1, close_r // 2)))
    n, cc, stats, centroids = cv2.connectedComponentsWithStats(fg, connectivity=8)
    if n <= 1:
        return fallback
    cx0, cx1, cy0, cy1 = w // 4, w - w // 4, h // 4, h - h // 4
    central = np.bincount(cc[cy0:cy1, cx0:cx1].ravel(), minlength=n).astype(np.float64)
    central[0] = 0
    areas = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    if central.max() > 0:
        best = int(central.argmax())
    else:  # nothing reaches the centre: the component whose centroid is closest to it
        d = np.hypot(centroids[1:, 0] - w / 2, centroids[1:, 1] - h / 2) / np.sqrt(areas[1:])
        best = 1 + int(d.argmin())
    chosen = [best] + [i for i in range(1, n)
                       if i != best and central[i] > 0 and areas[i] >= 0.25 * areas[best]]
    if areas[chosen].sum() < 0.005 * h * w:
        return fallback
    sel = np.isin(cc, chosen)
    x0, y0, x1, y1 = mask_box(sel)
    inv = 1.0 / scale
    mx, my = margin * W, margin * H
    box = (int(max(0, math.floor(x0 * inv - mx))), int(max(0, math.floor(y0 * inv - my))),
           int(min(W, math.ceil(x1 * inv + mx))), int(min(H, math.ceil(y1 * inv + my))))
    if (box[2] - box[0]) * (box[3] - box[1]) >= 0.98 * W * H:
        # The "object" fills the frame: the saliency failed (e.g. a busy border). A box that
        # leaves no background would give GrabCut nothing to learn from.
        return fallback
    return box


def _check_box(box, w: int, h: int) -> tuple[int, int, int, int]:
    try:
        x0, y0, x1, y1 = (int(round(float(v))) for v in box)
    except (TypeError, ValueError) as exc:
        raise InputError(f"box must be four numbers (x0, y0, x1, y1) in pixels; got {box!r}") from exc
    x0, x1 = max(0, min(x0, w)), max(0, min(x1, w))
    y0, y1 = max(0, min(y0, h)), max(0, min(y1, h))
    if x1 - x0 < 2 or y1 - y0 < 2:
        raise InputError(f"box {tuple(box)} is empty or lies outside the {w}x{h} image; give "
                         "(x0, y0, x1, y1) with x0 < x1, y0 < y1 inside the image")
    return x0, y0, x1, y1


def check_points(points, point_labels=None, *, width: int, height: int,
                 name: str = "points") -> tuple[np.ndarray, np.ndarray]:
    """Validate click prompts: (N, 2) pixel coordinates (x, y) and N labels (1 object, 0 background).

    Returns float64 (N, 2) points and int (N,) labels. ``None`` or an empty sequence gives N = 0.
    Raises InputError naming what to change for a wrong shape, a non-number, a NaN/Inf, a point
    outside the image, a label count that does not match, or a label other than 0/1.
    """
    if points is None:
        pts = np.zeros((0, 2))
    else:
        try:
            pts = np.asarray(_to_numpy(points) if isinstance(points, torch.Tensor) else list(points),
                             dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name} must be a list of (x, y) pixel coordinates; got {points!r}") from exc
        if pts.size == 0:
            pts = np.zeros((0, 2))
        elif pts.ndim == 1 and pts.shape[0] == 2:
            pts = pts[None]
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise InputError(f"{name} must be a list of (x, y) pixel coordinates, e.g. [(120, 80)]; "
                             f"got an array of shape {tuple(pts.shape)}")
    if not np.isfinite(pts).all():
        raise InputError(f"{name} contain NaN or Inf: give finite pixel coordinates (x, y)")
    for x, y in pts:
        if not (0 <= x < width and 0 <= y < height):
            raise InputError(f"{name[:-1] if name.endswith('s') else name} ({x:g}, {y:g}) lies outside the "
                             f"{width}x{height} image: x must be in [0, {width}) and y in [0, {height})")
    if point_labels is None:
        labels = np.ones(len(pts), dtype=np.int64)
    else:
        try:
            lab = np.asarray(_to_numpy(point_labels) if isinstance(point_labels, torch.Tensor)
                             else list(point_labels), dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise InputError(f"point_labels must be a list of 1 (object) / 0 (background); "
                             f"got {point_labels!r}") from exc
        if lab.shape[0] != len(pts):
            raise InputError(f"point_labels has {lab.shape[0]} entries but there are {len(pts)} points: "
                             "give one label (1 object, 0 background) per point")
        if not np.isin(lab, (0.0, 1.0)).all():
            raise InputError(f"point_labels must be 1 (object) or 0 (background); got {lab.tolist()}")
        labels = lab.astype(np.int64)
    return pts, labels


def seed_radius(height: int, width: int) -> int:
    """Radius of the certain-object / certain-background disk a click becomes: 1% of the short side."""
    return max(2, int(round(0.01 * min(height, width))))


# The first, box-finding pass of a click prompt runs at most at this long side: it only has to
# find roughly where the clicked object ends.
POINT_PASS_MAX_SIDE = 320


def _point_box(small: np.ndarray, fg_pts: np.ndarray, bg_pts: np.ndarray) -> tuple[int, int, int, int]:
    """A working box for clicks without a box: a coarse GrabCut pass over nearly the whole image.

    A click says where the object is, not how big it is. The first pass takes everything but a
    thin border frame as "probably object", the object clicks as certain object and background
    clicks as certain background; the connected region of its result that holds the object
    clicks, grown by a quarter of its size (and never smaller than a tenth of the image around
    the clicks), bounds the real pass. Measured on the benchmark photos
    (docs/quality.md), boxes grown from a small box around the click collapse onto the clicked
    colour when the object's colours also occur around it, and were worse. Runs at
    ``POINT_PASS_MAX_SIDE``; returns the box in the coordinates of ``small``.
    """
    h, w = small.shape[:2]
    tiny, s = _resize_to_max_side(small, POINT_PASS_MAX_SIDE)
    th, tw = tiny.shape[:2]
    fp = np.clip(np.floor(fg_pts * s), 0, [tw - 1, th - 1])
    bp = np.clip(np.floor(bg_pts * s), 0, [tw - 1, th - 1]) if len(bg_pts) else bg_pts
    bgr = np.ascontiguousarray(_to_u8(tiny)[:, :, ::-1])
    gc = np.full((th, tw), cv2.GC_PR_FGD, np.uint8)
    frame = max(1, int(round(0.01 * min(th, tw))))
    gc[:frame], gc[-frame:], gc[:, :frame], gc[:, -frame:] = cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD, cv2.GC_BGD
    _paint_seeds(gc, fp, bp, seed_radius(th, tw))
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    _grabcut_run(bgr, gc, None, bgd, fgd, 3, cv2.GC_INIT_WITH_MASK)
    fg = ((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)).astype(np.uint8)
    n, cc = cv2.connectedComponents(fg, connectivity=8)
    ids = sorted({int(cc[int(y), int(x)]) for x, y in fp} - {0})
    xs, ys = fp[:, 0], fp[:, 1]
    if ids:
        x0, y0, x1, y1 = mask_box(np.isin(cc, ids))
    else:
        x0, y0, x1, y1 = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
    x0, x1 = min(x0, xs.min() - 0.1 * tw), max(x1, xs.max() + 0.1 * tw)
    y0, y1 = min(y0, ys.min() - 0.1 * th), max(y1, ys.max() + 0.1 * th)
    gx, gy = 0.25 * (x1 - x0), 0.25 * (y1 - y0)
    inv = 1.0 / s
    return (int(max(0, (x0 - gx) * inv)), int(max(0, (y0 - gy) * inv)),
            int(min(w, math.ceil((x1 + gx) * inv))), int(min(h, math.ceil((y1 + gy) * inv))))



def _gmm_log_likelihood(model: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Log-density of the colours ``x`` (N, 3) under one of OpenCV GrabCut's colour models: its
    (1, 65) array holds 5 weights, 5 means (3) and 5 covariances (3x3), in that order."""
    k = 5
    model = np.asarray(model, np.float64).ravel()
    w, mu, cov = model[:k], model[k:4 * k].reshape(k, 3), model[4 * k:].reshape(k, 3, 3)
    acc = np.zeros(x.shape[0])
    for i in range(k):
        if w[i] <= 0:
            continue
        c = cov[i] + np.eye(3) * 1e-2  # OpenCV regularises singular components the same way
        d = x - mu[i]
        q = np.einsum("ni,ij,nj->n", d, np.linalg.inv(c), d)
        acc += w[i] * np.exp(-0.5 * q) / math.sqrt((2 * math.pi) ** 3 * max(np.linalg.det(c), 1e-300))
    return np.log(acc + 1e-300)


#: Box tightness: rows and columns of a box this far inside its edges (a fraction of the image's
#: size, plus 2 px: the slack of a box drawn by hand on the screen) must cross the object.
TIGHT_IMAGE_MARGIN = 0.04
TIGHT_ROUNDS = 2


def _tighten_to_box(bgr: np.ndarray, gc: np.ndarray, bgd: np.ndarray, fgd: np.ndarray,
                    rect: tuple[int, int, int, int], iters: int, graph=None) -> None:
    """The box-tightness prior (Lempitsky et al., ICCV 2009): a box drawn around an object touches
    it on every side, so every row and every column of the box (away from its edges by the slack
    of a hand-drawn box, ``TIGHT_IMAGE_MARGIN``) crosses the object. GrabCut's colour models often leave
    part of the object out (a rocket's differently lit nose cone, a wheel as dark as the floor);
    here each row or column of the box that the result misses gets its most object-like pixel (by
    the two colour models' likelihood ratio) as a certain-object seed, and GrabCut runs again from
    its current models; twice at most. A side of the box on the image's border is exempt (the
    object may go on past it). Changes ``gc`` in place."""
    h, w = gc.shape
    x0, y0, x1, y1 = rect
    if x1 - x0 < 8 or y1 - y0 < 8:
        return
    mx = int(TIGHT_IMAGE_MARGIN * w) + 2
    my = int(TIGHT_IMAGE_MARGIN * h) + 2
    colours = bgr[y0:y1, x0:x1].reshape(-1, 3).astype(np.float64)
    for _ in range(TIGHT_ROUNDS):
        fg = ((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD))[y0:y1, x0:x1]
        if not fg.any():
            return
        # A side on the image's border asks nothing past what was found (the object may go on).
        fy, fx = np.nonzero(fg)
        rows = range(y0 + my if y0 > 0 else y0 + int(fy.min()), y1 - my if y1 < h else y0 + int(fy.max()) + 1)
        cols = range(x0 + mx if x0 > 0 else x0 + int(fx.min()), x1 - mx if x1 < w else x0 + int(fx.max()) + 1)
        empty_rows = [r for r in rows if not fg[r - y0].any()]
        empty_cols = [c for c in cols if not fg[:, c - x0].any()]
        if not empty_rows and not empty_cols:
            return
        llr = (_gmm_log_likelihood(fgd, colours) - _gmm_log_likelihood(bgd, colours)).reshape(y1 - y0, x1 - x0)
        for r in empty_rows:
            gc[r, x0 + int(np.argmax(llr[r - y0]))] = cv2.GC_FGD
        for c in empty_cols:
            gc[y0 + int(np.argmax(llr[:, c - x0])), c] = cv2.GC_FGD
        graph = _grabcut_run(bgr, gc, None, bgd, fgd, max(1, int(iters) // 2), cv2.GC_EVAL, graph=graph)


#: A box prompt's GrabCut runs on the box grown by this fraction of its size on each side (not on
#: the whole photo): its background colour model then describes what borders the object.
BOX_WINDOW = 0.15


def _box_window(box: tuple[int, int, int, int], W: int, H: int) -> Optional[tuple[int, int, int, int]]:
    """The part of the photo a box prompt's GrabCut runs on: the box grown by ``BOX_WINDOW`` of its
    width and height on each side (at least 2 px, within the photo), or None when that is the whole
    photo.

    OpenCV's GrabCut learns its background colours from every pixel outside the box. Far from the
    object those are often colours that never border it (the lighter wall across the room from a
    clock whose blurred rim is pale grey, the sky far above a rocket), and the background model that
    has them claims the object's own pale or dark parts. Measured on the benchmark photos
    (docs/quality.md): with a window of 0.1-0.25 of the box, box IoU >= 0.85 on 6 of 8 against 5 with
    the whole photo, and under random box jitter (each side moved by up to 2 % of the photo, 4 draws)
    5-6 of 8 against 3."""
    x0, y0, x1, y1 = box
    gx = max(2, int(math.ceil(BOX_WINDOW * (x1 - x0))))
    gy = max(2, int(math.ceil(BOX_WINDOW * (y1 - y0))))
    wx0, wy0, wx1, wy1 = max(0, x0 - gx), max(0, y0 - gy), min(W, x1 + gx), min(H, y1 + gy)
    if (wx0, wy0, wx1, wy1) == (0, 0, W, H):
        return None
    return wx0, wy0, wx1, wy1


def _grabcut_in_window(img: np.ndarray, window, box, pts: np.ndarray, labels: np.ndarray, iters: int,
                       max_side, _click: str, _tight: bool, _strokes: bool = True) -> np.ndarray:
    """``grabcut`` of a box prompt run on ``window`` only (``_box_window``); clicks outside the window
    lie outside the box, which is background anyway, and are dropped (object clicks outside the box
    are refused as before)."""
    H, W = img.shape[:2]
    x0, y0, x1, y1 = _check_box(box, W, H)
    if len(pts):
        fx, fy = pts[labels == 1, 0], pts[labels == 1, 1]
        if ((fx < x0) | (fx >= x1) | (fy < y0) | (fy >= y1)).any():
            raise InputError(f"an object point lies outside the box {tuple(box)}: move the point "
                             "onto the object inside the box, or draw the box around it")
    wx0, wy0, wx1, wy1 = window
    inside = (pts[:, 0] >= wx0) & (pts[:, 0] < wx1) & (pts[:, 1] >= wy0) & (pts[:, 1] < wy1) if len(pts) else \
        np.zeros(0, bool)
    sub = np.ascontiguousarray(img[wy0:wy1, wx0:wx1])
    sp = pts[inside] - [wx0, wy0] if len(pts) else pts
    m = grabcut(sub, box=(x0 - wx0, y0 - wy0, x1 - wx0, y1 - wy0), points=sp if len(sp) else None,
                point_labels=labels[inside] if len(sp) else None, iters=iters, max_side=max_side,
                _click=_click, _tight=_tight, _window=False, _strokes=_strokes)
    out = np.zeros((H, W), bool)
    out[wy0:wy1, wx0:wx1] = m
    return out


#: Coarse to fine: a GrabCut whose working size is above COARSE_TRIGGER px on its long side runs at
#: COARSE_SIDE first, then at its working size again only in a band around that outline (BAND_FRACTION
#: of the short side each way), REFINE_ITERS iterations. GrabCut's max-flow is what costs, and on a
#: low-contrast photo it grows fast with the pixel count: at 1024 px one iteration took 2.2 s on the cat
#: photo. Measured on the eight benchmark photos enlarged to 1024 px (docs/quality.md): automatic
#: 1.7-13.7 s -> 1.1-4.2 s, box 0.4-18.4 s -> 0.4-4.0 s, the same count of good masks. 0 turns it off.
COARSE_SIDE = 512
COARSE_TRIGGER = 700
BAND_FRACTION = 0.02
REFINE_ITERS = 2
MIN_REFINE_SAMPLES = 64


def _refine_band(img: np.ndarray, coarse: np.ndarray, box, pts: np.ndarray, labels: np.ndarray,
                 work_side: int) -> np.ndarray:
    """The fine pass of a coarse-to-fine GrabCut: at the working size, pixels farther than the band from
    the coarse outline keep the coarse answer for certain; those in the band are "probably" it, and
    GrabCut (new colour models, the clicks and the box as given) decides them."""
    H, W = img.shape[:2]
    small, scale = _resize_to_max_side(img, work_side)
    h, w = small.shape[:2]
    cm = cv2.resize(coarse.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
    r = max(2, int(round(BAND_FRACTION * min(h, w))))
    k = _ellipse(r)
    band = (cv2.dilate(cm.astype(np.uint8), k) > 0) & ~(cv2.erode(cm.astype(np.uint8), k) > 0)
    gc = np.where(cm, cv2.GC_FGD, cv2.GC_BGD).astype(np.uint8)
    gc[band & cm] = cv2.GC_PR_FGD
    gc[band & ~cm] = cv2.GC_PR_BGD
    if box is not None:
        gc[_outside_box(box, W, H, scale, (h, w))] = cv2.GC_BGD
    sp = np.clip(np.floor(pts * scale), 0, [w - 1, h - 1]) if len(pts) else pts
    fg_pts, bg_pts = sp[labels == 1], sp[labels == 0]
    radius = seed_radius(h, w)
    _paint_seeds(gc, fg_pts, bg_pts, radius)
    is_fg = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    if min(int(is_fg.sum()), int((~is_fg).sum())) < MIN_REFINE_SAMPLES:
        return coarse  # too few pixels on one side for GrabCut's colour models: the coarse cut stands
    bgr = np.ascontiguousarray(_to_u8(small)[:, :, ::-1])
    bgd = np.zeros((1, 65), np.float64)
    fgd = np.zeros((1, 65), np.float64)
    _grabcut_run(bgr, gc, None, bgd, fgd, REFINE_ITERS, cv2.GC_INIT_WITH_MASK)
    return _labels_to_mask(gc, fg_pts, bg_pts, radius, (H, W))


def _outside_box(box, W: int, H: int, scale: float, shape: tuple[int, int]) -> np.ndarray:
    """The pixels of the working-size image (``shape``, the photo scaled by ``scale``) outside ``box``."""
    x0, y0, x1, y1 = _check_box(box, W, H)
    outside = np.ones(shape, bool)
    outside[int(y0 * scale):int(math.ceil(y1 * scale)), int(x0 * scale):int(math.ceil(x1 * scale))] = False
    return outside


def _labels_to_mask(gc: np.ndarray, fg_pts: np.ndarray, bg_pts: np.ndarray, radius: int,
                    size: tuple[int, int]) -> np.ndarray:
    """GrabCut's labels as the object mask at the photo's ``size`` (H, W): a separate part touching a
    background click dropped (``_drop_clicked_background``), upsampled smoothly."""
    fg = ((gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)).astype(np.uint8)
    if len(bg_pts):
        fg = _drop_clicked_background(fg, fg_pts, bg_pts, radius)
    fg = fg.astype(np.float32)
    if fg.shape != tuple(size):
        fg = cv2.resize(fg, (size[1], size[0]), interpolation=cv2.INTER_LINEAR)
    return fg > 0.5


#: A background click that GrabCut's object still borders after the cut (it took only the click's disk out of,
#: say, a patch of wall joined to the object) grows into a stroke: the pixels labelled object around it, within
#: STROKE_REACH of the short side, that the click reaches through colour steps of at most STROKE_STEP per channel
#: (8-bit, on the photo blurred by one pixel), become certain background, and GrabCut cuts again from its colour
#: models. (The same for object clicks was tried on the portrait's white cap: the cap's shading and embroidery
#: stop such a fill within a few pixels, and it added a strip of the flag pole instead; not used.)
STROKE_REACH = 0.15
STROKE_STEP = 3


def _background_strokes(bgr: np.ndarray, gc: np.ndarray, bg_pts: np.ndarray, radius: int) -> np.ndarray:
    """The pixels (bool (h, w)) the background clicks that the object still borders mean (``STROKE_*``)."""
    h, w = gc.shape
    obj = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    out = np.zeros((h, w), bool)
    reach = max(2 * int(radius), int(STROKE_REACH * min(h, w)))
    smooth = cv2.GaussianBlur(bgr, (0, 0), 1.0)
    for x, y in bg_pts:
        xi, yi = int(x), int(y)
        ring = np.zeros((h, w), np.uint8)
        cv2.circle(ring, (xi, yi), int(radius) + 2, 1, -1)
        if not (obj & (ring > 0)).any():
            continue
        area = np.zeros((h, w), np.uint8)
        cv2.circle(area, (xi, yi), reach, 1, -1)
        allowed = (area > 0) & ((gc == cv2.GC_PR_FGD) | (ring > 0))
        fill = np.ones((h + 2, w + 2), np.uint8)  # floodFill stops at non-zero mask pixels
        fill[1:-1, 1:-1][allowed] = 0
        step = (STROKE_STEP,) * 3
        cv2.floodFill(smooth, fill, (xi, yi), 0, step, step, 8 | cv2.FLOODFILL_MASK_ONLY | (2 << 8))
        out |= (fill[1:-1, 1:-1] == 2) & (gc == cv2.GC_PR_FGD)
    return out


def _paint_seeds(gc: np.ndarray, fg_pts: np.ndarray, bg_pts: np.ndarray, radius: int) -> None:
    for pts, value in ((bg_pts, cv2.GC_BGD), (fg_pts, cv2.GC_FGD)):
        for x, y in pts:
            cv2.circle(gc, (int(x), int(y)), int(radius), int(value), -1)


def grabcut(image, *, box=None, init_mask=None, points=None, point_labels=None, iters: int = 5,
            max_side: Optional[int] = None, progress=None, _click: str = "choose", _tight: bool = True,
            _window: bool = True, _until=None, _strokes: bool = True) -> np.ndarray:
    """GrabCut foreground (bool (H,W)) of an image, seeded by a box, a rough mask and/or clicks.

    - ``box`` (x0, y0, x1, y1): everything outside it is certainly background, and GrabCut learns
      the background from around the box only (``BOX_WINDOW``; see ``_box_window``).
    - ``init_mask``: its inside is "probably object", its outside "probably background" (a rough
      mask is refined), and far outside it certainly background.
    - ``points``: (x, y) pixel clicks with ``point_labels`` (1 object, 0 background; default all
      1). Each becomes a disk of certain object / background of ``seed_radius`` pixels, and a
      separate part of the result touching a background click (holding no object click) is
      dropped (``_drop_clicked_background``). Clicks
      with neither box nor mask: a first pass over nearly the whole image finds the clicked
      region, whose box (grown by a quarter) bounds the real pass (see ``_point_box``).
    - nothing: the box is ``auto_box``.
    Runs at ``max_side`` at most (coarse to fine above ``COARSE_TRIGGER`` px: ``_refine_band``); the
    result is upsampled smoothly. ``progress(done, total)`` (``progress.ProgressFn``) is called before
    every GrabCut iteration, the last time with ``done == total`` once the mask is there; it raises to
    cancel (ComfyUI's interrupt in the nodes).
    """
    img = as_image_array(image)
    H, W = img.shape[:2]
    if not (1 <= int(iters) <= 50):
        raise InputError(f"grabcut_iters must be between 1 and 50; got {iters}")
    pts, labels = check_points(points, point_labels, width=W, height=H)
    click = _click == "choose" and box is None and init_mask is None and bool((labels == 1).any())
    if progress is not None:
        # the iterations of one cut (with the tightness prior's and a coarse to fine cut's), and for a
        # click its search before it (``_click_prompted``: the growing box's passes, and the whole-image
        # candidate's point pass and cut)
        n = int(iters) + 2 * max(1, int(iters) // 2) + REFINE_ITERS + ((GROW_PASSES + 2) * int(iters) if click else 0)
        ticker = _CutProgress(progress, n + 1)
        with _ticking(ticker):
            m = grabcut(img, box=box, init_mask=init_mask, points=points, point_labels=point_labels, iters=iters,
                        max_side=max_side, _click=_click, _tight=_tight, _window=_window, _strokes=_strokes)
        report(progress, ticker.total, ticker.total)
        return m
    if click:
        return _click_prompted(img, pts, labels, int(iters), max_side)
    if box is not None and init_mask is None and _window:
        window = _box_window(_check_box(box, W, H), W, H)
        if window is not None:
            return _grabcut_in_window(img, window, box, pts, labels, iters, max_side, _click, _tight, _strokes)
    work_side = GRABCUT_MAX_SIDE if max_side is None else int(max_side)
    if COARSE_SIDE and min(work_side, max(H, W)) > COARSE_TRIGGER:
        coarse = grabcut(img, box=box, init_mask=init_mask, points=points, point_labels=point_labels, iters=iters,
                         max_side=COARSE_SIDE, _click=_click, _tight=_tight, _window=False, _strokes=_strokes)
        if coarse.any() and not coarse.all():
            return _refine_band(img, coarse, box, pts, labels, work_side)
        return coarse
    small, scale = _resize_to_max_side(img, work_side)
    h, w = small.shape[:2]
    sp = np.clip(np.floor(pts * scale), 0, [w - 1, h - 1]) if len(pts) else pts
    fg_pts, bg_pts = sp[labels == 1], sp[labels == 0]
    radius = seed_radius(h, w)
    bgr = np.ascontiguousarray(_to_u8(small)[:, :, ::-1])
    gc = np.zeros((h, w), np.uint8)
    bgd = np.zeros((1, 65), np.float64)
    fgd = np.zeros((1, 65), np.float64)
    if init_mask is not None:
        m0 = as_mask_array(init_mask, (H, W), "mask") > 0.5
        if not m0.any():
            raise InputError("The mask given to GrabCut is empty; draw the object or give a box")
        if m0.all():
            raise InputError("The mask given to GrabCut covers the whole image; GrabCut needs some "
                             "background to learn from")
        ms = cv2.resize(m0.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0.5
        far = cv2.dilate(ms.astype(np.uint8), _ellipse(max(2, int(0.05 * min(h, w))))) == 0
        gc[:] = cv2.GC_PR_BGD
        gc[ms] = cv2.GC_PR_FGD
        gc[far] = cv2.GC_BGD
        if box is not None:  # outside a given box is certainly background
            gc[_outside_box(box, W, H, scale, (h, w))] = cv2.GC_BGD
        _paint_seeds(gc, fg_pts, bg_pts, radius)
        if not ((gc == cv2.GC_PR_FGD) | (gc == cv2.GC_FGD)).any():
            raise InputError("The mask given to GrabCut vanished at the working resolution; it is "
                             "too small")
        _grabcut_run(bgr, gc, None, bgd, fgd, iters, cv2.GC_INIT_WITH_MASK)
    else:
        if box is not None:
            x0, y0, x1, y1 = _check_box(box, W, H)
            sx0, sy0 = int(math.floor(x0 * scale)), int(math.floor(y0 * scale))
            sx1, sy1 = min(w, int(math.ceil(x1 * scale))), min(h, int(math.ceil(y1 * scale)))
        elif len(fg_pts):
            sx0, sy0, sx1, sy1 = _point_box(small, fg_pts, bg_pts)
        else:
            x0, y0, x1, y1 = _check_box(auto_box(img), W, H)
            sx0, sy0 = int(math.floor(x0 * scale)), int(math.floor(y0 * scale))
            sx1, sy1 = min(w, int(math.ceil(x1 * scale))), min(h, int(math.ceil(y1 * scale)))
        # GrabCut learns the background from outside the box: keep at least a 1-pixel frame.
        if sx0 == 0 and sy0 == 0 and sx1 == w and sy1 == h:
            sx0, sy0, sx1, sy1 = 1, 1, w - 1, h - 1
        if len(pts):
            if box is not None and len(fg_pts):
                fx, fy = fg_pts[:, 0], fg_pts[:, 1]
                if ((fx < sx0) | (fx >= sx1) | (fy < sy0) | (fy >= sy1)).any():
                    raise InputError(f"an object point lies outside the box {tuple(box)}: move the point "
                                     "onto the object inside the box, or draw the box around it")
            gc[:] = cv2.GC_BGD
            gc[sy0:sy1, sx0:sx1] = cv2.GC_PR_FGD
            _paint_seeds(gc, fg_pts, bg_pts, radius)
            if not ((gc == cv2.GC_PR_FGD) | (gc == cv2.GC_FGD)).any():
                raise InputError("the background points cover the whole box: nothing is left for the object")
            # ``_until(mask, i)``: the growing box of a click stops a pass once its mask answers whether
            # the object reaches the box (``_grown_click``)
            until = (None if _until is None else
                     lambda g, i: _until(_labels_to_mask(g, fg_pts, bg_pts, radius, (H, W)), i))
            graph = _grabcut_run(bgr, gc, None, bgd, fgd, iters, cv2.GC_INIT_WITH_MASK, until)
            stroke = _background_strokes(bgr, gc, bg_pts, radius) if len(bg_pts) and _strokes else None
            if stroke is not None and stroke.any():
                gc[stroke] = cv2.GC_BGD
                graph = _grabcut_run(bgr, gc, None, bgd, fgd, iters, cv2.GC_EVAL, graph=graph)
            if box is not None and _tight:
                _tighten_to_box(bgr, gc, bgd, fgd, (sx0, sy0, sx1, sy1), iters, graph)
        else:
            rect = (sx0, sy0, max(1, sx1 - sx0), max(1, sy1 - sy0))
            graph = _grabcut_run(bgr, gc, rect, bgd, fgd, iters, cv2.GC_INIT_WITH_RECT)
            if box is not None and _tight:
                _tighten_to_box(bgr, gc, bgd, fgd, (sx0, sy0, sx1, sy1), iters, graph)
    return _labels_to_mask(gc, fg_pts, bg_pts, radius, (H, W))


#: Clicks without a box look for their object at this long side at most (two candidates, several
#: passes), then cut it once at full size.
CLICK_SEARCH_MAX_SIDE = 640
#: The growing box of a click: its first half-size (fraction of the image's long side), how much a
#: side grows when the object reaches it (fraction of the box's size), and at most how many passes.
GROW_START = 0.12
GROW_FACTOR = 0.6
GROW_PASSES = 6
#: A growing pass stops once this many GrabCut iterations in a row reach the same sides of its box
#: (0: every pass runs all its iterations).
GROW_DECIDE = 3
#: The click's last cut is a box prompt in its object's box grown by this fraction per side.
CLICK_RECUT_GROW = 0.04
#: The click's object is not cut again when its box's window (``_box_window``) adds less than this
#: fraction of the box's area around it: the background the re-cut would learn from (``_click_recut``).
CLICK_RECUT_MIN_RING = 0.2


def _grow_start_box(pts: np.ndarray, labels: np.ndarray, W: int, H: int) -> tuple[float, float, float, float]:
    """The first box of a click's growing box: the clicks grown by GROW_START of the long side."""
    S = float(max(H, W))
    fg = pts[labels == 1]
    x0, y0 = fg.min(0) - GROW_START * S
    x1, y1 = fg.max(0) + GROW_START * S
    return (max(0.0, float(x0)), max(0.0, float(y0)), min(float(W), float(x1) + 1), min(float(H), float(y1) + 1))


def _reach(m: np.ndarray, box, fg: np.ndarray, W: int, H: int):
    """The clicked part of ``m`` and which sides of ``box`` (left, top, right, bottom; not the image's
    border) it reaches, or None for the sides when no click is on ``m``."""
    n, cc = cv2.connectedComponents(m.astype(np.uint8), connectivity=8)
    ids = sorted({int(cc[int(y), int(x)]) for x, y in fg} - {0})
    comp = np.isin(cc, ids) if ids else m
    if not comp.any():
        return comp, None
    bx0, by0, bx1, by1 = mask_box(comp)
    tol = 3
    return comp, (bx0 <= box[0] + tol and box[0] > 0, by0 <= box[1] + tol and box[1] > 0,
                  bx1 >= box[2] - tol and box[2] < W, by1 >= box[3] - tol and box[3] < H)


def _grow_box(box, reach, W: int, H: int) -> tuple[float, float, float, float]:
    """The next box of a click's growing box: each side the clicked part reached moves out by
    GROW_FACTOR of the box's size."""
    bw, bh = box[2] - box[0], box[3] - box[1]
    return (max(0.0, box[0] - GROW_FACTOR * bw) if reach[0] else box[0],
            max(0.0, box[1] - GROW_FACTOR * bh) if reach[1] else box[1],
            min(float(W), box[2] + GROW_FACTOR * bw) if reach[2] else box[2],
            min(float(H), box[3] + GROW_FACTOR * bh) if reach[3] else box[3])


def _grow_pass(img: np.ndarray, pts: np.ndarray, labels: np.ndarray, iters: int, max_side, box, on_reach=None):
    """One pass of a click's growing box: GrabCut with ``box`` as its box and the clicks, on the whole
    photo; returns ``_reach`` of the result. A pass that is going to grow stops as soon as GROW_DECIDE
    iterations in a row reach the same sides (only that answer is used); a pass that reaches no side runs
    all its iterations, so the mask a chain ends on is the full cut. ``on_reach(sides)`` is told the sides
    after each iteration but the last (what ``_click_prompted`` guesses the next box from)."""
    H, W = img.shape[:2]
    fg = pts[labels == 1]
    seen: list = []

    def decided(m: np.ndarray, i: int) -> bool:
        r = _reach(m, box, fg, W, H)[1]
        seen.append(r)
        if on_reach is not None:
            on_reach(r)
        last = seen[-GROW_DECIDE:] if GROW_DECIDE > 0 else []
        return (len(last) == GROW_DECIDE > 0 and last[-1] is not None and any(last[-1])
                and all(r == last[-1] for r in last))

    # On the whole photo, not a box prompt's window (``_box_window``): a growing box starts inside the
    # object, where a window's ring is the object's own colour and the cut collapses onto the click (the
    # clock's click; the rocket's 0.525 -> 0.460).
    m = grabcut(img, box=[int(round(b)) for b in box], points=pts, point_labels=labels, iters=iters,
                max_side=max_side, _click="whole", _tight=False, _window=False, _until=decided, _strokes=False)
    return _reach(m, box, fg, W, H)


def _grow_ends(reach, depth: int) -> bool:
    """Whether the chain of growing passes ends at the pass ``depth`` (from 0) that reached ``reach``."""
    return reach is None or not any(reach) or depth >= GROW_PASSES - 1


def _grown_click(img: np.ndarray, pts: np.ndarray, labels: np.ndarray, iters: int, max_side) -> np.ndarray:
    """A click's object by a box grown from the click: GrabCut in a box around the clicks; while the
    clicked part reaches a side of its box (not the image's border), that side moves out and GrabCut
    runs again (``_grow_pass``). It finds a compact object (a cell, a rocket on a dark sky, a cup) that the
    whole-image pass merges with its surroundings, but collapses onto the clicked colour where the object's
    own colours surround it (a suit, a coat): ``_click_prompted`` chooses between the two. This is the
    chain one pass after the other; ``_click_prompted`` runs the same passes, some ahead of time."""
    H, W = img.shape[:2]
    box = _grow_start_box(pts, labels, W, H)
    for depth in range(GROW_PASSES):
        comp, reach = _grow_pass(img, pts, labels, iters, max_side, box)
        if _grow_ends(reach, depth):
            return comp
        box = _grow_box(box, reach, W, H)
    return comp


#: How many of a click's GrabCut cuts run at once (``_click_prompted``): 2 uses both cores of a small
#: machine; 1 runs them one after the other. The mask is the same either way.
CLICK_THREADS = 2


class _ClickJob:
    """One cut of a click's search on a worker thread: its future, whether it was called off, and (a
    growing pass) the sides of its box its clicked part reaches so far."""

    __slots__ = ("future", "cancel", "reach")

    def __init__(self):
        self.future, self.cancel, self.reach = None, False, None


def _choose_click(img: np.ndarray, whole, grown, fg_pts: np.ndarray):
    """The click's two candidates, each (mask, (cleaned, plausible) or None), to what wins: the larger
    plausible one, and when neither is plausible the whole-image one. Returns (k, cleaned) with k the
    winner's index, or (None, mask) when no candidate has a pixel left (that mask is the answer)."""
    best, best_key, best_clean, won = whole[0], None, None, 0
    for k, (cand, checked) in enumerate((whole, grown)):
        if not cand.any():
            continue
        cleaned, ok = checked if checked is not None else _clean_and_check(img, cand, fg_pts)
        key = (ok, float(cleaned.mean()) if ok else -k)
        if best_key is None or key > best_key:
            best, best_key, best_clean, won = cand, key, cleaned, k
    if best_clean is None or not best_clean.any():
        return None, best
    return won, best_clean


def _click_prompted(img: np.ndarray, pts: np.ndarray, labels: np.ndarray, iters: int, max_side) -> np.ndarray:
    """Clicks without a box: two candidates, the whole-image pass (``_point_box``) and the grown box
    (``_grown_click``), each cleaned and checked (``check.check_mask`` with the photo and the clicks);
    the larger plausible one wins (the whole-image pass errs by swallowing the surroundings, which the
    check catches; the grown box errs by shrinking onto a part, which it does not), and when neither is
    plausible the whole-image one. The winner is cut once more as a box prompt (``_click_recut``).
    Measured on the benchmark photos (docs/quality.md).

    The cuts run on CLICK_THREADS worker threads while this thread plans and reports: first what the
    answer needs for certain (the whole-image pass, the next growing pass, the winner's re-cut); on a
    free thread what it probably needs: the growing pass after a running one, its box grown by the sides
    the running pass reaches so far; a plausible candidate's re-cut before the other candidate is known.
    A guess that turns out wrong is called off at its next GrabCut iteration. Each cut is a function of
    its inputs only (GrabCut seeds its generator per call), so the mask is the one the chain gives one
    cut after the other (``_grown_click``), whichever ran when. This thread's hook (``_ticking``: the
    progress callback, ComfyUI's Cancel) is called once per GrabCut iteration of any worker, while the
    workers wait: when it raises, no worker starts another iteration."""
    fg_pts = pts[labels == 1]
    H, W = img.shape[:2]
    search = min(CLICK_SEARCH_MAX_SIDE, GRABCUT_MAX_SIDE if max_side is None else int(max_side))
    hook = getattr(_TICK, "fn", None)  # the progress callback's ticker (``grabcut(progress=)``), if any
    cv = threading.Condition()
    jobs: dict = {}
    state = {"started": 0, "stop": False}

    def tick(job: _ClickJob) -> None:
        with cv:
            if state["stop"] or job.cancel:
                raise _Cancelled()
            state["started"] += 1
            cv.notify_all()

    def told(job: _ClickJob, reach) -> None:
        with cv:
            job.reach = reach
            cv.notify_all()

    def whole_cut(job):
        whole = grabcut(img, points=pts, point_labels=labels, iters=iters, max_side=search, _click="whole",
                        _strokes=False)
        return whole, (_clean_and_check(img, whole, fg_pts) if whole.any() else None)

    def grow_cut(job, box, depth):
        comp, reach = _grow_pass(img, pts, labels, iters, search, box, on_reach=lambda r: told(job, r))
        told(job, reach)
        checked = _clean_and_check(img, comp, fg_pts) if _grow_ends(reach, depth) and comp.any() else None
        return comp, reach, checked

    def recut(job, cleaned):
        return _click_recut(img, cleaned, pts, labels, iters, max_side)

    def done(key):
        j = jobs.get(key)
        return j is not None and j.future.done()

    def plan():
        """(the answer or None, the cuts wanted in order: (key, function))."""
        want, later = [], []
        whole = jobs[("whole",)].future.result() if done(("whole",)) else None
        if whole is None:
            want.append((("whole",), whole_cut))
        box, depth, grown = _grow_start_box(pts, labels, W, H), 0, None
        while grown is None:
            key = ("grow", box, depth)
            if done(key):
                comp, reach, checked = jobs[key].future.result()
                if _grow_ends(reach, depth):
                    grown = (comp, checked)
                else:
                    box, depth = _grow_box(box, reach, W, H), depth + 1
                continue
            want.append((key, lambda job, b=box, d=depth: grow_cut(job, b, d)))
            j = jobs.get(key)  # the passes after it, grown by the sides it reaches so far
            while j is not None and j.reach is not None and not _grow_ends(j.reach, depth):
                box, depth = _grow_box(box, j.reach, W, H), depth + 1
                key = ("grow", box, depth)
                if not done(key):
                    later.append((key, lambda job, b=box, d=depth: grow_cut(job, b, d)))
                j = jobs.get(key)
            break
        if whole is not None and grown is not None:
            won, cleaned = _choose_click(img, whole, grown, fg_pts)
            if won is None:
                return cleaned, []
            key = ("recut", won)
            if done(key):
                return jobs[key].future.result(), []
            return None, [(key, lambda job, c=cleaned: recut(job, c))]
        # guesses: a plausible candidate's re-cut, the whole-image one's before the guessed passes (it
        # wins when plausible and larger), the grown box's after them
        guess = [[], []]
        for k, cand in ((0, whole), (1, grown)):
            if cand is not None and cand[1] is not None and cand[1][1] and cand[1][0].any() \
                    and not done(("recut", k)):
                guess[k].append((("recut", k), lambda job, c=cand[1][0]: recut(job, c)))
        return None, want + guess[0] + later + guess[1]

    def run(job: _ClickJob, fn):
        with _ticking(lambda: tick(job)):
            return fn(job)

    def wake(_future) -> None:
        with cv:
            cv.notify_all()

    pool = ThreadPoolExecutor(CLICK_THREADS + 2, thread_name_prefix="physmotion-click")
    finished = False
    try:
        with cv:
            reported = 0
            while True:
                while reported < state["started"]:
                    reported += 1
                    if hook is not None:
                        try:
                            hook()
                        except BaseException:
                            state["stop"] = True  # before any worker can start another iteration
                            raise
                answer, wanted = plan()
                if answer is not None:
                    break
                first = wanted[:max(1, int(CLICK_THREADS))]
                keys = {k for k, _ in first}
                for key in [k for k, j in jobs.items() if not j.future.done() and k not in keys]:
                    jobs.pop(key).cancel = True  # a guess no longer wanted, or one ranked lower now
                for key, fn in first:
                    if key not in jobs:
                        job = _ClickJob()
                        jobs[key] = job
                        job.future = pool.submit(run, job, fn)
                        job.future.add_done_callback(wake)
                cv.wait(0.5)
        finished = True
        return answer
    finally:
        with cv:
            state["stop"] = True  # every worker stops before its next GrabCut iteration
        # after a failure or Cancel, wait for the workers (at most the iteration under way); after an
        # answer, a guess no longer wanted finishes its iteration on its own
        pool.shutdown(wait=not finished, cancel_futures=True)


def _clean_and_check(img: np.ndarray, cand: np.ndarray, fg_pts: np.ndarray) -> tuple[np.ndarray, bool]:
    """A click candidate cleaned and cut down to its clicked part (with the parts ``_join_near_parts``
    joins to it), and whether it passes ``check_mask``."""
    from .check import check_mask

    tidy = clean_mask(cand).numpy() > 0.5
    cleaned = _join_near_parts(img, tidy, _keep_clicked(tidy, cand, fg_pts))
    return cleaned, check_mask(cleaned, object_points=[tuple(p) for p in fg_pts], image=img).ok


#: A click's candidate can come apart at a band of a colour GrabCut did not give to the object (a
#: dark collar between a face and a suit, a belt, a shadow line). Another part of the clean-up's
#: result (at least a fifth of the largest, ``clean_mask``) at most JOIN_GAP of the short side from
#: the clicked part is joined to it, with the gap between them, when the gap's colours are not the
#: background's around the two (the share of the gap's colour histogram that the histogram of a ring
#: around both, one gap wide, also holds, under JOIN_MAX_SHARED): a gap of the background's own colour
#: parts two objects (two cups side by side), and the click chose one.
JOIN_GAP = 0.15
JOIN_MAX_SHARED = 0.7
#: The gap between two parts: the pixels whose distances to the two add up to at most the gap's width
#: by this much more (and 2 px), the band that a straight bridge between their nearest sides sweeps.
JOIN_SLACK = 0.1


def _distance_to(m: np.ndarray) -> np.ndarray:
    """Each pixel's Euclidean distance (px) to the nearest pixel of ``m`` (bool (H, W))."""
    return cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def _join_near_parts(img: np.ndarray, tidy: np.ndarray, clicked: np.ndarray) -> np.ndarray:
    """``clicked`` (the clicked part of the cleaned mask ``tidy``) with the other parts of ``tidy`` that
    belong to it joined on, gap included (JOIN_GAP, JOIN_MAX_SHARED). On the benchmark photos
    (docs/quality.md) only the astronaut's candidate comes in two parts: her head, 66 px above her suit
    across the black collar (shared 0.45), which a click on the suit lost; two discs on a plain, a
    two-tone or a noisy ground share 0.93 or more."""
    from .check import lab_histogram

    if not clicked.any():
        return clicked
    n, cc = cv2.connectedComponents((tidy & ~clicked).astype(np.uint8), connectivity=8)
    if n <= 1:
        return clicked
    H, W = tidy.shape
    d_click = _distance_to(clicked)
    out, lab = clicked.copy(), None
    for i in range(1, n):
        part = cc == i
        gap = float(d_click[part].min())
        if gap > JOIN_GAP * min(H, W):
            continue
        between = (d_click + _distance_to(part) <= gap * (1.0 + JOIN_SLACK) + 2.0) & ~tidy
        d_both = _distance_to(clicked | part | between)
        around = (d_both > 0) & (d_both <= max(gap, 3.0)) & ~tidy
        if not between.any() or not around.any():
            continue
        if lab is None:
            lab = cv2.cvtColor(img, cv2.COLOR_RGB2LAB)
        shared = float(np.minimum(lab_histogram(lab, between), lab_histogram(lab, around)).sum())
        if shared < JOIN_MAX_SHARED:
            out |= part | between
    return out


def _click_recut(img: np.ndarray, clean: np.ndarray, pts: np.ndarray, labels: np.ndarray, iters: int,
                 max_side) -> np.ndarray:
    """The chosen click candidate cut once more, at full size, as a box prompt: its box (the cleaned
    clicked part's, grown by CLICK_RECUT_GROW) with the tightness prior and on the box's window
    (``_box_window``), so the background model learns what borders the object and not the far side of
    the photo. On the benchmark photos (docs/quality.md) this took the blurred clock's click from IoU
    0.74 to 0.86 and the cameraman's from 0.89 to 0.91, and cost the cell's 1.00 -> 0.99. A box whose
    window leaves less than CLICK_RECUT_MIN_RING of its area around it is not cut again (the candidate
    is returned): the astronaut's, her head and suit from the photo's left and top edge down to the
    bottom, learnt the background from a strip on the right only and took in the wall (0.89 -> 0.64)."""
    fg_pts = pts[labels == 1]
    H, W = img.shape[:2]
    x0, y0, x1, y1 = mask_box(clean)
    # every object click inside the box (a click GrabCut did not find is not on the mask)
    x0, y0 = min(x0, int(fg_pts[:, 0].min())), min(y0, int(fg_pts[:, 1].min()))
    x1, y1 = max(x1, int(fg_pts[:, 0].max()) + 1), max(y1, int(fg_pts[:, 1].max()) + 1)
    gx, gy = CLICK_RECUT_GROW * (x1 - x0) + 2, CLICK_RECUT_GROW * (y1 - y0) + 2
    box = [max(0, int(x0 - gx)), max(0, int(y0 - gy)), min(W, int(math.ceil(x1 + gx))), min(H, int(math.ceil(y1 + gy)))]
    # GrabCut learns the background from the box's window around it (``_box_window``). A box that nearly fills
    # the photo leaves it too little: under CLICK_RECUT_MIN_RING of the box's area, the candidate stands.
    window = _box_window(tuple(box), W, H) or (0, 0, W, H)
    ring = (window[2] - window[0]) * (window[3] - window[1]) / max(1, (box[2] - box[0]) * (box[3] - box[1])) - 1.0
    if ring < CLICK_RECUT_MIN_RING:
        return clean
    return grabcut(img, box=box, points=pts, point_labels=labels, iters=iters, max_side=max_side, _click="whole",
                   _tight=True, _window=True)


def _drop_clicked_background(fg: np.ndarray, fg_pts: np.ndarray, bg_pts: np.ndarray, radius: int) -> np.ndarray:
    """Remove the separate parts a background click lands on.

    GrabCut only makes the clicked disk background; when the clicked thing has the object's
    colours too (a second object inside the box), the rest of it stays. A part of the result
    that touches a background click's disk and holds no object click is what the click meant;
    it goes, unless nothing would be left. Without object clicks the part holding most of the
    result stays too: a background click next to the object (on a patch of wall GrabCut joined to
    it) must not take the object with it.
    """
    n, cc = cv2.connectedComponents(fg, connectivity=8)
    if n <= 1:
        return fg
    keep = {int(cc[int(y), int(x)]) for x, y in fg_pts} - {0}
    if not keep:
        sizes = np.bincount(cc.ravel(), minlength=n)
        sizes[0] = 0
        if sizes.max() * 2 > sizes.sum():
            keep = {int(np.argmax(sizes))}
    near = np.zeros_like(fg)
    for x, y in bg_pts:
        cv2.circle(near, (int(x), int(y)), int(radius) + 2, 1, -1)
    drop = sorted(set(np.unique(cc[near > 0]).tolist()) - {0} - keep)
    if not drop:
        return fg
    out = fg.copy()
    out[np.isin(cc, drop)] = 0
    return out if out.any() else fg


# ----------------------------------------------------------------------------------------------
# Background inpainting
# ----------------------------------------------------------------------------------------------


def default_dilate_px(height: int, width: int) -> int:
    """A few pixels at 600 px, scaling with resolution: 0.6% of the long side, at least 3."""
    return max(3, int(round(0.006 * max(height, width))))


def _exact_distance(m: np.ndarray) -> np.ndarray:
    # The squared distance between pixel centres is an integer: rounding it makes OpenCV's
    # precise transform reproducible to the bit (its float32 output can vary in the last bit).
    d = cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float64)
    return np.sqrt(np.rint(d * d))


def _inpaint_float(img: np.ndarray, hole: np.ndarray, radius: float, flags: int) -> np.ndarray:
    # OpenCV inpaints 3 channels only at 8 bits; 16-bit single channels keep the precision
    # (the float32 single-channel Telea path overshoots far outside 0..1).
    out = np.empty_like(img)
    hole_u8 = hole.astype(np.uint8)
    for c in range(img.shape[2]):
        ch = (np.clip(img[:, :, c], 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)
        out[:, :, c] = cv2.inpaint(ch, hole_u8, float(radius), flags).astype(np.float32) / 65535.0
    return out


def _grow_for_resampling(hole_small: np.ndarray) -> np.ndarray:
    # Bilinear/cubic resampling back to full size reads the neighbouring low-resolution pixels,
    # which therefore must be filled too, never hold object colours.
    return cv2.dilate(hole_small.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


def _resample_region(small: np.ndarray, full_shape: tuple[int, int], region: np.ndarray,
                     base: np.ndarray, interpolation: int) -> np.ndarray:
    """Upsample ``small`` onto the bounding box of ``region`` of a copy of ``base``."""
    H, W = full_shape
    h, w = small.shape[:2]
    x0, y0, x1, y1 = mask_box(region)
    pad = 2 + int(math.ceil(2.0 * W / w))
    x0, y0, x1, y1 = max(0, x0 - pad), max(0, y0 - pad), min(W, x1 + pad), min(H, y1 + pad)
    # A full-resolution pixel centre x sits at (x + 0.5) * w / W - 0.5 in the small image.
    xs = (np.arange(x0, x1, dtype=np.float32) + 0.5) * (w / W) - 0.5
    ys = (np.arange(y0, y1, dtype=np.float32) + 0.5) * (h / H) - 0.5
    mapx, mapy = np.meshgrid(xs, ys)
    patch = cv2.remap(small, mapx, mapy, interpolation, borderMode=cv2.BORDER_REPLICATE)
    out = base.copy()
    out[y0:y1, x0:x1] = np.clip(patch, 0.0, 1.0)
    return out


# A hole deeper than this (pixels from its edge to its middle) is first filled at a coarser scale
# where it is this deep: diffusion-style inpainting drifts and streaks across wide holes, and the
# coarse fill is smooth, fast and follows the surrounding colours. Only a band along the hole's
# edge is then inpainted at full detail, on top of the coarse fill.
COARSE_HOLE_DEPTH = 16.0


def _inpaint_multiscale(img: np.ndarray, hole: np.ndarray, radius: float, flags: int) -> np.ndarray:
    H, W = hole.shape
    dist = _exact_distance(hole)
    depth = float(dist.max())
    if depth <= COARSE_HOLE_DEPTH:
        return _inpaint_float(img, hole, radius, flags)
    scale = COARSE_HOLE_DEPTH / depth
    w, h = max(4, int(round(W * scale))), max(4, int(round(H * scale)))
    small = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    hole_s = _grow_for_resampling(cv2.resize(hole.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0)
    if hole_s.all():  # the coarse grid has no known pixel left: fill at full size instead
        return _inpaint_float(img, hole, radius, flags)
    coarse = _inpaint_float(small, hole_s, max(1.0, radius * scale * 2.0), flags)
    # Telea's fast marching leaves straight seams where fronts meet; a one-pixel blur at the
    # coarse scale hides them (only the hole's pixels are used).
    coarse = cv2.GaussianBlur(coarse, (0, 0), 1.0, borderType=cv2.BORDER_REPLICATE)
    prefilled = _resample_region(coarse, (H, W), hole, img, cv2.INTER_LINEAR)
    prefilled = np.where(hole[:, :, None], prefilled, img)
    band_px = max(4.0, 2.0 * float(radius))
    band = hole & (dist <= band_px)
    return _inpaint_float(prefilled, band, radius, flags)


def inpaint_background(image, mask, *, dilate_px: Optional[int] = None, radius: float = 5.0,
                       method: str = "harmonic", max_side: int = INPAINT_MAX_SIDE) -> torch.Tensor:
    """The image with the object's region (mask dilated by ``dilate_px``) filled from around it.

    Dilating first removes the object's halo (anti-aliased or shadowed edge pixels). Only pixels
    inside the dilated mask change; every other pixel is bit-identical to the input. ``method``:
    "harmonic" (default) or "patch" (``physmotion_core.inpaint.fill_hole``), or OpenCV's "telea"/"ns",
    whose wide holes are filled coarse-to-fine (see ``COARSE_HOLE_DEPTH``); images larger than ``max_side`` are
    inpainted at reduced size and only the filled region is upsampled, so a 4k photo costs about
    what a 1k photo does.
    """
    img = as_image_array(image)
    H, W = img.shape[:2]
    m = as_mask_array(mask, (H, W)) > 0.5
    if not m.any():
        raise InputError("Cannot inpaint the background: the mask is empty (no object pixels)")
    method = str(method).lower()
    flags = {"telea": cv2.INPAINT_TELEA, "ns": cv2.INPAINT_NS}.get(method)
    if flags is None and method not in ("harmonic", "patch"):
        raise InputError(f"inpaint method must be 'harmonic', 'patch', 'telea' or 'ns'; got {method!r}")

    def fill(im, ho):  # harmonic/patch: physmotion_core.inpaint (docs/quality.md, "Background fill")
        if flags is None:
            from ..inpaint import fill_hole

            return fill_hole(im, ho, method)
        return _inpaint_multiscale(im, ho, radius, flags)
    if dilate_px is None:
        dilate_px = default_dilate_px(H, W)
    dilate_px = int(dilate_px)
    if dilate_px < 0:
        raise InputError(f"dilate_px must be >= 0; got {dilate_px}")
    if not (0 < float(radius) <= 100):
        raise InputError(f"inpaint_radius must be in (0, 100] pixels; got {radius}")
    hole = m.astype(np.uint8)
    if dilate_px > 0:
        hole = cv2.dilate(hole, _ellipse(dilate_px))
    hole = hole > 0
    if hole.all():
        raise InputError("Cannot inpaint the background: the object mask (dilated by "
                         f"{dilate_px} px) covers the whole image, so there is nothing to fill "
                         "from. Use a tighter mask, or a smaller dilate_px.")
    small, scale = _resize_to_max_side(img, max_side)
    if scale >= 1.0:
        filled = fill(img, hole)
    else:
        h, w = small.shape[:2]
        hole_s = _grow_for_resampling(
            cv2.resize(hole.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0)
        if hole_s.all():
            raise InputError("Cannot inpaint the background: the object covers nearly the whole image")
        filled_s = fill(small, hole_s)
        filled = _resample_region(filled_s, (H, W), hole, img, cv2.INTER_LINEAR)
    out = np.where(hole[:, :, None], filled, img)
    return torch.from_numpy(np.ascontiguousarray(out.astype(np.float32)))


# ----------------------------------------------------------------------------------------------
# The entry point
# ----------------------------------------------------------------------------------------------


def _keep_clicked(m: np.ndarray, raw: np.ndarray, fg_pts: np.ndarray) -> np.ndarray:
    """Keep only the parts of ``m`` that hold an object click (all of ``m`` when none does).

    A clicked pixel that the clean-up removed (a thin part opened away, a speck dropped) gets its
    raw GrabCut component back, so a click-prompted mask holds its click whenever GrabCut found it.
    """
    if not len(fg_pts):
        return m
    m = m.copy()
    n, cc = cv2.connectedComponents(raw.astype(np.uint8), connectivity=8)
    for x, y in fg_pts:
        xi, yi = int(x), int(y)
        if not m[yi, xi] and cc[yi, xi] > 0:
            m |= cc == cc[yi, xi]
    n, cc = cv2.connectedComponents(m.astype(np.uint8), connectivity=8)
    ids = sorted({int(cc[int(y), int(x)]) for x, y in fg_pts} - {0})
    return np.isin(cc, ids) if ids else m


def segment(image, *, alpha=None, mask=None, box: Optional[Sequence[float]] = None,
            points=None, point_labels=None,
            method: str = "auto", grabcut_iters: int = 5, inpaint_radius: float = 5.0,
            dilate_px: Optional[int] = None, clean: Optional[bool] = None,
            inpaint_method: str = "harmonic", progress=None) -> Segmentation:
    """Cut the object out of ``image`` (H,W,3) and inpaint the background behind it.

    method:
      - "auto": the alpha channel if one is given and not fully opaque (threshold 0.5), else the
        given ``mask``, else GrabCut (seeded by ``box`` or by ``auto_box``).
      - "alpha" / "mask" / "grabcut": force one. GrabCut with a ``mask`` refines that mask.
    ``points`` (x, y) with ``point_labels`` (1 object, 0 background) and ``box`` prompt GrabCut
    (see ``grabcut``); after the clean-up only the parts holding an object click are kept. With an
    alpha or a mask the prompts change nothing here (``check.check_mask`` still tests them).
    ``clean`` runs ``clean_mask`` on the result (default: only for GrabCut, whose raw output has
    specks and holes; an alpha or a mask the user drew is taken as given). ``dilate_px``
    (default ``default_dilate_px``) grows the inpainted region past the object's edge so no halo
    of object colour remains in the background. ``progress(done, total)`` is called during GrabCut
    (before each of its iterations) and once at the end; it raises to cancel.
    """
    img = as_image_array(image)
    H, W = img.shape[:2]
    method = str(method).lower()
    if method not in METHODS:
        raise InputError(f"segmentation method must be one of {METHODS}; got {method!r}")
    alpha_arr = None
    if alpha is not None:
        alpha_arr = as_mask_array(alpha, (H, W), "alpha")
        if float(alpha_arr.min()) >= 1.0 - 0.5 / 255.0 and method == "auto":
            alpha_arr = None  # fully opaque: it says nothing about the object
    mask_arr = None if mask is None else as_mask_array(mask, (H, W), "mask")

    if method == "auto":
        method = "alpha" if alpha_arr is not None else ("mask" if mask_arr is not None else "grabcut")

    soft = None  # a soft (anti-aliased) matte: its faint edge must be inpainted away too
    if method == "alpha":
        if alpha_arr is None:
            raise InputError("method='alpha' needs an alpha channel: load an RGBA image or pass alpha=")
        m = alpha_arr > 0.5
        soft = alpha_arr
        what = "alpha channel"
    elif method == "mask":
        if mask_arr is None:
            raise InputError("method='mask' needs a mask: pass mask= (H, W) with the object at 1")
        m = mask_arr > 0.5
        soft = mask_arr
        what = "mask"
    else:
        m = grabcut(img, box=box, init_mask=mask_arr, points=points, point_labels=point_labels,
                    iters=grabcut_iters, progress=scaled(progress, 0, 95, 100))
        what = "GrabCut result"
    raw = m
    if clean if clean is not None else method == "grabcut":
        m = clean_mask(m).numpy() > 0.5
    if method == "grabcut" and points is not None:
        pts, labels = check_points(points, point_labels, width=W, height=H)
        m = _keep_clicked(m, raw, pts[labels == 1])
    if not m.any():
        fix = ("draw a box around the object or give a mask" if method == "grabcut"
               else "check that the object is marked with values above 0.5")
        raise InputError(f"The {what} is empty: no object pixels were found; {fix}")
    if m.all():
        raise InputError(f"The {what} covers the whole image, so there is no background to inpaint "
                         "from; the object must leave some of the image free")
    mf = m.astype(np.float32)
    # The inpainted region also covers a soft matte's faint edge (alpha below 0.5 but above 1/255),
    # which still holds the object's colour: otherwise its outline would stay in the background.
    hole = mf if soft is None else np.maximum(mf, (soft > 1.0 / 255.0).astype(np.float32))
    background = inpaint_background(img, hole, dilate_px=dilate_px, radius=inpaint_radius,
                                    method=inpaint_method)
    image_t = torch.from_numpy(img)
    mask_t = torch.from_numpy(mf)
    report(progress, 100, 100)
    return Segmentation(
        image=image_t,
        mask=mask_t,
        foreground=image_t * mask_t[:, :, None],
        background=background,
        box=mask_box(m),
        method=method,
    )
