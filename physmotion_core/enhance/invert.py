"""DDIM+ inversion of the coarse video, conditioned on depth + Canny edges and a text prompt.

The blended coarse frames (image space, upstream) are encoded by the VAE and walked from clean to
noisy along the sampling timesteps (paper: 1000 training steps, step size 20 = 50 steps, CFG 1),
each step the exact inverse of the deterministic DDIM sampling step for the model's prediction type
(``schedule.py``). "DDIM+" here means DDIM inversion conditioned through both ControlNets, plus
optional fixed-point refinement per step (``refine_iterations``): the model is re-evaluated at the
new estimate of x_t so that the following sampling step lands back on x_{t-1}. The latent at every
sampling timestep is kept (the source branch of the sampler replays them). Frames run in batches;
the result is deterministic and can be cached on disk by a content hash of its inputs.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import torch

from ..errors import InputError
from ..progress import ProgressFn, report
from .conditions import as_depth, as_frames, prepare_conditions, working_size
from .loader import DiffusionModels
from .ops import encode_images, encode_prompts, predict
from .schedule import DDIMSchedule

log = logging.getLogger("physmotion.enhance")


@dataclass
class Inversion:
    """Inverted latents of a clip and the conditions they were made with."""

    latents: torch.Tensor            # (S, F, 4, h, w) float32 CPU; latents[i] = x at timesteps[i] (0 = noisiest)
    clean: torch.Tensor              # (F, 4, h, w) the encoded frames
    timesteps: list
    prompt: str
    controls: dict                   # kind ("depth"/"canny") -> (F, 3, H', W') in [0,1], CPU
    control_scales: dict             # kind -> conditioning scale
    size: tuple                      # (H', W') working resolution in pixels
    input_size: tuple                # (H, W) of the given frames
    prediction_type: str
    model_fingerprint: str
    refine_iterations: int = 0
    notes: list = field(default_factory=list)

    @property
    def frames(self) -> int:
        return int(self.clean.shape[0])

    @property
    def steps(self) -> int:
        return len(self.timesteps)

    def control_list(self, kinds, idx) -> list:
        return [self.controls[k][idx] for k in kinds]

    def preview(self) -> torch.Tensor:
        """(F,H',W',3): the canny edges (or depth) the ControlNets see, for a node preview."""
        for k in ("canny", "depth"):
            if k in self.controls:
                return self.controls[k].permute(0, 2, 3, 1).contiguous()
        return torch.zeros(self.frames, *self.size, 3)


def _hash_inputs(frames: torch.Tensor, depth: Optional[torch.Tensor], settings: dict, fingerprint: str) -> str:
    h = hashlib.sha256()
    h.update((frames * 255 + 0.5).clamp(0, 255).to(torch.uint8).numpy().tobytes())
    if depth is not None:
        h.update((depth * 65535 + 0.5).clamp(0, 65535).to(torch.int32).numpy().tobytes())
    h.update(json.dumps(settings, sort_keys=True).encode())
    h.update(fingerprint.encode())
    return h.hexdigest()


def _save(inv: Inversion, path: Path, key: Optional[str] = None) -> None:
    from safetensors.torch import save_file

    from ..fsutil import atomic_output, tensors_digest

    tensors = {"latents": inv.latents.contiguous(), "clean": inv.clean.contiguous()}
    tensors.update({f"control_{k}": v.contiguous() for k, v in inv.controls.items()})
    meta = {"timesteps": json.dumps(inv.timesteps), "prompt": inv.prompt, "scales": json.dumps(inv.control_scales),
            "size": json.dumps(list(inv.size)), "input_size": json.dumps(list(inv.input_size)),
            "prediction_type": inv.prediction_type, "fingerprint": inv.model_fingerprint,
            "refine_iterations": str(inv.refine_iterations)}
    meta["content_sha256"] = tensors_digest(tensors)
    if key is not None:
        meta["cache_key"] = key
    with atomic_output(path, suffix=".safetensors") as tmp:
        save_file(tensors, str(tmp), metadata=meta)


def _load(path: Path, key: Optional[str] = None) -> Inversion:
    from ..fsutil import load_verified_safetensors

    t, meta = load_verified_safetensors(path, key)
    return Inversion(latents=t["latents"], clean=t["clean"], timesteps=json.loads(meta["timesteps"]),
                     prompt=meta["prompt"], controls={k[8:]: v for k, v in t.items() if k.startswith("control_")},
                     control_scales=json.loads(meta["scales"]), size=tuple(json.loads(meta["size"])),
                     input_size=tuple(json.loads(meta["input_size"])), prediction_type=meta["prediction_type"],
                     model_fingerprint=meta["fingerprint"], refine_iterations=int(meta["refine_iterations"]),
                     notes=["loaded from the inversion cache"])


def invert_frames(models: DiffusionModels, frames, depth=None, *, prompt: str, steps: int = 50,
                  resolution: int = 768, canny_low: float = 100, canny_high: float = 200, depth_scale: float = 1.0,
                  canny_scale: float = 1.0, frame_batch: int = 8, refine_iterations: int = 0,
                  cache_dir: Optional[os.PathLike] = None, progress: Optional[ProgressFn] = None) -> Inversion:
    """Invert IMAGE ``frames`` (F,H,W,3) with their rendered ``depth`` (F,H,W[,3], near = bright)."""
    imgs = as_frames(frames)
    F_, H, W = imgs.shape[:3]
    dep = as_depth(depth, F_) if depth is not None else None
    if frame_batch < 1:
        raise InputError(f"frame_batch must be >= 1; got {frame_batch}")
    if refine_iterations < 0:
        raise InputError(f"refine_iterations must be >= 0; got {refine_iterations}")
    if not isinstance(prompt, str):
        raise InputError("prompt must be text")
    size = working_size(H, W, int(resolution))
    kinds = list(models.controlnets)
    notes = []
    if dep is not None and "depth" not in kinds:
        notes.append("depth given but no depth ControlNet loaded: depth is not used")
    sched = DDIMSchedule.from_config(models.scheduler_config, int(steps), models.prediction_type)
    scales = {"depth": float(depth_scale), "canny": float(canny_scale)}
    scales = {k: scales[k] for k in kinds}
    settings = {"prompt": prompt, "steps": int(steps), "size": list(size), "canny": [float(canny_low), float(canny_high)],
                "scales": scales, "refine": int(refine_iterations), "pt": models.prediction_type,
                "timesteps": sched.timesteps}
    fingerprint = models.fingerprint()
    cache_path = None
    if cache_dir is not None:
        key = _hash_inputs(imgs, dep if "depth" in kinds else None, settings, fingerprint)
        cache_path = Path(cache_dir) / f"inversion_{key[:24]}.safetensors"
        if cache_path.is_file():
            try:
                inv = _load(cache_path, key)
                log.info("DDIM+ Invert: loaded %s from the cache", cache_path.name)
                report(progress, 1, 1)
                return inv
            except Exception as exc:  # noqa: BLE001 - a bad cache file is recomputed
                log.warning("DDIM+ Invert: ignoring unreadable cache file %s (%s)", cache_path, exc)

    x_img, d_img, e_img = prepare_conditions(imgs, dep, size, canny_low, canny_high,
                                             "depth" in kinds, "canny" in kinds)
    controls = {}
    if d_img is not None:
        controls["depth"] = d_img
    if e_img is not None:
        controls["canny"] = e_img
    models.activate_lora()
    text = encode_prompts(models, [prompt])
    clean = encode_images(models, x_img, batch=frame_batch)
    S = sched.steps
    latents = torch.empty((S,) + tuple(clean.shape), dtype=torch.float32)
    total = ((F_ + frame_batch - 1) // frame_batch) * S * (1 + refine_iterations)
    done = 0
    models.place("unet", "controlnets")
    try:
        with torch.no_grad():
            for s in range(0, F_, frame_batch):
                idx = slice(s, min(s + frame_batch, F_))
                x = clean[idx].to(models.device)
                n = x.shape[0]
                emb = text.expand(n, -1, -1)
                ctl = [controls[k][idx] for k in kinds]
                sc = [scales[k] for k in kinds]
                for i in range(S - 1, -1, -1):
                    t = sched.timesteps[i]
                    guess = x
                    for _ in range(1 + refine_iterations):
                        m = predict(models, guess, t, emb, ctl, sc)
                        guess = sched.invert(i, x, m)
                        done += 1
                        report(progress, done, total)
                    if not bool(torch.isfinite(guess).all()):
                        raise InputError(f"Inversion produced NaN/Inf at timestep {t}; the model may be broken "
                                         "(or fp16 overflow): try cpu_offload off / a different checkpoint.")
                    x = guess
                    latents[i, idx] = x.float().cpu()
    finally:
        models.release("unet", "controlnets")
    inv = Inversion(latents=latents, clean=clean.cpu(), timesteps=list(sched.timesteps), prompt=prompt,
                    controls=controls, control_scales=scales, size=size, input_size=(H, W),
                    prediction_type=sched.prediction_type, model_fingerprint=fingerprint,
                    refine_iterations=int(refine_iterations), notes=notes)
    if cache_path is not None:
        _save(inv, cache_path, key)
    for n_ in notes:
        log.info("DDIM+ Invert: %s", n_)
    return inv
