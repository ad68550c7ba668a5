"""Node classes and shipped workflows, checked without ComfyUI (see comfy_harness)."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from comfy_harness import ROOT, input_spec, is_widget, load_pack, node_classes, prepare_template_inputs, run_prompt

from physmotion_core.video import read_video
from physmotion_core.comfy.workflow import api_to_ui, node_schemas, ui_to_api, validate_prompt_against_schemas

API_DIR = ROOT / "example_workflows" / "api"
API_WORKFLOWS = sorted(API_DIR.glob("*.json"))
LINK_TYPES_ANY = {"*"}


def _ours():
    return load_pack().NODE_CLASS_MAPPINGS


def test_pack_loads_every_node_module():
    pack = load_pack()
    assert pack.FAILED_MODULES == {}
    assert len(pack.NODE_CLASS_MAPPINGS) >= 12
    assert set(pack.NODE_CLASS_MAPPINGS) == set(pack.NODE_DISPLAY_NAME_MAPPINGS)
    assert pack.WEB_DIRECTORY == "./web"


@pytest.mark.parametrize("name", sorted(load_pack().NODE_CLASS_MAPPINGS))
def test_node_class_is_a_valid_classic_node(name):
    cls = _ours()[name]
    assert name.startswith("PhysMotion")
    assert cls.CATEGORY.startswith("PhysMotion/")
    assert callable(getattr(cls, cls.FUNCTION))
    types = cls.INPUT_TYPES()
    assert set(types) <= {"required", "optional", "hidden"}
    assert isinstance(cls.RETURN_TYPES, tuple)
    if hasattr(cls, "RETURN_NAMES"):
        assert len(cls.RETURN_NAMES) == len(cls.RETURN_TYPES)
    for rt in cls.RETURN_TYPES:
        assert rt in ("IMAGE", "MASK", "STRING", "INT", "FLOAT", "VIDEO") or rt.startswith("PM_"), rt
    for section in ("required", "optional"):
        for inp, spec in types.get(section, {}).items():
            assert isinstance(spec, tuple) and 1 <= len(spec) <= 2, (inp, spec)
            opts = spec[1] if len(spec) > 1 else {}
            assert opts.get("tooltip"), f"{name}.{inp} has no tooltip"
            kind = spec[0]
            if isinstance(kind, list):
                assert kind, f"{name}.{inp}: empty combo"
                if "default" in opts:
                    assert opts["default"] in kind
            elif kind in ("INT", "FLOAT"):
                lo, hi, d = opts.get("min", -np.inf), opts.get("max", np.inf), opts["default"]
                assert lo <= d <= hi, (name, inp, lo, d, hi)
                if kind == "INT":
                    assert isinstance(d, int)
            elif kind in ("STRING", "BOOLEAN"):
                assert "default" in opts
            else:
                assert kind in ("IMAGE", "MASK") or kind.startswith("PM_"), (name, inp, kind)


def _schemas():
    from comfy_schemas import all_schemas  # the real native schemas, as the frontend has them

    return all_schemas()


def _runs_in_process(path) -> bool:
    """Every node of the template is one the in-process harness has (the pack and its stand-ins for
    LoadImage / CreateVideo / SaveVideo); templates with newer upstream nodes (TripoSplat, File3D)
    are only checked against the schemas (tests/test_template_schemas.py)."""
    classes = node_classes()
    return all(n["class_type"] in classes for n in json.loads(Path(path).read_text()).values())


from comfy_harness import TEMPLATES_NOT_YET as NOT_YET  # noqa: E402 - templates that cannot run yet, and why
IN_PROCESS = [p for p in API_WORKFLOWS if _runs_in_process(p)]
IN_PROCESS_RUNS = [pytest.param(p, marks=pytest.mark.skip(reason=NOT_YET[p.stem])) if p.stem in NOT_YET else p
                   for p in IN_PROCESS]


@pytest.mark.parametrize("path", IN_PROCESS, ids=lambda p: p.stem)
def test_api_workflow_matches_the_node_classes(path):
    """The classes the harness runs (not only the captured schemas) accept every template it runs."""
    from comfy_schemas import TEMPLATE_MODEL_FILES

    prompt = json.loads(path.read_text())
    errors = validate_prompt_against_schemas(prompt, node_schemas(node_classes()), TEMPLATE_MODEL_FILES)
    assert errors == [], "\n".join(errors)
    for node in prompt.values():  # a literal on a link-only input would be passed through unchecked
        spec = input_spec(node_classes()[node["class_type"]])
        for name, value in node["inputs"].items():
            assert isinstance(value, list) or is_widget(spec[name]), (node["class_type"], name)


@pytest.mark.parametrize("path", API_WORKFLOWS, ids=lambda p: p.stem)
def test_ui_template_and_api_twin_describe_the_same_graph(path):
    ui_path = ROOT / "example_workflows" / path.name
    assert ui_path.exists(), f"no UI template for {path.name}: run scripts/build_workflows.py"
    assert ui_path.with_suffix(".jpg").exists(), f"no thumbnail for {ui_path.name}"
    api = json.loads(path.read_text())
    ui = json.loads(ui_path.read_text())
    assert ui_to_api(ui, _schemas()) == api
    # And the template is exactly what the generator makes from the API file (no hand edits).
    import importlib.util

    spec = importlib.util.spec_from_file_location("build_workflows", ROOT / "scripts" / "build_workflows.py")
    build = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(build)
    assert json.loads(json.dumps(build.build_ui(api, _schemas()))) == ui


def test_workflow_conversion_detects_a_changed_link():
    api = json.loads(API_WORKFLOWS[0].read_text())
    ui = api_to_ui(api, _schemas())
    ui["links"][0][2] = 1 - ui["links"][0][2] if ui["links"][0][2] in (0, 1) else 0
    assert ui_to_api(ui, _schemas()) != api


SMALL = {"3.max_gaussians": 6000, "7.frames": 8, "7.grid_res": 10, "12.filename_prefix": "test/push"}
TINY = {"PhysMotionSilhouetteLift.max_gaussians": 4000, "PhysMotionMPMSimulate.frames": 5,
        "PhysMotionMPMSimulate.grid_res": 8,
        # the learned front end on tiny random-weight models (see _learned_models below)
        "PhysMotionLGMLoader.input_size": 64, "PhysMotionLGMLift.steps": 2, "PhysMotionLGMLift.max_gaussians": 300,
        "PhysMotionMultiViewGenerate.steps": 2, "PhysMotionHardDepthRefine.iterations": 2,
        "PhysMotionHardDepthRefine.max_render_side": 128,
        # the enhancement on tiny random-weight SD 2.1 + ControlNets (tests/tiny_sd21.py)
        "PhysMotionLoRAPersonalize.steps": 2, "PhysMotionLoRAPersonalize.resolution": 64,
        "PhysMotionDDIMInvert.steps": 2, "PhysMotionDDIMInvert.resolution": 64, "PhysMotionDDIMInvert.refine_iterations": 0,
        # Fit Gaussians to Photo (the "your own splat" template) at its coarse levels only
        "PhysMotionFitGaussiansToPhoto.max_render_side": 96}
LEARNED_LOADERS = {"PhysMotionSAMLoader", "PhysMotionImageDreamLoader", "PhysMotionLGMLoader",
                   "PhysMotionDiffusionLoader"}


@pytest.fixture(scope="session")
def tiny_models_root(tmp_path_factory):
    from tiny_models import write_tiny_models_root

    from tiny_sd21 import build_tiny_models_root

    root = write_tiny_models_root(tmp_path_factory.mktemp("models"))
    build_tiny_models_root(root)  # SD 2.1 + depth/canny ControlNets under the template's names
    return root


@pytest.fixture(autouse=True)
def _learned_models(request, monkeypatch):
    """Workflows with learned loaders get $PHYSMOTION_MODELS = tiny random-weight models in the
    official file layout and names (tests/tiny_models.py): the loaders list and load them there."""
    callspec = getattr(request.node, "callspec", None)
    path = callspec.params.get("path") if callspec is not None else None
    if path is not None and any(n["class_type"] in LEARNED_LOADERS for n in json.loads(Path(path).read_text()).values()):
        monkeypatch.setenv("PHYSMOTION_MODELS", str(request.getfixturevalue("tiny_models_root")))


@pytest.mark.parametrize("path", IN_PROCESS_RUNS, ids=lambda p: p.stem)
def test_every_api_workflow_runs_in_process_at_a_small_size(path, tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    prompt = json.loads(path.read_text())
    prepare_template_inputs(prompt, tmp_path, max_gaussians=4000)  # "your own splat": a stand-in .ply
    out = run_prompt(prompt, class_overrides=TINY)
    # The templates save through ComfyUI's CreateVideo -> SaveVideo (the harness's stand-ins).
    savers = [nid for nid, n in prompt.items() if n["class_type"] == "SaveVideo"]
    assert savers and not any(n["class_type"] == "PhysMotionSaveVideo" for n in prompt.values())
    for saver in savers:
        create = prompt[saver]["inputs"]["video"][0]
        assert prompt[create]["class_type"] == "CreateVideo"
        frames = out["results"][prompt[create]["inputs"]["images"][0]][0]
        assert frames.shape[0] == 5 and bool(torch.isfinite(frames).all())
        # Something moves between the first and the last frame.
        assert float((frames[-1] - frames[0]).abs().mean()) > 1e-4
        item = out["ui"][saver]["images"][0]
        assert out["ui"][saver]["animated"] == (True,) and item["type"] == "output"
        video, fps = read_video(tmp_path / item["subfolder"] / item["filename"])
        assert video.shape[:3] == tuple(frames.shape[:3])
        assert fps == pytest.approx(prompt[create]["inputs"]["fps"])
        # The decoded clip is the frames (up to H.264 at its default quality).
        err = np.abs(video.astype(np.float32) / 255 - frames.numpy()).mean()
        assert err < 0.03, err


def test_push_a_jelly_runs_in_process(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    prompt = json.loads((API_DIR / "push_a_jelly.json").read_text())
    out = run_prompt(prompt, SMALL)
    frames = out["results"]["9"][0]
    assert frames.shape == (8, 400, 600, 3)
    assert float(frames.min()) >= 0 and float(frames.max()) <= 1
    # The object moves: consecutive frames differ, and by more than encoding noise.
    diffs = (frames[1:] - frames[:-1]).abs().mean(dim=(1, 2, 3))
    assert bool((diffs > 1e-4).all()), diffs
    # Frame 0 is the input photo where the object is (the render reproduces the foreground).
    mask = out["results"]["2"][1][0] > 0.5
    photo = out["results"]["1"][0][0]
    err = (frames[0][mask] - photo[mask]).abs().mean()
    assert float(err) < 0.05
    # Create Video -> Save Video wrote a playable mp4 with the prompt in its metadata (as ComfyUI's
    # SaveVideo embeds it) and previews it; the .ply went to the output folder.
    ui = out["ui"]["12"]
    assert ui["animated"] == (True,)
    video_path = tmp_path / ui["images"][0]["subfolder"] / ui["images"][0]["filename"]
    video, fps = read_video(video_path)
    assert video.shape == (8, 400, 600, 3) and fps == pytest.approx(24.0)
    import av

    with av.open(str(video_path)) as c:
        embedded = json.loads(c.metadata["prompt"])
    assert embedded["7"]["class_type"] == "PhysMotionMPMSimulate" and embedded["7"]["inputs"]["frames"] == 8
    ply = tmp_path / out["results"]["11"][0]
    assert ply.exists() and ply.stat().st_size > 1000


def test_segment_node_handles_loadimage_masks():
    from comfy_harness import LoadImage

    seg = node_classes()["PhysMotionSegment"]()
    image, _ = LoadImage().load_image("physmotion_coffee.png")
    h, w = image.shape[1:3]
    # An RGBA cut-out arrives as LoadImage's MASK = 1 - alpha: black on the object.
    obj = torch.zeros(1, h, w)
    obj[:, 100:300, 150:450] = 1.0
    out = seg.run(image, "auto", "auto", 5, mask=1.0 - obj)
    fg, mask, bg, overlay = out["result"]
    assert torch.equal(mask, obj)
    assert overlay.shape == (1, h, 2 * w, 3)  # the outline over the photo | the filled background
    assert out["ui"]["images"][0]["type"] == "temp"  # the overlay, shown in the node
    # A uniform 64x64 mask (no alpha) means "no mask": GrabCut runs instead.
    fg, mask, bg, _ = seg.run(image, "auto", "auto", 5, mask=torch.zeros(1, 64, 64))["result"]
    assert mask.shape == (1, h, w) and 0.2 < float(mask.mean()) < 0.8
    with pytest.raises(ValueError, match="no mask"):
        seg.run(image, "mask", "auto", 5)


def test_output_paths_never_leave_the_output_folder(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    save = node_classes()["PhysMotionSaveVideo"]()
    with pytest.raises(ValueError, match="outside the output folder"):
        save.run(torch.zeros(2, 8, 8, 3), 24.0, "../../escape", 18)
    first = save.run(torch.zeros(2, 8, 8, 3), 24.0, "clips/a", 18)["result"][0]
    second = save.run(torch.zeros(2, 8, 8, 3), 24.0, "clips/a", 18)["result"][0]
    assert Path(first).parent == tmp_path / "clips" and first != second


def test_save_video_also_returns_a_video_the_native_nodes_take(tmp_path, monkeypatch):
    """PhysMotion Save Video's second output is a VIDEO: outside ComfyUI the library's VideoFile, with
    ComfyUI's comfy_api its VideoFromFile; the native SaveVideo (stand-in) re-saves it unchanged."""
    import sys
    import types

    from comfy_harness import SaveVideo

    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    t = torch.linspace(0, 1, 6)[:, None, None, None]
    frames = (torch.ones(6, 32, 48, 3) * t).clamp(0, 1)  # a fade from black to white
    cls = node_classes()["PhysMotionSaveVideo"]
    assert cls.RETURN_TYPES == ("STRING", "VIDEO")
    path, video = cls().run(frames, 12.0, "clips/fade", 18)["result"]
    assert Path(video.get_stream_source()) == Path(path)
    comp = video.get_components()
    assert tuple(comp.images.shape) == (6, 32, 48, 3) and comp.frame_rate == 12
    assert float(comp.images[0].mean()) < 0.05 and float(comp.images[-1].mean()) > 0.95
    assert video.get_dimensions() == (48, 32)
    ui = SaveVideo().run(video, "clips/again", "auto", "auto", prompt={"1": {"class_type": "X", "inputs": {}}})["ui"]
    again = tmp_path / ui["images"][0]["subfolder"] / ui["images"][0]["filename"]
    assert np.array_equal(read_video(again)[0], read_video(path)[0])  # a stream copy, not a re-encode
    import av

    with av.open(str(again)) as c:
        assert json.loads(c.metadata["prompt"])["1"]["class_type"] == "X"
    with pytest.raises(ValueError, match="not converted"):
        video.save_to(tmp_path / "x.webm", format="webm")

    # Inside ComfyUI the node hands over comfy_api's own class.
    class VideoFromFile:
        def __init__(self, file):
            self.file = file

    latest = types.ModuleType("comfy_api.latest")
    latest.InputImpl = types.SimpleNamespace(VideoFromFile=VideoFromFile)
    monkeypatch.setitem(sys.modules, "comfy_api", types.ModuleType("comfy_api"))
    monkeypatch.setitem(sys.modules, "comfy_api.latest", latest)
    path, video = cls().run(frames, 12.0, "clips/fade", 18)["result"]
    assert isinstance(video, VideoFromFile) and video.file == path


def test_video_previews_are_the_area_shrunk_clip(tmp_path, monkeypatch):
    """A node's preview clip: the frames shrunk to PREVIEW_MAX_SIDE by area averaging, clamped to 0..1 (what
    OpenCV's INTER_AREA gives for the clamped full-size frames, as the clip holds values in 0..1), encoded at 8 bits;
    a (T,H,W) mask is previewed grey; NaN frames are refused with the reason."""
    import cv2

    from physmotion_core.errors import InputError

    util = sys.modules[load_pack().__name__ + ".nodes._util"]
    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path))
    monkeypatch.setattr(util, "temp_directory", lambda: tmp_path)
    t, h, w = 4, 300, 640
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    frames = torch.stack([torch.stack([xx, yy, (xx + yy + 0.2 * i) % 1.0], -1) for i in range(t)])
    frames[:, 100:140, 200:260] = torch.tensor([1.0, 0.0, 0.0])  # a red block with sharp edges
    want = np.stack([cv2.resize(f.numpy(), (512, 240), interpolation=cv2.INTER_AREA) for f in frames])
    ui = util.preview_video(frames, 8.0, "test")
    video, _ = read_video(tmp_path / ui["images"][0]["filename"])
    assert video.shape == (t, 240, 512, 3)
    assert float(np.abs(video / 255.0 - want).mean()) < 0.02
    mask = (frames[..., 0] > 0.99).float()  # the block (and the right edge of the ramp)
    ui = util.preview_video(mask, 8.0, "mask")
    grey, _ = read_video(tmp_path / ui["images"][0]["filename"])
    want_mask = np.stack([cv2.resize(m.numpy(), (512, 240), interpolation=cv2.INTER_AREA) for m in mask])
    assert float(np.abs(grey.mean(-1) / 255.0 - want_mask).mean()) < 0.02
    assert np.abs(grey[..., 0].astype(int) - grey[..., 2].astype(int)).max() <= 6  # grey: equal channels
    frames[1, 5, 5, 1] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        util.preview_video(frames, 8.0, "bad")


def _two_objects():
    """A red disk (left) and a blue square (right) on a grey table: (1, H, W, 3)."""
    import numpy as np

    rng = np.random.default_rng(0)
    H, W = 96, 160
    img = 0.5 + 0.03 * rng.standard_normal((H, W, 3))
    yy, xx = np.mgrid[:H, :W]
    red = (xx - 45) ** 2 + (yy - 48) ** 2 <= 20 ** 2
    blue = (abs(xx - 115) <= 18) & (abs(yy - 48) <= 18)
    img[red] = (0.85, 0.1, 0.1)
    img[blue] = (0.1, 0.15, 0.85)
    return torch.from_numpy(np.clip(img, 0, 1).astype(np.float32))[None], red, blue


def test_segment_node_prompts_pick_the_object_clicked_or_boxed():
    seg = node_classes()["PhysMotionSegment"]()
    image, red, blue = _two_objects()
    for kw, want in (({"object_points": "115, 48"}, blue), ({"object_points": "45,48"}, red),
                     ({"box": "20, 22, 70, 74"}, red),
                     ({"object_points": "45, 48", "background_points": "115, 48"}, red)):
        m = seg.run(image, "auto", "auto", 5, **kw)["result"][1][0].numpy() > 0.5
        assert (m & want).sum() / (m | want).sum() > 0.85, kw


@pytest.mark.parametrize("kw, words", [({"object_points": "12"}, "x, y"), ({"box": "1, 2, 3"}, "4 numbers"),
                                       ({"object_points": "500, 10"}, "outside"),
                                       ({"background_points": "5, 5"}, "Only background points")])
def test_segment_node_bad_prompts_say_what_to_write(kw, words):
    seg = node_classes()["PhysMotionSegment"]()
    image, _, _ = _two_objects()
    with pytest.raises(ValueError, match=words):
        seg.run(image, "auto", "auto", 5, **kw)


def test_segment_node_refuses_an_implausible_automatic_mask_and_names_the_overlay(monkeypatch, caplog):
    import logging

    import numpy as np

    import physmotion_core.segment as segpkg

    real = segpkg.segment

    def table(img, **kw):  # GrabCut's automatic pass replaced by one that takes the table
        m = np.ones(img.shape[:2], np.float32)
        m[30:70, 40:90] = 0
        return real(img, mask=torch.from_numpy(m), method="mask")

    monkeypatch.setattr(segpkg, "segment", table)
    seg = node_classes()["PhysMotionSegment"]()
    image, _, _ = _two_objects()
    with pytest.raises(ValueError) as exc:
        seg.run(image, "auto", "auto", 5)
    msg = str(exc.value)
    assert "PhysMotion_segment" in msg and ".png" in msg  # the overlay file in the temp folder
    assert "object_points" in msg and "MASK" in msg
    # The same mask with a prompt is only warned about, with what to change for that prompt.
    def hints():
        return [r.getMessage() for r in caplog.records if "If the outline is not the object" in r.getMessage()]

    with caplog.at_level(logging.WARNING, logger="physmotion"):
        out = seg.run(image, "auto", "auto", 5, box="0, 0, 160, 96")
        assert out["result"][1].shape == (1, 96, 160)
        (h,) = hints()
        assert "move the box's sides" in h and "background_points" in h and "PhysMotion_segment" in h
        caplog.clear()
        seg.run(image, "auto", "auto", 5, object_points="45, 48")
        (h,) = hints()
        assert "drag a box around the whole object" in h and "surer prompt" in h
        caplog.clear()
        m = np.ones((96, 160), np.float32)
        m[30:70, 40:90] = 0
        seg.run(image, "mask", "auto", 5, mask=torch.from_numpy(m)[None])  # the user's own mask: no advice
        assert any("edges of the frame" in r.getMessage() for r in caplog.records) and hints() == []


def test_segment_node_shows_grabcuts_progress_and_honours_cancel(monkeypatch):
    """The no-model Segment node drives ComfyUI's progress bar through GrabCut (a click at 1024 px takes
    seconds) and Cancel stops it (a stand-in comfy package: tests/fake_comfy.py)."""
    from fake_comfy import InterruptProcessingException, install_fake_comfy

    state = install_fake_comfy(monkeypatch)
    seg = node_classes()["PhysMotionSegment"]()
    image, red, blue = _two_objects()
    m = seg.run(image, "auto", "auto", 5, object_points="115, 48")["result"][1][0].numpy() > 0.5
    assert (m & blue).sum() / (m | blue).sum() > 0.85
    values = [v for v, _ in state.updates]
    assert len(values) >= 6 and values == sorted(values) and state.updates[-1] == (100, 100)
    state.updates.clear()
    state.cancel_after = state.checks + 3
    with pytest.raises(InterruptProcessingException):
        seg.run(image, "auto", "auto", 5, object_points="45, 48")
    assert state.checks == state.cancel_after + 1 and state.updates[-1][0] < 100


def _segment_node_and_its_picture(tmp_path, monkeypatch):
    """The no-model Segment node with its previews written to ``tmp_path``, and a reader of the picture a
    run's UI result shows."""
    import cv2

    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path))

    def picture(out):
        (item,) = out["ui"]["images"]
        return cv2.imread(str(tmp_path / item["filename"]))

    return node_classes()["PhysMotionSegment"](), picture


def test_segment_nodes_picture_is_captioned_for_an_automatic_pick_and_its_image_output_is_not(tmp_path, monkeypatch):
    import cv2

    seg, picture = _segment_node_and_its_picture(tmp_path, monkeypatch)
    image, red, blue = _two_objects()
    H, W = image.shape[1:3]

    out = seg.run(image, "auto", "auto", 5, object_points="115, 48")
    assert picture(out).shape[:2] == (H, 2 * W) and out["result"][3].shape == (1, H, 2 * W, 3)
    before = set(tmp_path.glob("PhysMotion_segment_*.png"))
    try:
        out = seg.run(image, "auto", "auto", 5)
    except ValueError:  # refused: the picture was still written, with the caption
        (path,) = set(tmp_path.glob("PhysMotion_segment_*.png")) - before
        shown = cv2.imread(str(path))
    else:
        shown = picture(out)
        assert out["result"][3].shape == (1, H, 2 * W, 3)  # the IMAGE output: the plain overlay
    bar = shown[: shown.shape[0] - H]
    assert shown.shape[1] == 2 * W and bar.shape[0] >= 15 and (bar > 200).any() and np.median(bar) < 40


def test_segment_node_says_when_a_connected_mask_overrides_the_picks(tmp_path, monkeypatch, caplog):
    """An RGBA photo's alpha reaches the Segment node as a MASK (the templates connect Load Image's MASK), and
    a connected mask wins: points or a box clicked on the node would do nothing, silently. The node warns and
    its picture gets a caption saying so; without picks, or with method 'grabcut', it says nothing."""
    import torch

    seg, picture = _segment_node_and_its_picture(tmp_path, monkeypatch)
    image, red, blue = _two_objects()
    H, W = image.shape[1:3]
    alpha = torch.from_numpy(red.astype(np.float32))[None]  # ComfyUI's MASK: (1, H, W)

    with caplog.at_level("WARNING"):
        out = seg.run(image, "auto", "auto", 5, mask=alpha, box="90, 20, 140, 80")
    m = out["result"][1][0].numpy() > 0.5
    assert (m == red).mean() > 0.99  # the mask, not the box, made the object
    assert "points and box were not used" in caplog.text and "method to 'grabcut'" in caplog.text
    shown = picture(out)
    assert shown.shape[0] - H >= 15 and (shown[: shown.shape[0] - H] > 200).any()  # a caption bar
    caplog.clear()
    with caplog.at_level("WARNING"):
        plain = seg.run(image, "auto", "auto", 5, mask=alpha)
        forced = seg.run(image, "grabcut", "auto", 5, mask=alpha, object_points="115, 48")
    assert "not used" not in caplog.text
    assert picture(plain).shape[0] == H  # no caption: the mask was given, and it looks like one object
    fm = forced["result"][1][0].numpy() > 0.5
    assert (fm & blue).sum() / (fm | blue).sum() > 0.85  # 'grabcut' cuts by the click


def test_segment_node_names_a_box_that_reaches_past_the_photo(tmp_path, monkeypatch, caplog):
    """The template's coffee box (55, 6, 498, 395) on a smaller photo: cut to the photo and used, with a warning
    and a caption on the node's picture; a box inside the photo gets neither."""
    seg, picture = _segment_node_and_its_picture(tmp_path, monkeypatch)
    image, red, blue = _two_objects()
    H, W = image.shape[1:3]

    with caplog.at_level("WARNING"):
        out = seg.run(image, "auto", "auto", 5, box=f"90, 20, {W + 40}, 76")
    assert f"reaches past the {W}x{H} photo (right by 40 px)" in caplog.text
    assert picture(out).shape[0] > H  # the caption bar
    m = out["result"][1][0].numpy() > 0.5
    assert (m & blue).sum() / (m | blue).sum() > 0.8  # the box, cut to the photo, still found the square
    caplog.clear()
    with caplog.at_level("WARNING"):
        seg.run(image, "auto", "auto", 5, box="90, 20, 145, 76")
    assert "reaches past" not in caplog.text
