"""Monocular depth from a transformers depth model (DPT / MiDaS, Depth Anything), offline.

Models are transformers folders (``config.json`` + weights + ``preprocessor_config.json``) under
``models/physmotion/depth/<dir>``, loaded with ``local_files_only=True``. Relative models (DPT,
MiDaS, Depth Anything "relative") predict an affine-invariant *inverse* depth (disparity: larger is
nearer); metric models (Depth Anything "metric") predict depth in metres. ``DepthMap`` keeps that
distinction, and ``pseudo_depth`` turns either into a map that grows with distance, which is all the
scale- and shift-invariant depth losses need (DNGaussian uses 255 − disparity the same way).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import InputError, MissingModelError
from ..models import describe_folder, pick_device, resolve_model_dir
from ..segment.classic import as_image_array

log = logging.getLogger(__name__)

EXPECTED = ("a transformers depth-estimation folder (config.json, model.safetensors or pytorch_model.bin, "
            "preprocessor_config.json), e.g. Intel/dpt-hybrid-midas or depth-anything/Depth-Anything-V2-Small-hf")


@dataclass
class DepthModel:
    model: torch.nn.Module
    processor: object
    kind: str  # "disparity" | "depth"
    path: Path

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    def to(self, device) -> "DepthModel":
        self.model.to(device)
        return self


@dataclass
class DepthMap:
    """(H,W) float32 prediction and what it means: "disparity" (relative inverse depth) or "depth"."""

    values: torch.Tensor
    kind: str

    def pseudo_depth(self) -> torch.Tensor:
        """A map that increases with distance (affine-equivalent to depth for a disparity model's
        purposes: the losses that use it normalise away scale and shift)."""
        return -self.values if self.kind == "disparity" else self.values

    def preview(self, mask: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(H,W,3) in 0..1, near = bright, normalised over ``mask`` (or the whole map)."""
        d = self.pseudo_depth()
        sel = d[mask > 0.5] if mask is not None and bool((mask > 0.5).any()) else d.flatten()
        lo, hi = torch.quantile(sel, 0.02), torch.quantile(sel, 0.98)
        v = 1.0 - ((d - lo) / (hi - lo).clamp(min=1e-8)).clamp(0, 1)
        if mask is not None:
            v = v * (mask > 0.5)
        return v[..., None].expand(*v.shape, 3).contiguous()


def _kind_from_config(config) -> str:
    if getattr(config, "depth_estimation_type", "relative") == "metric":
        return "depth"
    return "disparity"


def load_depth_model(name: Optional[str] = None, *, device=None, root=None) -> DepthModel:
    """Load a depth model folder from ``models/physmotion/depth/`` (or an absolute folder)."""
    from transformers import AutoImageProcessor, AutoModelForDepthEstimation

    folder = resolve_model_dir("depth", name, expected=EXPECTED, required=["config.json"], root=root)
    weights = [p.name for p in folder.iterdir() if p.suffix in (".safetensors", ".bin")]
    if not weights:
        raise MissingModelError(f"The depth model folder {folder} has no weights (model.safetensors or "
                                f"pytorch_model.bin); {describe_folder(folder)}. Expected {EXPECTED}.")
    if not (folder / "preprocessor_config.json").exists():
        raise MissingModelError(f"The depth model folder {folder} lacks preprocessor_config.json (the image "
                                f"processor settings); {describe_folder(folder)}. Copy the whole model folder.")
    try:
        model = AutoModelForDepthEstimation.from_pretrained(str(folder), local_files_only=True)
        processor = AutoImageProcessor.from_pretrained(str(folder), local_files_only=True)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"Could not load the depth model in {folder}: {exc}. It must be {EXPECTED}.") from exc
    model.eval().to(pick_device(device))
    kind = _kind_from_config(model.config)
    log.info("depth model %s (%s, predicts %s)", folder.name, type(model).__name__, kind)
    return DepthModel(model=model, processor=processor, kind=kind, path=folder)


@torch.no_grad()
def estimate_depth(dm: DepthModel, image) -> DepthMap:
    """Predict depth for ``image`` (H,W,3 in 0..1); the map is resized to (H,W) bicubically."""
    img = as_image_array(image)
    H, W = img.shape[:2]
    u8 = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
    inputs = dm.processor(images=u8, return_tensors="pt")
    pv = inputs["pixel_values"].to(dm.device, next(dm.model.parameters()).dtype)
    pred = dm.model(pixel_values=pv).predicted_depth
    if pred.ndim == 3:
        pred = pred[:, None]
    pred = F.interpolate(pred.float(), size=(H, W), mode="bicubic", align_corners=False)[0, 0]
    if not bool(torch.isfinite(pred).all()):
        raise InputError(f"The depth model {dm.path.name} produced non-finite values; check the weights.")
    return DepthMap(values=pred.cpu(), kind=dm.kind)
