"""LGM network + Gaussian head: official checkpoint layout, golden forward (both rotation variants),
rays, input normalisation, loading from the model folder and its errors."""

import json
import math
import shutil
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from physmotion_core.errors import InputError, MissingModelError
from physmotion_core.lift.learned import lgm_input
from physmotion_core.lift.lgm import (LGM_BIG, IMAGENET_MEAN, IMAGENET_STD, LGMNet, default_rays,
                                      gaussian_activations, lgm_architecture, load_lgm, orbit_pose,
                                      plucker_rays, rotation_dim_for_file)

DATA = Path(__file__).resolve().parent / "data" / "models"
TINY = DATA / "lgm_tiny.safetensors"
# Golden outputs came from the original code in float32 on CPU; the README's suggested check.
ATOL = RTOL = 1e-4


@pytest.fixture(scope="module")
def manifest():
    return json.loads((DATA / "lgm_big_state_dict.json").read_text())


@pytest.fixture(scope="module")
def golden():
    return (load_file(str(DATA / "lgm_tiny_input.safetensors")), load_file(str(DATA / "lgm_tiny_output.safetensors")),
            json.loads((DATA / "lgm_tiny_config.json").read_text()))


@pytest.fixture(scope="module")
def tiny(golden):
    state = load_file(str(TINY))
    net = LGMNet(lgm_architecture(state, input_size=64))
    net.load_state_dict({k: v.float() for k, v in state.items()}, strict=True)
    return net.eval()


@pytest.fixture(scope="module")
def tiny_forward(tiny, golden):
    """(raw [2, 4096, 14], unet output, conv output) of the golden input, computed once."""
    inp = golden[0]
    with torch.no_grad():
        u = tiny.unet(inp["images"].reshape(8, 9, 64, 64))
        c = tiny.conv(u)
        raw = tiny.forward_raw(inp["images"])
    return raw, u, c


# ----------------------------------------------------------------------------------------------
# layout
# ----------------------------------------------------------------------------------------------

def test_big_model_has_exactly_the_official_keys_and_shapes(manifest):
    with torch.device("meta"):
        net = LGMNet(LGM_BIG)
    got = {k: list(v.shape) for k, v in net.state_dict().items()}
    assert len(got) == 376 == manifest["_meta"]["num_tensors"]
    assert got == manifest["state_dict"]
    assert list(got) == list(manifest["state_dict"])                 # same order, too
    assert sum(math.prod(s) for s in got.values()) == manifest["_meta"]["num_parameters"] == 415042848
    assert not list(net.buffers())


def test_architecture_is_read_back_from_the_official_shapes(manifest):
    state = {k: torch.empty(v, device="meta") for k, v in manifest["state_dict"].items()}
    assert lgm_architecture(state) == LGM_BIG
    assert LGM_BIG.splat_size == 128 and LGM_BIG.input_size == 256


def test_tiny_architecture_matches_the_golden_config(golden, tiny):
    cfg = golden[2]["unet_constructor_as_called_by_LGM"]
    assert list(tiny.cfg.down_channels) == cfg["down_channels"]
    assert list(tiny.cfg.up_channels) == cfg["up_channels"]
    assert list(tiny.cfg.down_attention) == cfg["down_attention"]
    assert list(tiny.cfg.up_attention) == cfg["up_attention"]
    assert tiny.cfg.splat_size == golden[2]["overrides"]["splat_size"] == 32
    assert len(tiny.state_dict()) == 370
    assert sum(p.numel() for p in tiny.parameters()) == golden[2]["num_parameters"]


# ----------------------------------------------------------------------------------------------
# golden forward
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("rotation_dim, key", [(-1, "gaussians"), (1, "gaussians_rotdim1")])
def test_tiny_golden_gaussians(tiny_forward, golden, rotation_dim, key):
    g = gaussian_activations(tiny_forward[0], rotation_dim)
    assert g.shape == (2, 4096, 14) and g.dtype == torch.float32
    torch.testing.assert_close(g, golden[1][key], atol=ATOL, rtol=RTOL)


def test_forward_gaussians_end_to_end(tiny, golden):
    inp, out, _ = golden
    with torch.no_grad():
        g = tiny.forward_gaussians(inp["images"][1:])                 # the network's own rotation_dim (-1)
    torch.testing.assert_close(g, out["gaussians"][1:], atol=ATOL, rtol=RTOL)


def test_tiny_golden_intermediates(tiny_forward, golden):
    _, out, _ = golden
    raw, u, c = tiny_forward
    torch.testing.assert_close(u, out["unet_out"], atol=ATOL, rtol=RTOL)
    torch.testing.assert_close(c, out["conv_out"], atol=ATOL, rtol=RTOL)


def test_rotation_variants_differ_only_in_the_quaternions(tiny_forward):
    raw = tiny_forward[0]
    a, b = gaussian_activations(raw, -1), gaussian_activations(raw, 1)
    keep = [i for i in range(14) if not 7 <= i < 11]
    assert torch.equal(a[..., keep], b[..., keep])
    torch.testing.assert_close(a[..., 7:11].norm(dim=-1), torch.ones(2, 4096))          # unit per Gaussian
    torch.testing.assert_close(b[..., 7:11].norm(dim=1), torch.ones(2, 4))              # unit per component
    # the quirk's quaternions are tiny (about 2/sqrt(N) long), far from unit
    assert float(b[..., 7:11].norm(dim=-1).max()) < 0.2
    # layout: positions clamped, opacity sigmoid, scale 0.1 softplus, colour in 0..1
    assert float(a[..., 0:3].abs().max()) <= 1.0
    torch.testing.assert_close(a[..., 4:7], 0.1 * torch.nn.functional.softplus(raw[..., 4:7]))
    assert 0 <= float(a[..., 11:].min()) and float(a[..., 11:].max()) <= 1
    with pytest.raises(InputError, match="rotation_dim"):
        gaussian_activations(raw, 0)


def test_gaussian_order_is_view_major_then_row_then_column(tiny_forward):
    raw, _, conv = tiny_forward                                               # conv: [B*4, 14, 32, 32]
    b, v, y, x = 1, 2, 5, 17
    torch.testing.assert_close(raw[b, v * 1024 + y * 32 + x], conv[b * 4 + v, :, y, x])


# ----------------------------------------------------------------------------------------------
# rays and input
# ----------------------------------------------------------------------------------------------

def test_default_rays_match_golden(tiny, golden):
    inp, _, _ = golden
    rays = default_rays(tiny.cfg)
    assert rays.shape == (4, 6, 64, 64)
    torch.testing.assert_close(rays, inp["rays_plucker"], atol=1e-6, rtol=0)
    assert torch.equal(inp["images"][0, :, 3:], inp["rays_plucker"])     # the golden input carries them


def test_rays_geometry():
    # azimuth 0: camera on +z looking down -z; 90: on +x looking down -x (kiui orbit_camera)
    for az, pos in ((0, (0, 0, 1.5)), (90, (1.5, 0, 0)), (180, (0, 0, -1.5)), (270, (-1.5, 0, 0))):
        pose = orbit_pose(0, az, 1.5)
        torch.testing.assert_close(pose[:3, 3], torch.tensor(pos, dtype=torch.float32), atol=1e-6, rtol=0)
        torch.testing.assert_close(pose[:3, 2], torch.tensor(pos, dtype=torch.float32) / 1.5, atol=1e-6, rtol=0)
    r = plucker_rays(orbit_pose(0, 0, 1.5), 8, 49.1)
    d, m = r[3:], r[:3]
    torch.testing.assert_close(d.norm(dim=0), torch.ones(8, 8))
    # the top-left pixel looks up and to the left, the moment o x d is orthogonal to d
    assert d[0, 0, 0] < 0 and d[1, 0, 0] > 0 and d[2, 0, 0] < 0
    torch.testing.assert_close((d * m).sum(0), torch.zeros(8, 8), atol=1e-6, rtol=0)
    # pinhole: pixel centre x = 7.5 of 8 is 3.5 / 4 of the way to the edge of the field of view
    assert float(d[0, 4, 7] / -d[2, 4, 7]) == pytest.approx(3.5 / 4 * math.tan(math.radians(49.1 / 2)), rel=1e-5)


def test_lgm_input_normalises_like_the_original(tiny, golden):
    inp, _, _ = golden
    views = inp["rgb_unnormalized"][0].permute(0, 2, 3, 1)                   # [4, 64, 64, 3]
    x = lgm_input(views, tiny)
    assert x.shape == (1, 4, 9, 64, 64)
    torch.testing.assert_close(x, inp["images"][:1], atol=1e-6, rtol=0)
    mean = torch.tensor(IMAGENET_MEAN)
    std = torch.tensor(IMAGENET_STD)
    torch.testing.assert_close(x[0, 0, :3, 0, 0], (views[0, 0, 0] - mean) / std, atol=1e-6, rtol=0)
    # other view sizes are resized (bilinearly) to the network's input size
    assert lgm_input(torch.ones(4, 32, 32, 3), tiny).shape == (1, 4, 9, 64, 64)
    with pytest.raises(InputError, match="4 square RGB"):
        lgm_input(torch.ones(3, 64, 64, 3), tiny)


# ----------------------------------------------------------------------------------------------
# loading
# ----------------------------------------------------------------------------------------------

def _root_with(tmp_path, name, src=TINY):
    folder = tmp_path / "physmotion" / "lgm"
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, folder / name)
    return tmp_path


@pytest.mark.parametrize("name, dim, key", [("model_fp16_fixrot.safetensors", -1, "gaussians"),
                                            ("model_fp16.safetensors", 1, "gaussians_rotdim1")])
def test_loader_picks_the_rotation_from_the_file_name(tmp_path, monkeypatch, golden, tiny_forward, name, dim, key):
    monkeypatch.setenv("PHYSMOTION_MODELS", str(_root_with(tmp_path, name)))
    net = load_lgm(input_size=64, device="cpu")                # the only file in the folder
    assert net.rotation_dim == dim == rotation_dim_for_file(name)
    assert net.dtype == torch.float32 and net.device.type == "cpu"
    assert not any(p.requires_grad for p in net.parameters())
    # the loaded network is the golden one (weights checked exactly below); with the rotation
    # variant it picked, its head gives the matching golden output
    torch.testing.assert_close(gaussian_activations(tiny_forward[0], net.rotation_dim), golden[1][key],
                               atol=ATOL, rtol=RTOL)


def test_loader_rotation_override(tmp_path):
    root = _root_with(tmp_path, "model_fp16.safetensors")
    assert load_lgm("model_fp16.safetensors", root=root, input_size=64, rotation="per_gaussian").rotation_dim == -1
    assert load_lgm("model_fp16.safetensors", root=root, input_size=64, rotation=1).rotation_dim == 1
    with pytest.raises(InputError, match="rotation normalisation"):
        load_lgm("model_fp16.safetensors", root=root, input_size=64, rotation="sideways")
    assert rotation_dim_for_file("my_lgm_fixrot_v2.safetensors") == -1
    assert rotation_dim_for_file("renamed.safetensors") == 1


def test_loader_loads_the_weights_exactly(tmp_path):
    root = _root_with(tmp_path, "model_fp16_fixrot.safetensors")
    net = load_lgm("model_fp16_fixrot.safetensors", root=root, input_size=64)
    want = load_file(str(TINY))
    got = net.state_dict()
    assert set(got) == set(want) and all(torch.equal(got[k], want[k].float()) for k in want)
    half = load_lgm("model_fp16_fixrot.safetensors", root=root, input_size=64, dtype=torch.float16)
    assert half.dtype == torch.float16


def test_missing_weights_name_folder_expected_file_and_contents(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_MODELS", str(tmp_path))
    with pytest.raises(MissingModelError) as exc:
        load_lgm()
    msg = str(exc.value)
    assert str(tmp_path / "physmotion" / "lgm") in msg and "model_fp16_fixrot.safetensors" in msg
    assert "does not exist" in msg and "never downloaded" in msg
    (tmp_path / "physmotion" / "lgm").mkdir(parents=True)
    (tmp_path / "physmotion" / "lgm" / "notes.txt").write_text("x")
    with pytest.raises(MissingModelError, match="found: notes.txt"):
        load_lgm()
    with pytest.raises(MissingModelError, match="model_fp16.safetensors.*not found"):
        load_lgm("model_fp16.safetensors")


def test_wrong_checkpoint_is_named(tmp_path):
    root = _root_with(tmp_path, "model_fp16.safetensors", DATA / "imagedream_tiny.safetensors")
    with pytest.raises(InputError, match="Not an LGM checkpoint") as exc:
        load_lgm("model_fp16.safetensors", root=root)
    msg = str(exc.value)
    assert str(root / "physmotion" / "lgm") in msg and "found: model_fp16.safetensors" in msg
    assert "model_fp16_fixrot.safetensors" in msg


def test_mismatched_shapes_are_reported(tmp_path):
    state = load_file(str(TINY))
    state["conv.weight"] = torch.zeros(14, 14, 3, 3, dtype=torch.float16)
    del state["unet.norm_out.bias"]
    folder = tmp_path / "physmotion" / "lgm"
    folder.mkdir(parents=True)
    save_file(state, str(folder / "model_fp16_fixrot.safetensors"))
    with pytest.raises(InputError, match="do not match") as exc:
        load_lgm(root=tmp_path, input_size=64)
    msg = str(exc.value)
    assert "1 missing" in msg and "unet.norm_out.bias" in msg and "conv.weight" in msg and str(folder) in msg


def test_only_the_official_layout_with_strict_official(tmp_path):
    root = _root_with(tmp_path, "model_fp16_fixrot.safetensors")
    with pytest.raises(InputError, match="'big'") as exc:
        load_lgm(root=root, input_size=64, strict_official=True)
    assert "other shapes" in str(exc.value)


def test_truncated_file(tmp_path):
    folder = tmp_path / "physmotion" / "lgm"
    folder.mkdir(parents=True)
    data = TINY.read_bytes()
    (folder / "model_fp16_fixrot.safetensors").write_bytes(data[: len(data) // 3])
    with pytest.raises(InputError, match="truncated") as exc:
        load_lgm(root=tmp_path)
    assert str(folder) in str(exc.value) and "model_fp16_fixrot.safetensors" in str(exc.value)


def test_several_files_need_a_name(tmp_path):
    root = _root_with(tmp_path, "model_fp16.safetensors")
    _root_with(tmp_path, "model_fp16_fixrot.safetensors")
    with pytest.raises(InputError, match="say which"):
        load_lgm(root=root)


def test_input_size_must_fit_the_network(tmp_path):
    root = _root_with(tmp_path, "model_fp16.safetensors")
    with pytest.raises(InputError, match="multiple of 32"):
        load_lgm(root=root, input_size=100)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_fp16_cuda_forward_close_to_golden(tmp_path, golden):
    root = _root_with(tmp_path, "model_fp16_fixrot.safetensors")
    net = load_lgm(root=root, input_size=64, device="cuda")
    assert net.dtype == torch.float16
    inp, out, _ = golden
    with torch.no_grad(), torch.autocast("cuda", dtype=torch.float16):
        g = net.forward_gaussians(inp["images"].cuda()).cpu()
    keep = [i for i in range(14) if not 7 <= i < 11]
    torch.testing.assert_close(g[..., keep], out["gaussians"][..., keep], atol=2e-2, rtol=0)
