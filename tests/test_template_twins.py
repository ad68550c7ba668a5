"""Each UI template against its node's current inputs and against its API twin, the way the frontend
reads it (no browser): drift between a node's inputs and a template, or between the twins, fails here.

The frontend gives a node one widget for every widget input of its schema, required and optional, in
schema order (a seed also gets its "control after generate" value, an upload its button); it fills them
from ``widgets_values`` by position and ``graphToPrompt()`` sends every widget's value (a widget fed by a
link sends the link). So a template whose ``widgets_values`` has fewer or more values than its node now
has widgets loads shifted or defaulted values, and the prompt it queues is not its API twin.
"""

from __future__ import annotations

import json

import pytest

from comfy_harness import ROOT
from comfy_schemas import all_schemas

from physmotion_core.comfy.workflow import _extra_widget_values, _inputs, is_widget, types_compatible

UI = sorted(p for p in (ROOT / "example_workflows").glob("*.json"))
API_DIR = ROOT / "example_workflows" / "api"


@pytest.fixture(scope="module")
def schemas():
    return all_schemas()


def widget_slots(schema: dict) -> list[tuple[str, int]]:
    """(input name, number of widgets_values it takes) for every widget the frontend makes, in order."""
    return [(name, 1 + len(_extra_widget_values(name, spec))) for name, spec, _req in _inputs(schema)
            if is_widget(spec)]


def graph_to_prompt(workflow: dict, schemas: dict) -> tuple[dict, list[str]]:
    """The API prompt the frontend queues for ``workflow`` (its graphToPrompt), and what does not line up."""
    problems = []
    link_src = {l[0]: (str(l[1]), int(l[2])) for l in workflow["links"]}
    prompt = {}
    for n in workflow["nodes"]:
        where = f"node {n['id']} ({n['type']})"
        schema = schemas.get(n["type"])
        if schema is None:
            problems.append(f"{where}: no such node")
            continue
        values = list(n.get("widgets_values", []))
        slots = widget_slots(schema)
        need = sum(k for _, k in slots)
        if len(values) != need:
            problems.append(f"{where}: {len(values)} widgets_values for {need} widget values "
                            f"({', '.join(name for name, _ in slots)})")
        linked = {i["name"]: link_src[i["link"]] for i in n.get("inputs", []) if i.get("link") is not None}
        known = {name for name, _spec, _req in _inputs(schema)}
        for name in linked:
            if name not in known:
                problems.append(f"{where}: a link into '{name}', which the node does not have")
        inputs, pos = {}, 0
        for name, spec, _req in _inputs(schema):
            if is_widget(spec):
                value = values[pos] if pos < len(values) else None
                pos += 1 + len(_extra_widget_values(name, spec))
                inputs[name] = list(linked[name]) if name in linked else value
            elif name in linked:
                inputs[name] = list(linked[name])
        prompt[str(n["id"])] = {"class_type": n["type"], "inputs": inputs}
    return prompt, problems


def test_there_is_a_ui_template_for_every_api_twin_and_back():
    assert {p.stem for p in UI} == {p.stem for p in API_DIR.glob("*.json")}


@pytest.mark.parametrize("path", UI, ids=lambda p: p.stem)
def test_ui_template_matches_the_node_inputs_and_its_api_twin(path, schemas):
    ui = json.loads(path.read_text())
    prompt, problems = graph_to_prompt(ui, schemas)
    assert problems == [], "\n".join(problems)
    api = json.loads((API_DIR / path.name).read_text())
    for nid in sorted(set(prompt) | set(api), key=int):
        assert nid in prompt and nid in api, f"node {nid} is only in the {'API' if nid in api else 'UI'} twin"
        assert prompt[nid]["class_type"] == api[nid]["class_type"], nid
        assert prompt[nid]["inputs"] == api[nid]["inputs"], (
            f"node {nid} ({api[nid]['class_type']}): the UI template queues {prompt[nid]['inputs']}, "
            f"the API twin says {api[nid]['inputs']}")


@pytest.mark.parametrize("path", UI, ids=lambda p: p.stem)
def test_ui_links_carry_the_types_the_nodes_output_now(path, schemas):
    ui = json.loads(path.read_text())
    nodes = {n["id"]: n for n in ui["nodes"]}
    for lid, src, slot, dst, dst_slot, kind in ui["links"]:
        out = schemas[nodes[src]["type"]]["output"][slot]
        assert kind == out, f"link {lid}: stored as {kind}, node {src} ({nodes[src]['type']}) outputs {out}"
        assert nodes[src]["outputs"][slot]["type"] == out, (lid, nodes[src]["outputs"][slot])
        name = nodes[dst]["inputs"][dst_slot]["name"]
        spec = dict((n, s) for n, s, _ in _inputs(schemas[nodes[dst]["type"]]))[name]
        assert types_compatible(out, spec[0]), f"link {lid}: {out} into {nodes[dst]['type']}.{name} ({spec[0]})"


def test_the_check_catches_a_template_that_lacks_a_new_optional_input(schemas):
    """What happened to the Fit templates when Fit gained focal_px / principal_x / principal_y: fewer
    widgets_values than widgets, and a prompt without them."""
    ui = json.loads((ROOT / "example_workflows" / "own_splat_to_physics.json").read_text())
    fit = next(n for n in ui["nodes"] if n["type"] == "PhysMotionFitGaussiansToPhoto")
    fit["widgets_values"] = fit["widgets_values"][:-3]
    _prompt, problems = graph_to_prompt(ui, schemas)
    assert len(problems) == 1 and "PhysMotionFitGaussiansToPhoto" in problems[0] and "focal_px" in problems[0]
    # and a value shifted by one (an input inserted in the middle) reaches the wrong widget
    ui = json.loads((ROOT / "example_workflows" / "own_splat_to_physics.json").read_text())
    fit = next(n for n in ui["nodes"] if n["type"] == "PhysMotionFitGaussiansToPhoto")
    fit["widgets_values"] = [fit["widgets_values"][1]] + fit["widgets_values"][:1] + fit["widgets_values"][2:]
    prompt, _ = graph_to_prompt(ui, schemas)
    api = json.loads((API_DIR / "own_splat_to_physics.json").read_text())
    assert prompt[str(fit["id"])]["inputs"] != api[str(fit["id"])]["inputs"]


def test_picks_in_pixels_name_the_photo_they_were_set_on():
    """A template's Segment box or points in pixels, and a Force/Torque image point, carry the photo they
    belong to (a node property the pickers read: web/picker_math.js PROMPT_PHOTO_PROPERTY), so the picker
    warns as soon as a user loads their own photo; picks that fit any photo (none, fractions, the whole
    object) carry none."""
    import re
    import sys

    sys.path.insert(0, str(ROOT / "scripts"))
    from build_workflows import PROMPT_PHOTO

    js = (ROOT / "web" / "picker_math.js").read_text()
    assert re.search(r'PROMPT_PHOTO_PROPERTY = "' + PROMPT_PHOTO + '"', js)
    stamped = 0
    for path in UI:
        wf = json.loads(path.read_text())
        photos = {n["widgets_values"][0] for n in wf["nodes"] if n["type"] == "LoadImage"}
        for n in wf["nodes"]:
            v, stamp = n.get("widgets_values", []), n.get("properties", {}).get(PROMPT_PHOTO)
            if n["type"] == "PhysMotionSegment":
                pixel = any(str(x).strip() for x in v[3:6])
            elif n["type"] == "PhysMotionSAMSegment":
                pixel = v[2] != "fraction" and any(str(x).strip() for x in v[:2])
            elif n["type"] in ("PhysMotionForce", "PhysMotionTorque"):
                pixel = v[3] == "image point"
            else:
                pixel = False
            assert (stamp is not None) == pixel, (path.name, n["type"], v, stamp)
            if pixel:
                assert len(photos) == 1 and stamp in photos, (path.name, stamp, photos)
                stamped += 1
    assert stamped >= 15  # the coffee templates' boxes and pushes, the clay's and the bar's pushes
