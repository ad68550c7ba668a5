"""Make each template's .jpg thumbnail from a frame the template really produces.

Runs every API workflow in-process (tests/comfy_harness.py), takes the frame at 40 % of the clip
and writes example_workflows/<name>.jpg (printing the run time). CPU-capable workflows only. With --sheet DIR it also writes a
contact sheet of six frames per workflow to DIR (for reviewing the motion). Usage:
    .venv/bin/python scripts/make_thumbnails.py [--sheet DIR] [name ...]
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

from comfy_harness import node_classes, prepare_template_inputs, run_prompt  # noqa: E402

from physmotion_core.errors import MissingModelError  # noqa: E402

#: Native nodes that need weights (or a newer ComfyUI) and the stand-in .ply their output is replaced
#: with for the thumbnail (the frame is then labelled as made with a stand-in).
STANDIN_SPLATS = {"VAEDecodeTripoSplat": "PhysMotion/standin_splat.ply"}


def standin_prompt(prompt: dict) -> tuple[dict, str]:
    """The prompt with each node of STANDIN_SPLATS replaced by PhysMotion Load Gaussians of a stand-in
    .ply (see comfy_harness.write_standin_splat) and the nodes only they used dropped; with a label
    for the thumbnail ("" when nothing was replaced)."""
    prompt = json.loads(json.dumps(prompt))
    replaced = [nid for nid, n in prompt.items() if n["class_type"] in STANDIN_SPLATS]
    for nid in replaced:
        prompt[nid] = {"class_type": "PhysMotionLoadGaussians",
                       "inputs": {"ply_path": STANDIN_SPLATS[prompt[nid]["class_type"]]}}
    classes = node_classes()
    while True:  # drop nodes nothing uses that are not outputs (the model loaders, sampler, ...)
        used = {v[0] for n in prompt.values() for v in n["inputs"].values() if isinstance(v, list) and len(v) == 2}
        unused = [nid for nid, n in prompt.items() if nid not in used
                  and not getattr(classes.get(n["class_type"]), "OUTPUT_NODE", False)]
        if not unused:
            break
        for nid in unused:
            del prompt[nid]
    return prompt, ("stand-in splat (no TripoSplat weights here)" if replaced else "")


def frames_node(prompt: dict) -> str:
    """The node whose first output feeds the first video: CreateVideo's images (the templates save
    with ComfyUI's Create Video -> Save Video), or PhysMotion Save Video's frames."""
    found = None
    for nid in sorted(prompt, key=int):
        node = prompt[nid]
        if node["class_type"] == "CreateVideo":
            found = node["inputs"]["images"][0]
        elif node["class_type"] == "PhysMotionSaveVideo":
            found = node["inputs"]["frames"][0]
        if found is not None:
            break
    if found is None:
        raise ValueError("workflow has no CreateVideo or PhysMotionSaveVideo node")
    return found


def contact_sheet(frames, path: Path) -> None:
    idx = np.linspace(0, frames.shape[0] - 1, 6).round().astype(int)
    tiles = [(np.clip(frames[i].numpy(), 0, 1) * 255).astype(np.uint8) for i in idx]
    sheet = np.concatenate([np.concatenate(tiles[:3], 1), np.concatenate(tiles[3:], 1)], 0)
    scale = 900 / sheet.shape[1]
    cv2.imwrite(str(path), cv2.resize(sheet, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)[..., ::-1])


def main(names: list[str]) -> int:
    sheet_dir = None
    if names[:1] == ["--sheet"]:
        sheet_dir, names = Path(names[1]), names[2:]
        sheet_dir.mkdir(parents=True, exist_ok=True)
    node_classes()
    paths = sorted((ROOT / "example_workflows" / "api").glob("*.json"))
    if names:
        paths = [p for p in paths if p.stem in names]
    for path in paths:
        prompt, label = standin_prompt(json.loads(path.read_text()))
        missing = sorted({n["class_type"] for n in prompt.values()} - set(node_classes()))
        if missing:
            print(f"{path.stem}: skipped (the harness has no {', '.join(missing)})", flush=True)
            continue
        with tempfile.TemporaryDirectory() as tmp:
            os.environ["PHYSMOTION_OUTPUT_DIR"] = tmp
            # A 4000-Gaussian stand-in splat keeps the thumbnail run short; Fit lines it up at this size and
            # at the full 20000 alike (IoU 0.98, colour error 0.043-0.048: docs/lift.md).
            prepare_template_inputs(prompt, Path(tmp), max_gaussians=4000)
            t0 = time.perf_counter()
            try:
                out = run_prompt(prompt)
            except MissingModelError as exc:  # a learned stage the stand-ins do not replace: keep its thumbnail
                print(f"{path.stem}: skipped (needs learned weights: {str(exc).split(' not found')[0]})", flush=True)
                continue
            wall = time.perf_counter() - t0
        frames = out["results"][frames_node(prompt)][0]
        sims = [r[0] for r in out["results"].values() if r and type(r[0]).__name__ == "SimResult"]
        if sims:
            st = sims[0].stats
            print(f"{path.stem}: whole workflow {wall:.1f} s, simulation {st['wall_time_s']:.1f} s, "
                  f"{st['particles']:,} particles, {st['substeps']:,} substeps, {frames.shape[0]} frames",
                  flush=True)
        if sheet_dir is not None:
            contact_sheet(frames, sheet_dir / f"{path.stem}.png")
        frame = frames[int(0.4 * (frames.shape[0] - 1))].numpy()
        img = (np.clip(frame, 0, 1) * 255 + 0.5).astype(np.uint8)[..., ::-1]
        scale = 512 / max(img.shape[:2])
        if scale < 1:
            img = cv2.resize(img, (round(img.shape[1] * scale), round(img.shape[0] * scale)), interpolation=cv2.INTER_AREA)
        if label:
            cv2.putText(img, label, (8, img.shape[0] - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                        cv2.LINE_AA)
        target = ROOT / "example_workflows" / f"{path.stem}.jpg"
        cv2.imwrite(str(target), img, [cv2.IMWRITE_JPEG_QUALITY, 85])
        print(f"wrote {target.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
