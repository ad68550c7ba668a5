"""Make each template's .jpg thumbnail from a frame the template really produces.

Runs every API workflow in-process (tests/comfy_harness.py), takes the frame at 40 % of the clip
and writes workflows/<name>.jpg. CPU-capable workflows only. Usage:
    .venv/bin/python scripts/make_thumbnails.py [name ...]
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from comfy_harness import node_classes, run_prompt  # noqa: E402


def frames_node(prompt: dict) -> str:
    """The node whose first output feeds the video saver."""
    for node in prompt.values():
        if node["class_type"] == "PhysMotionSaveVideo":
            return node["inputs"]["frames"][0]
    raise ValueError("workflow has no PhysMotionSaveVideo node")


def main(names: list[str]) -> int:
    node_classes()
    paths = sorted((ROOT / "workflows" / "api").glob("*.json"))
    if names:
        paths = [p for p in paths if p.stem in names]
    for path in paths:
        prompt = json.loads(path.read_text())
        with tempfile.TemporaryDirectory() as tmp:
            os.environ["PHYSMOTION_OUTPUT_DIR"] = tmp
            out = run_prompt(prompt)
        frames = out["results"][frames_node(prompt)][0]
        frame = frames[int(0.4 * (frames.shape[0] - 1))].numpy()
        img = (np.clip(frame, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1]
        scale = 512 / max(img.shape[:2])
        if scale < 1:
            img = cv2.resize(img, (round(img.shape[1] * scale), round(img.shape[0] * scale)), interpolation=cv2.INTER_AREA)
        target = ROOT / "workflows" / f"{path.stem}.jpg"
        cv2.imwrite(str(target), img, [cv2.IMWRITE_JPEG_QUALITY, 85])
        print(f"wrote {target.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
