"""Tiny random-weight models in the official file layout, in a models root (``$PHYSMOTION_MODELS``).

Shared by the learned-lift tests and the in-process workflow test: the learned front end's
loaders find these files exactly where they look for the real weights, under the official names.

* ``sams/sam_vit_h_4b8939.pth``: the segment-anything architecture with a tiny ViT (test_sam).
* ``physmotion/imagedream/imagedream-ipmv-diffusers/``: the tiny ImageDream diffusers folder
  (test_imagedream; 64 px views).
* ``physmotion/lgm/model_fp16_fixrot.safetensors``: the golden tiny LGM (fp16, the README's config;
  run it at input size 64).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import torch

DATA = Path(__file__).resolve().parent / "data" / "models"

SAM_NAME = "sam_vit_h_4b8939.pth"
IMAGEDREAM_NAME = "imagedream-ipmv-diffusers"
LGM_NAME = "model_fp16_fixrot.safetensors"
LGM_INPUT_SIZE = 64


def write_tiny_lgm(root: Path, name: str = LGM_NAME) -> Path:
    folder = Path(root) / "physmotion" / "lgm"
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(DATA / "lgm_tiny.safetensors", folder / name)
    return folder / name


def write_tiny_imagedream(root: Path, name: str = IMAGEDREAM_NAME) -> Path:
    from test_imagedream import _write_tiny_model

    folder = Path(root) / "physmotion" / "imagedream" / name
    if not folder.exists():
        _write_tiny_model(folder)
    return folder


def write_tiny_sam(root: Path, name: str = SAM_NAME) -> Path:
    from test_sam import tiny_sam

    folder = Path(root) / "sams"
    folder.mkdir(parents=True, exist_ok=True)
    torch.save(tiny_sam().state_dict(), folder / name)      # official style: a plain state dict
    return folder / name


def write_tiny_models_root(root: Path, *, sam: bool = True, imagedream: bool = True, lgm: bool = True) -> Path:
    root = Path(root)
    if sam:
        write_tiny_sam(root)
    if imagedream:
        write_tiny_imagedream(root)
    if lgm:
        write_tiny_lgm(root)
    return root
