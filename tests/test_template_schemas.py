"""Every template checked against real node schemas (ComfyUI 0.3.64's /object_info, the newer upstream
nodes typed from their source, this pack's classes) with the validator the other tools use, and the
validator itself shown to catch what ComfyUI's POST /prompt rejects."""

from __future__ import annotations

import copy
import json

import pytest

from comfy_harness import ROOT
from comfy_schemas import OBJECT_INFO, TEMPLATE_MODEL_FILES, UPSTREAM, all_schemas, native_schemas

from physmotion_core.comfy.workflow import types_compatible, validate_prompt_against_schemas

API = sorted((ROOT / "example_workflows" / "api").glob("*.json"))


@pytest.fixture(scope="module")
def schemas():
    return all_schemas()


@pytest.mark.parametrize("path", API, ids=lambda p: p.stem)
def test_every_template_validates_against_the_node_schemas(path, schemas):
    errors = validate_prompt_against_schemas(json.loads(path.read_text()), schemas, TEMPLATE_MODEL_FILES)
    assert errors == [], "\n".join(errors)


def test_the_schemas_are_the_captured_ones():
    shared = ROOT.parent / "shared" / "comfy" / OBJECT_INFO.name
    if shared.exists():
        assert shared.read_bytes() == OBJECT_INFO.read_bytes()
    native = native_schemas()
    assert {"CreateVideo", "SaveVideo", "LoadImage", "KSampler", "CLIPVisionLoader"} <= set(native)
    upstream = json.loads(UPSTREAM.read_text())
    for path, note in upstream["_sources"].items():
        if path.endswith(".py") and "nodes_" in path:
            assert len(note.split()[0]) == 40, f"{path}: say which commit was read"
    assert {"File3DToGaussian", "File3DToSplat", "VAEDecodeTripoSplat", "TripoSplatConditioning"} <= set(upstream["nodes"])
    # a current ComfyUI's TripoSplat decode outputs SPLAT (IO.Splat), and the pack's splat inputs take it
    assert upstream["nodes"]["VAEDecodeTripoSplat"]["output"] == ["SPLAT"]
    assert upstream["nodes"]["File3DToSplat"]["output"] == ["SPLAT"]


def _jelly():
    return json.loads((ROOT / "example_workflows" / "api" / "push_a_jelly.json").read_text())


def _find(prompt, cls):
    return next(nid for nid, n in prompt.items() if n["class_type"] == cls)


def test_a_valid_prompt_has_no_errors_and_each_fault_is_named(schemas):
    good = _jelly()
    assert validate_prompt_against_schemas(good, schemas) == []
    sim, lift, mat = _find(good, "PhysMotionMPMSimulate"), _find(good, "PhysMotionSilhouetteLift"), \
        _find(good, "PhysMotionMaterial")

    p = copy.deepcopy(good)  # wrong link type: the camera (PM_CAMERA) where Gaussians go
    p[sim]["inputs"]["gaussians"] = [lift, 1]
    (e,) = validate_prompt_against_schemas(p, schemas)
    assert "return_type_mismatch" in e and "PM_CAMERA" in e and f"node {sim} " in e

    p = copy.deepcopy(good)  # out of range
    p[sim]["inputs"]["frames"] = 0
    (e,) = validate_prompt_against_schemas(p, schemas)
    assert "value_smaller_than_min" in e and ".frames" in e
    p[sim]["inputs"]["frames"] = 10 ** 9
    assert "value_bigger_than_max" in validate_prompt_against_schemas(p, schemas)[0]

    p = copy.deepcopy(good)  # bad dropdown value
    p[mat]["inputs"]["preset"] = "marshmallow"
    (e,) = validate_prompt_against_schemas(p, schemas)
    assert "value_not_in_list" in e and "'marshmallow'" in e

    p = copy.deepcopy(good)  # wrong literal types
    p[sim]["inputs"]["frames"] = 4.5
    p[lift]["inputs"]["on_ground"] = "yes"
    errs = validate_prompt_against_schemas(p, schemas)
    assert len(errs) == 2 and all("invalid_input_type" in e for e in errs)

    p = copy.deepcopy(good)  # missing input, unknown input, missing node, bad slot, unknown class
    del p[sim]["inputs"]["material"]
    p[sim]["inputs"]["frame_count"] = 3
    p[_find(good, "PhysMotionRender")]["inputs"]["simulation"] = ["99", 0]
    p[_find(good, "PhysMotionBlend")]["inputs"]["rgb"] = [_find(good, "PhysMotionRender"), 7]
    p["50"] = {"class_type": "NoSuchNode", "inputs": {}}
    text = "\n".join(validate_prompt_against_schemas(p, schemas))
    for needle in ("required_input_missing", "frame_count: no such input", "links to missing node 99",
                   "has no output 7", "NoSuchNode does not exist"):
        assert needle in text, (needle, text)


def test_output_nodes_cycles_and_native_v3_widgets(schemas):
    p = _jelly()
    for nid in [n for n, v in p.items() if v["class_type"] in ("SaveVideo", "PhysMotionSaveGaussians")]:
        del p[nid]
    assert validate_prompt_against_schemas(p, schemas) == [
        "prompt_no_outputs: the prompt has no output node (e.g. SaveVideo)"]

    cyc = {"1": {"class_type": "ImageInvert", "inputs": {"image": ["2", 0]}},
           "2": {"class_type": "ImageInvert", "inputs": {"image": ["1", 0]}},
           "3": {"class_type": "PreviewImage", "inputs": {"images": ["2", 0]}}}
    assert any("cycle" in e for e in validate_prompt_against_schemas(cyc, schemas))

    # V3 nodes: COMBO + options, FLOAT range, a link of the right type.
    video = {"1": {"class_type": "LoadImage", "inputs": {"image": "physmotion_coffee.png"}},
             "2": {"class_type": "CreateVideo", "inputs": {"images": ["1", 0], "fps": 24.0}},
             "3": {"class_type": "SaveVideo", "inputs": {"video": ["2", 0], "filename_prefix": "x",
                                                         "format": "auto", "codec": "h264"}}}
    assert validate_prompt_against_schemas(video, schemas) == []
    bad = copy.deepcopy(video)
    bad["3"]["inputs"]["codec"] = "vp9"
    bad["2"]["inputs"]["fps"] = 500.0
    bad["3"]["inputs"]["video"] = ["1", 0]
    text = "\n".join(validate_prompt_against_schemas(bad, schemas))
    assert "value_not_in_list: 'vp9'" in text and "value_bigger_than_max" in text
    assert "received_type(IMAGE) mismatch input_type(VIDEO)" in text

    # INT step (TripoSplat Preprocess: size step 16 from min 256) and model-file dropdowns.
    tp = {"1": {"class_type": "LoadImage", "inputs": {"image": "physmotion_coffee.png"}},
          "2": {"class_type": "TripoSplatPreprocessImage",
                "inputs": {"image": ["1", 0], "mask": ["1", 1], "erode_radius": 1, "size": 1000}},
          "3": {"class_type": "PreviewImage", "inputs": {"images": ["2", 0]}},
          "4": {"class_type": "CLIPVisionLoader", "inputs": {"clip_name": "dino_v3_vit_h.safetensors"}}}
    errs = validate_prompt_against_schemas(tp, schemas)
    assert len(errs) == 2 and "value_not_on_step" in errs[0] and "value_not_in_list" in errs[1], errs
    tp["2"]["inputs"]["size"] = 1024
    assert validate_prompt_against_schemas(tp, schemas, TEMPLATE_MODEL_FILES) == []


def test_link_type_rules_follow_comfyui():
    assert types_compatible("IMAGE", "IMAGE")
    assert not types_compatible("IMAGE", "MASK")
    assert types_compatible("*", "IMAGE") and types_compatible("IMAGE", "*")
    assert types_compatible("GAUSSIAN", "PM_GAUSSIANS,SPLAT,GAUSSIAN")  # a union takes any of its members
    assert types_compatible("SPLAT", "PM_GAUSSIANS,SPLAT,GAUSSIAN")
    assert types_compatible("PM_GAUSSIANS", "PM_GAUSSIANS,SPLAT,GAUSSIAN")
    assert types_compatible("STRING,INT", "INT,FLOAT")  # non-strict: one shared type is enough
    assert not types_compatible("SPLAT", "PM_GAUSSIANS,GAUSSIAN")
    assert types_compatible("COMBO", ["a", "b"]) and not types_compatible("STRING", ["a", "b"])


def _chain(prompt, start_cls, end_cls):
    """Class names along a path of links from the node of ``start_cls`` to the node of ``end_cls``."""
    def path(nid):
        if prompt[nid]["class_type"] == start_cls:
            return [start_cls]
        for v in prompt[nid]["inputs"].values():
            if isinstance(v, list):
                found = path(v[0])
                if found:
                    return found + [prompt[nid]["class_type"]]
        return None

    return path(_find(prompt, end_cls))


def test_native_3d_templates_go_native_3d_to_physics_to_native_video():
    api = ROOT / "example_workflows" / "api"
    tp = json.loads((api / "triposplat_to_physics.json").read_text())
    assert _chain(tp, "VAEDecodeTripoSplat", "SaveVideo") == [
        "VAEDecodeTripoSplat", "PhysMotionFitGaussiansToPhoto", "PhysMotionMPMSimulate", "PhysMotionRender",
        "PhysMotionBlend", "CreateVideo", "SaveVideo"]
    assert _chain(tp, "LoadImage", "VAEDecodeTripoSplat") == [
        "LoadImage", "TripoSplatPreprocessImage", "TripoSplatConditioning", "KSampler", "VAEDecodeTripoSplat"]
    fit = tp[_find(tp, "PhysMotionFitGaussiansToPhoto")]["inputs"]
    # The photo and the object's mask the fit lines the splat up with are the ones the scene uses.
    assert fit["image"] == ["1", 0] and tp[fit["mask"][0]]["class_type"] == "PhysMotionSegment"
    sim = tp[_find(tp, "PhysMotionMPMSimulate")]["inputs"]
    assert sim["camera"] == [_find(tp, "PhysMotionFitGaussiansToPhoto"), 1]

    own = json.loads((api / "own_splat_to_physics.json").read_text())
    assert _chain(own, "PhysMotionLoadGaussians", "SaveVideo") == [
        "PhysMotionLoadGaussians", "PhysMotionFitGaussiansToPhoto", "PhysMotionMPMSimulate", "PhysMotionRender",
        "PhysMotionBlend", "CreateVideo", "SaveVideo"]
    # The schemas say the TripoSplat decode's SPLAT may feed the Fit: the link type check is real.
    bad = copy.deepcopy(tp)
    bad[_find(tp, "PhysMotionFitGaussiansToPhoto")]["inputs"]["gaussians"] = [_find(tp, "KSampler"), 0]
    errs = validate_prompt_against_schemas(bad, all_schemas(), TEMPLATE_MODEL_FILES)
    assert len(errs) == 1 and "received_type(LATENT)" in errs[0]
