"""The contract EVERY node in NODE_CLASS_MAPPINGS keeps (ours and any added later): ids, display
names, `PhysMotion/<stage>` categories, `PM_` custom types, a tooltip on every input, defaults inside
their ranges, a run function that takes exactly the declared inputs, output tooltips that match the
outputs; and progress + Cancel wired through ComfyUI's own hooks in the long-running nodes.
"""

from __future__ import annotations

import inspect
import re
import sys
import threading
import time

import numpy as np
import pytest
import torch

from comfy_harness import load_pack

PACK = load_pack()
NODES = PACK.NODE_CLASS_MAPPINGS
CORE_TYPES = {"IMAGE", "MASK", "STRING", "INT", "FLOAT", "BOOLEAN", "LATENT", "CONDITIONING", "MODEL", "VAE",
              "CLIP", "VIDEO"}
WIDGET_TYPES = {"INT", "FLOAT", "STRING", "BOOLEAN"}
#: ComfyUI's own types that a PM_ input may also take, as a comma-separated union ("PM_GAUSSIANS,SPLAT,GAUSSIAN")
NATIVE_UNION_TYPES = {"GAUSSIAN", "SPLAT"}


def _link_type_ok(kind: str) -> bool:
    """A core type, a PM_* type, or a union "PM_X,NATIVE" (no spaces: the front end does not trim)."""
    if kind in CORE_TYPES or re.fullmatch(r"PM_[A-Z0-9_]+", kind):
        return True
    parts = kind.split(",")
    return (len(parts) > 1 and re.fullmatch(r"PM_[A-Z0-9_]+", parts[0]) is not None
            and all(p in NATIVE_UNION_TYPES for p in parts[1:]))
CATEGORY_RE = re.compile(r"^PhysMotion/[a-z0-9_]+(/[a-z0-9_]+)?$")


def _inputs(cls):
    t = cls.INPUT_TYPES()
    return t.get("required", {}), t.get("optional", {}), t.get("hidden", {})


def _all_types():
    out = set()
    for cls in NODES.values():
        req, opt, _ = _inputs(cls)
        out |= {t for s in {**req, **opt}.values() if isinstance(s[0], str) for t in s[0].split(",")}
        out |= set(cls.RETURN_TYPES)
    return out


@pytest.mark.parametrize("name", sorted(NODES))
def test_node_identity_category_and_types(name):
    cls = NODES[name]
    assert re.fullmatch(r"PhysMotion[A-Z][A-Za-z0-9]+", name), f"{name}: ids are PhysMotion<CamelCase>"
    display = PACK.NODE_DISPLAY_NAME_MAPPINGS.get(name, "")
    assert display.startswith("PhysMotion "), f"{name}: display name '{display}' must start with 'PhysMotion '"
    assert CATEGORY_RE.match(cls.CATEGORY), f"{name}: category '{cls.CATEGORY}' is not PhysMotion/<stage>"
    assert isinstance(cls.FUNCTION, str) and callable(getattr(cls, cls.FUNCTION, None)), name
    assert isinstance(cls.RETURN_TYPES, tuple), name
    for t in cls.RETURN_TYPES:
        assert t in CORE_TYPES or re.fullmatch(r"PM_[A-Z0-9_]+", t), f"{name}: output type {t} (custom types are PM_*)"
    names = getattr(cls, "RETURN_NAMES", None)
    if names is not None:
        assert len(names) == len(cls.RETURN_TYPES), name
    tips = getattr(cls, "OUTPUT_TOOLTIPS", None)
    if tips is not None:
        assert len(tips) == len(cls.RETURN_TYPES) and all(isinstance(t, str) and t for t in tips), name
    assert cls.RETURN_TYPES or getattr(cls, "OUTPUT_NODE", False), f"{name}: no outputs and not an output node"


@pytest.mark.parametrize("name", sorted(NODES))
def test_every_input_has_a_tooltip_a_valid_default_and_a_range(name):
    cls = NODES[name]
    req, opt, hidden = _inputs(cls)
    assert not set(req) & set(opt), name
    for inp, spec in {**req, **opt}.items():
        assert isinstance(spec, tuple) and 1 <= len(spec) <= 2, (name, inp, spec)
        opts = spec[1] if len(spec) > 1 else {}
        tip = opts.get("tooltip", "")
        assert isinstance(tip, str) and len(tip) >= 8, f"{name}.{inp}: no (useful) tooltip"
        kind = spec[0]
        if isinstance(kind, (list, tuple)):
            assert kind and len(set(map(str, kind))) == len(kind), f"{name}.{inp}: empty or repeated choices"
            if "default" in opts:
                assert opts["default"] in kind, (name, inp, opts["default"])
        elif kind in ("INT", "FLOAT"):
            assert {"default", "min", "max"} <= set(opts), f"{name}.{inp}: numbers need default, min and max"
            assert opts["min"] <= opts["default"] <= opts["max"], (name, inp, opts)
            if kind == "INT":
                assert all(isinstance(opts[k], int) and not isinstance(opts[k], bool)
                           for k in ("default", "min", "max")), f"{name}.{inp}: INT bounds must be ints"
            if "step" in opts:
                assert opts["step"] > 0, (name, inp)
        elif kind == "BOOLEAN":
            assert isinstance(opts.get("default"), bool), f"{name}.{inp}: BOOLEAN needs a bool default"
        elif kind == "STRING":
            assert isinstance(opts.get("default"), str), f"{name}.{inp}: STRING needs a default"
        else:
            assert _link_type_ok(kind), f"{name}.{inp}: type {kind}"
            assert "default" not in opts, f"{name}.{inp}: a link input has no default"


@pytest.mark.parametrize("name", sorted(NODES))
def test_the_run_function_takes_exactly_the_declared_inputs(name):
    cls = NODES[name]
    req, opt, hidden = _inputs(cls)
    sig = inspect.signature(getattr(cls, cls.FUNCTION))
    params = {k: p for k, p in sig.parameters.items() if k != "self"}
    var_kw = any(p.kind is p.VAR_KEYWORD for p in params.values())
    for inp in req:
        assert inp in params or var_kw, f"{name}.{cls.FUNCTION} does not take required input '{inp}'"
    for inp in opt:
        if inp in params:
            assert params[inp].default is not inspect.Parameter.empty, \
                f"{name}.{cls.FUNCTION}: optional input '{inp}' needs a default (ComfyUI omits unconnected ones)"
        else:
            assert var_kw, f"{name}.{cls.FUNCTION} does not take optional input '{inp}'"
    declared = set(req) | set(opt) | set(hidden)
    for k, p in params.items():
        if p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL):
            continue
        assert k in declared or p.default is not inspect.Parameter.empty, \
            f"{name}.{cls.FUNCTION}: parameter '{k}' is no input and has no default"


def test_every_custom_type_is_produced_by_some_node():
    produced = {t for cls in NODES.values() for t in cls.RETURN_TYPES}
    for t in sorted(x for x in _all_types() if x.startswith("PM_")):
        assert t in produced, f"{t} is consumed but no node outputs it"


def test_pack_loads_without_gsplat(monkeypatch):
    """gsplat is optional: an ImportError (missing or a CUDA build that failed) must cost nothing
    but the CUDA rasterizer, never the pack or a node."""
    import builtins
    import importlib

    real_import = builtins.__import__

    def no_gsplat(name, *args, **kwargs):
        if name == "gsplat" or name.startswith("gsplat."):
            raise ImportError("simulated: gsplat failed to build its CUDA kernels")
        return real_import(name, *args, **kwargs)

    saved = {k: v for k, v in sys.modules.items() if k == "physmotion_pack_nogsplat" or k.startswith(
        ("physmotion_pack_nogsplat.", "gsplat"))}
    for k in saved:
        monkeypatch.delitem(sys.modules, k)
    monkeypatch.setattr(builtins, "__import__", no_gsplat)
    for mod in [m for m in sys.modules if m.startswith("physmotion_core.render")]:
        monkeypatch.delitem(sys.modules, mod)
    pack = load_pack("physmotion_pack_nogsplat")
    try:
        assert pack.FAILED_MODULES == {}
        assert set(pack.NODE_CLASS_MAPPINGS) == set(NODES)
        render = importlib.import_module("physmotion_core.render.rasterize")
        assert render.gsplat_available() is False  # the failed import was caught, not raised
        from physmotion_core.types import Camera, Gaussians

        g = Gaussians.from_rgb(torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.2, 0.1]]),
                               torch.full((1, 3), 0.05), torch.tensor([0.9]))
        cam = Camera.look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), fov_y_deg=40.0, width=32, height=32)
        for backend in ("auto", "gsplat"):  # even asked for by name, it falls back (with a warning)
            out = render.rasterize(g, cam, backend=backend)
            assert out.backend == "warp"  # our rasterizer's CPU path (no gradient asked)
            assert out.rgb.shape == (32, 32, 3) and float(out.alpha.max()) > 0.5
    finally:
        sys.modules.pop("physmotion_pack_nogsplat", None)


# ------------------------------------------------------------------------------------------------
# Progress and Cancel through ComfyUI's hooks (a stand-in `comfy` package with the same API).
# ------------------------------------------------------------------------------------------------

from fake_comfy import InterruptProcessingException, install_fake_comfy  # noqa: E402


@pytest.fixture
def fake_comfy(monkeypatch):
    return install_fake_comfy(monkeypatch)


def _block(n=6):
    from physmotion_core.types import Gaussians

    axes = [torch.linspace(-0.05, 0.05, n)] * 3
    g = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    g[:, 1] += 0.06
    return Gaussians.from_rgb(g, torch.rand(len(g), 3), torch.full((len(g), 3), 0.01), torch.full((len(g),), 0.9))


def _simulate(frames, grid_res=8):
    from physmotion_core.types import Material

    return NODES["PhysMotionMPMSimulate"]().run(_block(), Material.preset("jelly"), frames, 24.0, "standard",
                                                grid_res, 8, 0.4, 1.0, "cpu", 0)


def test_simulate_reports_progress_to_comfyui(fake_comfy):
    (sim,) = _simulate(6)
    assert sim.num_frames == 6
    # by the simulated time: PROGRESS_PER_FRAME steps a frame, 5 frames after frame 0
    import importlib

    per = importlib.import_module("physmotion_core.sim.simulate").PROGRESS_PER_FRAME
    assert fake_comfy.updates and all(t == 5 * per for _, t in fake_comfy.updates)
    assert fake_comfy.updates[-1] == (5 * per, 5 * per)
    assert [v for v, _ in fake_comfy.updates] == sorted(v for v, _ in fake_comfy.updates)


def test_cancel_stops_a_simulation_with_slow_substeps_within_a_second(fake_comfy, monkeypatch):
    """Each substep made slow (40 ms, like a large grid on a CPU): Cancel must still act within a
    second, i.e. the loop checks for it between substeps, not once per frame or per 64 substeps."""
    from physmotion_core.sim import mpm

    real = mpm.MPMSolver.substep

    def slow(self, *a, **k):
        time.sleep(0.04)
        return real(self, *a, **k)

    monkeypatch.setattr(mpm.MPMSolver, "substep", slow)

    def cancel_later():
        time.sleep(1.5)
        fake_comfy.asked_at = time.monotonic()
        fake_comfy.interrupt = True

    threading.Thread(target=cancel_later, daemon=True).start()
    t0 = time.monotonic()
    with pytest.raises(InterruptProcessingException):
        _simulate(2000)
    latency = fake_comfy.raised_at - fake_comfy.asked_at
    assert latency < 1.0, f"Cancel took {latency:.2f}s"
    assert time.monotonic() - t0 < 10


def test_render_reports_every_frame_and_cancels(fake_comfy, tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    from physmotion_core.types import Camera

    (sim,) = _simulate(4)
    cam = Camera.look_at((0.0, 0.06, 0.5), (0.0, 0.06, 0.0), fov_y_deg=40.0, width=48, height=32)
    fake_comfy.updates.clear()
    out = NODES["PhysMotionRender"]().run(sim, cam, 0, 0)
    assert [v for v, _ in fake_comfy.updates] == [1, 2, 3, 4]
    rgb, alpha, depth = out["result"]
    assert rgb.shape == (4, 32, 48, 3)
    # The preview is a clip in the temp folder, in ComfyUI's own format for animated previews.
    ui = out["ui"]
    assert ui["animated"] == (True,) and ui["images"][0]["type"] == "temp"
    from physmotion_core.video import read_video

    clip, _ = read_video(tmp_path / ".previews" / ui["images"][0]["filename"])
    assert clip.shape[:3] == (4, 32, 48)
    fake_comfy.interrupt = True
    with pytest.raises(InterruptProcessingException):
        NODES["PhysMotionRender"]().run(sim, cam, 0, 0)


def test_blend_preview_and_input_errors(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    from physmotion_core.errors import InputError

    blend = NODES["PhysMotionBlend"]()
    rgb = torch.zeros(3, 16, 20, 3)
    alpha = torch.zeros(3, 16, 20)
    alpha[:, 4:12, 5:15] = 1.0
    rgb[:, 4:12, 5:15] = torch.tensor([1.0, 0.0, 0.0])
    bg = torch.full((1, 16, 20, 3), 0.5)
    out = blend.run(rgb, alpha, bg, fps=12.0)
    frames = out["result"][0]
    assert torch.allclose(frames[0, 8, 10], torch.tensor([1.0, 0.0, 0.0]))
    assert torch.allclose(frames[0, 0, 0], torch.tensor([0.5, 0.5, 0.5]))
    from physmotion_core.video import read_video

    clip, fps = read_video(tmp_path / ".previews" / out["ui"]["images"][0]["filename"])
    assert clip.shape[0] == 3 and fps == pytest.approx(12.0)
    with pytest.raises(InputError, match="alpha output of the same"):
        blend.run(rgb, alpha[:2], bg)
    with pytest.raises(InputError, match="one background image or one per frame"):
        blend.run(rgb, alpha, bg.expand(2, -1, -1, -1))


def test_refine_saves_the_gaussians_as_ply_for_preview3d(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    from physmotion_core.lift import silhouette_lift
    from physmotion_core.ply import read_ply

    H, W = 40, 48
    yy, xx = np.mgrid[:H, :W]
    mask = ((xx - 24) ** 2 / 200 + (yy - 20) ** 2 / 150 < 1).astype(np.float32)
    img = np.where(mask[..., None] > 0, [0.8, 0.3, 0.2], [0.2, 0.4, 0.6]).astype(np.float32)
    lift = silhouette_lift(img, mask, max_gaussians=800, fit_colors=False)
    out = NODES["PhysMotionHardDepthRefine"]().run(lift.gaussians, lift.camera, torch.from_numpy(img)[None],
                                                  torch.from_numpy(mask)[None], 3, 2, 1e-3, False, 64, 0.0, 0,
                                                  filename_prefix="refined/test")
    g, preview, ply = out["result"]
    assert ply.startswith("refined/test_") and ply.endswith(".ply")
    back = read_ply(tmp_path / ply)
    assert len(back) == len(g)
    assert torch.allclose(back.means, g.means.float(), atol=1e-6)
    assert out["ui"]["text"] == [ply] and out["ui"]["images"][0]["type"] == "temp"


def test_simulate_shows_its_forecast_on_the_node_before_the_wait_and_its_warnings_after(fake_comfy):
    """In ComfyUI the console is out of sight: the forecast (mass, material, what each push does) goes onto the
    node itself (PromptServer.send_progress_text, as the core Get Image Size node does) once the objects are
    filled, before the frames; after the run the text is sent again (with the after-run warnings when the node
    has the camera)."""
    from physmotion_core.types import Material

    (sim,) = NODES["PhysMotionMPMSimulate"]().run(_block(), Material.preset("jelly"), 6, 24.0, "standard", 8, 8,
                                                  0.4, 1.0, "cpu", 0, unique_id="17")
    assert [n for n, _, _ in fake_comfy.texts] == ["17", "17"]
    (_, first, updates_before), (_, last, _) = fake_comfy.texts
    assert first.startswith("object: jelly") and "kg" in first
    assert updates_before <= 1 < len(fake_comfy.updates)  # shown before the frames were simulated
    assert last.startswith(first) and "nothing moved" not in first
    # without the node's id (outside ComfyUI's executor) nothing is sent
    NODES["PhysMotionMPMSimulate"]().run(_block(), Material.preset("jelly"), 3, 24.0, "standard", 8, 8, 0.4, 1.0,
                                         "cpu", 0)
    assert len(fake_comfy.texts) == 2


def test_simulate_puts_a_slow_runs_pace_on_the_node_while_it_runs(fake_comfy, monkeypatch):
    """A run whose first seconds say it takes minutes says so on the node as well as in the console: a third
    text, between the forecast and the final one, with what sets the step (thresholds set to 0 here)."""
    import importlib

    from physmotion_core.types import Material

    S = importlib.import_module("physmotion_core.sim.simulate")
    monkeypatch.setattr(S, "PACE_CHECK_S", 0.0)
    monkeypatch.setattr(S, "PACE_WARN_S", 0.0)
    NODES["PhysMotionMPMSimulate"]().run(_block(), Material.preset("jelly"), 4, 24.0, "standard", 8, 8, 0.4, 1.0,
                                         "cpu", 0, unique_id="17")
    texts = [t for _, t, _ in fake_comfy.texts]
    assert len(texts) == 3
    assert "At the pace so far this simulation takes about" not in texts[0]
    assert "warning: At the pace so far this simulation takes about" in texts[1] and "carries waves at" in texts[1]
    assert texts[2].startswith(texts[1])
