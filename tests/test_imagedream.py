"""ImageDream multi-view UNet + pipeline: checkpoint layout, golden forward, cameras, loading, sampling."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from physmotion_core.errors import InputError, Interrupted, MissingModelError
from physmotion_core.lift.imagedream import (LGM_VIEW_ORDER, VIEW_AZIMUTHS, MultiViewUNet, generate_views,
                                             get_camera, load_imagedream, timestep_embedding,
                                             views_for_lgm)

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data" / "models"
TOKENIZER = ROOT / "physmotion_core" / "data" / "sd21_configs" / "tokenizer"


# ----------------------------------------------------------------------------------------------
# checkpoint layout and golden forward
# ----------------------------------------------------------------------------------------------

def test_state_dict_matches_official_manifest():
    manifest = json.loads((DATA / "imagedream_unet_state_dict.json").read_text())
    with torch.device("meta"):
        unet = MultiViewUNet(manifest["_meta"]["config"])
    got = {k: list(v.shape) for k, v in unet.state_dict().items()}
    assert len(got) == 773 == len(manifest["state_dict"])
    assert got == manifest["state_dict"]
    assert list(got) == list(manifest["state_dict"])          # same order, too
    assert sum(math.prod(s) for s in got.values()) == manifest["_meta"]["num_parameters"]


@pytest.fixture(scope="module")
def tiny_golden():
    cfg = json.loads((DATA / "imagedream_tiny_config.json").read_text())
    unet = MultiViewUNet(cfg["config"])
    weights = load_file(str(DATA / "imagedream_tiny.safetensors"))
    unet.load_state_dict({k: v.float() for k, v in weights.items()}, strict=True)
    unet.eval()
    return (unet, load_file(str(DATA / "imagedream_tiny_input.safetensors")),
            load_file(str(DATA / "imagedream_tiny_output.safetensors")))


def test_tiny_golden_forward(tiny_golden):
    unet, inp, ref = tiny_golden
    assert len(unet.state_dict()) == 771
    x = inp["x"].clone()
    with torch.no_grad():
        out = unet(x, inp["timesteps"], inp["context"], camera=inp["camera"], num_frames=5,
                   ip=inp["ip"], ip_img=inp["ip_img"])
        t_emb = unet.time_embed(timestep_embedding(inp["timesteps"], unet.model_channels))
        cam_emb = unet.camera_embed(inp["camera"])
        ip_emb = unet.image_embed(inp["ip"])
    assert out.shape == (10, 4, 32, 32) and out.dtype == torch.float32
    torch.testing.assert_close(out, ref["out"], atol=1e-4, rtol=0)
    torch.testing.assert_close(t_emb, ref["time_embed_out"], atol=1e-5, rtol=0)
    torch.testing.assert_close(cam_emb, ref["camera_embed_out"], atol=1e-5, rtol=0)
    torch.testing.assert_close(ip_emb, ref["ip_emb"], atol=1e-5, rtol=0)
    torch.testing.assert_close(x, ref["x_after_ip_img_insert"], atol=0, rtol=0)


def test_ip_img_is_written_into_x_in_place(tiny_golden):
    unet, inp, _ = tiny_golden
    x = inp["x"].clone()
    with torch.no_grad():
        unet(x, inp["timesteps"], inp["context"], camera=inp["camera"], num_frames=5,
             ip=inp["ip"], ip_img=inp["ip_img"])
    assert torch.equal(x[4], inp["ip_img"][0]) and torch.equal(x[9], inp["ip_img"][1])
    keep = [i for i in range(10) if i not in (4, 9)]
    assert torch.equal(x[keep], inp["x"][keep])


def test_get_camera_matches_golden_and_conventions():
    inp = load_file(str(DATA / "imagedream_tiny_input.safetensors"))
    cam = get_camera(4, elevation=0, extra_view=True)
    assert cam.shape == (5, 16) and cam.dtype == torch.float32
    torch.testing.assert_close(cam.repeat(2, 1), inp["camera"], atol=1e-6, rtol=0)
    assert torch.count_nonzero(cam[4]) == 0
    assert get_camera(4).shape == (4, 16)
    # positive elevation = camera above the object (Blender z-up: translation z = sin(elevation))
    pose = get_camera(4, elevation=30)[0].reshape(4, 4)
    assert pose[2, 3].item() == pytest.approx(0.5, abs=1e-6)
    for p in get_camera(4, elevation=30).reshape(-1, 4, 4):
        assert torch.allclose(p[:3, :3] @ p[:3, :3].T, torch.eye(3), atol=1e-5)
    assert VIEW_AZIMUTHS[LGM_VIEW_ORDER[0]] == 0.0
    assert [VIEW_AZIMUTHS[i] for i in LGM_VIEW_ORDER] == [0.0, 90.0, 180.0, 270.0]


# ----------------------------------------------------------------------------------------------
# a tiny pipeline in the official folder layout
# ----------------------------------------------------------------------------------------------

TINY_UNET = {"_class_name": "MultiViewUNetModel", "_diffusers_version": "0.23.1", "image_size": 8,
             "in_channels": 4, "out_channels": 4, "model_channels": 32, "attention_resolutions": [4, 2, 1],
             "num_res_blocks": 1, "channel_mult": [1, 1, 2], "num_head_channels": 16, "transformer_depth": 1,
             "context_dim": 32, "use_checkpoint": False, "camera_dim": 16, "ip_dim": 4}


def _randomise(module, seed):
    """Re-initialise so that no layer is zero (the UNet zero-inits its output convolutions)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in module.named_parameters():
            if p.ndim >= 2:
                bound = 1.0 / math.sqrt(p[0].numel())
                p.copy_((torch.rand(p.shape, generator=g) * 2 - 1) * bound)
            elif name.endswith("weight"):
                p.copy_(1 + 0.1 * torch.randn(p.shape, generator=g))
            else:
                p.copy_(0.05 * torch.randn(p.shape, generator=g))


def _write_tiny_model(folder: Path):
    from diffusers import AutoencoderKL, DDIMScheduler
    from transformers import (CLIPImageProcessor, CLIPTextConfig, CLIPTextModel, CLIPTokenizer,
                              CLIPVisionConfig, CLIPVisionModel)

    torch.manual_seed(0)
    unet = MultiViewUNet(TINY_UNET)
    _randomise(unet, 1)
    (folder / "unet").mkdir(parents=True)
    (folder / "unet" / "config.json").write_text(json.dumps(TINY_UNET))
    save_file({k: v.half().contiguous() for k, v in unet.state_dict().items()},
              str(folder / "unet" / "diffusion_pytorch_model.safetensors"))

    AutoencoderKL(block_out_channels=(32, 32, 32, 32), layers_per_block=1, latent_channels=4,
                  down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
                  sample_size=64, scaling_factor=0.18215).save_pretrained(folder / "vae")
    CLIPTextModel(CLIPTextConfig(hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                                 num_attention_heads=2, max_position_embeddings=77, vocab_size=49408,
                                 hidden_act="gelu")).save_pretrained(folder / "text_encoder")
    CLIPTokenizer.from_pretrained(str(TOKENIZER), local_files_only=True).save_pretrained(folder / "tokenizer")
    # the Resampler's input width (1280, CLIP ViT-H/14) is hard-coded in the model, so the tiny
    # vision tower keeps that width and shrinks everything else
    CLIPVisionModel(CLIPVisionConfig(hidden_size=1280, intermediate_size=64, num_hidden_layers=1,
                                     num_attention_heads=4, image_size=28, patch_size=14,
                                     hidden_act="gelu")).save_pretrained(folder / "image_encoder")
    CLIPImageProcessor(size={"shortest_edge": 28}, crop_size={"height": 28, "width": 28}).save_pretrained(
        folder / "feature_extractor")
    DDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False,
                  set_alpha_to_one=False, steps_offset=1, prediction_type="epsilon").save_pretrained(
        folder / "scheduler")
    (folder / "model_index.json").write_text(json.dumps({
        "_class_name": ["pipeline_mvdream", "MVDreamPipeline"], "unet": ["mv_unet", "MultiViewUNetModel"],
        "vae": ["diffusers", "AutoencoderKL"], "text_encoder": ["transformers", "CLIPTextModel"],
        "tokenizer": ["transformers", "CLIPTokenizer"], "image_encoder": ["transformers", "CLIPVisionModel"],
        "feature_extractor": ["transformers", "CLIPImageProcessor"], "scheduler": ["diffusers", "DDIMScheduler"]}))
    return unet


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("imagedream") / "imagedream-tiny"
    _write_tiny_model(folder)
    return folder


@pytest.fixture(scope="module")
def tiny_pipe(tiny_dir):
    return load_imagedream(str(tiny_dir), device="cpu")


def _object_image(h=48, w=40):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.ones((h, w, 3), np.float32)
    inside = (xx - w / 2) ** 2 + (yy - h / 2) ** 2 < (min(h, w) / 3) ** 2
    img[inside] = np.stack([0.8 + 0.1 * np.sin(xx / 3), 0.3 + 0.2 * np.cos(yy / 4), 0.2 + 0 * xx], -1)[inside]
    return img


def test_load_tiny_pipeline(tiny_pipe, tiny_dir):
    assert tiny_pipe.device.type == "cpu" and tiny_pipe.dtype == torch.float32
    assert tiny_pipe.image_size == 64
    want = load_file(str(tiny_dir / "unet" / "diffusion_pytorch_model.safetensors"))
    got = tiny_pipe.unet.state_dict()
    assert set(got) == set(want)
    assert all(torch.equal(got[k], want[k].float()) for k in want)
    assert tiny_pipe.scheduler.config.steps_offset == 1
    assert tiny_pipe.to("cpu") is tiny_pipe


def test_generate_views_shape_range_determinism(tiny_pipe):
    img = _object_image()
    calls = []
    a = generate_views(tiny_pipe, img, num_inference_steps=2, seed=0, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 2), (2, 2)]
    assert a.shape == (4, 64, 64, 3) and a.dtype == torch.float32
    assert float(a.min()) >= 0.0 and float(a.max()) <= 1.0 and torch.isfinite(a).all()
    b = generate_views(tiny_pipe, torch.from_numpy(img)[None], num_inference_steps=2, seed=0)
    assert torch.equal(a, b)
    c = generate_views(tiny_pipe, img, num_inference_steps=2, seed=1)
    assert (a - c).abs().max() > 1e-3
    d = generate_views(tiny_pipe, img, num_inference_steps=2, seed=0, guidance_scale=1.0)
    assert d.shape == a.shape and not torch.equal(a, d)
    lgm = views_for_lgm(a)
    assert torch.equal(lgm[0], a[1]) and torch.equal(lgm[3], a[0])


def test_cancel_stops_sampling(tiny_pipe):
    steps = []

    def cancel():
        if len(steps) == 1:
            raise Interrupted("stop")

    with pytest.raises(Interrupted):
        generate_views(tiny_pipe, _object_image(), num_inference_steps=3, seed=0, cancel=cancel,
                       progress=lambda d, t: steps.append(d))
    assert steps == [1]


@pytest.mark.parametrize("kwargs, match", [
    (dict(guidance_scale=0.5), "guidance_scale"),
    (dict(num_inference_steps=0), "num_inference_steps"),
    (dict(num_inference_steps=1001), "num_inference_steps"),
    (dict(seed=-1), "seed"),
    (dict(elevation=95), "elevation"),
])
def test_generate_views_validates_parameters(tiny_pipe, kwargs, match):
    with pytest.raises(InputError, match=match):
        generate_views(tiny_pipe, _object_image(), **kwargs)


@pytest.mark.parametrize("image, match", [
    (np.ones((32, 32), np.float32), r"\[H, W, 3\]"),
    (np.full((32, 32, 3), 255, np.uint8), "float"),
    (np.full((32, 32, 3), 200.0, np.float32), "0..1"),
    (np.full((32, 32, 3), np.nan, np.float32), "NaN"),
])
def test_generate_views_validates_image(tiny_pipe, image, match):
    with pytest.raises(InputError, match=match):
        generate_views(tiny_pipe, image, num_inference_steps=1)


# ----------------------------------------------------------------------------------------------
# loading errors
# ----------------------------------------------------------------------------------------------

def test_missing_folder(tmp_path):
    with pytest.raises(MissingModelError, match="not found") as exc:
        load_imagedream(str(tmp_path / "nope"))
    assert "imagedream-ipmv-diffusers" in str(exc.value)


def test_no_model_in_models_root(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_MODELS", str(tmp_path))
    with pytest.raises(MissingModelError, match="physmotion/imagedream"):
        load_imagedream()


def test_missing_subfolder(tiny_dir, tmp_path):
    broken = tmp_path / "imagedream"
    shutil.copytree(tiny_dir, broken)
    shutil.rmtree(broken / "image_encoder")
    with pytest.raises(MissingModelError, match="missing image_encoder") as exc:
        load_imagedream(str(broken))
    assert "found:" in str(exc.value) and "unet/" in str(exc.value)


def test_missing_unet_weights(tiny_dir, tmp_path):
    broken = tmp_path / "imagedream"
    shutil.copytree(tiny_dir, broken)
    (broken / "unet" / "diffusion_pytorch_model.safetensors").unlink()
    with pytest.raises(MissingModelError, match="diffusion_pytorch_model.safetensors") as exc:
        load_imagedream(str(broken))
    assert "config.json" in str(exc.value)          # the listing of what is there


def test_wrong_unet_weights(tiny_dir, tmp_path):
    broken = tmp_path / "imagedream"
    shutil.copytree(tiny_dir, broken)
    path = broken / "unet" / "diffusion_pytorch_model.safetensors"
    state = load_file(str(path))
    state.pop("image_embed.latents")
    state["out.2.weight"] = torch.zeros(4, 32, 1, 1)
    save_file(state, str(path))
    with pytest.raises(InputError, match="do not match") as exc:
        load_imagedream(str(broken))
    msg = str(exc.value)
    assert "1 missing" in msg and "image_embed.latents" in msg and "out.2.weight" in msg


def test_fp16_variant_and_bin_weights_load(tiny_dir, tmp_path, monkeypatch):
    alt = tmp_path / "imagedream"
    shutil.copytree(tiny_dir, alt)
    src = alt / "unet" / "diffusion_pytorch_model.safetensors"
    torch.save(load_file(str(src)), alt / "unet" / "diffusion_pytorch_model.fp16.bin")
    src.unlink()
    from physmotion_core.lift.imagedream import load_unet

    # A pickle in a folder given by absolute path (not a model folder) needs an explicit opt-in.
    with pytest.raises(InputError, match="pickled checkpoint outside the model folders"):
        load_unet(alt / "unet", device="cpu")
    monkeypatch.setenv("PHYSMOTION_ALLOW_PICKLE", "1")
    unet = load_unet(alt / "unet", device="cpu")
    assert unet.dtype == torch.float32 and len(unet.state_dict()) == len(load_file(str(
        tiny_dir / "unet" / "diffusion_pytorch_model.safetensors")))


def test_not_an_imagedream_unet(tiny_dir, tmp_path):
    alt = tmp_path / "imagedream"
    shutil.copytree(tiny_dir, alt)
    (alt / "unet" / "config.json").write_text(json.dumps({"_class_name": "UNet2DConditionModel"}))
    with pytest.raises(InputError, match="not an ImageDream folder"):
        load_imagedream(str(alt))
