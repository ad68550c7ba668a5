"""Tiny random-weight SD 2.1 + ControlNet models of the real architectures, for tests and benchmarks.

The configs are the shipped SD 2.1 configs (``physmotion_core/data/sd21_configs``) with only the
sizes shrunk (channels, layers, heads); the block layout (4 down / 4 up blocks, cross-attention in
down blocks 0-2 and up blocks 1-3, linear projections, v-prediction scheduler) is kept, so module
names such as ``up_blocks.1.resnets.1`` mean the same thing as in the real model. The models are
saved in the real formats (a diffusers folder, diffusers ControlNet folders, and, through
:func:`to_ldm_checkpoint`, the original single-file layout that ``models/checkpoints/`` holds) and
are loaded back through :func:`physmotion_core.enhance.loader.load_diffusion`, never used directly.

Nothing here downloads anything; the weights are random (seeded).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Optional

import torch

from physmotion_core.enhance.configs import SD21_CONFIG_DIR, read_config

TINY_UNET = {
    "block_out_channels": [16, 16, 32, 32],
    "attention_head_dim": [2, 2, 4, 4],
    "cross_attention_dim": 32,
    "norm_num_groups": 8,
    "sample_size": 8,
}
TINY_CONTROLNET = {
    "block_out_channels": [16, 16, 32, 32],
    "attention_head_dim": [2, 2, 4, 4],
    "cross_attention_dim": 32,
    "norm_num_groups": 8,
    "conditioning_embedding_out_channels": [4, 8, 8, 16],
}
TINY_VAE = {"block_out_channels": [8, 8, 16, 16], "layers_per_block": 1, "norm_num_groups": 4, "sample_size": 64}
TINY_TEXT = {"hidden_size": 32, "intermediate_size": 64, "num_attention_heads": 2, "num_hidden_layers": 2,
             "projection_dim": 32}

#: Names the template and the tests use for the tiny models inside a models root.
TINY_NAMES = {"diffusers": "stable-diffusion-2-1", "controlnet_depth": "controlnet-sd21-depth-diffusers",
              "controlnet_canny": "controlnet-sd21-canny-diffusers"}


def tiny_configs() -> dict:
    """The shipped configs with the tiny sizes (a dict per component)."""
    unet = {**read_config("unet"), **TINY_UNET}
    cn = {**read_config("controlnet_depth"), **TINY_CONTROLNET}
    vae = {**read_config("vae"), **TINY_VAE}
    text = {**read_config("text_encoder"), **TINY_TEXT}
    sched = read_config("scheduler")
    return {"unet": unet, "controlnet": cn, "vae": vae, "text_encoder": text, "scheduler": sched}


def _randomise_zero_layers(module: torch.nn.Module, generator: torch.Generator, scale: float = 0.05) -> None:
    """Give zero-initialised layers (ControlNet zero convs) random values, so conditions matter."""
    with torch.no_grad():
        for p in module.parameters():
            if p.abs().max() == 0 and p.ndim >= 1 and p.numel() > 1:
                p.copy_(torch.randn(p.shape, generator=generator) * scale)


def build_tiny_components(seed: int = 0, configs: Optional[dict] = None) -> dict:
    """Random-weight UNet, VAE, CLIP text encoder and two ControlNets (float32, CPU)."""
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    cfg = configs or tiny_configs()
    strip = lambda d: {k: v for k, v in d.items() if not k.startswith("_")}  # noqa: E731
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    unet = UNet2DConditionModel(**strip(cfg["unet"]))
    vae = AutoencoderKL(**strip(cfg["vae"]))
    text = CLIPTextModel(CLIPTextConfig(**{k: v for k, v in cfg["text_encoder"].items()
                                          if k not in ("architectures", "_name_or_path")}))
    cns = {}
    for kind in ("depth", "canny"):
        cn = ControlNetModel(**strip(cfg["controlnet"]))
        _randomise_zero_layers(cn, gen)
        cns[kind] = cn
    _randomise_zero_layers(unet, gen)
    # Like SD's 0.18215, scale the VAE latents of natural-ish images to unit variance: a random VAE's
    # raw latents are tiny, and the UNet's first GroupNorm would blow small differences up.
    with torch.no_grad():
        probe = torch.rand(4, 3, 64, 64, generator=gen) * 0.5 + 0.25
        std = float(vae.encode(probe * 2 - 1).latent_dist.mean.std())
    vae.register_to_config(scaling_factor=1.0 / max(std, 1e-6))
    return {"unet": unet.eval(), "vae": vae.eval(), "text_encoder": text.eval(), "controlnet_depth": cns["depth"].eval(),
            "controlnet_canny": cns["canny"].eval(), "scheduler": cfg["scheduler"]}


def save_diffusers_folder(components: dict, folder: os.PathLike, *, tokenizer: bool = True) -> Path:
    """An SD 2.1 diffusers folder (model_index.json, unet/, vae/, text_encoder/, tokenizer/, scheduler/)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    components["unet"].save_pretrained(folder / "unet")
    components["vae"].save_pretrained(folder / "vae")
    components["text_encoder"].save_pretrained(folder / "text_encoder")
    (folder / "scheduler").mkdir(exist_ok=True)
    (folder / "scheduler" / "scheduler_config.json").write_text(json.dumps(components["scheduler"], indent=1))
    if tokenizer:
        shutil.copytree(SD21_CONFIG_DIR / "tokenizer", folder / "tokenizer", dirs_exist_ok=True)
    shutil.copyfile(SD21_CONFIG_DIR / "model_index.json", folder / "model_index.json")
    return folder


def save_config_folder(components: dict, folder: os.PathLike) -> Path:
    """A configs-only folder laid out like ``sd21_configs`` (what single-file loading reads)."""
    folder = Path(folder)
    for name in ("unet", "vae", "controlnet_depth", "controlnet_canny"):
        components[name].save_config(folder / name)
    components["text_encoder"].config.save_pretrained(folder / "text_encoder")
    (folder / "scheduler").mkdir(parents=True, exist_ok=True)
    (folder / "scheduler" / "scheduler_config.json").write_text(json.dumps(components["scheduler"], indent=1))
    shutil.copytree(SD21_CONFIG_DIR / "tokenizer", folder / "tokenizer", dirs_exist_ok=True)
    shutil.copyfile(SD21_CONFIG_DIR / "model_index.json", folder / "model_index.json")
    return folder


def build_tiny_models_root(root: os.PathLike, seed: int = 0, *, single_files: bool = False) -> dict:
    """Populate a models root with the tiny SD 2.1 folder and ControlNet folders under :data:`TINY_NAMES`
    (and, with ``single_files``, an original-layout checkpoint + ControlNet files and a matching
    config folder). Returns the paths."""
    root = Path(root)
    comps = build_tiny_components(seed)
    out = {"root": root}
    out["diffusers"] = save_diffusers_folder(comps, root / "diffusers" / TINY_NAMES["diffusers"])
    for kind in ("depth", "canny"):
        path = root / "controlnet" / TINY_NAMES[f"controlnet_{kind}"]
        comps[f"controlnet_{kind}"].save_pretrained(path)
        out[f"controlnet_{kind}"] = path
    if single_files:
        from safetensors.torch import save_file

        ckpt = root / "checkpoints" / "tiny-sd21.safetensors"
        ckpt.parent.mkdir(parents=True, exist_ok=True)
        save_file(to_ldm_checkpoint(comps["unet"], comps["vae"], comps["text_encoder"]), str(ckpt))
        out["checkpoint"] = ckpt
        for kind in ("depth", "canny"):
            f = root / "controlnet" / f"tiny_control_sd21_{kind}.safetensors"
            save_file(controlnet_to_ldm(comps[f"controlnet_{kind}"]), str(f))
            out[f"controlnet_{kind}_file"] = f
        out["config_dir"] = save_config_folder(comps, root / "tiny_sd21_configs")
    return out


# ----------------------------------------------------------------------------------------------
# diffusers -> original (LDM / OpenCLIP) key layout, to write single-file checkpoints for tests.
# diffusers ships only the other direction; the round trip through its converter is tested.
# ----------------------------------------------------------------------------------------------

_RESNET_TO_LDM = (("norm1", "in_layers.0"), ("conv1", "in_layers.2"), ("time_emb_proj", "emb_layers.1"),
                  ("norm2", "out_layers.0"), ("conv2", "out_layers.3"), ("conv_shortcut", "skip_connection"))


def _resnet_key(rest: str) -> str:
    for new, old in _RESNET_TO_LDM:
        if rest.startswith(new + "."):
            return old + rest[len(new):]
    raise KeyError(rest)


def _unet_like_to_ldm(state: dict, config: dict, *, controlnet: bool = False) -> dict:
    """UNet (or ControlNet encoder) keys from diffusers names to ``input_blocks/middle_block/output_blocks``."""
    from diffusers.loaders.single_file_utils import DIFFUSERS_TO_LDM_MAPPING

    fixed = DIFFUSERS_TO_LDM_MAPPING["controlnet" if controlnet else "unet"]["layers"]
    lpb = int(config["layers_per_block"])
    out = {}
    for key, value in state.items():
        parts = key.split(".")
        if key in fixed:
            out[fixed[key]] = value
        elif parts[0] == "down_blocks":
            i, kind = int(parts[1]), parts[2]
            if kind == "resnets":
                out[f"input_blocks.{1 + i * (lpb + 1) + int(parts[3])}.0." + _resnet_key(".".join(parts[4:]))] = value
            elif kind == "attentions":
                out[f"input_blocks.{1 + i * (lpb + 1) + int(parts[3])}.1." + ".".join(parts[4:])] = value
            elif kind == "downsamplers":
                out[f"input_blocks.{(i + 1) * (lpb + 1)}.0.op." + parts[-1]] = value
            else:
                raise KeyError(key)
        elif parts[0] == "mid_block":
            j = int(parts[2])
            if parts[1] == "resnets":
                out[f"middle_block.{2 * j}." + _resnet_key(".".join(parts[3:]))] = value
            else:
                out["middle_block.1." + ".".join(parts[3:])] = value
        elif parts[0] == "up_blocks":
            i, kind = int(parts[1]), parts[2]
            has_attn = any(k.startswith(f"up_blocks.{i}.attentions.") for k in state)
            if kind == "resnets":
                out[f"output_blocks.{i * (lpb + 1) + int(parts[3])}.0." + _resnet_key(".".join(parts[4:]))] = value
            elif kind == "attentions":
                out[f"output_blocks.{i * (lpb + 1) + int(parts[3])}.1." + ".".join(parts[4:])] = value
            elif kind == "upsamplers":
                out[f"output_blocks.{i * (lpb + 1) + lpb}.{2 if has_attn else 1}.conv." + parts[-1]] = value
            else:
                raise KeyError(key)
        elif controlnet and parts[0] == "controlnet_down_blocks":
            out[f"zero_convs.{parts[1]}.0.{parts[2]}"] = value
        elif controlnet and parts[0] == "controlnet_mid_block":
            out[f"middle_block_out.0.{parts[1]}"] = value
        elif controlnet and key.startswith("controlnet_cond_embedding.blocks."):
            out[f"input_hint_block.{2 * (int(parts[2]) + 1)}.{parts[3]}"] = value
        else:
            raise KeyError(f"no original-layout name for {key}")
    return out


def _vae_to_ldm(state: dict, config: dict) -> dict:
    from diffusers.loaders.single_file_utils import DIFFUSERS_TO_LDM_MAPPING

    fixed = DIFFUSERS_TO_LDM_MAPPING["vae"]
    n_up = len(config["up_block_types"])
    attn_names = {"group_norm": "norm", "to_q": "q", "to_k": "k", "to_v": "v", "to_out.0": "proj_out"}
    out = {}
    for key, value in state.items():
        parts = key.split(".")
        if key in fixed:
            out[fixed[key]] = value
            continue
        side = parts[0]
        if parts[1] == "down_blocks":
            i = parts[2]
            if parts[3] == "resnets":
                out[f"{side}.down.{i}.block.{parts[4]}." + ".".join(parts[5:]).replace("conv_shortcut", "nin_shortcut")] = value
            else:
                out[f"{side}.down.{i}.downsample.conv.{parts[-1]}"] = value
        elif parts[1] == "up_blocks":
            i = n_up - 1 - int(parts[2])
            if parts[3] == "resnets":
                out[f"{side}.up.{i}.block.{parts[4]}." + ".".join(parts[5:]).replace("conv_shortcut", "nin_shortcut")] = value
            else:
                out[f"{side}.up.{i}.upsample.conv.{parts[-1]}"] = value
        elif parts[1] == "mid_block" and parts[2] == "resnets":
            out[f"{side}.mid.block_{int(parts[3]) + 1}." + ".".join(parts[4:]).replace("conv_shortcut", "nin_shortcut")] = value
        elif parts[1] == "mid_block" and parts[2] == "attentions":
            rest = ".".join(parts[4:-1])
            name = attn_names[rest]
            v = value[:, :, None, None] if value.ndim == 2 else value  # linear -> 1x1 conv, as the original
            out[f"{side}.mid.attn_1.{name}.{parts[-1]}"] = v
        else:
            raise KeyError(f"no original-layout name for {key}")
    return out


def _openclip_to_ldm(state: dict) -> dict:
    state = {k.removeprefix("text_model."): v for k, v in state.items()}
    out = {"token_embedding.weight": state["embeddings.token_embedding.weight"],
           "positional_embedding": state["embeddings.position_embedding.weight"],
           "ln_final.weight": state["final_layer_norm.weight"], "ln_final.bias": state["final_layer_norm.bias"]}
    hidden = out["ln_final.weight"].shape[0]
    out["text_projection"] = torch.eye(hidden)
    layers = sorted({int(k.split(".")[2]) for k in state if k.startswith("encoder.layers.")})
    rename = {"layer_norm1": "ln_1", "layer_norm2": "ln_2", "mlp.fc1": "mlp.c_fc", "mlp.fc2": "mlp.c_proj",
              "self_attn.out_proj": "attn.out_proj"}
    for n in layers:
        p = f"encoder.layers.{n}."
        for kind in ("weight", "bias"):
            out[f"transformer.resblocks.{n}.attn.in_proj_{kind}"] = torch.cat(
                [state[p + f"self_attn.{x}_proj.{kind}"] for x in ("q", "k", "v")], 0)
            for new, old in rename.items():
                out[f"transformer.resblocks.{n}.{old}.{kind}"] = state[p + f"{new}.{kind}"]
    return out


def to_ldm_checkpoint(unet, vae, text_encoder) -> dict:
    """One state dict in the original SD 2.x single-file layout (``model.diffusion_model.*``,
    ``first_stage_model.*``, ``cond_stage_model.model.*``)."""
    sd = {}
    for k, v in _unet_like_to_ldm(unet.state_dict(), dict(unet.config)).items():
        sd["model.diffusion_model." + k] = v.contiguous()
    for k, v in _vae_to_ldm(vae.state_dict(), dict(vae.config)).items():
        sd["first_stage_model." + k] = v.contiguous()
    for k, v in _openclip_to_ldm(text_encoder.state_dict()).items():
        sd["cond_stage_model.model." + k] = v.contiguous()
    return sd


def controlnet_to_ldm(controlnet) -> dict:
    """A ControlNet state dict in the layout of the thibaud SD 2.1 single files (no prefix)."""
    return {k: v.contiguous() for k, v in _unet_like_to_ldm(controlnet.state_dict(), dict(controlnet.config),
                                                           controlnet=True).items()}
