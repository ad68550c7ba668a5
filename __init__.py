"""PhysMotion for ComfyUI: physics-grounded image-to-video.

ComfyUI imports this file. Each node module is imported on its own, so a missing optional
dependency disables only that module's nodes (with the reason in the log), never the whole pack.
"""

from __future__ import annotations

import importlib
import logging
import os
import sys

log = logging.getLogger("physmotion")

_HERE = os.path.dirname(os.path.abspath(__file__))
# The library ships inside the pack; make it importable as `physmotion_core` without pip.
if _HERE not in sys.path:
    sys.path.append(_HERE)

NODE_MODULES = ("segment", "lift", "refine", "physics", "render", "enhance", "fit", "gaussian_native", "video_control")

NODE_CLASS_MAPPINGS: dict = {}
NODE_DISPLAY_NAME_MAPPINGS: dict = {}
FAILED_MODULES: dict = {}
WEB_DIRECTORY = "./web"

try:
    from .nodes._util import register_model_folders

    register_model_folders()
except Exception as _exc:  # noqa: BLE001 - never stop the pack from loading
    log.warning("PhysMotion: model folders not registered: %s", _exc)

for _name in NODE_MODULES:
    try:
        _mod = importlib.import_module(f".nodes.{_name}", __name__)
    except Exception as _exc:  # noqa: BLE001 - report and keep loading the other modules
        FAILED_MODULES[_name] = repr(_exc)
        log.warning("PhysMotion: nodes in '%s' are unavailable: %s", _name, _exc)
        continue
    NODE_CLASS_MAPPINGS.update(getattr(_mod, "NODE_CLASS_MAPPINGS", {}))
    NODE_DISPLAY_NAME_MAPPINGS.update(getattr(_mod, "NODE_DISPLAY_NAME_MAPPINGS", {}))



def _install_example_images() -> None:
    """Copy the bundled example photos into ComfyUI's input folder as physmotion_<name>.png (once,
    never overwriting), so the templates' LoadImage nodes find them."""
    try:
        import shutil

        import folder_paths

        photos = os.path.join(_HERE, "photos")
        for name in sorted(os.listdir(photos)):
            if name.endswith(".png"):
                target = os.path.join(folder_paths.get_input_directory(), "physmotion_" + name)
                if not os.path.exists(target):
                    shutil.copyfile(os.path.join(photos, name), target)
    except Exception as exc:  # noqa: BLE001 - outside ComfyUI, or a read-only input folder
        log.debug("PhysMotion: example images not installed: %s", exc)


_install_example_images()

__all__ = ["NODE_CLASS_MAPPINGS", "NODE_DISPLAY_NAME_MAPPINGS", "WEB_DIRECTORY"]
