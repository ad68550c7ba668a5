"""Thumbnails of the Wan templates (example_workflows/wan_*.json) from a frame their CPU part really produces.

The Wan nodes need the Wan weights and a GPU, so only the PhysMotion part of each template runs here
(in-process, tests/comfy_harness.py): everything upstream of the PhysMotion video-control node, and
that node. The thumbnail is its preview at 40 % of the clip: the point tracks drawn over the first
frame (PhysMotionPointTracks, as the template sets its preview), or the VACE control, depth inside the
object's mask over the coarse video (PhysMotionControlVideos). Usage:
    .venv/bin/python scripts/make_wan_thumbnails.py [name ...]
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from comfy_harness import node_classes, run_prompt  # noqa: E402

#: The video-control node of a Wan template and which of its outputs the thumbnail shows.
CONTROL_NODES = {"PhysMotionPointTracks": 1, "PhysMotionControlVideos": 4}


def upstream(prompt: dict, nid: str) -> dict:
    """The sub-prompt of ``nid`` and every node it depends on."""
    keep, stack = set(), [nid]
    while stack:
        n = stack.pop()
        if n in keep:
            continue
        keep.add(n)
        stack += [v[0] for v in prompt[n]["inputs"].values() if isinstance(v, list) and len(v) == 2
                  and isinstance(v[0], str)]
    return {k: v for k, v in prompt.items() if k in keep}


def control_node(prompt: dict) -> tuple[str, int]:
    for nid, node in prompt.items():
        if node["class_type"] in CONTROL_NODES:
            return nid, CONTROL_NODES[node["class_type"]]
    raise ValueError("no PhysMotion video-control node in this workflow")


def main(names: list[str]) -> int:
    node_classes()
    paths = sorted((ROOT / "example_workflows" / "api").glob("wan_*.json"))
    if names:
        paths = [p for p in paths if p.stem in names]
    for path in paths:
        prompt = json.loads(path.read_text())
        nid, slot = control_node(prompt)
        with tempfile.TemporaryDirectory() as tmp:
            os.environ["PHYSMOTION_OUTPUT_DIR"] = tmp
            t0 = time.perf_counter()
            out = run_prompt(upstream(prompt, nid))
            print(f"{path.stem}: PhysMotion part {time.perf_counter() - t0:.1f} s", flush=True)
        frames = out["results"][nid][slot]
        frame = frames[int(0.4 * (frames.shape[0] - 1))].numpy()
        img = (np.clip(frame, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1]
        scale = 512 / max(img.shape[:2])
        if scale < 1:
            img = cv2.resize(img, (round(img.shape[1] * scale), round(img.shape[0] * scale)),
                             interpolation=cv2.INTER_AREA)
        target = ROOT / "example_workflows" / f"{path.stem}.jpg"
        cv2.imwrite(str(target), img, [cv2.IMWRITE_JPEG_QUALITY, 85])
        print(f"wrote {target.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
