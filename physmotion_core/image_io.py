"""Loading and saving images as the library's float tensors.

Everything inside the library is RGB float32 in 0..1 with shape (H, W, 3); an alpha channel, when
an image has a meaningful one, travels separately as (H, W) float32 in 0..1. OpenCV does the file
work (it reads PNG, JPEG, WebP and TIFF at 8 or 16 bits) so no extra imaging dependency is needed.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Union

import cv2
import numpy as np
import torch

from .errors import InputError
from .fsutil import atomic_output

PathLike = Union[str, os.PathLike]

# An alpha channel whose every value is at least this is "opaque": it carries no segmentation.
_OPAQUE = 1.0 - 0.5 / 255.0


def _scale_for(dtype: np.dtype) -> float:
    if dtype == np.uint8:
        return 255.0
    if dtype == np.uint16:
        return 65535.0
    if np.issubdtype(dtype, np.floating):
        return 1.0
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    raise InputError(f"Unsupported image pixel type {dtype}")


def decode_image(array: np.ndarray, name: str = "image") -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """An OpenCV-layout array (H,W), (H,W,1|3|4), BGR(A), any bit depth, to (rgb, alpha)."""
    if array is None or array.size == 0:
        raise InputError(f"{name} is empty")
    scale = _scale_for(array.dtype)
    img = array.astype(np.float32) / scale
    if img.ndim == 2:
        img = img[:, :, None]
    if img.ndim != 3:
        raise InputError(f"{name} must be a 2D image; got array of shape {array.shape}")
    channels = img.shape[2]
    alpha = None
    if channels == 1:
        rgb = np.repeat(img, 3, axis=2)
    elif channels == 2:  # gray + alpha
        rgb = np.repeat(img[:, :, :1], 3, axis=2)
        alpha = img[:, :, 1]
    elif channels == 3:
        rgb = img[:, :, ::-1]
    elif channels == 4:
        rgb = img[:, :, 2::-1]
        alpha = img[:, :, 3]
    else:
        raise InputError(f"{name} has {channels} channels; expected 1 (gray), 3 (RGB) or 4 (RGBA)")
    rgb = np.clip(rgb, 0.0, 1.0)
    rgb_t = torch.from_numpy(np.ascontiguousarray(rgb))
    alpha_t = None
    if alpha is not None:
        alpha = np.clip(alpha, 0.0, 1.0)
        if float(alpha.min()) < _OPAQUE:
            alpha_t = torch.from_numpy(np.ascontiguousarray(alpha))
    return rgb_t, alpha_t


def load_image(path: PathLike) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """Read an image file as (rgb (H,W,3) float32 0..1, alpha (H,W) float32 0..1 or None).

    Grayscale becomes three equal channels; 16-bit files keep their precision; an alpha channel
    that is fully opaque is dropped (returned as None) since it says nothing about the object.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"Image file not found: '{p}'. Check the path (relative paths are taken "
                         f"from the current directory '{os.getcwd()}').")
    if not p.is_file():
        raise InputError(f"Image path '{p}' is not a file")
    # imdecode from bytes instead of imread: imread cannot open non-ASCII paths on Windows.
    try:
        data = np.fromfile(str(p), dtype=np.uint8)
    except OSError as exc:
        raise InputError(f"Cannot read image file '{p}': {exc}") from exc
    array = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if array is None:
        raise InputError(f"Cannot decode image file '{p}': not a PNG/JPEG/WebP/TIFF image OpenCV "
                         "can read, or the file is damaged")
    return decode_image(array, name=f"image '{p}'")


def to_uint8(img) -> np.ndarray:
    """A float image (torch or numpy) in 0..1 to uint8 with rounding; other layouts unchanged."""
    if isinstance(img, torch.Tensor):
        img = img.detach().cpu().numpy()
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    return (np.clip(img.astype(np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_image(path: PathLike, rgb, alpha=None) -> Path:
    """Write an RGB (H,W,3) (or gray (H,W)) image in 0..1, optionally with alpha, atomically.

    The file is written next to its destination under a temporary name and then renamed over it,
    so readers never see a half-written image. The format follows the extension.
    """
    p = Path(path)
    arr = to_uint8(rgb)
    if arr.ndim == 3 and arr.shape[2] == 3:
        arr = arr[:, :, ::-1]
    elif not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 1)):
        raise InputError(f"save_image expects an (H,W,3) or (H,W) image; got shape {arr.shape}")
    if alpha is not None:
        a = to_uint8(alpha)
        if a.shape != arr.shape[:2]:
            raise InputError(f"save_image: alpha shape {a.shape} does not match image {arr.shape[:2]}")
        if arr.ndim == 2 or arr.shape[2] == 1:
            arr = np.repeat(arr.reshape(arr.shape[0], arr.shape[1], 1), 3, axis=2)
        arr = np.concatenate([arr, a[:, :, None]], axis=2)
    ext = p.suffix.lower() or ".png"
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(arr))
    if not ok:
        raise InputError(f"Cannot encode an image as '{ext}' for '{p}'; use .png, .jpg, .webp or .tif")
    with atomic_output(p, suffix=ext) as tmp:
        tmp.write_bytes(buf.tobytes())
    return p
