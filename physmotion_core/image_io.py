"""Loading and saving images as the library's float tensors.

Everything inside the library is RGB float32 in 0..1 with shape (H, W, 3); an alpha channel, when
an image has a meaningful one, travels separately as (H, W) float32 in 0..1. OpenCV decodes the
pixels (PNG, JPEG, WebP and TIFF at 8 or 16 bits); Pillow reads the header first (the size, checked
against a pixel limit before decoding, and the EXIF orientation, applied to the decoded pixels).
Every image file the library reads goes through ``load_image``.
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


#: The most pixels an image file may have before it is decoded (Pillow's own default limit, about
#: 9459 x 9459). Larger files are refused from their header, before any pixel is decoded: a
#: "decompression bomb" (a few KB that claim 100000 x 100000 pixels, or a real 25000 x 25000 PNG of
#: 2 MB) would otherwise take tens of GB. ``$PHYSMOTION_MAX_IMAGE_PIXELS`` changes it.
MAX_IMAGE_PIXELS = 89_478_485
#: RAM a decode takes per pixel at most: the decoded array (up to 4 channels of 16 bits), its
#: float32 copy and the (H,W,3) + (H,W) float32 results.
DECODE_BYTES_PER_PIXEL = 8 + 16 + 16

# EXIF orientation (tag 0x0112) -> how to turn the stored pixels upright (as Pillow's
# ImageOps.exif_transpose does): phones store the sensor's pixels and say how to rotate them.
_ORIENT = {
    2: lambda a: a[:, ::-1],                     # mirrored left-right
    3: lambda a: a[::-1, ::-1],                  # rotated 180
    4: lambda a: a[::-1, :],                     # mirrored top-bottom
    5: lambda a: np.swapaxes(a, 0, 1),           # transposed
    6: lambda a: np.rot90(a, -1),                # rotated 90 clockwise to be upright
    7: lambda a: np.swapaxes(a[::-1, ::-1], 0, 1),  # transversed
    8: lambda a: np.rot90(a, 1),                 # rotated 90 counter-clockwise to be upright
}


def max_image_pixels() -> int:
    env = os.environ.get("PHYSMOTION_MAX_IMAGE_PIXELS", "").strip()
    if env:
        try:
            return max(1, int(float(env)))
        except ValueError:
            raise InputError(f"$PHYSMOTION_MAX_IMAGE_PIXELS must be a number of pixels; got {env!r}") from None
    return MAX_IMAGE_PIXELS


def image_header(data: bytes, name: str = "image") -> tuple[Optional[tuple[int, int]], int]:
    """((width, height) or None when Pillow does not know the format, EXIF orientation 1..8) from a
    file's header, without decoding its pixels."""
    import io
    import warnings

    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DecompressionBombWarning: we apply our own limit
            saved, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, None
            try:
                im = Image.open(io.BytesIO(data))
            finally:
                Image.MAX_IMAGE_PIXELS = saved
            size = (int(im.size[0]), int(im.size[1]))
            try:
                if im.format == "PNG":
                    # Pillow's PNG getexif() decodes the whole image to look for an eXIf chunk after
                    # the pixels (a bomb would be decoded here); the chunk belongs before them.
                    exif = Image.Exif()
                    if im.info.get("exif"):
                        exif.load(im.info["exif"])
                else:
                    exif = im.getexif()  # JPEG, WebP, TIFF: read from the header, no pixels decoded
                orientation = int(exif.get(0x0112, 1) or 1)
            except Exception:  # noqa: BLE001 - a damaged EXIF block: treat the pixels as upright
                orientation = 1
    except Exception:  # noqa: BLE001 - not a format Pillow reads (OpenCV may); no header facts
        return None, 1
    return size, orientation if orientation in range(1, 9) else 1


def check_image_size(width: int, height: int, name: str = "image") -> None:
    """Refuse, before decoding, an image with more pixels than the limit or than RAM can hold."""
    from .memory import fmt_bytes, host_available_bytes

    px, limit = int(width) * int(height), max_image_pixels()
    if width <= 0 or height <= 0:
        raise InputError(f"{name} claims a size of {width}x{height} pixels; the file is damaged")
    if px > limit:
        raise InputError(f"{name} is {width}x{height} pixels ({px / 1e6:.0f} megapixels), more than the "
                         f"{limit / 1e6:.0f} megapixels an image may have (a file this large, or one whose header "
                         "claims it, would need "
                         f"{fmt_bytes(px * DECODE_BYTES_PER_PIXEL)} to decode). Scale it down first (the pipeline "
                         "works at 1024 pixels on the long side by default), or raise the limit with "
                         "$PHYSMOTION_MAX_IMAGE_PIXELS.")
    need, have = px * DECODE_BYTES_PER_PIXEL, host_available_bytes()
    if need > 0.8 * have:
        from .memory import over_limit_message

        raise InputError(f"{name} is {width}x{height} pixels: decoding it {over_limit_message(need, have, 0.8)}. "
                         "Scale the image down first, or free memory.")


def load_image(path: PathLike) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """Read an image file as (rgb (H,W,3) float32 0..1, alpha (H,W) float32 0..1 or None).

    Grayscale becomes three equal channels; 16-bit files keep their precision; an alpha channel
    that is fully opaque is dropped (returned as None) since it says nothing about the object.
    The EXIF orientation is applied (a phone photo taken upright is upright here). An image with
    more pixels than ``MAX_IMAGE_PIXELS`` (or than RAM holds) is refused from its header, before
    any decoding.
    """
    p = Path(path)
    if "\x00" in os.fspath(path):
        raise InputError(f"image path {os.fspath(path)!r} contains a NUL byte; no file name can hold one")
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
    if not data.size:
        raise InputError(f"Cannot decode image file '{p}': the file is empty")
    size, orientation = image_header(data.tobytes(), f"image '{p}'")
    if size is not None:
        check_image_size(size[0], size[1], f"image '{p}'")
    try:
        array = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:  # OpenCV's own limits (CV_IO_MAX_IMAGE_PIXELS), unsupported variants
        raise InputError(f"Cannot decode image file '{p}': {str(exc).strip().splitlines()[-1][:200]}. Use a "
                         "PNG/JPEG/WebP/TIFF image of at most "
                         f"{max_image_pixels() / 1e6:.0f} megapixels.") from None
    if array is None:
        raise InputError(f"Cannot decode image file '{p}': not a PNG/JPEG/WebP/TIFF image OpenCV "
                         "can read, or the file is damaged")
    if size is None:
        check_image_size(array.shape[1], array.shape[0], f"image '{p}'")
    if orientation != 1:
        array = np.ascontiguousarray(_ORIENT[orientation](array))
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
