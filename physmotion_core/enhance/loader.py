"""Load SD 2.1 + the depth and canny ControlNets (+ an optional LoRA) from the model folders, offline.

Sources (docs/enhance.md, "Weights"; README.md, "Where weights go"):

* SD 2.1 as a diffusers folder ``models/diffusers/<dir>`` (unet/, vae/, text_encoder/, tokenizer/,
  scheduler/), or as one original-layout file in ``models/checkpoints/`` (e.g.
  ``v2-1_768-ema-pruned.safetensors``), read with diffusers' ``from_single_file`` against the configs
  and CLIP tokenizer shipped in ``physmotion_core/data/sd21_configs`` with ``local_files_only``.
* ControlNets (depth, canny) from ``models/controlnet/``: a diffusers folder or a single file (the
  thibaud SD 2.1 files), used together through diffusers' ``MultiControlNetModel``.
* An optional LoRA from ``models/loras/`` (the peft safetensors our personalisation writes, or a
  diffusers/kohya LoRA file diffusers can read).

Weights are loaded on the CPU in the dtype of the device they will run on (fp16 for CUDA, fp32 for
CPU) and moved there per stage; the VAE stays fp32 (its decoder overflows in fp16 at 768²). Nothing is
ever downloaded: a missing or wrong file is an error naming the folder, the expected file and what
was found.
"""

from __future__ import annotations

import copy
import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import torch

from ..errors import InputError, MissingModelError
from ..models import default_dtype, describe_folder, model_dir, pick_device, safe_child, trust_folder
from .configs import SD21_CONFIG_DIR
from .schedule import PREDICTION_TYPES

log = logging.getLogger("physmotion.enhance")

EXPECTED_SD_FOLDER = ("an SD 2.1 diffusers folder (model_index.json, unet/, vae/, text_encoder/ with their weights; "
                      "tokenizer/ and scheduler/ optional), e.g. the whole stabilityai/stable-diffusion-2-1 repository")
EXPECTED_SD_FILE = "an SD 2.1 single-file checkpoint (.safetensors or .ckpt), e.g. v2-1_768-ema-pruned.safetensors"
EXPECTED_CONTROLNET = ("an SD 2.1 ControlNet: a diffusers folder (config.json + diffusion_pytorch_model.safetensors, "
                       "e.g. thibaud/controlnet-sd21-depth-diffusers) or a single file such as "
                       "control_v11p_sd21_depth.safetensors")
SINGLE_FILE_SUFFIXES = (".safetensors", ".ckpt", ".pt", ".pth", ".bin")

_DIFFUSERS_WEIGHTS = ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.bin")
_TRANSFORMERS_WEIGHTS = ("model.safetensors", "pytorch_model.bin")


# ----------------------------------------------------------------------------------------------
# Finding the files
# ----------------------------------------------------------------------------------------------

def _weights_variant(folder: Path, names: Sequence[str]) -> Optional[str]:
    """"" when plain weights exist, "fp16" when only fp16 variants do, None when neither."""
    if any((folder / n).is_file() for n in names):
        return ""
    for n in names:
        stem, ext = n.rsplit(".", 1)
        if (folder / f"{stem}.fp16.{ext}").is_file():
            return "fp16"
    # sharded weights (index files)
    if any((folder / f"{n}.index.json").is_file() for n in names):
        return ""
    return None


def check_sd_folder(folder: Path) -> str:
    """Validate a diffusers SD folder; returns the weights variant ("" or "fp16")."""
    problems, variants = [], set()
    for sub, names in (("unet", _DIFFUSERS_WEIGHTS), ("vae", _DIFFUSERS_WEIGHTS), ("text_encoder", _TRANSFORMERS_WEIGHTS)):
        d = folder / sub
        if not (d / "config.json").is_file():
            problems.append(f"{sub}/config.json")
            continue
        v = _weights_variant(d, names)
        if v is None:
            problems.append(f"{sub}/{names[0]}")
        else:
            variants.add(v)
    if problems:
        raise MissingModelError(
            f"SD 2.1 folder {folder} is incomplete: missing {', '.join(problems)}. Expected {EXPECTED_SD_FOLDER}; "
            f"{describe_folder(folder)}. Weights are never downloaded: copy the whole folder there.")
    return "fp16" if variants == {"fp16"} else ""


def resolve_sd_source(name: str, root: Optional[os.PathLike] = None) -> tuple[str, Path]:
    """("folder" | "file", path) for a model name: an absolute path, a folder in models/diffusers/
    or a file in models/checkpoints/."""
    if not name or name.strip() in ("", "(none found)"):
        raise MissingModelError(
            f"No SD 2.1 model chosen. Expected {EXPECTED_SD_FOLDER} in {model_dir('diffusers', root)} "
            f"({describe_folder(model_dir('diffusers', root))}) or {EXPECTED_SD_FILE} in "
            f"{model_dir('checkpoints', root)} ({describe_folder(model_dir('checkpoints', root))}). "
            "Weights are never downloaded.")
    p = Path(name).expanduser()
    # an absolute path is the library caller's own choice; a name must stay inside the model folders
    candidates = [p] if p.is_absolute() else [safe_child(model_dir(k, root), name, "SD model")
                                              for k in ("diffusers", "checkpoints")]
    for c in candidates:
        if c.is_dir():
            return "folder", c
        if c.is_file():
            if c.suffix.lower() not in SINGLE_FILE_SUFFIXES:
                raise InputError(f"{c} is not a checkpoint file (expected {', '.join(SINGLE_FILE_SUFFIXES)}).")
            if not p.is_absolute():
                trust_folder(c.parent)
            return "file", c
    where = "; ".join(f"{c.parent} ({describe_folder(c.parent)})" for c in candidates)
    raise MissingModelError(f"SD 2.1 model {name!r} not found. Expected {EXPECTED_SD_FOLDER} in models/diffusers/ "
                            f"or {EXPECTED_SD_FILE} in models/checkpoints/. Looked in: {where}. "
                            "Weights are never downloaded.")


def resolve_controlnet(name: str, kind: str, root: Optional[os.PathLike] = None) -> Path:
    base = model_dir("controlnet", root)
    p = Path(name).expanduser()
    c = p if p.is_absolute() else safe_child(base, name, f"ControlNet ({kind})")
    if c.is_file() and not p.is_absolute():
        trust_folder(base)
    if c.is_dir():
        if not (c / "config.json").is_file() or _weights_variant(c, _DIFFUSERS_WEIGHTS) is None:
            raise MissingModelError(
                f"ControlNet ({kind}) folder {c} is incomplete: expected config.json and "
                f"diffusion_pytorch_model.safetensors; {describe_folder(c)}. Expected {EXPECTED_CONTROLNET}.")
        return c
    if c.is_file():
        return c
    raise MissingModelError(f"ControlNet ({kind}) {name!r} not found at {c}. Expected {EXPECTED_CONTROLNET} in "
                            f"{c.parent}; {describe_folder(c.parent)}. Weights are never downloaded.")


def resolve_lora(name: str, root: Optional[os.PathLike] = None) -> Path:
    base = model_dir("loras", root)
    p = Path(name).expanduser()
    c = p if p.is_absolute() else safe_child(base, name, "LoRA")
    if not c.is_file():
        raise MissingModelError(f"LoRA {name!r} not found at {c}. Expected a .safetensors LoRA (e.g. one written by "
                                f"PhysMotion LoRA Personalize) in {c.parent}; {describe_folder(c.parent)}.")
    return c


# ----------------------------------------------------------------------------------------------
# Checks on single files before diffusers sees them (so the user gets a clear message)
# ----------------------------------------------------------------------------------------------

def _checkpoint_keys(path: Path) -> dict[str, tuple]:
    """Key -> shape of a checkpoint without keeping its tensors."""
    try:
        if path.suffix.lower() == ".safetensors":
            from safetensors import safe_open

            with safe_open(str(path), framework="pt") as fh:
                return {k: tuple(fh.get_slice(k).get_shape()) for k in fh.keys()}
        from ..models import load_state_dict_file

        return {k: tuple(v.shape) for k, v in load_state_dict_file(path).items() if hasattr(v, "shape")}
    except (InputError, MissingModelError):
        raise
    except Exception as exc:  # noqa: BLE001 - corrupt file
        raise InputError(f"Could not read {path}: {exc}. The file may be truncated; re-download it.") from exc


def check_sd_checkpoint(path: Path, cross_attention_dim: int) -> None:
    keys = _checkpoint_keys(path)
    sample = ", ".join(sorted(keys)[:3]) or "no tensors"
    if not any(k.startswith("model.diffusion_model.") for k in keys):
        if any(k.startswith(("down_blocks.", "conv_in.")) for k in keys):
            raise InputError(f"{path.name} holds diffusers-format UNet weights only, not a full SD checkpoint. Put "
                             f"the whole diffusers folder in models/diffusers/ instead. Expected {EXPECTED_SD_FILE}.")
        raise InputError(f"{path.name} is not a Stable Diffusion checkpoint (no model.diffusion_model.* keys; found "
                         f"e.g. {sample}). Expected {EXPECTED_SD_FILE}.")
    if any(k.startswith("conditioner.embedders.") for k in keys):
        raise InputError(f"{path.name} is an SDXL checkpoint; the enhancement needs SD 2.1 ({EXPECTED_SD_FILE}).")
    if any(k.startswith("cond_stage_model.transformer.") for k in keys):
        raise InputError(f"{path.name} is an SD 1.x checkpoint (CLIP ViT-L text encoder); the enhancement needs "
                         f"SD 2.1 (OpenCLIP ViT-H). Expected {EXPECTED_SD_FILE}.")
    if not any(k.startswith("first_stage_model.") for k in keys) or not any(
            k.startswith("cond_stage_model.model.") for k in keys):
        raise InputError(f"{path.name} lacks the VAE (first_stage_model.*) or the OpenCLIP text encoder "
                         "(cond_stage_model.model.*); use a full SD 2.1 checkpoint, not a pruned UNet-only file.")
    k = "model.diffusion_model.input_blocks.1.1.transformer_blocks.0.attn2.to_k.weight"
    if k in keys and keys[k][-1] != cross_attention_dim:
        raise InputError(f"{path.name} has text-conditioning width {keys[k][-1]}, the SD 2.1 config expects "
                         f"{cross_attention_dim}: this is not an SD 2.x checkpoint.")


def check_controlnet_file(path: Path, kind: str, cross_attention_dim: int) -> None:
    keys = _checkpoint_keys(path)
    hints = ("input_hint_block.0.weight", "control_model.input_hint_block.0.weight",
             "controlnet_cond_embedding.conv_in.weight")
    if not any(h in keys for h in hints):
        raise InputError(f"{path.name} in models/controlnet/ is not a ControlNet (no input_hint_block / "
                         f"controlnet_cond_embedding weights; found e.g. {', '.join(sorted(keys)[:3])}). "
                         f"Expected {EXPECTED_CONTROLNET}.")
    for k in ("input_blocks.1.1.transformer_blocks.0.attn2.to_k.weight",
              "control_model.input_blocks.1.1.transformer_blocks.0.attn2.to_k.weight",
              "down_blocks.0.attentions.0.transformer_blocks.0.attn2.to_k.weight"):
        if k in keys and keys[k][-1] != cross_attention_dim:
            raise InputError(f"ControlNet ({kind}) {path.name} was trained for a model with text width {keys[k][-1]} "
                             f"(SD 1.5 ControlNets have 768); SD 2.1 needs {cross_attention_dim}. Use an SD 2.1 "
                             "ControlNet (e.g. thibaud's control_v11p_sd21_*).")


def _no_meta(module: torch.nn.Module, what: str, path: Path) -> None:
    missing = [n for n, p in module.named_parameters() if p.is_meta]
    if missing:
        raise InputError(f"{path.name}: the {what} weights are incomplete ({len(missing)} tensors missing, e.g. "
                         f"{', '.join(missing[:3])}). Check that the file is a complete SD 2.1 release.")


# ----------------------------------------------------------------------------------------------
# The loaded models
# ----------------------------------------------------------------------------------------------

@dataclass
class LoraSpec:
    path: Path
    strength: float = 1.0


@dataclass
class DiffusionModels:
    """SD 2.1 components + ControlNets, on the CPU until a stage places them on ``device``."""

    unet: torch.nn.Module
    vae: torch.nn.Module
    text_encoder: torch.nn.Module
    tokenizer: object
    controlnets: dict  # "depth" / "canny" -> ControlNetModel (a kind may be absent)
    scheduler_config: dict
    prediction_type: str
    device: torch.device
    dtype: torch.dtype
    name: str
    cpu_offload: bool = False
    lora: Optional[LoraSpec] = None
    vae_dtype: torch.dtype = torch.float32
    notes: list = field(default_factory=list)

    # -- identity ------------------------------------------------------------------------------
    def fingerprint(self, with_lora: bool = True) -> str:
        """A content hash of the base weights (a few tensors + configs) and the LoRA, for caches."""
        h = hashlib.sha256()
        h.update(json.dumps({"unet": dict(self.unet.config), "pt": self.prediction_type,
                             "cn": sorted(self.controlnets)}, sort_keys=True, default=str).encode())
        sd = self.unet.state_dict()
        for k in ("conv_in.weight", "conv_out.weight", "time_embedding.linear_1.weight"):
            if k in sd:
                h.update(sd[k].detach().float().cpu().numpy().tobytes())
        for kind in sorted(self.controlnets):
            w = self.controlnets[kind].controlnet_cond_embedding.conv_in.weight
            h.update(kind.encode() + w.detach().float().cpu().numpy().tobytes())
        if with_lora and self.lora is not None:
            h.update(str(Path(self.lora.path).resolve()).encode() + str(Path(self.lora.path).stat().st_mtime_ns).encode())
            h.update(repr(float(self.lora.strength)).encode())
        return h.hexdigest()

    def with_lora(self, path: Optional[os.PathLike], strength: float = 1.0) -> "DiffusionModels":
        """A copy sharing the modules that applies ``path`` (None: no LoRA) whenever it runs."""
        other = copy.copy(self)
        other.notes = list(self.notes)
        other.lora = None if path is None else LoraSpec(Path(path), float(strength))
        return other

    @property
    def has_controlnets(self) -> bool:
        return bool(self.controlnets)

    # -- placement -----------------------------------------------------------------------------
    def modules(self) -> dict:
        out = {"unet": self.unet, "vae": self.vae, "text_encoder": self.text_encoder}
        out.update({f"controlnet_{k}": v for k, v in self.controlnets.items()})
        return out

    def parameter_bytes(self, names: Optional[Sequence[str]] = None) -> int:
        mods = self.modules()
        total = 0
        for n, m in mods.items():
            if names is None or n in names:
                total += sum(p.numel() * p.element_size() for p in m.parameters())
        return total

    def place(self, *names: str) -> None:
        """Move the named modules to ``device`` (the rest stay where they are)."""
        mods = self.modules()
        for n in names:
            if n == "controlnets":
                for cn in self.controlnets.values():
                    cn.to(self.device)
            else:
                mods[n].to(self.device)

    def release(self, *names: str) -> None:
        """With cpu_offload, move the named modules back to the CPU after their stage."""
        if not self.cpu_offload:
            return
        self.offload(names)

    def offload(self, names: Optional[Sequence[str]] = None, device: torch.device | str = "cpu") -> None:
        for n, m in self.modules().items():
            if names is None or n in names or (n.startswith("controlnet_") and "controlnets" in (names or ())):
                m.to(device)
        if torch.device(self.device).type == "cuda":
            torch.cuda.empty_cache()

    # -- LoRA ----------------------------------------------------------------------------------
    def activate_lora(self) -> None:
        """Make the UNet's active adapter match ``self.lora`` (load it once, then switch)."""
        from .lora import activate_lora

        activate_lora(self.unet, self.lora)


def load_diffusion(model: str, *, controlnet_depth: Optional[str] = None, controlnet_canny: Optional[str] = None,
                   lora: Optional[str] = None, lora_strength: float = 1.0, device=None, dtype=None,
                   cpu_offload: bool = False, prediction_type: str = "auto", config_dir: Optional[os.PathLike] = None,
                   root: Optional[os.PathLike] = None) -> DiffusionModels:
    """Load SD 2.1 (+ ControlNets, + LoRA) offline. ``model``/``controlnet_*``/``lora`` are names in the
    model folders (or absolute paths); ``config_dir`` replaces the shipped SD 2.1 configs for
    single files (a folder laid out like ``sd21_configs``)."""
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import CLIPTextModel, CLIPTokenizer

    dev = pick_device(device)
    dt = dtype or default_dtype(dev)
    if prediction_type not in ("auto",) + PREDICTION_TYPES:
        raise InputError(f"prediction_type must be 'auto' or one of {PREDICTION_TYPES}; got {prediction_type!r}")
    cfg_dir = Path(config_dir) if config_dir is not None else SD21_CONFIG_DIR
    kind, path = resolve_sd_source(model, root)
    notes: list[str] = []
    if kind == "folder":
        variant = check_sd_folder(path) or None
        kw = dict(torch_dtype=dt, local_files_only=True, variant=variant)
        unet = UNet2DConditionModel.from_pretrained(path, subfolder="unet", **kw)
        vae = AutoencoderKL.from_pretrained(path, subfolder="vae", torch_dtype=torch.float32, local_files_only=True,
                                            variant=variant)
        text = CLIPTextModel.from_pretrained(path / "text_encoder", torch_dtype=dt, local_files_only=True,
                                             variant=variant)
        tok_dir = path / "tokenizer"
        if not ((tok_dir / "vocab.json").is_file() and (tok_dir / "merges.txt").is_file()):
            tok_dir = cfg_dir / "tokenizer"
            notes.append("tokenizer: the folder has none, using the shipped SD 2.1 CLIP tokenizer")
        tokenizer = CLIPTokenizer.from_pretrained(str(tok_dir), local_files_only=True)
        sched_file = path / "scheduler" / "scheduler_config.json"
        if sched_file.is_file():
            sched_cfg = json.loads(sched_file.read_text())
        else:
            sched_cfg = json.loads((cfg_dir / "scheduler" / "scheduler_config.json").read_text())
            if prediction_type == "auto":
                notes.append("scheduler: the folder has none, using the shipped SD 2.1 768 (v-prediction) config; "
                             "set prediction_type to epsilon for SD 2.1-base")
    else:
        from diffusers import StableDiffusionPipeline

        ucfg = json.loads((cfg_dir / "unet" / "config.json").read_text())
        check_sd_checkpoint(path, int(ucfg["cross_attention_dim"]))
        try:
            pipe = StableDiffusionPipeline.from_single_file(
                str(path), config=str(cfg_dir), local_files_only=True, torch_dtype=dt, safety_checker=None,
                feature_extractor=None, requires_safety_checker=False)
        except (InputError, MissingModelError):
            raise
        except Exception as exc:  # noqa: BLE001 - diffusers' conversion errors, made readable
            raise InputError(f"Could not load {path.name} as SD 2.1 with the configs in {cfg_dir}: {exc}. "
                             f"Expected {EXPECTED_SD_FILE}.") from exc
        unet, vae, text, tokenizer = pipe.unet, pipe.vae.to(torch.float32), pipe.text_encoder, pipe.tokenizer
        for what, m in (("UNet", unet), ("VAE", vae), ("text encoder", text)):
            _no_meta(m, what, path)
        sched_cfg = dict(pipe.scheduler.config)
        del pipe
    pt = sched_cfg.get("prediction_type", "epsilon") if prediction_type == "auto" else prediction_type
    sched_cfg = {**sched_cfg, "prediction_type": pt}
    if sched_cfg.get("clip_sample") or sched_cfg.get("thresholding"):
        notes.append("scheduler: clip_sample/thresholding are ignored (deterministic DDIM needs the linear step)")

    controlnets = {}
    for ckind, cname in (("depth", controlnet_depth), ("canny", controlnet_canny)):
        if not cname or cname in ("(none)", "(none found)"):
            continue
        cpath = resolve_controlnet(cname, ckind, root)
        if cpath.is_dir():
            cn = ControlNetModel.from_pretrained(cpath, torch_dtype=dt, local_files_only=True,
                                                 variant=_weights_variant(cpath, _DIFFUSERS_WEIGHTS) or None)
        else:
            check_controlnet_file(cpath, ckind, int(unet.config.cross_attention_dim))
            try:
                cn = ControlNetModel.from_single_file(str(cpath), config=str(cfg_dir), subfolder=f"controlnet_{ckind}",
                                                      local_files_only=True, torch_dtype=dt)
            except (InputError, MissingModelError):
                raise
            except Exception as exc:  # noqa: BLE001
                raise InputError(f"Could not load ControlNet ({ckind}) {cpath.name}: {exc}. "
                                 f"Expected {EXPECTED_CONTROLNET}.") from exc
            _no_meta(cn, f"ControlNet ({ckind})", cpath)
        if (cn.config.cross_attention_dim != unet.config.cross_attention_dim
                or list(cn.config.block_out_channels) != list(unet.config.block_out_channels)):
            raise InputError(f"ControlNet ({ckind}) {cpath.name} does not fit this SD model (text width "
                             f"{cn.config.cross_attention_dim} vs {unet.config.cross_attention_dim}, channels "
                             f"{list(cn.config.block_out_channels)} vs {list(unet.config.block_out_channels)}). "
                             "Use an SD 2.1 ControlNet.")
        controlnets[ckind] = cn.eval().requires_grad_(False)
    if not controlnets:
        notes.append("no ControlNet: inversion and sampling are conditioned on the prompt only")

    for m in (unet, vae, text):
        m.eval().requires_grad_(False)
    models = DiffusionModels(unet=unet, vae=vae, text_encoder=text, tokenizer=tokenizer, controlnets=controlnets,
                             scheduler_config=sched_cfg, prediction_type=pt, device=dev, dtype=dt,
                             name=path.name, cpu_offload=bool(cpu_offload), notes=notes)
    if lora:
        models = models.with_lora(resolve_lora(lora, root), lora_strength)
        models.activate_lora()  # fail now, not in the middle of a run, if the file is not a LoRA we can read
    for n in notes:
        log.info("Diffusion Loader: %s", n)
    return models
