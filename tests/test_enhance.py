"""Generative enhancement (issue 7) on tiny random-weight SD 2.1 / ControlNet / VAE / CLIP models.

The models are the shipped SD 2.1 configs with shrunk sizes (tests/tiny_sd21.py),
saved as a diffusers folder, diffusers ControlNet folders and original-layout single files, and
loaded through the real loader. Everything runs on the CPU at 64x64 pixels (8x8 latents) with a
few DDIM steps.
"""

from __future__ import annotations

import json
import math
import socket
from pathlib import Path

import numpy as np
import pytest
import torch

from physmotion_core.enhance import (LoraSettings, SampleSettings, invert_frames, keyframe_shared_sample,
                                     load_diffusion, personalize)
from physmotion_core.enhance.attention import (FEATURE_LAYER, SharedAttention, nearest_neighbours, shared_attention,
                                               self_attention_layers)
from physmotion_core.enhance.schedule import DDIMSchedule, step_coefficients
from tiny_sd21 import TINY_NAMES, build_tiny_models_root
from physmotion_core.errors import InputError, Interrupted, MissingModelError


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Tiny models are dominated by per-op overhead: one thread is the fastest (and deterministic)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return build_tiny_models_root(tmp_path_factory.mktemp("enhance_models"), seed=0, single_files=True)


def _load(tiny, **kw):
    kw.setdefault("controlnet_depth", TINY_NAMES["controlnet_depth"])
    kw.setdefault("controlnet_canny", TINY_NAMES["controlnet_canny"])
    return load_diffusion(TINY_NAMES["diffusers"], root=tiny["root"], device="cpu", **kw)


@pytest.fixture(scope="module")
def models(tiny):
    return _load(tiny)


def _clip(frames=3, seed=0, size=64):
    g = torch.Generator().manual_seed(seed)
    # smooth random texture (structure at several scales), so Canny finds edges and the VAE sees an image
    base = torch.rand(frames, 3, size // 8, size // 8, generator=g)
    img = torch.nn.functional.interpolate(base, size=(size, size), mode="bilinear", align_corners=False)
    img = (img + 0.15 * torch.rand(frames, 3, size, size, generator=g)).clamp(0, 1)
    depth = torch.linspace(0.2, 0.9, size)[None, :, None].expand(frames, size, size).contiguous()
    return img.permute(0, 2, 3, 1).contiguous(), depth


# ----------------------------------------------------------------------------------------------
# DDIM algebra
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("prediction_type", ["v_prediction", "epsilon", "sample"])
def test_ddim_step_matches_diffusers_and_inverts_exactly(models, prediction_type):
    from diffusers import DDIMScheduler

    cfg = {**models.scheduler_config, "prediction_type": prediction_type}
    ours = DDIMSchedule.from_config(cfg, 10)
    ref = DDIMScheduler.from_config({k: v for k, v in cfg.items() if not k.startswith("_")})
    ref.set_timesteps(10)
    assert ours.timesteps == [int(t) for t in ref.timesteps] == list(range(901, 0, -100))
    g = torch.Generator().manual_seed(1)
    for i in (0, 4, 9):
        x = torch.randn(2, 4, 8, 8, generator=g, dtype=torch.float64)
        m = torch.randn(2, 4, 8, 8, generator=g, dtype=torch.float64)
        expected = ref.step(m, ref.timesteps[i], x, eta=0.0).prev_sample
        got = ours.step(i, x, m)
        assert torch.allclose(got, expected, atol=1e-6), (prediction_type, i)  # diffusers keeps ᾱ in fp32
        assert torch.allclose(ours.invert(i, got, m), x, atol=1e-10)
    # v-prediction's step is a rotation: A² + B² = 1
    A, B = step_coefficients(0.3, 0.7, "v_prediction")
    assert A * A + B * B == pytest.approx(1.0, abs=1e-12)


# ----------------------------------------------------------------------------------------------
# Loader
# ----------------------------------------------------------------------------------------------

def test_loader_reads_the_diffusers_folder_offline(models):
    from diffusers import ControlNetModel, UNet2DConditionModel

    assert set(models.controlnets) == {"depth", "canny"}
    assert models.prediction_type == "v_prediction"  # from the (SD 2.1 768) scheduler config
    assert models.dtype == torch.float32 and models.vae_dtype == torch.float32  # CPU: fp32
    assert isinstance(models.unet, UNet2DConditionModel)
    assert isinstance(models.controlnets["depth"], ControlNetModel)
    ids = models.tokenizer(["a photo of a cat"]).input_ids[0]
    assert ids == [49406, 320, 1125, 539, 320, 2368, 49407]  # the shipped SD 2.1 CLIP tokenizer
    assert not any(p.requires_grad for p in models.unet.parameters())


def _block_network(monkeypatch) -> list:
    """Make every network access fail loudly, and record attempts."""
    attempts: list = []

    def refuse(*args, **kwargs):
        attempts.append(args[:2])
        raise OSError("network access attempted")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    import huggingface_hub
    import huggingface_hub.constants

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    for name in ("hf_hub_download", "snapshot_download"):
        monkeypatch.setattr(huggingface_hub, name, refuse)
        import diffusers.loaders.single_file_utils as sfu
        import diffusers.utils.hub_utils as hu

        for mod in (sfu, hu):
            if hasattr(mod, name):
                monkeypatch.setattr(mod, name, refuse)
    return attempts


def test_single_file_checkpoint_and_controlnets_load_offline_and_match_the_folder(tiny, models, monkeypatch):
    attempts = _block_network(monkeypatch)
    sf = load_diffusion(str(tiny["checkpoint"]), controlnet_depth=str(tiny["controlnet_depth_file"]),
                        controlnet_canny=str(tiny["controlnet_canny_file"]), config_dir=tiny["config_dir"],
                        device="cpu")
    assert attempts == []
    assert sf.prediction_type == "v_prediction"
    for name, mod in sf.modules().items():
        ref = models.modules()[name].state_dict()
        got = mod.state_dict()
        assert set(got) == set(ref), name
        assert max(float((got[k].float() - ref[k].float()).abs().max()) for k in ref) == 0.0, name
    # the same names resolve through the model folders too (checkpoints/ and controlnet/)
    sf2 = load_diffusion("tiny-sd21.safetensors", controlnet_depth="tiny_control_sd21_depth.safetensors",
                         config_dir=tiny["config_dir"], root=tiny["root"], device="cpu")
    assert set(sf2.controlnets) == {"depth"} and attempts == []


def test_missing_and_wrong_weight_files_give_clear_errors(tiny, tmp_path):
    import shutil

    from safetensors.torch import load_file, save_file

    root = tmp_path / "models"
    with pytest.raises(MissingModelError, match=r"not found.*models/diffusers/.*the folder does not exist"):
        load_diffusion("stable-diffusion-2-1", root=root, device="cpu")
    with pytest.raises(InputError, match="must be a name inside"):  # names cannot climb out of the folders
        load_diffusion("../../etc", root=root, device="cpu")
    # an incomplete diffusers folder names the missing file and what is there
    broken = root / "diffusers" / "sd21"
    shutil.copytree(tiny["diffusers"], broken)
    (broken / "unet" / "diffusion_pytorch_model.safetensors").unlink()
    with pytest.raises(MissingModelError, match=r"incomplete: missing unet/diffusion_pytorch_model.safetensors.*found:"):
        load_diffusion("sd21", root=root, device="cpu")
    # an SD 1.x checkpoint (CLIP ViT-L text encoder keys) is refused by name
    sd = load_file(str(tiny["checkpoint"]))
    sd1 = {k.replace("cond_stage_model.model.", "cond_stage_model.transformer."): v for k, v in sd.items()}
    (root / "checkpoints").mkdir(parents=True)
    save_file(sd1, str(root / "checkpoints" / "sd15.safetensors"))
    with pytest.raises(InputError, match="SD 1.x checkpoint"):
        load_diffusion("sd15.safetensors", root=root, device="cpu", config_dir=tiny["config_dir"])
    save_file({"foo.weight": torch.zeros(2)}, str(root / "checkpoints" / "junk.safetensors"))
    with pytest.raises(InputError, match="not a Stable Diffusion checkpoint"):
        load_diffusion("junk.safetensors", root=root, device="cpu", config_dir=tiny["config_dir"])
    # a file that is not a ControlNet, and a ControlNet for another text width (SD 1.5: 768)
    (root / "controlnet").mkdir()
    save_file({"foo.weight": torch.zeros(2)}, str(root / "controlnet" / "junk.safetensors"))
    with pytest.raises(InputError, match="is not a ControlNet"):
        load_diffusion(str(tiny["diffusers"]), controlnet_depth="junk.safetensors", root=root, device="cpu",
                       config_dir=tiny["config_dir"])
    cn = load_file(str(tiny["controlnet_depth_file"]))
    k = "input_blocks.1.1.transformer_blocks.0.attn2.to_k.weight"
    cn[k] = torch.zeros(cn[k].shape[0], 768)
    save_file(cn, str(root / "controlnet" / "sd15_depth.safetensors"))
    with pytest.raises(InputError, match="text width 768"):
        load_diffusion(str(tiny["diffusers"]), controlnet_depth="sd15_depth.safetensors", root=root, device="cpu",
                       config_dir=tiny["config_dir"])
    with pytest.raises(MissingModelError, match=r"ControlNet \(canny\) 'nope' not found"):
        load_diffusion(str(tiny["diffusers"]), controlnet_canny="nope", root=root, device="cpu")
    # a LoRA file that is not a LoRA
    (root / "loras").mkdir()
    save_file({"foo.weight": torch.zeros(2)}, str(root / "loras" / "junk.safetensors"))
    with pytest.raises(InputError, match="as a LoRA"):
        load_diffusion(str(tiny["diffusers"]), lora="junk.safetensors", root=root, device="cpu")


# ----------------------------------------------------------------------------------------------
# Inversion and reconstruction
# ----------------------------------------------------------------------------------------------

def _reconstruct(models, frames, depth, refine, steps=10):
    inv = invert_frames(models, frames, depth, prompt="a jelly cube", steps=steps, resolution=64,
                        refine_iterations=refine, frame_batch=2)
    res = keyframe_shared_sample(models, inv, SampleSettings(prompt="a jelly cube", guidance=1.0, tau_features=0.0,
                                                             tau_attention=0.0, attention="per_frame",
                                                             output_size="diffusion"))
    return inv, float((res.latents - inv.clean).abs().max())


def _epsilon_models(tiny, tmp_path):
    """The tiny SD folder as an ε-prediction model (scheduler config says so; the loader's 'auto' reads
    it). Its output conv is scaled by 0.1: LDM zero-initialises that layer, and a trained ε-model is
    near the identity at high noise, whereas a random one is so sensitive there that the fixed-point
    inversion contracts too slowly for a quick test (see docs/enhance.md)."""
    import shutil

    from safetensors.torch import load_file, save_file

    folder = tmp_path / "diffusers" / "sd21-eps"
    shutil.copytree(tiny["diffusers"], folder)
    cfg = folder / "scheduler" / "scheduler_config.json"
    cfg.write_text(json.dumps({**json.loads(cfg.read_text()), "prediction_type": "epsilon"}))
    w = folder / "unet" / "diffusion_pytorch_model.safetensors"
    sd = load_file(str(w))
    sd = {k: (v * 0.1 if k.startswith("conv_out.") else v) for k, v in sd.items()}
    save_file(sd, str(w))
    m = load_diffusion(str(folder), controlnet_depth=str(tiny["controlnet_depth"]),
                       controlnet_canny=str(tiny["controlnet_canny"]), device="cpu")
    assert m.prediction_type == "epsilon"
    return m


@pytest.mark.parametrize("prediction_type", ["v_prediction", "epsilon"])
def test_inversion_then_sampling_reconstructs_the_latents(tiny, models, prediction_type, tmp_path):
    m = models if prediction_type == "v_prediction" else _epsilon_models(tiny, tmp_path)
    frames, depth = _clip(3)
    errs = {}
    for refine in (0, 1, 2):
        inv, errs[refine] = _reconstruct(m, frames, depth, refine)
    assert inv.latents.shape == (10, 3, 4, 8, 8) and inv.timesteps == list(range(901, 0, -100))
    assert float(inv.clean.std()) == pytest.approx(1.0, rel=0.5)  # latents at SD's unit scale
    # DDIM+ fixed-point refinement: each iteration shrinks the error; with 2 the round trip is
    # within 5e-3 of latents of unit scale (measured ~1e-3 at 10 steps).
    assert errs[2] < 5e-3, errs
    assert errs[0] > errs[1] > errs[2], errs
    # the stored trajectory starts at the noisiest step and its last entry is one step from clean
    assert float((inv.latents[-1] - inv.clean).abs().mean()) < float((inv.latents[0] - inv.clean).abs().mean())


def test_inversion_is_deterministic_batch_independent_and_cached(models, tmp_path):
    frames, depth = _clip(3)
    a = invert_frames(models, frames, depth, prompt="x", steps=3, resolution=64, frame_batch=3)
    b = invert_frames(models, frames, depth, prompt="x", steps=3, resolution=64, frame_batch=1)
    assert torch.allclose(a.latents, b.latents, atol=1e-5)
    assert torch.equal(invert_frames(models, frames, depth, prompt="x", steps=3, resolution=64, frame_batch=3).latents,
                       a.latents)
    # the canny condition is OpenCV's Canny of the frames at the working size
    import cv2

    u8 = (frames[0].numpy() * 255 + 0.5).astype(np.uint8)
    expected = cv2.Canny(cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY), 100, 200) > 0
    assert np.array_equal(a.controls["canny"][0, 0].numpy() > 0.5, expected)
    assert torch.allclose(a.controls["depth"][:, 0], depth, atol=1e-6)
    c1 = invert_frames(models, frames, depth, prompt="x", steps=3, resolution=64, cache_dir=tmp_path)
    files = list(tmp_path.glob("inversion_*.safetensors"))
    assert len(files) == 1
    calls = []
    c2 = invert_frames(models, frames, depth, prompt="x", steps=3, resolution=64, cache_dir=tmp_path,
                       progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 1)] and torch.equal(c1.latents, c2.latents) and c2.notes == ["loaded from the inversion cache"]


# ----------------------------------------------------------------------------------------------
# Attention processors
# ----------------------------------------------------------------------------------------------

def _unet_out(models, x, t, emb, state=None, **state_kw):
    with torch.no_grad():
        if state is None:
            return models.unet(x, t, encoder_hidden_states=emb).sample
        for k, v in state_kw.items():
            setattr(state, k, v)
        with shared_attention(models.unet, state):
            return models.unet(x, t, encoder_hidden_states=emb).sample


def test_extended_attention_over_one_keyframe_is_ordinary_self_attention(models):
    g = torch.Generator().manual_seed(3)
    x = torch.randn(1, 4, 8, 8, generator=g)
    emb = torch.randn(1, 77, 32, generator=g)
    plain = _unet_out(models, x, 500, emb)
    ext = _unet_out(models, x, 500, emb, SharedAttention(), mode="keyframe", branches=1, frames=[0])
    assert float((plain - ext).abs().max()) < 1e-5
    # two identical keyframes: duplicated keys/values leave every softmax average unchanged
    ext2 = _unet_out(models, x.repeat(2, 1, 1, 1), 500, emb.repeat(2, 1, 1), SharedAttention(), mode="keyframe",
                     branches=1, frames=[0, 1])
    assert float((ext2 - plain).abs().max()) < 1e-5
    # and the processors are removed afterwards
    assert all(type(p).__name__ != "SharedSelfAttnProcessor" for p in models.unet.attn_processors.values())


def test_extended_attention_of_two_keyframes_matches_a_direct_computation(models):
    """Each keyframe's queries attend over the keys/values of both keyframes (checked by a hook
    against an independent computation)."""
    name = "down_blocks.0.attentions.0.transformer_blocks.0.attn1"
    attn = models.unet.get_submodule(name)
    seen = {}
    h = attn.register_forward_hook(lambda mod, args, out: seen.update(io=(args[0], out)))
    g = torch.Generator().manual_seed(4)
    x = torch.randn(2, 4, 8, 8, generator=g)
    emb = torch.randn(2, 77, 32, generator=g)
    try:
        _unet_out(models, x, 300, emb, SharedAttention(), mode="keyframe", branches=1, frames=[0, 1])
    finally:
        h.remove()
    hid, out = seen["io"]
    heads = attn.heads
    q, k, v = attn.to_q(hid), attn.to_k(hid), attn.to_v(hid)
    d = q.shape[-1] // heads
    split = lambda t: t.view(2, -1, heads, d).permute(2, 0, 1, 3)  # noqa: E731  (heads, frame, N, d)
    q, k, v = split(q), split(k), split(v)
    keys, vals = k.reshape(heads, -1, d), v.reshape(heads, -1, d)  # both frames' tokens
    w = torch.softmax(q @ keys.transpose(-1, -2)[:, None] / math.sqrt(d), dim=-1)
    o = (w @ vals[:, None]).permute(1, 2, 0, 3).reshape(2, -1, heads * d)
    expected = attn.to_out[0](o)
    assert float((out - expected).abs().max()) < 1e-5
    # and it is not per-frame attention
    w1 = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(d), dim=-1)
    per_frame = attn.to_out[0]((w1 @ v).permute(1, 2, 0, 3).reshape(2, -1, heads * d))
    assert float((out - per_frame).abs().max()) > 1e-3


def test_identical_frames_give_identical_outputs(models):
    frames, depth = _clip(1)
    frames, depth = frames.expand(7, -1, -1, -1).contiguous(), depth.expand(7, -1, -1).contiguous()
    inv = invert_frames(models, frames, depth, prompt="a cube", steps=4, resolution=64)
    res = keyframe_shared_sample(models, inv, SampleSettings(prompt="a shiny cube", keyframe_interval=5, frame_batch=3))
    assert res.keyframes == [0, 5]
    assert float((res.frames - res.frames[:1]).abs().max()) < 1e-5
    assert float((res.latents - res.latents[:1]).abs().max()) < 1e-5
    # and the enhancement did change the frames (guidance 7.5, another prompt)
    assert float((res.latents - inv.clean).abs().mean()) > 1e-2


def test_injection_happens_on_exactly_the_intended_layers_and_steps(models):
    """PnP: residual features of up_blocks.1.resnets.1 for the first τ_f of the steps, decoder
    self-attention Q/K for the first τ_A — recorded by the processors and checked independently by
    hooks on the modules."""
    frames, depth = _clip(6, seed=2)
    S, tau_f, tau_a = 10, 0.4, 0.3
    inv = invert_frames(models, frames, depth, prompt="a cube", steps=S, resolution=64)
    unet = models.unet
    feature_in, attn_io = [], {}
    # input of the module after the injected resnet == the resnet's output after our hook
    consumer = unet.get_submodule("up_blocks.1.attentions.1")
    hooks = [consumer.register_forward_pre_hook(lambda mod, args: feature_in.append(args[0].clone()))]
    layers = self_attention_layers(unet)
    probe = {"up_blocks.2.attentions.0.transformer_blocks.0.attn1": True,
             "down_blocks.1.attentions.0.transformer_blocks.0.attn1": False}
    for name in probe:
        attn_io[name] = []
        hooks.append(unet.get_submodule(name).register_forward_hook(
            lambda mod, args, out, name=name: attn_io[name].append((args[0].clone(), out.clone()))))
    try:
        res = keyframe_shared_sample(models, inv, SampleSettings(prompt="a red cube", guidance=7.5, tau_features=tau_f,
                                                                 tau_attention=tau_a, keyframe_interval=5,
                                                                 frame_batch=4), record=True)
    finally:
        for h in hooks:
            h.remove()
    n_f, n_a = int(S * tau_f), int(S * tau_a)
    ev = res.events
    assert {(s, n) for s, kind, n, *_ in ev if kind == "features"} == {(s, FEATURE_LAYER) for s in range(n_f)}
    qk = {(s, n) for s, kind, n, *_ in ev if kind == "qk"}
    decoder = {n for n, dec in layers.items() if dec}
    assert decoder == {n for n in layers if n.startswith("up_blocks.")} and len(decoder) == 9
    assert qk == {(s, n) for s in range(n_a) for n in decoder}
    # calls per step: one keyframe pass (frames 0, 5) + one propagation pass (frames 1-4); 3 branches
    assert res.keyframes == [0, 5] and len(feature_in) == 2 * S
    for c, x in enumerate(feature_in):
        step = c // 2
        b = x.view(3, -1, *x.shape[1:])
        same = float((b[1:] - b[:1]).abs().max())
        assert (same == 0.0) == (step < n_f), (step, same)
    # Q/K injection: only on the decoder layer, only in its steps; checked on the keyframe passes
    for name, is_decoder in probe.items():
        attn = unet.get_submodule(name)
        for c, (hid, out) in enumerate(attn_io[name]):
            if c % 2:  # propagation passes compute no attention
                continue
            step = c // 2
            heads = attn.heads
            q, k, v = attn.to_q(hid), attn.to_k(hid), attn.to_v(hid)
            d = q.shape[-1] // heads
            sp = lambda t: t.view(3, -1, heads, d).transpose(1, 2)  # noqa: E731 (branch, heads, 2 frames x N, d)
            q, k, v = sp(q), sp(k), sp(v)

            def extended(qq, kk):
                w = torch.softmax(qq @ kk.transpose(-1, -2) / math.sqrt(d), -1)
                return attn.to_out[0]((w @ v).transpose(1, 2).reshape(out.shape))

            own = extended(q, k)
            injected = extended(q[:1].expand_as(q), k[:1].expand_as(k))
            want_injected = is_decoder and step < n_a
            err_inj, err_own = float((out - injected).abs().max()), float((out - own).abs().max())
            if want_injected:
                assert err_inj < 1e-4 < err_own, (name, step, err_inj, err_own)
            else:
                assert err_own < 1e-4 < err_inj, (name, step, err_inj, err_own)


def test_correspondences_recover_a_known_translation():
    g = torch.Generator().manual_seed(5)
    H = W = 12
    a = torch.randn(H, W, 16, generator=g)
    b = torch.roll(a, shifts=(2, -3), dims=(0, 1))  # frame b = frame a moved down 2, left 3 (wrapping)
    idx = nearest_neighbours(b.reshape(-1, 16), a.reshape(-1, 16), chunk=7)
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    expected = ((ys - 2) % H) * W + (xs + 3) % W
    assert torch.equal(idx, expected.reshape(-1))
    # cosine, not Euclidean: a token scaled by 10 still matches itself
    c = a.reshape(-1, 16).clone()
    c[0] *= 10
    assert int(nearest_neighbours(c[:1], a.reshape(-1, 16))[0]) == 0


def test_propagation_blends_the_nearest_keyframes_by_frame_distance(models):
    """A non-keyframe's attention output, token by token: w_prev x (previous keyframe's output at the
    token's nearest source token) + w_next x (next keyframe's), with known correspondences."""
    from physmotion_core.enhance.attention import SharedSelfAttnProcessor
    from physmotion_core.enhance.sample import keyframe_batches, keyframe_neighbours

    nb = keyframe_neighbours(12, [0, 5, 10])
    assert nb[0] == (0, 0, 1.0, 0.0) and nb[5] == (5, 5, 1.0, 0.0)
    assert nb[2] == (0, 5, pytest.approx(0.6), pytest.approx(0.4)) and nb[11] == (10, 10, 1.0, 0.0)
    assert keyframe_batches([0, 5, 10, 15, 20], 3) == [([0, 5, 10], {0, 5, 10}), ([0, 15, 20], {15, 20})]
    assert keyframe_batches([0, 5], 8) == [([0, 5], {0, 5})]

    name = "down_blocks.0.attentions.0.transformer_blocks.0.attn1"
    attn = models.unet.get_submodule(name)
    g = torch.Generator().manual_seed(8)
    N, C = 64, 16
    A = torch.randn(N, C, generator=g)
    perm_b, perm_s = torch.randperm(N, generator=g), torch.randperm(N, generator=g)
    B = A[perm_b]                      # keyframe 5: the same tokens, moved
    S = A[perm_s]                      # frame 2's source tokens: the same tokens, moved again
    OA, OB = torch.randn(2, N, C, generator=g), torch.randn(2, N, C, generator=g)  # 2 branches
    state = SharedAttention(mode="propagate", branches=2, frames=[2, 11], has_source=True,
                            neighbours={2: (0, 5, 0.6, 0.4), 11: (5, 5, 1.0, 0.0)}, chunk=5)
    state.store[name] = {0: (A, OA), 5: (B, OB)}
    hidden = torch.stack([torch.stack([S, B]), torch.randn(2, N, C, generator=g)]).reshape(4, N, C)
    out = SharedSelfAttnProcessor(state, name, decoder=False)(attn, hidden).view(2, 2, N, C)
    inv_b = torch.argsort(perm_b)
    expected2 = 0.6 * OA[:, perm_s] + 0.4 * OB[:, inv_b[perm_s]]
    assert torch.allclose(out[:, 0], expected2, atol=1e-6)
    assert torch.allclose(out[:, 1], OB, atol=1e-6)  # past the last keyframe: that keyframe only


# ----------------------------------------------------------------------------------------------
# Whole sampling runs
# ----------------------------------------------------------------------------------------------

def test_same_inputs_same_result_and_cancel_restores_the_unet(models):
    frames, depth = _clip(4, seed=3)
    inv = invert_frames(models, frames, depth, prompt="a cube", steps=3, resolution=64)
    st = SampleSettings(prompt="a glass cube", keyframe_interval=2, frame_batch=1)
    a = keyframe_shared_sample(models, inv, st)
    b = keyframe_shared_sample(models, inv, st)
    assert torch.equal(a.frames, b.frames) and a.frames.shape == (4, 64, 64, 3)
    before = {k: type(v) for k, v in models.unet.attn_processors.items()}

    def cancel(done, total):
        if done >= 2:
            raise Interrupted("cancelled")

    with pytest.raises(Interrupted):
        keyframe_shared_sample(models, inv, st, progress=cancel)
    assert {k: type(v) for k, v in models.unet.attn_processors.items()} == before
    assert not models.unet.get_submodule(FEATURE_LAYER)._forward_hooks
    c = keyframe_shared_sample(models, inv, st)
    assert torch.equal(c.frames, a.frames)


def test_tokenflow_is_more_consistent_than_per_frame_on_a_static_clip(models):
    """Frames that differ by small noise only: shared keyframe attention makes the outputs closer
    together than independent per-frame sampling."""
    g = torch.Generator().manual_seed(11)
    frames, depth = _clip(1, seed=11)
    frames = (frames.expand(6, -1, -1, -1) + 0.03 * torch.randn(6, 64, 64, 3, generator=g)).clamp(0, 1)
    depth = depth.expand(6, -1, -1).contiguous()
    inv = invert_frames(models, frames, depth, prompt="a cube", steps=4, resolution=64)
    spread = {}
    for mode in ("tokenflow", "per_frame"):
        r = keyframe_shared_sample(models, inv, SampleSettings(prompt="a red cube", attention=mode, keyframe_interval=5))
        spread[mode] = float((r.latents - r.latents.mean(0, keepdim=True)).pow(2).mean())
    assert spread["tokenflow"] < spread["per_frame"], spread


def test_memory_is_estimated_up_front_refused_or_reduced(models):
    frames, depth = _clip(7, seed=1)
    inv = invert_frames(models, frames, depth, prompt="a cube", steps=2, resolution=64)
    st = SampleSettings(frame_batch=4, keyframe_batch=8)
    ok = keyframe_shared_sample(models, inv, st)
    # the keyframe store's estimate is exact
    assert ok.store_peak > 0 and ok.memory.keyframe_store == ok.store_peak
    need = ok.memory.device_peak
    with pytest.raises(InputError, match=r"more memory than is available.*keyframe store.*frame_batch"):
        keyframe_shared_sample(models, inv, st, device_available=need // 3)
    # reduce: smaller batches fit a budget just under the original need (weights dominate here)
    budget = need - 1
    red = keyframe_shared_sample(models, inv, replace_settings(st, memory="reduce"), device_available=budget)
    assert red.memory.device_peak <= budget and red.settings.frame_batch < 4 and red.notes
    assert red.frames.shape == ok.frames.shape
    # the estimate grows with frames (store, host latents) and with resolution
    from physmotion_core.enhance.budget import RunShape, estimate

    s1 = RunShape(frames=16, height=512, width=512, steps=50, keyframes=4, branches=3, frame_batch=4,
                  keyframe_batch=8, attention_chunk=0)
    s2 = RunShape(**{**s1.__dict__, "frames": 48, "keyframes": 10})
    e1, e2 = estimate(models, s1, fused=False), estimate(models, s2, fused=False)
    assert e2.keyframe_store == e1.keyframe_store * 10 // 4 and e2.host_latents == 3 * e1.host_latents
    chunked = estimate(models, RunShape(**{**s2.__dict__, "attention_chunk": 1024}), fused=False)
    assert chunked.attention_scores < e2.attention_scores / 10


def replace_settings(st, **kw):
    from dataclasses import replace

    return replace(st, **kw)


def test_bad_inputs_give_clear_errors(tiny, models):
    frames, depth = _clip(3)
    with pytest.raises(InputError, match="depth has 2 images but there are 3 frames"):
        invert_frames(models, frames, depth[:2], prompt="x", steps=2, resolution=64)
    with pytest.raises(InputError, match=r"frames must be IMAGE frames \[F,H,W,3\]"):
        invert_frames(models, frames[..., 0], depth, prompt="x", steps=2, resolution=64)
    with pytest.raises(InputError, match="no depth was given"):
        invert_frames(models, frames, None, prompt="x", steps=2, resolution=64)
    nan = frames.clone()
    nan[0, 0, 0, 0] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        invert_frames(models, nan, depth, prompt="x", steps=2, resolution=64)
    inv = invert_frames(models, frames, depth, prompt="x", steps=2, resolution=64)
    for kw, msg in (({"tau_features": 1.5}, "tau_features must be in"), ({"attention": "magic"}, "attention must be"),
                    ({"keyframe_interval": 0}, "keyframe_interval"), ({"guidance": -1.0}, "guidance")):
        with pytest.raises(InputError, match=msg):
            keyframe_shared_sample(models, inv, SampleSettings(**kw))
    other = _load(tiny, controlnet_canny=None)
    with pytest.raises(InputError, match="another model"):
        keyframe_shared_sample(other, inv)
    with pytest.raises(InputError, match="instance prompt is empty"):
        personalize(models, [frames[0]], settings=LoraSettings(prompt=" "))


# ----------------------------------------------------------------------------------------------
# LoRA personalisation
# ----------------------------------------------------------------------------------------------

def _eval_loss(models, images, prompt):
    """The diffusion loss (v-prediction target) on fixed noise/timesteps, computed here directly."""
    from physmotion_core.enhance.lora import prepare_images
    from physmotion_core.enhance.ops import encode_images, encode_prompts

    imgs = prepare_images(images, (), 64)
    x0 = encode_images(models, imgs)
    g = torch.Generator().manual_seed(99)
    ac = DDIMSchedule.from_config(models.scheduler_config, 1).alphas_cumprod.float()
    text = encode_prompts(models, [prompt])
    total = 0.0
    for t in (100, 300, 500, 700, 900):
        noise = torch.randn(x0.shape, generator=g)
        a = ac[t]
        xt = a.sqrt() * x0 + (1 - a).sqrt() * noise
        target = a.sqrt() * noise - (1 - a).sqrt() * x0
        with torch.no_grad():
            pred = models.unet(xt, t, encoder_hidden_states=text.expand(x0.shape[0], -1, -1)).sample
        total += float(((pred - target) ** 2).mean())
    return total / 5


def test_lora_trains_saves_reloads_and_is_cached(tiny, models, tmp_path):
    frames, _ = _clip(2, seed=9)
    images = [frames[0], frames[1]]
    prompt = "a photo of sks cube"
    # lr far above the paper's 1e-6 so 40 steps show an effect on the tiny model
    st = LoraSettings(steps=40, learning_rate=5e-3, rank=4, resolution=64, prompt=prompt, seed=3, flip=False)
    models.with_lora(None).activate_lora()
    before = _eval_loss(models, images, prompt)
    res = personalize(models, images, settings=st, folder=tmp_path)
    assert res.trained and len(res.losses) == 40 and res.path.parent == tmp_path
    assert res.path.name == f"physmotion_lora_{res.key[:16]}.safetensors"
    assert res.reload_max_diff < 1e-5
    tuned = models.with_lora(res.path)
    tuned.activate_lora()
    after = _eval_loss(tuned, images, prompt)
    assert after < 0.92 * before, (before, after)  # measured 1.42 -> 1.19
    meta = json.loads(__import__("physmotion_core.enhance.lora", fromlist=["x"]).read_metadata(res.path)["lora_config"])
    assert meta["r"] == 4 and set(meta["target_modules"]) == {"to_q", "to_k", "to_v", "to_out.0"}
    # a fresh loader reading the file gives the same UNet output as the trained models
    fresh = _load(tiny, lora=str(res.path))
    g = torch.Generator().manual_seed(0)
    x, emb = torch.randn(1, 4, 8, 8, generator=g), torch.randn(1, 77, 32, generator=g)
    fresh.activate_lora()
    tuned.activate_lora()
    with torch.no_grad():
        o1 = fresh.unet(x, 400, encoder_hidden_states=emb).sample
        o2 = tuned.unet(x, 400, encoder_hidden_states=emb).sample
        models.with_lora(None).activate_lora()
        o0 = models.unet(x, 400, encoder_hidden_states=emb).sample
    assert float((o1 - o2).abs().max()) < 1e-6 and float((o1 - o0).abs().max()) > 1e-4
    # the same request is a cache hit: no training, the file untouched
    mtime = res.path.stat().st_mtime_ns
    again = personalize(models, images, settings=st, folder=tmp_path)
    assert not again.trained and again.path == res.path and again.losses == []
    assert res.path.stat().st_mtime_ns == mtime
    # another seed is another adapter, the same seed the same one
    other = personalize(models, images, settings=replace_settings(st, seed=4, steps=5), folder=tmp_path)
    same = personalize(models, images, settings=replace_settings(st, seed=4, steps=5), folder=tmp_path / "b")
    from safetensors.torch import load_file

    a, b, c = load_file(str(other.path)), load_file(str(same.path)), load_file(str(res.path))
    assert all(torch.equal(a[k], b[k]) for k in a) and other.path != res.path
    assert any(not torch.equal(a[k], c[k]) for k in a)
    models.with_lora(None).activate_lora()


# ----------------------------------------------------------------------------------------------
# Nodes
# ----------------------------------------------------------------------------------------------

def test_enhancement_nodes_run_end_to_end(tiny, monkeypatch, tmp_path):
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from comfy_harness import node_classes

    monkeypatch.setenv("PHYSMOTION_MODELS", str(tiny["root"]))
    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path / "temp"))
    nodes = node_classes()
    loader = nodes["PhysMotionDiffusionLoader"]
    spec = loader.INPUT_TYPES()["required"]
    assert TINY_NAMES["diffusers"] in spec["model"][0] and "tiny-sd21.safetensors" in spec["model"][0]
    assert spec["controlnet_depth"][1]["default"] == TINY_NAMES["controlnet_depth"]
    (models,) = loader().run(TINY_NAMES["diffusers"], TINY_NAMES["controlnet_depth"], TINY_NAMES["controlnet_canny"],
                             "auto", False)
    frames, depth = _clip(4, seed=5, size=64)
    lora_models, lora_name = nodes["PhysMotionLoRAPersonalize"]().run(
        models, frames[:1], "a photo of sks cube", 3, 1e-4, 2, 64, 0, 1.0, multiview_images=frames[1:3])
    assert (tiny["root"] / "loras" / lora_name).is_file()
    inv, edges = nodes["PhysMotionDDIMInvert"]().run(lora_models, frames, depth[..., None].expand(-1, -1, -1, 3),
                                                    "a photo of sks cube", 3, 64, 1, 100, 200, 1.0, 1.0, 2)
    assert edges.shape == (4, 64, 64, 3) and inv.steps == 3
    out = nodes["PhysMotionKeyframeSharedSample"]().run(lora_models, inv, "", "", 7.5, 0.8, 0.5, 2, "tokenflow", 2, 8,
                                                        4096, "refuse", "input")
    video = out["result"][0]
    assert video.shape == (4, 64, 64, 3) and bool(torch.isfinite(video).all())
    assert out["ui"]["animated"] == (True,)
    # models are back on the CPU after each node
    assert next(models.unet.parameters()).device.type == "cpu"


def test_nodes_report_progress_and_cancel_through_comfyui_hooks(tiny, monkeypatch, tmp_path):
    """A stand-in `comfy` package with ComfyUI's API: the nodes drive its progress bar, and its
    interrupt, raised from the progress callback, stops sampling mid-run with the UNet restored."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from comfy_harness import node_classes
    from fake_comfy import InterruptProcessingException as Interrupt
    from fake_comfy import install_fake_comfy

    state = install_fake_comfy(monkeypatch)
    monkeypatch.setenv("PHYSMOTION_MODELS", str(tiny["root"]))
    monkeypatch.setenv("PHYSMOTION_TEMP_DIR", str(tmp_path / "temp"))
    nodes = node_classes()
    (models,) = nodes["PhysMotionDiffusionLoader"]().run(TINY_NAMES["diffusers"], TINY_NAMES["controlnet_depth"],
                                                         TINY_NAMES["controlnet_canny"], "auto", False)
    frames, depth = _clip(4, seed=6)
    inv, _ = nodes["PhysMotionDDIMInvert"]().run(models, frames, depth[..., None].expand(-1, -1, -1, 3), "a cube",
                                                 3, 64, 0, 100, 200, 1.0, 1.0, 2)
    # 2 frame batches x 3 steps, reported in order up to the total
    assert state.updates[-1] == (6, 6) and [v for v, _ in state.updates] == sorted(v for v, _ in state.updates)
    sample = nodes["PhysMotionKeyframeSharedSample"]()
    args = (models, inv, "", "", 7.5, 0.8, 0.5, 2, "tokenflow", 1, 8, 4096, "refuse", "diffusion")
    state.updates.clear()
    sample.run(*args)
    total = state.updates[-1][1]
    assert state.updates[-1] == (total, total) and total == 3 * (1 + 2) + 4  # steps x passes + decoded frames
    state.updates.clear()
    state.checks, state.cancel_after = 0, 4
    with pytest.raises(Interrupt):
        sample.run(*args)
    assert max(v for v, _ in state.updates) < total
    assert all(type(p).__name__ != "SharedSelfAttnProcessor" for p in models.unet.attn_processors.values())
    assert next(models.unet.parameters()).device.type == "cpu"
