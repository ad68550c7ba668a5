"""ComfyUI's native GAUSSIAN <-> our Gaussians: exact round trips, the axes, the simulated sequence as a
GAUSSIAN batch, nodes taking either type, and the pack loading without the type."""

from __future__ import annotations

import logging
import math
import sys
import types

import pytest
import torch

from comfy_harness import load_pack

from physmotion_core import interop_gaussian as ig
from physmotion_core.errors import InputError
from physmotion_core.types import Camera, Gaussians, Material, SimSettings, quat_to_rotmat

FIELDS = ("means", "quats", "scales", "opacities", "sh")
D = torch.diag(torch.tensor([1.0, -1.0, -1.0]))


class FakeGAUSSIAN:
    """Upstream's class (comfy_api/latest/_util/geometry_types.py, commit 2c682860): same constructor, fields."""

    def __init__(self, positions, scales, rotations, opacities, sh, counts=None):
        self.positions = positions
        self.scales = scales
        self.rotations = rotations
        self.opacities = opacities
        self.sh = sh
        self.counts = counts


def _random(n, k=16, seed=0, ids=None) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1)
    return Gaussians(means=torch.randn(n, 3, generator=gen), quats=q,
                     scales=torch.rand(n, 3, generator=gen) * 0.05 + 1e-3,
                     opacities=torch.rand(n, generator=gen), sh=torch.randn(n, k, 3, generator=gen),
                     object_ids=ids)


def _same(a: Gaussians, b: Gaussians):
    for f in FIELDS:
        assert getattr(a, f).dtype == getattr(b, f).dtype, f
        assert torch.equal(getattr(a, f), getattr(b, f)), f


# ------------------------------------------------------------------------------------------------
# Library: exact round trips and the layout
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("axes", ig.AXES)
@pytest.mark.parametrize("k", [1, 4, 16])
def test_ours_to_native_and_back_is_bit_exact(axes, k):
    g = _random(300, k)
    nat = ig.to_native(g, FakeGAUSSIAN, axes=axes)
    assert tuple(nat.positions.shape) == (1, 300, 3) and tuple(nat.rotations.shape) == (1, 300, 4)
    assert tuple(nat.opacities.shape) == (1, 300, 1) and tuple(nat.sh.shape) == (1, 300, k, 3)
    assert nat.counts is None
    # activations are the same: linear scales and opacities in [0, 1] are copied, not re-encoded
    assert torch.equal(nat.scales[0], g.scales) and torch.equal(nat.opacities[0, :, 0], g.opacities)
    (back,) = ig.from_native(nat, axes=axes)
    _same(back, g)


def test_native_variable_length_batch_round_trips_bit_exactly():
    lengths = [5, 17, 0, 11]
    n = max(lengths)
    gen = torch.Generator().manual_seed(3)
    pos = torch.zeros(4, n, 3)
    scl, rot = torch.zeros(4, n, 3), torch.zeros(4, n, 4)
    opa, sh = torch.zeros(4, n, 1), torch.zeros(4, n, 9, 3)
    for b, c in enumerate(lengths):  # real rows, then zero padding (as upstream pads)
        pos[b, :c] = torch.randn(c, 3, generator=gen)
        scl[b, :c] = torch.rand(c, 3, generator=gen) + 1e-3
        rot[b, :c] = torch.nn.functional.normalize(torch.randn(c, 4, generator=gen), dim=-1)
        opa[b, :c] = torch.rand(c, 1, generator=gen)
        sh[b, :c] = torch.randn(c, 9, 3, generator=gen)
    nat = FakeGAUSSIAN(pos, scl, rot, opa, sh, counts=torch.tensor(lengths))
    items = ig.from_native(nat)
    assert [len(g) for g in items] == lengths
    again = ig.to_native(items, FakeGAUSSIAN)
    assert again.counts.tolist() == lengths
    for f in ("positions", "scales", "rotations", "opacities", "sh"):
        assert torch.equal(getattr(again, f), getattr(nat, f)), f
    # as one scene: one object per non-empty item, numbered in batch order
    scene = ig.from_native_scene(nat)
    assert len(scene) == sum(lengths)
    assert scene.object_ids.tolist() == [0] * 5 + [1] * 17 + [2] * 11


def test_objects_split_into_batch_items_and_back():
    ids = torch.tensor([0] * 40 + [1] * 25 + [2] * 60)
    g = _random(125, 4, seed=1, ids=ids)
    nat = ig.to_native(g, FakeGAUSSIAN, split=True)
    assert nat.positions.shape[0] == 3 and nat.counts.tolist() == [40, 25, 60]
    back = ig.from_native_scene(nat)
    _same(back, g)
    assert torch.equal(back.object_ids, ids)
    whole = ig.to_native(g, FakeGAUSSIAN)  # not split: the scene is one item (its ids are not carried)
    assert whole.positions.shape[:2] == (1, 125)


def test_y_down_axes_match_the_native_renderer_projection():
    """Upstream's _render_gaussian projects camera-space points with u = cx + f x/z, v = cy + f y/z (camera
    looking down +z, rows growing with +y). Our camera at +z looking down -z, converted by the same rotation,
    must put every centre on the same pixel, and the covariances must be the rotated ones."""
    g = _random(200, 1, seed=2)
    g = Gaussians(means=g.means * 0.3, quats=g.quats, scales=g.scales, opacities=g.opacities, sh=g.sh)
    cam = Camera.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=256, height=192, fov_y_deg=40.0)
    uv, z = cam.project(g.means)
    nat = ig.to_native(g, FakeGAUSSIAN, axes="y_down")
    eye_native = D @ torch.tensor([0.0, 0.0, 3.0])
    pc = nat.positions[0] - eye_native  # native camera: axes = world axes, looking down +z
    u = cam.cx + cam.fx * pc[:, 0] / pc[:, 2]
    v = cam.cy + cam.fy * pc[:, 1] / pc[:, 2]
    assert torch.allclose(torch.stack([u, v], -1), uv, atol=1e-3)
    assert torch.allclose(pc[:, 2], z, atol=1e-5)
    R = quat_to_rotmat(nat.rotations[0])
    cov_native = (R * nat.scales[0][:, None, :]) @ (R * nat.scales[0][:, None, :]).transpose(1, 2)
    assert torch.allclose(cov_native, D @ g.covariance() @ D, atol=1e-7)
    assert torch.det(D) == 1.0  # a rotation: both frames are right-handed


def _sh_eval(sh: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
    """Colour of SH (N,16,3) seen along unit directions d (N,3): the 3DGS real SH basis up to degree 3
    (written out from the spherical-harmonic polynomials, independent of the code under test)."""
    x, y, z = d.unbind(-1)
    c1, c2 = 0.4886025119029199, [1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                                  -1.0925484305920792, 0.5462742152960396]
    c3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
          -0.4570457994644658, 1.445305721320277, -0.5900435899266435]
    basis = [torch.full_like(x, 0.28209479177387814), -c1 * y, c1 * z, -c1 * x,
             c2[0] * x * y, c2[1] * y * z, c2[2] * (2 * z * z - x * x - y * y), c2[3] * x * z,
             c2[4] * (x * x - y * y),
             c3[0] * y * (3 * x * x - y * y), c3[1] * x * y * z, c3[2] * y * (4 * z * z - x * x - y * y),
             c3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y), c3[4] * x * (4 * z * z - x * x - y * y),
             c3[5] * z * (x * x - y * y), c3[6] * x * (x * x - 3 * y * y)]
    return (torch.stack(basis, -1)[..., None] * sh).sum(1)


def test_sh_of_degree_3_turn_with_the_axes():
    g = _random(64, 16, seed=4)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(5)), dim=-1)
    nat = ig.to_native(g, FakeGAUSSIAN, axes="y_down")
    ours = _sh_eval(g.sh.double(), d.double())
    theirs = _sh_eval(nat.sh[0].double(), (d @ D.T).double())  # the same direction in the native frame
    assert torch.allclose(ours, theirs, atol=1e-9)
    # and the signs are not trivial: some coefficients did flip
    assert bool((nat.sh[0] == -g.sh).any()) and bool((nat.sh[0] == g.sh).any())


def test_deformed_covariances_convert_within_float32_rounding():
    g = _random(100, 1, seed=6)
    F = torch.eye(3) + 0.3 * torch.randn(100, 3, 3, generator=torch.Generator().manual_seed(7))
    cov = F @ g.covariance() @ F.transpose(1, 2)
    gc = Gaussians(means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities, sh=g.sh, covars=cov)
    (back,) = ig.from_native(ig.to_native(gc, FakeGAUSSIAN))
    rel = (back.covariance() - cov).norm(dim=(1, 2)) / cov.norm(dim=(1, 2))
    assert float(rel.max()) < 1e-5
    assert torch.equal(back.means, g.means)


def test_half_precision_native_fields_become_float32():
    g = _random(20, 4, seed=10)
    nat = ig.to_native(g, FakeGAUSSIAN)
    half = FakeGAUSSIAN(*(getattr(nat, f).half() for f in ig.NATIVE_FIELDS))
    (back,) = ig.from_native(half)
    assert all(getattr(back, f).dtype == torch.float32 for f in FIELDS)
    assert torch.allclose(back.means, g.means, rtol=1e-3, atol=1e-3)


def test_bad_native_input_is_refused_clearly():
    with pytest.raises(InputError, match="rotations"):
        ig.from_native(FakeGAUSSIAN(torch.zeros(1, 4, 3), torch.ones(1, 4, 3), torch.zeros(1, 4, 3),
                                    torch.ones(1, 4, 1), torch.zeros(1, 4, 1, 3)))
    with pytest.raises(InputError, match="counts"):
        ig.from_native(FakeGAUSSIAN(torch.zeros(2, 4, 3), torch.ones(2, 4, 3), torch.zeros(2, 4, 4),
                                    torch.ones(2, 4, 1), torch.zeros(2, 4, 1, 3), counts=torch.tensor([4, 9])))
    with pytest.raises(InputError, match="degree"):
        ig.sh_flip_signs(5)
    with pytest.raises(InputError, match="axes"):
        ig.to_native(_random(3), FakeGAUSSIAN, axes="z_up")


# ------------------------------------------------------------------------------------------------
# The simulated sequence as a GAUSSIAN batch
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_sim():
    from physmotion_core.sim import simulate
    from physmotion_core.types import Conditions

    ax = [torch.linspace(-0.05, 0.05, 6)] * 3
    pts = torch.stack(torch.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    pts[:, 1] += 0.06
    g = Gaussians.from_rgb(pts, torch.rand(len(pts), 3, generator=torch.Generator().manual_seed(0)),
                           torch.full((len(pts), 3), 0.01), torch.full((len(pts),), 0.9))
    return simulate(g, Material.preset("jelly"), Conditions(),
                    SimSettings(frames=5, fps=24, grid_res=8, device="cpu"))


def test_sim_to_native_has_one_item_per_frame_shaped_as_the_renderer_draws_it(small_sim):
    from physmotion_core.render.rasterize import rasterize

    t = ig.sim_to_native_tensors(small_sim)
    n = len(small_sim.rest)
    assert tuple(t["positions"].shape) == (small_sim.num_frames, n, 3) and t["counts"] is None
    cam = Camera.look_at((0.0, 0.1, 0.6), (0.0, 0.06, 0.0), width=48, height=48)
    for k in (0, small_sim.num_frames - 1):
        drawn = small_sim.gaussians_at(k)
        assert torch.equal(t["positions"][k], drawn.means * torch.tensor([1.0, -1.0, -1.0]))
        R = quat_to_rotmat(t["rotations"][k])
        M = R * t["scales"][k][:, None, :]
        cov = D @ (M @ M.transpose(1, 2)) @ D
        rel = (cov - drawn.covariance()).norm(dim=(1, 2)) / drawn.covariance().norm(dim=(1, 2))
        assert float(rel.max()) < 1e-5
        (item,) = ig.from_native(FakeGAUSSIAN(*(t[f][k:k + 1] for f in ig.NATIVE_FIELDS)))
        a, b = rasterize(item, cam), rasterize(drawn, cam)
        assert float((a.rgb - b.rgb).abs().max()) < 1e-4 and float((a.alpha - b.alpha).abs().max()) < 1e-4
    assert small_sim.num_frames == 5
    assert ig.sim_to_native_tensors(small_sim, every=2)["positions"].shape[0] == 3  # frames 0, 2, 4


# ------------------------------------------------------------------------------------------------
# Nodes: both input types; the converter nodes only with the native type
# ------------------------------------------------------------------------------------------------


def _fresh_pack(name, monkeypatch):
    for mod in [m for m in sys.modules if m == name or m.startswith(name + ".")]:
        monkeypatch.delitem(sys.modules, mod, raising=False)  # its nodes too: they read comfy_api on import
    pack = load_pack(name)
    monkeypatch.setitem(sys.modules, name, pack)
    return pack


@pytest.fixture(params=["GAUSSIAN", "SPLAT"])
def native_comfy_api(monkeypatch, request):
    """A comfy_api.latest with Types.GAUSSIAN and IO.Gaussian, as ComfyUI has since the GAUSSIAN type (and
    with the class spelled SPLAT, as a later upstream commit of geometry_types.py names it)."""
    latest = types.ModuleType("comfy_api.latest")
    io_name = "Gaussian" if request.param == "GAUSSIAN" else "Splat"
    latest.Types = types.SimpleNamespace(**{request.param: FakeGAUSSIAN})
    latest.IO = types.SimpleNamespace(**{io_name: types.SimpleNamespace(io_type=request.param)})
    api = types.ModuleType("comfy_api")
    api.latest = latest
    monkeypatch.setitem(sys.modules, "comfy_api", api)
    monkeypatch.setitem(sys.modules, "comfy_api.latest", latest)
    return latest


def test_pack_loads_without_the_native_type_with_one_log_line(monkeypatch, caplog):
    monkeypatch.setitem(sys.modules, "comfy_api", None)  # "import comfy_api" fails, as on 0.3.64 it lacks it
    with caplog.at_level(logging.INFO, logger="physmotion"):
        pack = _fresh_pack("physmotion_pack_nogaussian", monkeypatch)
    assert pack.FAILED_MODULES == {}
    assert not any("GAUSSIAN" in n for n in pack.NODE_CLASS_MAPPINGS)
    assert "PhysMotionMPMSimulate" in pack.NODE_CLASS_MAPPINGS
    lines = [r for r in caplog.records if "GAUSSIAN" in r.getMessage()]
    assert len(lines) == 1 and "not registered" in lines[0].getMessage()


def test_converter_nodes_with_the_native_type(native_comfy_api, monkeypatch, small_sim, tmp_path, caplog):
    with caplog.at_level(logging.INFO, logger="physmotion"):
        pack = _fresh_pack("physmotion_pack_gaussian", monkeypatch)
    nodes = pack.NODE_CLASS_MAPPINGS
    assert {"PhysMotionFromGAUSSIAN", "PhysMotionToGAUSSIAN", "PhysMotionSimToGAUSSIAN"} <= set(nodes)
    assert not [r for r in caplog.records if "GAUSSIAN" in r.getMessage()]
    # the output is what the running ComfyUI defines, the inputs take both names
    name = "SPLAT" if hasattr(native_comfy_api.Types, "SPLAT") else "GAUSSIAN"
    assert nodes["PhysMotionToGAUSSIAN"].RETURN_TYPES == (name,)
    assert nodes["PhysMotionSimToGAUSSIAN"].RETURN_TYPES == (name,)
    assert set(nodes["PhysMotionFromGAUSSIAN"].INPUT_TYPES()["required"]["gaussian"][0].split(",")) == {"SPLAT", "GAUSSIAN"}
    assert nodes["PhysMotionMPMSimulate"].INPUT_TYPES()["required"]["gaussians"][0] == "PM_GAUSSIANS,SPLAT,GAUSSIAN"

    g = _random(80, 4, seed=8, ids=torch.tensor([0] * 30 + [1] * 50))
    (nat,) = nodes["PhysMotionToGAUSSIAN"]().run(g, "y_down", True)
    assert isinstance(nat, FakeGAUSSIAN) and nat.counts.tolist() == [30, 50]
    (back,) = nodes["PhysMotionFromGAUSSIAN"]().run(nat, "y_down")
    _same(back, g)
    assert torch.equal(back.object_ids, g.object_ids)
    (as_is,) = nodes["PhysMotionToGAUSSIAN"]().run(g, "as_is", False)
    assert torch.equal(as_is.positions[0], g.means)

    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    (seq,) = nodes["PhysMotionSimToGAUSSIAN"]().run(small_sim, 1, "y_down")
    assert isinstance(seq, FakeGAUSSIAN) and seq.positions.shape[0] == small_sim.num_frames


def test_nodes_that_take_gaussians_also_take_a_native_gaussian(monkeypatch, tmp_path):
    from physmotion_core.ply import read_ply

    nodes = load_pack().NODE_CLASS_MAPPINGS
    consumers = {name: [inp for inp, spec in {**cls.INPUT_TYPES().get("required", {}),
                                             **cls.INPUT_TYPES().get("optional", {})}.items()
                        if isinstance(spec[0], str) and "PM_GAUSSIANS" in spec[0].split(",")]
                 for name, cls in nodes.items()}
    consumers = {k: v for k, v in consumers.items() if v}
    assert {"PhysMotionCombineObjects", "PhysMotionMPMSimulate", "PhysMotionHardDepthRefine",
            "PhysMotionSaveGaussians"} <= set(consumers)
    for name, inputs in consumers.items():
        for inp in inputs:
            spec = nodes[name].INPUT_TYPES()
            kind = {**spec.get("required", {}), **spec.get("optional", {})}[inp][0]
            assert kind == "PM_GAUSSIANS,SPLAT,GAUSSIAN", (name, inp, kind)

    g = _random(50, 4, seed=9)
    nat = ig.to_native(g, FakeGAUSSIAN)
    monkeypatch.setenv("PHYSMOTION_OUTPUT_DIR", str(tmp_path))
    out_native = nodes["PhysMotionSaveGaussians"]().run(nat, "native")["result"][0]
    out_ours = nodes["PhysMotionSaveGaussians"]().run(g, "ours")["result"][0]
    a, b = read_ply(tmp_path / out_native), read_ply(tmp_path / out_ours)
    for f in FIELDS:
        assert torch.equal(getattr(a, f), getattr(b, f)), f

    jelly = Material.preset("jelly")
    scene, mats = nodes["PhysMotionCombineObjects"]().run(nat, jelly, g, jelly, 1.0, 0.0, 0.0)
    assert len(scene) == 100 and len(mats) == 2 and scene.object_ids.tolist() == [0] * 50 + [1] * 50
    assert torch.equal(scene.means[:50], g.means) and torch.equal(scene.means[50:], g.means + torch.tensor([1.0, 0, 0]))
    with pytest.raises(InputError, match="PM_GAUSSIANS or a native SPLAT/GAUSSIAN"):
        nodes["PhysMotionCombineObjects"]().run("not splats", jelly, g, jelly, 0.0, 0.0, 0.0)


def test_simulate_node_gives_the_same_result_from_either_type():
    nodes = load_pack().NODE_CLASS_MAPPINGS
    ax = [torch.linspace(-0.05, 0.05, 5)] * 3
    pts = torch.stack(torch.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    pts[:, 1] += 0.06
    g = Gaussians.from_rgb(pts, torch.full((len(pts), 3), 0.5), torch.full((len(pts), 3), 0.01),
                           torch.full((len(pts),), 0.9))
    nat = ig.to_native(g, FakeGAUSSIAN)
    args = (Material.preset("jelly"), 3, 24.0, "standard", 8, 8, 0.4, 1.0, "cpu", 0)
    (a,) = nodes["PhysMotionMPMSimulate"]().run(nat, *args)
    (b,) = nodes["PhysMotionMPMSimulate"]().run(g, *args)
    assert torch.equal(a.x, b.x)
    assert math.isclose(float(a.x[-1, :, 1].mean()), float(b.x[-1, :, 1].mean()))


# ------------------------------------------------------------------------------------------------
# Batch meaning (upstream's: one item = one independent splat) and the frame batch fed back
# ------------------------------------------------------------------------------------------------


def _batch(*items):
    return ig.to_native(list(items), FakeGAUSSIAN)


def _gio():
    import importlib

    return importlib.import_module(f"{load_pack().__name__}.nodes._gaussian_io")


def test_a_splat_input_takes_one_item_and_refuses_a_batch_with_what_to_do():
    gio = _gio()
    a, b = _random(40, 4, seed=11), _random(30, 4, seed=12)
    one = gio.as_pm_gaussians(_batch(a))
    _same(one, a)
    assert one.object_ids is None
    with pytest.raises(InputError, match=r"gaussians: the splat batch holds 2 items.*independent splat.*Merge Splats"):
        gio.as_pm_gaussians(_batch(a, b))
    # the converter is where a batch becomes objects (its stated meaning), unchanged
    scene = ig.from_native_scene(_batch(a, b))
    assert scene.object_ids.tolist() == [0] * 40 + [1] * 30


def test_the_simulated_frames_fed_back_are_refused_as_objects(native_comfy_api, monkeypatch, small_sim):
    pack = _fresh_pack("physmotion_pack_frames", monkeypatch)
    nodes = pack.NODE_CLASS_MAPPINGS
    (frames,) = nodes["PhysMotionSimToGAUSSIAN"]().run(small_sim, 1, "y_down")
    assert frames.physmotion_frame_batch is True
    with pytest.raises(InputError, match=r"frames of one motion.*Simulation to SPLAT.*overlapping"):
        nodes["PhysMotionFromGAUSSIAN"]().run(frames, "y_down")
    args = (Material.preset("jelly"), 3, 24.0, "standard", 8, 8, 0.4, 1.0, "cpu", 0)
    with pytest.raises(InputError, match=r"frames of one motion"):
        nodes["PhysMotionMPMSimulate"]().run(frames, *args)
    # an upstream node that makes a new object drops the mark: the frames are still told by their content
    copy = FakeGAUSSIAN(frames.positions.clone(), frames.scales, frames.rotations, frames.opacities, frames.sh)
    assert not hasattr(copy, "physmotion_frame_batch")
    assert "same colours and opacities" in ig.frame_batch_reason(copy)
    with pytest.raises(InputError, match=r"frames of one motion"):
        nodes["PhysMotionFromGAUSSIAN"]().run(copy, "y_down")
    # independent splats of the same length are not frames
    assert ig.frame_batch_reason(_batch(_random(20, 1, seed=1), _random(20, 1, seed=2))) is None
    # one frame of it is a splat like any other
    one = FakeGAUSSIAN(*(getattr(frames, f)[2:3] for f in ig.NATIVE_FIELDS))
    assert len(pack.nodes._gaussian_io.as_pm_gaussians(one)) == len(small_sim.rest)


# ------------------------------------------------------------------------------------------------
# Axes: a .ply the pack wrote, through upstream's loader (x y z copied as stored), arrives upright
# ------------------------------------------------------------------------------------------------


def _upstream_style_ply_load(path) -> FakeGAUSSIAN:
    """What upstream's File3DToSplat does with a binary .ply (read independently here): every property
    as stored, scales exp'd, opacity through a sigmoid, rotations normalised, no change of axes."""
    import numpy as np

    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    names = [ln.split()[-1] for ln in data[:end].decode().splitlines() if ln.startswith("property")]
    arr = np.frombuffer(data[end:], dtype=[(n, "<f4") for n in names])
    t = lambda *ks: torch.from_numpy(np.stack([arr[k].astype(np.float32) for k in ks], 1))  # noqa: E731
    rot = torch.nn.functional.normalize(t("rot_0", "rot_1", "rot_2", "rot_3"), dim=-1)
    rest = [k for k in names if k.startswith("f_rest_")]
    kk = len(rest) // 3 + 1
    sh = torch.cat([t("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
                    t(*rest).reshape(-1, 3, kk - 1).transpose(1, 2)], 1) if rest else t("f_dc_0", "f_dc_1", "f_dc_2")[:, None]
    return FakeGAUSSIAN(t("x", "y", "z")[None], torch.exp(t("scale_0", "scale_1", "scale_2"))[None], rot[None],
                        torch.sigmoid(t("opacity"))[None], sh[None])


def test_a_pack_written_ply_round_trips_upright_through_the_upstream_loader(tmp_path):
    from physmotion_core.ply import ply_axes, read_ply, write_ply

    g = _random(64, 4, seed=21)
    g.means[:, 1] = g.means[:, 1].abs() + 0.1  # an object standing above the ground: y > 0 everywhere
    path = write_ply(tmp_path / "obj.ply", g)
    assert ply_axes(path) == "y_down"
    nat = _upstream_style_ply_load(path)
    assert bool((nat.positions[0, :, 1] < 0).all())  # stored in the native frame: y down
    back = _gio().as_pm_gaussians(nat)  # the default of every splat input
    for f in FIELDS:
        assert torch.allclose(getattr(back, f), getattr(g, f), rtol=1e-5, atol=1e-5), f
    assert bool((back.means[:, 1] > 0).all())  # upright
    # as_is is the other choice where a splat enters: x y z as stored (here: upside down)
    flipped = _gio().as_pm_gaussians(nat, axes="as_is")
    assert torch.allclose(flipped.means, g.means * torch.tensor([1.0, -1.0, -1.0]), atol=1e-6)
    # our own reader honours the record; asked to copy as stored it does
    _same_close = lambda a, b: all(torch.allclose(getattr(a, f), getattr(b, f), rtol=1e-5, atol=1e-5) for f in FIELDS)  # noqa: E731
    assert _same_close(read_ply(path), g)
    assert torch.allclose(read_ply(path, axes="as_is").means, nat.positions[0])


def test_an_unmarked_ply_is_read_as_stored_and_y_up_files_say_so(tmp_path):
    from physmotion_core.ply import ply_axes, read_ply, write_ply

    g = _random(16, 1, seed=22)
    up = write_ply(tmp_path / "up.ply", g, axes="y_up")
    assert ply_axes(up) == "y_up" and torch.allclose(read_ply(up).means, g.means)
    raw = up.read_bytes()
    old = tmp_path / "old.ply"  # a file from before the record (or from another tool): no axes comment
    old.write_bytes(b"".join(ln for ln in raw.splitlines(keepends=True) if b"physmotion_axes" not in ln[:40]))
    assert ply_axes(old) is None
    assert torch.allclose(read_ply(old).means, g.means)
    assert torch.allclose(read_ply(old, axes="y_down").means, g.means * torch.tensor([1.0, -1.0, -1.0]))
    with pytest.raises(InputError, match="axes must be"):
        read_ply(old, axes="sideways")


def test_fit_offers_the_axes_choice_where_the_splat_enters():
    spec = load_pack().NODE_CLASS_MAPPINGS["PhysMotionFitGaussiansToPhoto"].INPUT_TYPES()
    assert spec["optional"]["splat_axes"][0] == ["y_down", "as_is"]
    assert spec["optional"]["splat_axes"][1]["default"] == "y_down"
