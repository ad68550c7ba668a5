"""SAM segmentation: the official checkpoints through the ``segment-anything`` package.

The architecture (vit_b / vit_l / vit_h, or any other size) is read from the checkpoint's own
tensor shapes, so the user never has to say which file is which and a renamed file still loads:

* image encoder width, depth, MLP ratio and input size from ``patch_embed``, ``blocks.*`` and
  ``pos_embed``; head size from the relative-position tables (``rel_pos_h`` is
  ``[2·window − 1, head_dim]`` in windowed blocks and ``[2·(img/16) − 1, head_dim]`` in the
  global-attention ones, which also tells which blocks are global);
* prompt/mask-decoder widths from the neck, ``mask_downscaling`` and the IoU head.
The two-way transformer's head count (8) is the only constant that shapes cannot tell.

Prompts: per object, any number of positive/negative points and at most one box. SAM returns three
candidate masks per prompt; the one with the highest predicted IoU is kept (for a single point
SAM's own paper recommends exactly this). The automatic mode (no prompt) scores candidates from a
grid of point prompts and a saliency box, and keeps the most salient object (see
``salience_scores``).
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from ..errors import InputError, MissingModelError
from ..models import check_state_dict, describe_folder, load_state_dict_file, pick_device, resolve_weight_file
from .classic import Segmentation, as_image_array, auto_box, clean_mask, segment

log = logging.getLogger(__name__)

OFFICIAL_FILES = {"vit_h": "sam_vit_h_4b8939.pth", "vit_l": "sam_vit_l_0b3195.pth", "vit_b": "sam_vit_b_01ec64.pth"}
_VARIANT_BY_WIDTH = {768: "vit_b", 1024: "vit_l", 1280: "vit_h"}
DECODER_HEADS = 8


@dataclass
class SamModel:
    """A loaded SAM network with what the nodes show about it."""

    model: torch.nn.Module
    variant: str  # vit_b / vit_l / vit_h / custom
    path: Optional[Path] = None
    info: dict = field(default_factory=dict)

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    def to(self, device) -> "SamModel":
        self.model.to(device)
        return self


def _count(prefix_re: str, keys) -> int:
    idx = {int(m.group(1)) for k in keys for m in [re.match(prefix_re, k)] if m}
    return max(idx) + 1 if idx else 0


def sam_architecture(state: dict) -> dict:
    """The constructor arguments of the network that ``state`` belongs to (see the module doc)."""
    need = ["image_encoder.patch_embed.proj.weight", "image_encoder.pos_embed", "image_encoder.neck.0.weight",
            "prompt_encoder.mask_downscaling.0.weight", "mask_decoder.iou_prediction_head.layers.0.weight",
            "mask_decoder.transformer.layers.0.mlp.lin1.weight"]
    missing = [k for k in need if k not in state]
    if missing:
        raise InputError(f"This is not a SAM checkpoint: it lacks {', '.join(missing[:3])}. Put an official "
                         f"segment-anything .pth ({', '.join(OFFICIAL_FILES.values())}) in the sams folder.")
    keys = list(state)
    pw = state["image_encoder.patch_embed.proj.weight"]
    dim, _, patch, _ = pw.shape
    grid = state["image_encoder.pos_embed"].shape[1]
    depth = _count(r"image_encoder\.blocks\.(\d+)\.", keys)
    head_dim = state["image_encoder.blocks.0.attn.rel_pos_h"].shape[1]
    global_idx, window = [], 0
    for i in range(depth):
        span = state[f"image_encoder.blocks.{i}.attn.rel_pos_h"].shape[0]
        if span == 2 * grid - 1:
            global_idx.append(i)
        else:
            window = (span + 1) // 2
    prompt_dim = state["image_encoder.neck.0.weight"].shape[0]
    return {
        "embed_dim": int(dim), "depth": depth, "num_heads": int(dim // head_dim), "patch_size": int(patch),
        "img_size": int(grid * patch), "mlp_ratio": state["image_encoder.blocks.0.mlp.lin1.weight"].shape[0] / dim,
        "global_attn_indexes": tuple(global_idx), "window_size": window, "prompt_dim": int(prompt_dim),
        "mask_in_chans": int(state["prompt_encoder.mask_downscaling.3.weight"].shape[0]),
        "decoder_depth": _count(r"mask_decoder\.transformer\.layers\.(\d+)\.", keys),
        "decoder_mlp_dim": int(state["mask_decoder.transformer.layers.0.mlp.lin1.weight"].shape[0]),
        "iou_hidden": int(state["mask_decoder.iou_prediction_head.layers.0.weight"].shape[0]),
        "iou_depth": _count(r"mask_decoder\.iou_prediction_head\.layers\.(\d+)\.", keys),
        "num_multimask_outputs": int(state["mask_decoder.mask_tokens.weight"].shape[0]) - 1,
    }


def build_sam(arch: dict) -> torch.nn.Module:
    """The segment-anything network for ``arch`` (as returned by ``sam_architecture``)."""
    from segment_anything.modeling import ImageEncoderViT, MaskDecoder, PromptEncoder, Sam, TwoWayTransformer

    emb = arch["img_size"] // arch["patch_size"]
    return Sam(
        image_encoder=ImageEncoderViT(
            depth=arch["depth"], embed_dim=arch["embed_dim"], img_size=arch["img_size"],
            mlp_ratio=arch["mlp_ratio"], norm_layer=partial(torch.nn.LayerNorm, eps=1e-6),
            num_heads=arch["num_heads"], patch_size=arch["patch_size"], qkv_bias=True, use_rel_pos=True,
            global_attn_indexes=arch["global_attn_indexes"], window_size=arch["window_size"],
            out_chans=arch["prompt_dim"]),
        prompt_encoder=PromptEncoder(
            embed_dim=arch["prompt_dim"], image_embedding_size=(emb, emb),
            input_image_size=(arch["img_size"], arch["img_size"]), mask_in_chans=arch["mask_in_chans"]),
        mask_decoder=MaskDecoder(
            num_multimask_outputs=arch["num_multimask_outputs"],
            transformer=TwoWayTransformer(depth=arch["decoder_depth"], embedding_dim=arch["prompt_dim"],
                                          mlp_dim=arch["decoder_mlp_dim"], num_heads=DECODER_HEADS),
            transformer_dim=arch["prompt_dim"], iou_head_depth=arch["iou_depth"],
            iou_head_hidden_dim=arch["iou_hidden"]),
        pixel_mean=[123.675, 116.28, 103.53],
        pixel_std=[58.395, 57.12, 57.375],
    )


def load_sam(name: Optional[str] = None, *, device=None, root=None) -> SamModel:
    """Load a SAM checkpoint (``weights_only=True``) from the ``sams`` folder or an absolute path."""
    expected = "an official segment-anything checkpoint (" + ", ".join(OFFICIAL_FILES.values()) + ")"
    path = resolve_weight_file("sams", name, expected=expected, root=root, suffixes=(".pth", ".pt", ".safetensors"))
    state = load_state_dict_file(path)
    try:
        arch = sam_architecture(state)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    except (KeyError, IndexError, ValueError, TypeError, AttributeError, ZeroDivisionError) as exc:
        # A tensor SAM's layout is read from has another rank or size (a damaged or modified file).
        raise InputError(f"{path} is not a SAM checkpoint this can read: a tensor that gives the network's layout has "
                         f"an unexpected shape ({type(exc).__name__}: {exc}). Use an unmodified official checkpoint "
                         f"({', '.join(OFFICIAL_FILES.values())}).") from None
    try:
        with torch.device("meta"):
            model = build_sam(arch)
    except Exception as exc:  # noqa: BLE001 - e.g. a head count that does not divide the width
        raise InputError(f"{path} describes a SAM network that cannot be built ({exc}); use an unmodified official "
                         "checkpoint.") from None
    reference = model.state_dict()
    check_state_dict(state, {k: tuple(v.shape) for k, v in reference.items()},
                     f"SAM (layout read from the file: width {arch['embed_dim']}, depth {arch['depth']})", path,
                     float_keys=[k for k, v in reference.items() if v.is_floating_point()])
    model = build_sam(arch)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[0:3]
        raise InputError(f"{path} does not load into the SAM network its shapes describe ({' '.join(first)}). "
                         "Use an unmodified official checkpoint.") from exc
    model.eval().to(pick_device(device))
    variant = _VARIANT_BY_WIDTH.get(arch["embed_dim"]) if arch["depth"] in (12, 24, 32) else None
    variant = variant or f"custom (width {arch['embed_dim']}, depth {arch['depth']})"
    log.info("SAM %s loaded from %s", variant, path)
    return SamModel(model=model, variant=variant, path=Path(path), info=arch)


# ----------------------------------------------------------------------------------------------
# Prompts
# ----------------------------------------------------------------------------------------------


@dataclass
class ObjectPrompt:
    """The prompt for one object: points (x, y) in pixels with labels (1 object, 0 not) and a box."""

    points: list = field(default_factory=list)  # [(x, y)]
    labels: list = field(default_factory=list)  # [1 | 0]
    box: Optional[tuple] = None  # (x0, y0, x1, y1)


def _numbers(text: str, what: str) -> list[list[float]]:
    items = [s.strip() for s in re.split(r"[;\n]", text or "") if s.strip()]
    out = []
    for s in items:
        try:
            vals = [float(v) for v in re.split(r"[,\s]+", s.strip("()[] ")) if v]
        except ValueError:
            raise InputError(f"Could not read {what} entry {s!r}: write numbers separated by commas, "
                             "entries separated by ';' or new lines") from None
        if not all(math.isfinite(v) for v in vals):
            raise InputError(f"{what} entry {s!r} has a non-finite number")
        out.append(vals)
    return out


def parse_prompts(points: str = "", boxes: str = "", *, width: int, height: int,
                  fraction: bool = False) -> list[ObjectPrompt]:
    """Turn the Segment node's text fields into one ``ObjectPrompt`` per object.

    ``points``: entries ``x, y`` (object point), ``x, y, 0`` (background point) or ``x, y, label, k``
    (point of object number k, counted from 0). ``boxes``: entries ``x0, y0, x1, y1``, one object
    each. Grouping without k: each box is an object; an object point inside a box belongs to that
    box's object, one outside every box starts an object of its own; background points apply to
    every object. With ``fraction`` the coordinates are fractions of the width/height.
    """
    sx, sy = (width, height) if fraction else (1.0, 1.0)
    objs: list[ObjectPrompt] = []
    for vals in _numbers(boxes, "box"):
        if len(vals) != 4:
            raise InputError(f"A box needs 4 numbers x0, y0, x1, y1; got {vals}")
        x0, y0, x1, y1 = vals[0] * sx, vals[1] * sy, vals[2] * sx, vals[3] * sy
        x0, x1 = sorted((x0, x1))
        y0, y1 = sorted((y0, y1))
        if x1 - x0 < 1 or y1 - y0 < 1:
            raise InputError(f"The box {vals} is empty: x1 must exceed x0 and y1 exceed y0")
        objs.append(ObjectPrompt(box=(x0, y0, x1, y1)))
    negatives, explicit = [], {}
    for vals in _numbers(points, "point"):
        if len(vals) not in (2, 3, 4):
            raise InputError(f"A point is 'x, y', 'x, y, label' or 'x, y, label, object'; got {vals}")
        x, y = vals[0] * sx, vals[1] * sy
        label = int(vals[2]) if len(vals) >= 3 else 1
        if label not in (0, 1):
            raise InputError(f"A point's label is 1 (object) or 0 (background); got {vals[2]}")
        if not (-0.5 <= x <= width + 0.5 and -0.5 <= y <= height + 0.5):
            unit = "fractions (0..1)" if fraction else f"pixels (0..{width} x 0..{height})"
            raise InputError(f"The point ({vals[0]}, {vals[1]}) lies outside the image; coordinates are {unit}")
        if len(vals) == 4:
            k = int(vals[3])
            if k < 0:
                raise InputError(f"Object numbers count from 0; got {k}")
            explicit.setdefault(k, []).append((x, y, label))
        elif label == 0:
            negatives.append((x, y))
        else:
            home = next((o for o in objs if o.box and o.box[0] <= x <= o.box[2] and o.box[1] <= y <= o.box[3]), None)
            if home is None:
                home = ObjectPrompt()
                objs.append(home)
            home.points.append((x, y))
            home.labels.append(1)
    for k in sorted(explicit):
        while len(objs) <= k:
            objs.append(ObjectPrompt())
        for x, y, label in explicit[k]:
            objs[k].points.append((x, y))
            objs[k].labels.append(label)
    if negatives and not objs:
        raise InputError("Only background points were given (label 0): add an object point or a box")
    for o in objs:
        for x, y in negatives:
            o.points.append((x, y))
            o.labels.append(0)
    for i, o in enumerate(objs):
        if o.box is None and 1 not in o.labels:
            raise InputError(f"Object {i} has only background points: give it an object point or a box")
    return objs


# ----------------------------------------------------------------------------------------------
# Choosing among candidates
# ----------------------------------------------------------------------------------------------


def best_by_iou(masks: torch.Tensor, iou: torch.Tensor) -> tuple[torch.Tensor, float, int]:
    """The candidate with the highest predicted IoU (first on ties): (mask, iou, index)."""
    i = int(torch.argmax(iou).item())
    return masks[i], float(iou[i]), i


def stability(logits: torch.Tensor, threshold: float = 0.0, offset: float = 1.0) -> torch.Tensor:
    """IoU between the masks at logit thresholds t+offset and t−offset (SAM's stability score)."""
    hi = (logits > threshold + offset).flatten(-2).sum(-1).float()
    lo = (logits > threshold - offset).flatten(-2).sum(-1).float()
    return torch.where(lo > 0, hi / lo.clamp(min=1), torch.zeros_like(lo))


def salience_scores(masks: torch.Tensor, iou: torch.Tensor, stab: torch.Tensor, *,
                    min_area: float = 0.005, max_area: float = 0.8, centre_sigma: float = 0.35) -> torch.Tensor:
    """Score candidate masks (K,H,W bool) as "the object of the photo"; 0 for rejected ones.

    score = predicted IoU × stability × centre weight × border penalty, where the centre weight is
    exp(−d²/2σ²) for the centroid's distance d from the image centre (in half-diagonals), and the
    border penalty is 1 − the fraction of the image border the mask covers (a mask that hugs the
    frame is background, sky, a table). Masks below ``min_area`` or above ``max_area`` of the image
    are rejected.
    """
    K, H, W = masks.shape
    m = masks.float()
    area = m.flatten(1).mean(1)
    ys = torch.linspace(-1, 1, H).view(1, H, 1)
    xs = torch.linspace(-1, 1, W).view(1, 1, W)
    denom = m.flatten(1).sum(1).clamp(min=1)
    cy = (m * ys).flatten(1).sum(1) / denom
    cx = (m * xs).flatten(1).sum(1) / denom
    d2 = (cx ** 2 + cy ** 2) / 2.0
    centre = torch.exp(-d2 / (2 * centre_sigma ** 2))
    border = torch.cat([m[:, 0, :], m[:, -1, :], m[:, :, 0], m[:, :, -1]], dim=1).mean(1)
    score = iou.float().clamp(min=0) * stab.float() * centre * (1 - border)
    ok = (area >= min_area) & (area <= max_area)
    return torch.where(ok, score, torch.zeros_like(score))


# ----------------------------------------------------------------------------------------------
# Segmenting
# ----------------------------------------------------------------------------------------------


@dataclass
class SamResult:
    """Per-object masks (K,H,W float {0,1}) with their predicted IoU, plus the usual Segmentation
    of the union (foreground and the background with every object inpainted away)."""

    masks: torch.Tensor
    scores: list
    segmentation: Segmentation
    prompts: list


def _predictor(sam: SamModel, img_u8: np.ndarray):
    from segment_anything import SamPredictor

    pred = SamPredictor(sam.model)
    with torch.no_grad():
        pred.set_image(img_u8, image_format="RGB")
    return pred


def _predict(pred, prompt: ObjectPrompt, multimask: bool):
    pc = np.asarray(prompt.points, np.float32) if prompt.points else None
    pl = np.asarray(prompt.labels, np.int64) if prompt.points else None
    box = np.asarray(prompt.box, np.float32) if prompt.box is not None else None
    with torch.no_grad():
        masks, iou, low = pred.predict(point_coords=pc, point_labels=pl, box=box, multimask_output=multimask,
                                       return_logits=True)
    return torch.from_numpy(masks), torch.from_numpy(iou)


def _automatic(pred, img: np.ndarray, grid: int) -> tuple[torch.Tensor, float]:
    """The most salient object: candidates from a grid of point prompts and the saliency box.

    Candidates are scored on SAM's low-resolution logits (cropped to the image's part of the padded
    square input), so a 64-point grid costs a few MB; only the winner is decoded at full size.
    """
    H, W = img.shape[:2]
    xs = (np.arange(grid) + 0.5) / grid * W
    ys = (np.arange(grid) + 0.5) / grid * H
    pts = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2).astype(np.float32)
    dev = pred.device
    rh, rw = pred.input_size  # the resized image inside the padded square
    side = pred.model.image_encoder.img_size
    prompts: list[ObjectPrompt] = [ObjectPrompt(points=[tuple(p)], labels=[1]) for p in pts]
    prompts.append(ObjectPrompt(box=tuple(float(v) for v in auto_box(img))))
    lows, ious = [], []
    with torch.no_grad():
        coords = pred.transform.apply_coords(pts, (H, W))
        for s in range(0, len(coords), 64):
            c = torch.as_tensor(coords[s:s + 64], device=dev)[:, None, :]
            lab = torch.ones(c.shape[0], 1, dtype=torch.int64, device=dev)
            _, iou, low = pred.predict_torch(c, lab, multimask_output=True, return_logits=True)
            lows.append(low.cpu())
            ious.append(iou.cpu())
        box = torch.as_tensor(pred.transform.apply_boxes(np.asarray(prompts[-1].box, np.float32), (H, W)),
                              device=dev)
        _, iou, low = pred.predict_torch(None, None, box, multimask_output=True, return_logits=True)
        lows.append(low.cpu())
        ious.append(iou.cpu())
    low = torch.cat(lows)  # (P, 3, 256, 256)
    iou = torch.cat(ious)  # (P, 3)
    n_out = low.shape[1]
    lh = max(1, int(round(low.shape[-2] * rh / side)))
    lw = max(1, int(round(low.shape[-1] * rw / side)))
    low = low[..., :lh, :lw].flatten(0, 1)
    scores = salience_scores(low > 0, iou.flatten(), stability(low))
    best = int(torch.argmax(scores))
    if float(scores[best]) <= 0:
        raise InputError("Automatic segmentation found no object-sized region away from the image border; "
                         "give a point on the object or a box")
    logits, full_iou = _predict(pred, prompts[best // n_out], True)
    k = best % n_out
    return logits[k] > 0, float(full_iou[k])


def sam_segment(sam: SamModel, image, prompts: Sequence[ObjectPrompt] = (), *, multimask: bool = True,
                clean: bool = True, grid: int = 8, inpaint_radius: float = 5.0) -> SamResult:
    """Masks of the prompted objects (or of the most salient one when ``prompts`` is empty).

    The image encoder runs once; each object's prompt goes through the decoder and the candidate
    with the highest predicted IoU is kept. ``clean`` fills small holes and drops specks
    (``clean_mask``). The background has every object inpainted away.
    """
    img = as_image_array(image)
    H, W = img.shape[:2]
    u8 = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
    pred = _predictor(sam, u8)
    masks, scores = [], []
    if not prompts:
        m, s = _automatic(pred, img, int(grid))
        masks.append(m)
        scores.append(s)
    for i, p in enumerate(prompts):
        logits, iou = _predict(pred, p, multimask)
        m, s, _ = best_by_iou(logits > 0, iou)
        if not bool(m.any()):
            raise InputError(f"SAM found nothing for object {i}'s prompt; move the point onto the object "
                             "or draw a box around it")
        masks.append(m)
        scores.append(s)
    out = []
    for m in masks:
        m = m.cpu().numpy()
        if clean:
            m = clean_mask(m).numpy() > 0.5
        out.append(torch.from_numpy(m.astype(np.float32)))
    stack = torch.stack(out)
    union = stack.amax(0)
    seg = segment(img, mask=union, method="mask", inpaint_radius=inpaint_radius)
    return SamResult(masks=stack, scores=scores, segmentation=seg, prompts=list(prompts))


def sams_folder_error(root=None) -> MissingModelError:
    from ..models import model_dir

    folder = model_dir("sams", root)
    return MissingModelError(f"No SAM checkpoint in {folder}; {describe_folder(folder)}. Put one of "
                             f"{', '.join(OFFICIAL_FILES.values())} there (never downloaded).")
