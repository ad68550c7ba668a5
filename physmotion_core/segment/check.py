"""Is this mask plausibly one object? Cheap rules that catch the usual ways segmentation fails.

The model-free segmentation (GrabCut from an automatic box) can pick the wrong thing on a real
photo: the sky around a rocket, a cat's eyes and nose, a whole shelf. A wrong mask costs the user
a full simulation and render before they see it, so ``check_mask`` looks at the mask first and
lists what looks wrong, in plain sentences; ``enforce_plausible`` refuses an automatic mask that
fails (with the overlay file to look at and how to give a point, a box or a mask) and only warns
when the user prompted the segmentation (they asked for this object).

The thresholds were tuned on the benchmark photos (benchmarks/bench_segment.py, docs/quality.md).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from ..errors import InputError

log = logging.getLogger("physmotion")

# A mask touching this many frame edges is usually the background (or most of the scene).
MAX_EDGES = 3
# Above this share of the image a mask is rarely one object (a close-up may rightly cover 60%).
MAX_AREA_FRACTION = 0.8
# Below this share of the image the mask is a speck, not the object.
MIN_AREA_FRACTION = 0.003
# A disjoint part at least this share of the largest part counts as another sizeable piece ...
PART_FRACTION = 0.25
# ... and this many sizeable pieces means the mask is several things, not one object.
MAX_PARTS = 2
# Parts smaller than this share of the image are ignored when counting pieces.
MIN_PART_FRACTION = 0.01
# With the image: the median colour step (CIE Lab ΔE) across the outline below which the outline
# follows no visible edge (a cut through the sky, a halo's soft rim; a motion-blurred clock's rim
# measures 5.6) ...
MIN_EDGE_CONTRAST = 5.5
# ... and the colour-histogram overlap (Bhattacharyya coefficient) of the bands just inside and
# just outside the outline above which, together with a weak edge (median step under
# ``WEAK_EDGE_CONTRAST``), the mask cuts through one surface (a cat's face cut out of its fur).
MAX_BAND_OVERLAP = 0.85
WEAK_EDGE_CONTRAST = 10.0

EDGE_NAMES = ("top", "bottom", "left", "right")

CLI_HOW_TO_FIX = (
    "Tell it which object you mean: click on it with --object-point U,V (pixels, repeatable), "
    "mark what is not the object with --background-point U,V, draw a box with --box X0,Y0,X1,Y1, "
    "or give your own mask with --mask FILE (white = object).")
NODE_HOW_TO_FIX = (
    "Tell it which object you mean: in the Segment node set object_points (clicks on the object, "
    "e.g. \"120,80; 200,150\") and background_points, or a box \"x0,y0,x1,y1\" - the click picker "
    "on the image writes them for you - or connect a MASK from any node (a SAM node, a painted "
    "mask, a loaded alpha).")


def retry_hint(*, points: bool, box: bool, model: bool = False, node: bool = False) -> str:
    """What to change when a prompted mask fails the checks, for the prompt the user gave: clicks alone,
    or a box (with or without clicks). Empty for a given mask (the user drew it: the warnings say what
    looks wrong and that is all). ``model``: the mask came from SAM, not GrabCut."""
    if box:
        if node:
            return ("If the outline is not the object you mean: move the box's sides to just around the object, "
                    "add object_points on parts it missed and background_points on what it took wrongly, or "
                    "connect a MASK from another node.")
        return ("If the outline is not the object you mean: move the --box sides to just around the object, add "
                "--object-point U,V on parts it missed and --background-point U,V on what it took wrongly, or "
                "give --mask FILE.")
    if points:
        why = ("" if model else " Without a segmentation model one click can take too little or too much of "
               "the photo; a box is the surer prompt (docs/quality.md).")
        if node:
            return ("If the outline is not the object you mean: drag a box around the whole object in the node "
                    "(the box and your clicks are used together)." + why + " Or connect a MASK from another node.")
        return ("If the outline is not the object you mean: draw a box around the whole object with --box "
                "X0,Y0,X1,Y1 (with or without the clicks)." + why + " Or give --mask FILE.")
    return ""


#: What the caption over an automatic pick's overlay says to do, on the command line and in ComfyUI.
CLI_PROMPT_TIP = "not your object? give --object-point U,V on it, or --box X0,Y0,X1,Y1 around it"
NODE_PROMPT_TIP = "not your object? click on it, or drag a box around it, on the picture in this node"


def box_past_photo(box, width: int, height: int, slack: float = 2.0):
    """A note for a box that reaches past the photo by more than ``slack`` pixels (it is cut to the photo and
    used): often a box drawn on another, larger photo (a template's, kept after loading your own). None when
    the box lies within the photo or there is no box."""
    if box is None:
        return None
    x0, y0, x1, y1 = (float(c) for c in box)
    over = [f"{side} by {d:g} px" for side, d in (("left", -x0), ("top", -y0), ("right", x1 - width),
                                                   ("bottom", y1 - height)) if d > slack]
    if not over:
        return None
    return (f"note: the box ({x0:g}, {y0:g}, {x1:g}, {y1:g}) reaches past the {width}x{height} photo ("
            f"{', '.join(over)}) and was cut to it: was it drawn on another photo?")


def overlay_caption(report: "MaskReport", *, prompted: bool, tip: str) -> list[str]:
    """The lines written over the overlay (``overlay.with_caption``): what the checks found wrong, and for
    an automatic pick, that it was one and how to say which object is meant."""
    lines = [f"check: {p}" for p in report.problems[:2]]
    if not prompted:
        lines.append(f"Picked automatically (no point, box or mask): {tip}")
    return lines


@dataclass
class MaskReport:
    """What ``check_mask`` found. ``problems`` empty means the mask looks like one object."""

    area_fraction: float  # mask pixels / image pixels
    components: int  # number of sizeable disjoint parts
    edges: tuple[str, ...]  # frame edges the mask touches, of ("top", "bottom", "left", "right")
    box: tuple[int, int, int, int]  # x0, y0, x1, y1 (exclusive); (0, 0, 0, 0) for an empty mask
    height_px: int
    problems: list[str] = field(default_factory=list)
    missed_points: list[tuple[float, float]] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary_lines(self) -> list[str]:
        x0, y0, x1, y1 = self.box
        lines = [f"mask: {100.0 * self.area_fraction:.1f}% of the image, {self.components} part"
                 f"{'' if self.components == 1 else 's'}, box x {x0}..{x1}, y {y0}..{y1} "
                 f"({self.height_px} px tall)",
                 "touches the frame: " + (", ".join(self.edges) if self.edges else "no edge")]
        lines += [f"problem: {p}" for p in self.problems]
        if not self.problems:
            lines.append("looks plausible")
        return lines


def _as_bool_mask(mask) -> np.ndarray:
    m = mask.detach().cpu().numpy() if isinstance(mask, torch.Tensor) else np.asarray(mask)
    if m.ndim == 3 and m.shape[0] == 1:
        m = m[0]
    elif m.ndim == 3 and m.shape[2] == 1:
        m = m[:, :, 0]
    if m.ndim != 2 or m.shape[0] < 2 or m.shape[1] < 2:
        raise InputError(f"check_mask: the mask must have shape (H, W); got {tuple(m.shape)}")
    if m.dtype == np.bool_:
        return m
    m = m.astype(np.float32)
    if not np.isfinite(m).all():
        raise InputError("check_mask: the mask contains NaN or Inf values")
    return m > (127.5 if m.max() > 1.0 else 0.5)


def _points(points, name: str, w: int, h: int) -> list[tuple[float, float]]:
    out = []
    for p in points if points is not None else ():
        try:
            x, y = (float(v) for v in p)
        except (TypeError, ValueError) as exc:
            raise InputError(f"{name}: each point must be (x, y) in pixels; got {p!r}") from exc
        if not (np.isfinite(x) and np.isfinite(y)):
            raise InputError(f"{name}: point ({x}, {y}) is not finite; give pixel coordinates")
        if not (0 <= x < w and 0 <= y < h):
            raise InputError(f"{name}: point ({x:g}, {y:g}) lies outside the {w}x{h} image")
        out.append((x, y))
    return out


def _inside(m: np.ndarray, x: float, y: float, slack: int) -> bool:
    h, w = m.shape
    xi, yi = int(x), int(y)
    return bool(m[max(0, yi - slack):min(h, yi + slack + 1), max(0, xi - slack):min(w, xi + slack + 1)].any())


def _outline_measures(image, m: np.ndarray) -> tuple[float, float]:
    """(median Lab colour step across the outline, histogram overlap of the inner/outer bands).

    The step compares, at each outline pixel (not along the frame, where there is no outside),
    the local mean colour of a band just inside the mask with that of a band just outside (bands
    1.5% of the short side wide, means weighted by a Gaussian of twice that). The overlap is the
    Bhattacharyya coefficient of 8x8x8-bin Lab histograms of 5%-wide bands. Runs at 512 px at most.
    """
    from .classic import as_image_array

    img = as_image_array(image)
    h, w = m.shape
    if img.shape[:2] != (h, w):
        raise InputError(f"check_mask: the image is {img.shape[1]}x{img.shape[0]} but the mask is {w}x{h}")
    s = min(1.0, 512.0 / max(h, w))
    mu = m.astype(np.uint8)
    if s < 1.0:
        size = (max(2, int(round(w * s))), max(2, int(round(h * s))))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        mu = cv2.resize(mu, size, interpolation=cv2.INTER_NEAREST)
    lab = cv2.cvtColor(img, cv2.COLOR_RGB2LAB)

    def bands(frac):
        r = max(2, int(round(frac * min(mu.shape))))
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        return (mu - cv2.erode(mu, k)).astype(np.float32), (cv2.dilate(mu, k) - mu).astype(np.float32), r

    inb, outb, r = bands(0.015)

    def local_mean(band):
        wsum = cv2.GaussianBlur(band, (0, 0), 2.0 * r)
        return cv2.GaussianBlur(lab * band[:, :, None], (0, 0), 2.0 * r) / np.maximum(wsum, 1e-6)[:, :, None], wsum

    a, wa = local_mean(inb)
    b, wb = local_mean(outb)
    outline = mu - cv2.erode(mu, np.ones((3, 3), np.uint8))
    outline[0, :] = outline[-1, :] = 0
    outline[:, 0] = outline[:, -1] = 0
    sel = (outline > 0) & (wa > 1e-3) & (wb > 1e-3)
    step = float(np.median(np.linalg.norm(a[sel] - b[sel], axis=1))) if sel.sum() >= 10 else float("nan")
    inb, outb, _ = bands(0.05)
    return step, colour_overlap(lab, inb > 0, outb > 0)


def lab_histogram(lab: np.ndarray, sel: np.ndarray, bins: int = 8) -> np.ndarray:
    """The colours of a region: the normalised ``bins``^3-bin histogram of ``lab`` (float CIE Lab,
    (H, W, 3), as OpenCV gives for a float RGB image in 0..1) over ``sel`` (bool (H, W)); all zeros
    when the region is empty."""
    q = np.stack([lab[:, :, 0] / 100.0, (lab[:, :, 1] + 128.0) / 256.0, (lab[:, :, 2] + 128.0) / 256.0], -1)
    q = np.clip((q * bins).astype(np.int64), 0, bins - 1)
    idx = (q[:, :, 0] * bins + q[:, :, 1]) * bins + q[:, :, 2]
    h = np.bincount(idx[sel], minlength=bins ** 3).astype(np.float64)
    return h / h.sum() if h.sum() > 0 else h


def colour_overlap(lab: np.ndarray, a: np.ndarray, b: np.ndarray, bins: int = 8) -> float:
    """How alike the colours of two regions (bool (H, W)) are: the Bhattacharyya coefficient (0 none
    alike, 1 the same) of their ``lab_histogram``s. NaN when a region is empty."""
    ha, hb = lab_histogram(lab, a, bins), lab_histogram(lab, b, bins)
    if ha.sum() == 0 or hb.sum() == 0:
        return float("nan")
    return float(np.sqrt(ha * hb).sum())


def check_mask(mask, *, object_points=(), background_points=(), force_points=(), image=None) -> MaskReport:
    """Measure a binary object mask (H, W) and list what makes it implausible as one object.

    Rules: empty or a speck (under ``MIN_AREA_FRACTION``); over ``MAX_AREA_FRACTION`` of the
    image; touching ``MAX_EDGES`` or more frame edges; ``MAX_PARTS`` or more sizeable disjoint
    parts; an object point or a force point outside the mask; a background point inside it.
    With ``image`` (the photo, (H, W, 3)) also: an outline that follows no visible edge
    (``MIN_EDGE_CONTRAST``), or one that cuts through a single surface (the same colours just
    inside and just outside, ``MAX_BAND_OVERLAP``, with a weak edge). Pass the image whenever
    you have it: on the benchmark photos these two rules catch the wrong automatic masks that
    the geometric rules miss (the sky around a rocket, a cat's face cut out of its fur, a cell
    with its halo). A point counts as inside when the mask is within 1% of the short side of it (a click on the
    outline is on the object). Points are (x, y) pixels.
    """
    m = _as_bool_mask(mask)
    h, w = m.shape
    obj = _points(object_points, "object_points", w, h)
    bgp = _points(background_points, "background_points", w, h)
    frc = _points(force_points, "force_points", w, h)
    area = float(m.mean())
    problems: list[str] = []
    if not m.any():
        problems.append("The mask is empty: nothing was found as the object.")
        return MaskReport(0.0, 0, (), (0, 0, 0, 0), 0, problems, obj + frc)
    ys, xs = np.nonzero(m)
    box = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
    edges = tuple(name for name, touched in zip(EDGE_NAMES, (m[0].any(), m[-1].any(), m[:, 0].any(), m[:, -1].any()))
                  if touched)
    n, _, stats, _ = cv2.connectedComponentsWithStats(m.astype(np.uint8), connectivity=8)
    areas = np.sort(stats[1:, cv2.CC_STAT_AREA])[::-1]
    parts = int(((areas >= PART_FRACTION * areas[0]) & (areas >= MIN_PART_FRACTION * h * w)).sum()) or 1

    if area < MIN_AREA_FRACTION:
        problems.append(f"The mask is tiny ({100 * area:.2f}% of the image): probably a speck, not the object.")
    if area > MAX_AREA_FRACTION:
        problems.append(f"The mask covers {100 * area:.0f}% of the image: that is most of the scene, "
                        "rarely one object.")
    if len(edges) >= MAX_EDGES:
        problems.append(f"The mask touches {len(edges)} edges of the frame ({', '.join(edges)}): it "
                        "probably holds background, not just the object.")
    if parts >= MAX_PARTS:
        problems.append(f"The mask is {parts} large separate pieces: probably several things, "
                        "not one object.")
    if image is not None and 0 < area < 1:
        step, overlap = _outline_measures(image, m)
        if step < MIN_EDGE_CONTRAST:
            problems.append(f"The mask's outline follows no visible edge in the photo (colour step "
                            f"{step:.1f} across it): it probably cuts through the background or "
                            "the object.")
        elif overlap > MAX_BAND_OVERLAP and step < WEAK_EDGE_CONTRAST:
            problems.append("The colours just inside the mask's outline are the same as just outside "
                            f"it ({100 * overlap:.0f}% alike): it probably cuts one surface in two "
                            "(part of the object, or object and background together).")
    slack = max(1, int(round(0.01 * min(h, w))))
    missed = []
    for x, y in obj:
        if not _inside(m, x, y, slack):
            missed.append((x, y))
            problems.append(f"The object point ({x:g}, {y:g}) is not on the mask.")
    for x, y in frc:
        if not _inside(m, x, y, slack):
            missed.append((x, y))
            problems.append(f"The force point ({x:g}, {y:g}) is not on the object: the mask is at "
                            f"x {box[0]}..{box[2]}, y {box[1]}..{box[3]}; move the push onto it.")
    for x, y in bgp:
        if m[int(y), int(x)]:
            problems.append(f"The background point ({x:g}, {y:g}) is inside the mask.")
    return MaskReport(area, parts, edges, box, box[3] - box[1], problems, missed)


def enforce_plausible(report: MaskReport, *, prompted: bool, overlay=None,
                      how_to_fix: str = CLI_HOW_TO_FIX, hint: str = "") -> None:
    """Refuse an implausible automatic mask; only warn about a prompted one.

    ``prompted``: the user gave points, a box or a mask, so the mask is what they asked for; the
    problems are logged as warnings (logger "physmotion") and the run goes on. Otherwise the
    problems raise InputError naming the overlay image (``overlay``: a path, if one was written)
    and ``how_to_fix`` (``CLI_HOW_TO_FIX`` or ``NODE_HOW_TO_FIX``). ``hint`` (``retry_hint``), for a
    prompted mask: what to change, logged after the problems with the overlay to look at.
    """
    if report.ok:
        return
    if prompted:
        for p in report.problems:
            log.warning("segmentation: %s", p)
        if hint:
            where = f"Look at {overlay}. " if overlay is not None else ""
            log.warning("segmentation: %s%s", where, hint)
        return
    lines = ["The automatic segmentation does not look like one object:"]
    lines += [f"  - {p}" for p in report.problems]
    if overlay is not None:
        lines.append(f"Look at {overlay} (left: the mask's outline on the photo; right: the filled background).")
    lines.append(how_to_fix)
    raise InputError("\n".join(lines))
