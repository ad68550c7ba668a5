"""The SD 2.1 / ControlNet configs and CLIP tokenizer shipped with the package (see
``physmotion_core/data/sd21_configs/SOURCES.md``), used for single-file checkpoints."""

from __future__ import annotations

import json
from pathlib import Path

SD21_CONFIG_DIR = Path(__file__).resolve().parent.parent / "data" / "sd21_configs"

_FILES = {"unet": "unet/config.json", "vae": "vae/config.json", "text_encoder": "text_encoder/config.json",
          "scheduler": "scheduler/scheduler_config.json", "controlnet_depth": "controlnet_depth/config.json",
          "controlnet_canny": "controlnet_canny/config.json"}


def read_config(component: str, config_dir: Path = SD21_CONFIG_DIR) -> dict:
    """One component's config as a dict (``unet``, ``vae``, ``text_encoder``, ``scheduler``,
    ``controlnet_depth``, ``controlnet_canny``)."""
    return json.loads((Path(config_dir) / _FILES[component]).read_text())
