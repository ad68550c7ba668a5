"""Generate the UI-format templates in example_workflows/ from their API-format twins in example_workflows/api/.

The API file is the single source of truth; run this after editing one:
    .venv/bin/python scripts/build_workflows.py
After a node gains an optional widget, ``--fill-defaults`` first writes it at its default into every API
twin that uses the node (the frontend sends every widget's value, so the twins must list it).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from comfy_schemas import all_schemas  # noqa: E402

from physmotion_core.comfy.workflow import _inputs, api_to_ui, is_widget  # noqa: E402

TITLES = {  # friendlier titles for the core nodes in the templates
    "LoadImage": "Load the photo",
    "PhysMotionLoadGaussians": "Load your splat (.ply in output/, or an absolute path)",
    "PhysMotionSegment": "Segment: click the object, Shift-click background, drag a box (or connect any node's MASK)",
    "PhysMotionSAMSegment": "SAM Segment: click the object, Shift-click background, drag a box (or connect a MASK)",
    "PhysMotionFillBackground": "Fill the background (or wire any inpainting node's IMAGE into Blend instead)",
}
# Nodes with the force/torque picker (web/force_picker.js) or the segmentation picker
# (web/segment_picker.js) are taller: their widgets plus the photo.
SIZES = {"PhysMotionForce": [360, 600], "PhysMotionTorque": [360, 600], "PhysMotionSegment": [380, 620],
         "PhysMotionSAMSegment": [380, 680]}


def schemas() -> dict:
    """The node schemas the frontend would have: ComfyUI 0.3.64's /object_info for its own nodes, the
    newer upstream nodes (GAUSSIAN, TripoSplat) typed from their source, the pack's classes."""
    return all_schemas()


#: The node property naming the photo a picker's points, box or image point were set on (web/picker_math.js,
#: PROMPT_PHOTO_PROPERTY): the pickers warn when the Load Image feeding the node shows another photo.
PROMPT_PHOTO = "physmotion_prompt_photo"


def _picks_in_pixels(node: dict) -> bool:
    """Whether a node holds picks in the photo's pixels (which go stale on another photo)."""
    kind, inputs = node["class_type"], node["inputs"]
    said = lambda *names: any(str(inputs.get(k) or "").strip() for k in names)  # noqa: E731
    if kind == "PhysMotionSegment":
        return said("object_points", "background_points", "box")
    if kind == "PhysMotionSAMSegment":
        return inputs.get("coordinates") != "fraction" and said("points", "boxes")
    if kind in ("PhysMotionForce", "PhysMotionTorque"):
        return inputs.get("region") == "image point"
    return False


def picks_photo(prompt: dict, nid: str) -> str | None:
    """The Load Image photo nearest to node ``nid`` by links either way (as the pickers find it), named as
    its widget names it without an ``[input]`` tag, or None."""
    near: dict[str, set] = {n: set() for n in prompt}
    for n, node in prompt.items():
        for v in node["inputs"].values():
            if isinstance(v, list) and len(v) == 2 and str(v[0]) in prompt:
                near[n].add(str(v[0]))
                near[str(v[0])].add(n)
    seen, frontier = {nid}, [nid]
    while frontier:
        nxt = []
        for n in frontier:
            for m in sorted(near[n], key=int):
                if m in seen:
                    continue
                seen.add(m)
                if prompt[m]["class_type"] == "LoadImage":
                    name = str(prompt[m]["inputs"].get("image") or "").strip()
                    return name[: -len(" [input]")] if name.endswith(" [input]") else name or None
                nxt.append(m)
        frontier = nxt
    return None


def build_ui(prompt: dict, sch: dict | None = None) -> dict:
    """The UI template for an API prompt (what this script writes; the tests regenerate with it). Nodes with
    picks in pixels name the photo they were set on (``PROMPT_PHOTO``), so that the pickers warn once a user
    loads another photo."""
    titles = {nid: TITLES[n["class_type"]] for nid, n in prompt.items() if n["class_type"] in TITLES}
    ui = api_to_ui(prompt, sch or schemas(), titles, SIZES)
    for node in ui["nodes"]:
        nid = str(node["id"])
        if _picks_in_pixels(prompt[nid]):
            photo = picks_photo(prompt, nid)
            if photo:
                node["properties"][PROMPT_PHOTO] = photo
    return ui


def widget_default(spec):
    """The value the frontend gives a new widget: the declared default, else a list's first option, else
    the type's zero."""
    opts = spec[1] if len(spec) > 1 and isinstance(spec[1], dict) else {}
    if "default" in opts:
        return opts["default"]
    kind = spec[0]
    if isinstance(kind, (list, tuple)):
        return kind[0] if kind else ""
    if kind == "COMBO":
        return (opts.get("options") or [""])[0]
    return {"INT": 0, "FLOAT": 0.0, "BOOLEAN": False, "STRING": ""}.get(kind, None)


def fill_defaults(prompt: dict, sch: dict) -> int:
    """Give every node of an API prompt the optional widgets its class gained since the file was written,
    at their defaults (what the frontend's graphToPrompt sends for them, so the twins stay equal; the run
    does not change). Returns how many inputs were added."""
    added = 0
    for node in prompt.values():
        schema = sch.get(node["class_type"])
        if schema is None:
            continue
        for name, spec, required in _inputs(schema):
            if not required and is_widget(spec) and name not in node["inputs"]:
                node["inputs"][name] = widget_default(spec)
                added += 1
    return added


def main() -> int:
    sch = schemas()
    fill = "--fill-defaults" in sys.argv[1:]
    for api_path in sorted((ROOT / "example_workflows" / "api").glob("*.json")):
        prompt = json.loads(api_path.read_text())
        if fill and fill_defaults(prompt, sch):
            api_path.write_text(json.dumps(prompt, indent=2, ensure_ascii=False) + "\n")
            print(f"filled the new optional widgets of {api_path.relative_to(ROOT)}")
        ui = build_ui(prompt, sch)
        out = ROOT / "example_workflows" / api_path.name
        out.write_text(json.dumps(ui, indent=1) + "\n")
        print(f"wrote {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
