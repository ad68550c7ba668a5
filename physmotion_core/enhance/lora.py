"""Personalisation (DreamBooth-style LoRA with peft) and LoRA loading/switching on the SD UNet.

The UNet's attention projections (``to_q``, ``to_k``, ``to_v``, ``to_out.0``) get a peft LoRA that is
fine-tuned with the ordinary diffusion loss (the target follows the scheduler's prediction type:
ε, v or x0) on the segmented object and its multi-view images, all under one instance prompt
("a photo of sks ..."). Paper settings: 1500 steps at learning rate 1e-6 (both exposed).

The adapter is saved as peft safetensors in ``models/loras/`` with its LoraConfig and a content hash
of everything that determines it (images, masks, prompt, settings, base-model fingerprint) in the
file's metadata; the file name carries the hash, so the same request finds the file and never
trains twice. Writes are atomic (a Cancel leaves no half-written adapter).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..autograd import normal_parameters, with_autograd
from ..errors import InputError
from ..progress import ProgressFn, report

log = logging.getLogger("physmotion.enhance")

FORMAT = "physmotion-peft-lora-v1"
TRAIN_ADAPTER = "physmotion_train"


@dataclass
class LoraSettings:
    steps: int = 1500                 # paper
    learning_rate: float = 1e-6       # paper
    rank: int = 4
    alpha: Optional[float] = None     # None = rank (scale 1)
    resolution: int = 512
    prompt: str = "a photo of sks object"
    seed: int = 0
    batch_size: int = 1
    flip: bool = True                 # horizontal-flip augmentation
    target_modules: tuple = ("to_q", "to_k", "to_v", "to_out.0")
    weight_decay: float = 1e-2
    gradient_checkpointing: Optional[bool] = None  # None = on CUDA only

    def validate(self) -> None:
        if self.steps < 0:
            raise InputError(f"LoRA steps must be >= 0; got {self.steps}")
        if not (self.learning_rate > 0 and math.isfinite(self.learning_rate)):
            raise InputError(f"LoRA learning_rate must be a positive number; got {self.learning_rate}")
        if self.rank < 1:
            raise InputError(f"LoRA rank must be >= 1; got {self.rank}")
        if self.resolution < 64 or self.resolution % 8:
            raise InputError(f"LoRA resolution must be a multiple of 8 and >= 64; got {self.resolution}")
        if self.batch_size < 1:
            raise InputError(f"LoRA batch_size must be >= 1; got {self.batch_size}")
        if not self.prompt.strip():
            raise InputError("The LoRA instance prompt is empty: give e.g. 'a photo of sks jelly'.")


@dataclass
class LoraResult:
    path: Path
    trained: bool                     # False: found in the cache
    key: str
    losses: list = field(default_factory=list)
    seconds: float = 0.0
    reload_max_diff: float = 0.0      # saved-then-reloaded adapter vs the trained one, on a probe input


# ----------------------------------------------------------------------------------------------
# Training images
# ----------------------------------------------------------------------------------------------

def prepare_images(images: Sequence, masks: Sequence = (), resolution: int = 512) -> torch.Tensor:
    """(N,3,R,R) in [0,1]: each image composited on white through its mask (when given), padded to a
    square with white around the centre, resized to ``resolution``."""
    out = []
    masks = list(masks) + [None] * (len(images) - len(masks))
    for i, (img, m) in enumerate(zip(images, masks)):
        t = torch.as_tensor(np.asarray(img) if not isinstance(img, torch.Tensor) else img).float().cpu()
        if t.ndim == 4 and t.shape[0] == 1:
            t = t[0]
        if t.ndim != 3 or t.shape[-1] not in (3, 4):
            raise InputError(f"personalisation image {i} must be [H,W,3]; got shape {tuple(t.shape)}")
        if t.shape[-1] == 4 and m is None:
            m = t[..., 3]
        t = t[..., :3].clamp(0, 1)
        if m is not None:
            mt = torch.as_tensor(np.asarray(m) if not isinstance(m, torch.Tensor) else m).float().cpu()
            if mt.ndim == 3:
                mt = mt[0]
            if tuple(mt.shape) != tuple(t.shape[:2]):
                raise InputError(f"mask {i} is {tuple(mt.shape)} but image {i} is {tuple(t.shape[:2])}")
            a = mt.clamp(0, 1)[..., None]
            t = t * a + (1 - a)
        H, W = t.shape[:2]
        S = max(H, W)
        canvas = torch.ones(S, S, 3)
        y0, x0 = (S - H) // 2, (S - W) // 2
        canvas[y0:y0 + H, x0:x0 + W] = t
        c = canvas.permute(2, 0, 1)[None]
        mode = "area" if S > resolution else "bilinear"
        c = F.interpolate(c, size=(resolution, resolution), mode=mode,
                          **({} if mode == "area" else {"align_corners": False}))
        out.append(c[0].clamp(0, 1))
    if not out:
        raise InputError("Personalisation needs at least one image of the object.")
    return torch.stack(out)


def cache_key(images: torch.Tensor, settings: LoraSettings, base_fingerprint: str) -> str:
    h = hashlib.sha256()
    h.update(FORMAT.encode())
    h.update((images * 255 + 0.5).clamp(0, 255).to(torch.uint8).numpy().tobytes())
    h.update(json.dumps(asdict(settings), sort_keys=True, default=str).encode())
    h.update(base_fingerprint.encode())
    return h.hexdigest()


def lora_path_for(key: str, folder: os.PathLike) -> Path:
    return Path(folder) / f"physmotion_lora_{key[:16]}.safetensors"


def read_metadata(path: os.PathLike) -> dict:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as fh:
            return dict(fh.metadata() or {})
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"{Path(path).name} is not a readable .safetensors LoRA: {exc}") from exc


# ----------------------------------------------------------------------------------------------
# Adapters on the UNet
# ----------------------------------------------------------------------------------------------

@contextlib.contextmanager
def _quiet_peft():
    """peft warns whenever a second adapter joins a model; several adapters is what we mean to have."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Already found a `peft_config` attribute")
        warnings.filterwarnings("ignore", message="Adapter .* was active which is now deleted")
        yield


def _registry(unet) -> dict:
    reg = getattr(unet, "_physmotion_adapters", None)
    if reg is None:
        reg = {}
        unet._physmotion_adapters = reg
    return reg


def _file_id(path: Path) -> tuple:
    p = Path(path).resolve()
    return (str(p), p.stat().st_mtime_ns)


def load_lora_file(unet, path: Path, adapter_name: str) -> None:
    """Add the LoRA in ``path`` to the UNet as ``adapter_name`` (our peft format, or any SD LoRA file
    diffusers can convert)."""
    from peft import LoraConfig, set_peft_model_state_dict
    from safetensors.torch import load_file

    path = Path(path)
    meta = read_metadata(path) if path.suffix == ".safetensors" else {}
    if meta.get("format") == FORMAT:
        config = LoraConfig(**json.loads(meta["lora_config"]))
        state = load_file(str(path))
        with _quiet_peft():
            unet.add_adapter(config, adapter_name=adapter_name)
        res = set_peft_model_state_dict(unet, state, adapter_name=adapter_name)
        unexpected = list(getattr(res, "unexpected_keys", []) or [])
        if unexpected:
            with _quiet_peft():
                unet.delete_adapters(adapter_name)
            raise InputError(f"LoRA {path.name} does not fit this UNet ({len(unexpected)} unexpected tensors, e.g. "
                             f"{unexpected[0]}); it was trained for another base model.")
        return
    try:
        from diffusers import StableDiffusionPipeline

        state, alphas = StableDiffusionPipeline.lora_state_dict(str(path))
        if not any(k.startswith("unet.") for k in state):
            raise ValueError("no UNet LoRA weights in the file")
        with _quiet_peft():
            unet.load_lora_adapter(state, network_alphas=alphas, prefix="unet", adapter_name=adapter_name)
        if any(k.startswith("text_encoder") for k in state):
            log.warning("LoRA %s: its text-encoder part is ignored (only the UNet part is used)", path.name)
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"Could not read {path.name} as a LoRA for SD 2.1: {exc}. Use a file written by PhysMotion "
                         "LoRA Personalize or a diffusers/kohya SD 2.x LoRA.") from exc


def activate_lora(unet, spec) -> None:
    """Make the UNet run with exactly the LoRA of ``spec`` (a LoraSpec or None) at its strength."""
    reg = _registry(unet)
    if spec is None:
        if getattr(unet, "_hf_peft_config_loaded", False):
            unet.disable_adapters()
        return
    fid = _file_id(spec.path)
    name = reg.get(fid)
    if name is None:
        name = f"physmotion_{len(reg)}"
        load_lora_file(unet, spec.path, name)
        reg[fid] = name
    unet.enable_adapters()
    unet.set_adapters([name], [float(spec.strength)])


# ----------------------------------------------------------------------------------------------
# Training
# ----------------------------------------------------------------------------------------------

@with_autograd
def personalize(models, images: Sequence, masks: Sequence = (), settings: Optional[LoraSettings] = None,
                folder: Optional[os.PathLike] = None, progress: Optional[ProgressFn] = None,
                force: bool = False) -> LoraResult:
    """Fine-tune a LoRA on the object images (cached by content hash in ``folder``, default
    models/loras/). Returns the adapter file; the models are left with the adapter loaded."""
    from safetensors.torch import save_file

    from ..fsutil import atomic_output, tensors_digest
    from ..models import model_dir
    from .ops import encode_prompts
    from .schedule import DDIMSchedule

    st = settings or LoraSettings()
    st.validate()
    imgs = prepare_images(images, masks, st.resolution)
    key = cache_key(imgs, st, models.fingerprint(with_lora=False))
    folder = Path(folder) if folder is not None else model_dir("loras")
    path = lora_path_for(key, folder)
    if path.is_file() and not force:
        from ..fsutil import load_verified_safetensors

        try:
            load_verified_safetensors(path, key)
            log.info("LoRA Personalize: %s already trained for these inputs; not training again", path.name)
            report(progress, 1, 1)
            return LoraResult(path=path, trained=False, key=key)
        except Exception as exc:  # noqa: BLE001 - a damaged or foreign file is retrained and replaced
            log.warning("LoRA Personalize: not using %s (%s); training again", path.name, exc)
    from peft import LoraConfig, get_peft_model_state_dict

    t0 = time.monotonic()
    dev = models.device
    unet = models.unet
    gen = torch.Generator().manual_seed(int(st.seed))
    # Latent posteriors of every image (and its mirror), and the prompt, computed once.
    batch = torch.cat([imgs, imgs.flip(-1)]) if st.flip else imgs
    models.place("vae")
    try:
        with torch.no_grad():
            dists = [models.vae.encode((batch[i:i + 1].to(dev, models.vae_dtype) * 2 - 1)).latent_dist
                     for i in range(batch.shape[0])]
            means = torch.cat([d.mean.float() for d in dists]).cpu()
            stds = torch.cat([d.std.float() for d in dists]).cpu()
    finally:
        models.release("vae")
    text = encode_prompts(models, [st.prompt])
    sched = DDIMSchedule.from_config(models.scheduler_config, 1)

    models.place("unet")
    normal_parameters(unet)  # weights loaded or placed inside ComfyUI's inference mode cannot carry gradients
    was_training = unet.training
    if TRAIN_ADAPTER in (getattr(unet, "peft_config", None) or {}):
        with _quiet_peft():
            unet.delete_adapters(TRAIN_ADAPTER)
    config = LoraConfig(r=int(st.rank), lora_alpha=float(st.alpha or st.rank), init_lora_weights="gaussian",
                        target_modules=list(st.target_modules))
    torch.manual_seed(int(st.seed))  # LoRA A init (peft draws from the global generator)
    with _quiet_peft():
        unet.add_adapter(config, adapter_name=TRAIN_ADAPTER)
    unet.set_adapters([TRAIN_ADAPTER], [1.0])
    unet.enable_adapters()
    params = []
    for n, p in unet.named_parameters():
        train = f".{TRAIN_ADAPTER}." in n or n.endswith(f".{TRAIN_ADAPTER}")
        p.requires_grad_(train)
        if train:
            p.data = p.data.float()
            params.append(p)
    if not params:
        raise RuntimeError("peft added no trainable LoRA parameters to the UNet")
    use_ckpt = st.gradient_checkpointing if st.gradient_checkpointing is not None else dev.type == "cuda"
    if use_ckpt and hasattr(unet, "enable_gradient_checkpointing"):
        unet.enable_gradient_checkpointing()
    opt = torch.optim.AdamW(params, lr=float(st.learning_rate), weight_decay=float(st.weight_decay))
    amp = dev.type == "cuda" and models.dtype == torch.float16
    scaler = torch.amp.GradScaler("cuda") if amp else None
    losses: list[float] = []
    unet.train()
    try:
        for step in range(int(st.steps)):
            idx = torch.randint(0, means.shape[0], (st.batch_size,), generator=gen)
            x0 = means[idx] + stds[idx] * torch.randn(means[idx].shape, generator=gen)
            noise = torch.randn(x0.shape, generator=gen)
            t = torch.randint(0, sched.num_train_timesteps, (st.batch_size,), generator=gen)
            xt = sched.add_noise(x0.double(), noise.double(), t).float()
            target = sched.training_target(x0.double(), noise.double(), t).float()
            with torch.autocast("cuda", dtype=torch.float16, enabled=amp):
                pred = unet(xt.to(dev, models.dtype), t.to(dev), encoder_hidden_states=text.expand(st.batch_size, -1, -1),
                            return_dict=False)[0]
            loss = F.mse_loss(pred.float(), target.to(dev))
            if not torch.isfinite(loss):
                raise InputError(f"LoRA training diverged at step {step} (loss {float(loss)}); lower learning_rate.")
            opt.zero_grad(set_to_none=True)
            if scaler is not None:
                scaler.scale(loss).backward()
                scaler.step(opt)
                scaler.update()
            else:
                loss.backward()
                opt.step()
            losses.append(float(loss.detach()))
            report(progress, step + 1, int(st.steps))
        unet.eval()
        probe_gen = torch.Generator().manual_seed(12345)
        probe = torch.randn((1,) + tuple(means.shape[1:]), generator=probe_gen).to(dev, models.dtype)
        probe_t = torch.full((1,), sched.num_train_timesteps // 2, device=dev, dtype=torch.long)
        with torch.no_grad():
            reference = unet(probe, probe_t, encoder_hidden_states=text, return_dict=False)[0].float()
        state = {k: v.detach().float().cpu().contiguous()
                 for k, v in get_peft_model_state_dict(unet, adapter_name=TRAIN_ADAPTER).items()}
        cfg_dict = {"r": int(st.rank), "lora_alpha": float(st.alpha or st.rank), "target_modules": list(st.target_modules),
                    "init_lora_weights": "gaussian"}
        meta = {"format": FORMAT, "cache_key": key, "lora_config": json.dumps(cfg_dict),
                "settings": json.dumps(asdict(st), default=str), "base_model": models.name,
                "final_loss": f"{losses[-1]:.6g}" if losses else "nan", "images": str(int(imgs.shape[0]))}
        meta["content_sha256"] = tensors_digest(state)
        with atomic_output(path, suffix=".safetensors") as tmp:
            save_file(state, str(tmp), metadata=meta)
    finally:
        if use_ckpt and hasattr(unet, "disable_gradient_checkpointing"):
            unet.disable_gradient_checkpointing()
        unet.train(was_training)
        for p in unet.parameters():
            p.requires_grad_(False)
        # The trained weights now live in the file: load them from there under the file's name, so
        # the run that trained and any later run use the very same adapter.
        with _quiet_peft():
            unet.delete_adapters(TRAIN_ADAPTER)
    from .loader import LoraSpec

    try:
        activate_lora(unet, LoraSpec(path, 1.0))
        with torch.no_grad():
            reloaded = unet(probe, probe_t, encoder_hidden_states=text, return_dict=False)[0].float()
        reload_diff = float((reloaded - reference).abs().max())
        tol = (1e-2 if models.dtype == torch.float16 else 1e-5) * max(1.0, float(reference.abs().max()))
        if not reload_diff <= tol:
            raise RuntimeError(f"the saved LoRA {path.name} does not reproduce the trained one (max diff {reload_diff})")
    finally:
        models.release("unet")
    seconds = time.monotonic() - t0
    log.info("LoRA Personalize: %d steps in %.1f s, loss %.4g -> %.4g, saved %s", len(losses), seconds,
             losses[0] if losses else float("nan"), losses[-1] if losses else float("nan"), path)
    return LoraResult(path=path, trained=True, key=key, losses=losses, seconds=seconds, reload_max_diff=reload_diff)
