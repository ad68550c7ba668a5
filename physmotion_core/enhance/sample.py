"""Keyframe-shared sampling: PnP injection + extended keyframe attention + TokenFlow propagation.

Per DDIM step i (timestep t_i, the same timesteps the inversion used):

1. The source branch is the inverted latent of every frame at t_i with the source prompt (empty by
   default); the enhanced branch (unconditional + conditional halves when guidance ≠ 1) is the
   latent being denoised, started from the inverted latent at the first (noisiest) step.
2. Keyframe pass: the keyframes (every ``keyframe_interval`` frames, the first always) run together;
   in every self-attention layer each keyframe's queries attend over the keys and values of all
   keyframes of the pass (extended attention), and the outputs are stored. With more keyframes than
   ``keyframe_batch`` they run in batches that each also contain the first keyframe (its keys and
   values anchor every batch; its output is kept from the first batch only).
3. Propagation pass: the other frames run in batches of ``frame_batch``; their self-attention
   outputs come from the stored keyframe outputs through nearest-neighbour correspondences of the
   source branch's tokens, blended by frame distance between the previous and the next keyframe.
4. In both passes, for the first τ_f of the steps the enhanced branch takes the source branch's
   features at ``up_blocks[1].resnets[1]``, and for the first τ_A its decoder self-attention queries
   and keys (PnP).
5. Classifier-free guidance (7.5 by default) and one deterministic DDIM step on every frame.

``attention="per_frame"`` skips 2-3 (each frame attends to itself; PnP still applies) — the ablation
that shows what the keyframe sharing buys.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Optional

import torch
import torch.nn.functional as F

from ..errors import InputError
from ..progress import ProgressFn, report
from . import budget
from .attention import SharedAttention, shared_attention
from .invert import Inversion
from .loader import DiffusionModels
from .ops import decode_latents, encode_prompts, predict
from .schedule import DDIMSchedule

log = logging.getLogger("physmotion.enhance")

ATTENTION_MODES = ("tokenflow", "per_frame")


@dataclass
class SampleSettings:
    prompt: str = ""                  # "" = the inversion prompt
    negative_prompt: str = ""
    source_prompt: str = ""           # the source branch's prompt (PnP: empty)
    guidance: float = 7.5
    tau_features: float = 0.8
    tau_attention: float = 0.5
    keyframe_interval: int = 5
    attention: str = "tokenflow"
    frame_batch: int = 4
    keyframe_batch: int = 8
    attention_chunk: int = 4096
    store_on_cpu: bool = False
    memory: str = "refuse"            # "refuse" | "reduce"
    output_size: str = "input"        # "input" (the coarse frames' size) | "diffusion" (working resolution)
    vae_batch: int = 1

    def validate(self) -> None:
        if not (self.guidance >= 0):
            raise InputError(f"guidance must be >= 0; got {self.guidance}")
        for name in ("tau_features", "tau_attention"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise InputError(f"{name} must be in [0, 1] (a fraction of the steps); got {v}")
        if self.keyframe_interval < 1:
            raise InputError(f"keyframe_interval must be >= 1; got {self.keyframe_interval}")
        if self.attention not in ATTENTION_MODES:
            raise InputError(f"attention must be one of {ATTENTION_MODES}; got {self.attention!r}")
        if self.frame_batch < 1 or self.keyframe_batch < 1 or self.vae_batch < 1:
            raise InputError("frame_batch, keyframe_batch and vae_batch must be >= 1")
        if self.attention_chunk < 0:
            raise InputError(f"attention_chunk must be >= 0 (0 = no chunking); got {self.attention_chunk}")
        if self.memory not in ("refuse", "reduce"):
            raise InputError(f"memory must be 'refuse' or 'reduce'; got {self.memory!r}")
        if self.output_size not in ("input", "diffusion"):
            raise InputError(f"output_size must be 'input' or 'diffusion'; got {self.output_size!r}")


@dataclass
class EnhanceResult:
    frames: torch.Tensor              # (F,H,W,3) float32 in [0,1], CPU
    latents: torch.Tensor             # (F,4,h,w) final latents
    keyframes: list
    settings: SampleSettings          # as run (after any memory reduction)
    memory: budget.MemoryEstimate
    seconds: float
    events: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    store_peak: int = 0               # measured bytes of the keyframe store (largest over the steps)


def keyframe_indices(frames: int, interval: int) -> list[int]:
    """Every ``interval``-th frame, starting with the first."""
    return list(range(0, frames, max(1, int(interval))))


def keyframe_neighbours(frames: int, keyframes: list[int]) -> dict:
    """frame -> (previous keyframe, next keyframe, weight of the previous, weight of the next);
    weights fall linearly with the frame distance. Past the last keyframe only the last is used."""
    out = {}
    for f in range(frames):
        a = max(k for k in keyframes if k <= f)
        later = [k for k in keyframes if k >= f]
        b = min(later) if later else a
        if b == a:
            out[f] = (a, a, 1.0, 0.0)
        else:
            out[f] = (a, b, (b - f) / (b - a), (f - a) / (b - a))
    return out


def keyframe_batches(keyframes: list[int], batch: int) -> list[tuple[list[int], set]]:
    """Lists of keyframes to run together and which of them to store (the anchor repeats)."""
    if len(keyframes) <= batch:
        return [(list(keyframes), set(keyframes))]
    if batch == 1:
        return [([k], {k}) for k in keyframes]
    anchor, rest = keyframes[0], keyframes[1:]
    m = batch - 1
    out = []
    for j in range(0, len(rest), m):
        group = rest[j:j + m]
        out.append(([anchor] + group, set(group) | ({anchor} if j == 0 else set())))
    return out


def _memory_available(device: torch.device) -> int:
    from ..memory import device_available_bytes

    return device_available_bytes(f"cuda:{device.index or 0}" if device.type == "cuda" else "cpu")


def keyframe_shared_sample(models: DiffusionModels, inversion: Inversion, settings: Optional[SampleSettings] = None,
                           *, progress: Optional[ProgressFn] = None, record: bool = False,
                           device_available: Optional[int] = None,
                           host_available: Optional[int] = None) -> EnhanceResult:
    """Enhance the inverted clip (see the module docstring); returns IMAGE-layout frames."""
    from ..memory import host_available_bytes

    st = settings or SampleSettings()
    st.validate()
    if inversion.model_fingerprint != models.fingerprint():
        raise InputError("The inversion was made with another model (or LoRA) than the one connected to the "
                         "sampler: connect the same Diffusion Loader / LoRA output to both nodes.")
    t0 = time.monotonic()
    sched = DDIMSchedule.from_config(models.scheduler_config, inversion.steps, models.prediction_type)
    if list(sched.timesteps) != list(inversion.timesteps):
        raise InputError("The sampler's timesteps differ from the inversion's (a different scheduler config): "
                         "use the same model for both.")
    F_ = inversion.frames
    S = inversion.steps
    H, W = inversion.size
    per_frame = st.attention == "per_frame"
    keyframes = [] if per_frame else keyframe_indices(F_, st.keyframe_interval)
    guided = st.guidance != 1.0
    shape = budget.RunShape(frames=F_, height=H, width=W, steps=S, keyframes=len(keyframes),
                            branches=3 if guided else 2, frame_batch=st.frame_batch, keyframe_batch=st.keyframe_batch,
                            attention_chunk=st.attention_chunk, store_on_cpu=st.store_on_cpu, per_frame=per_frame,
                            vae_batch=st.vae_batch)
    dev_avail = device_available if device_available is not None else (
        _memory_available(models.device) + (models.parameter_bytes() if torch.device(models.device).type == "cuda"
                                             and next(models.unet.parameters()).device.type == "cuda" else 0))
    host_avail = host_available if host_available is not None else host_available_bytes()
    shape, est, reductions = budget.plan(models, shape, device_available=dev_avail, host_available=host_avail,
                                         allow_reduce=st.memory == "reduce")
    st = replace(st, frame_batch=shape.frame_batch, keyframe_batch=shape.keyframe_batch,
                 attention_chunk=shape.attention_chunk, store_on_cpu=shape.store_on_cpu)
    log.info("Keyframe-Shared Sample: %d frames at %dx%d, %d steps, %d keyframes; memory %s", F_, W, H, S,
             len(keyframes), est.describe())

    kinds = list(models.controlnets)
    scales = [float(inversion.control_scales.get(k, 1.0)) for k in kinds]
    prompt = st.prompt if st.prompt.strip() else inversion.prompt
    models.activate_lora()
    emb_src, emb_neg, emb_pos = encode_prompts(models, [st.source_prompt, st.negative_prompt, prompt]).split(1)
    n_feat = int(S * st.tau_features)
    n_attn = int(S * st.tau_attention)
    kf_batches = keyframe_batches(keyframes, st.keyframe_batch) if keyframes else []
    kf_set = set(keyframes)
    others = [f for f in range(F_) if f not in kf_set]
    prop_batches = [others[s:s + st.frame_batch] for s in range(0, len(others), st.frame_batch)]
    total = S * (len(kf_batches) + len(prop_batches)) + F_
    done = 0
    store_peak = 0

    state = SharedAttention(chunk=st.attention_chunk, record=record,
                            store_device=torch.device("cpu") if st.store_on_cpu else None,
                            neighbours=keyframe_neighbours(F_, keyframes) if keyframes else {})
    x = inversion.latents[0].clone().to(models.device)  # the enhanced branch starts at the noisiest inverted latent
    models.place("unet", "controlnets")
    try:
        with torch.no_grad(), shared_attention(models.unet, state):
            for i in range(S):
                t = inversion.timesteps[i]
                state.step = i
                state.inject_features = i < n_feat
                state.inject_qk = i < n_attn
                need_source = (not per_frame) or state.inject_features or state.inject_qk
                state.has_source = need_source
                src_lat = inversion.latents[i]
                out = torch.empty_like(x)
                state.clear_store()

                def run(frame_ids: list[int]) -> torch.Tensor:
                    n = len(frame_ids)
                    idx = torch.tensor(frame_ids)
                    lat, emb = [], []
                    if need_source:
                        lat.append(src_lat[idx].to(models.device))
                        emb.append(emb_src.expand(n, -1, -1))
                    if guided:
                        lat.append(x[idx])
                        emb.append(emb_neg.expand(n, -1, -1))
                    lat.append(x[idx])
                    emb.append(emb_pos.expand(n, -1, -1))
                    nb = len(lat)
                    state.branches, state.frames = nb, list(frame_ids)
                    ctl = [inversion.controls[k][idx].repeat(nb, 1, 1, 1) for k in kinds]
                    m = predict(models, torch.cat(lat), t, torch.cat(emb), ctl, scales).view(nb, n, *x.shape[1:])
                    if guided:
                        return m[-2] + st.guidance * (m[-1] - m[-2])
                    return m[-1]

                if per_frame:
                    state.mode = "frame"
                    for s in range(0, F_, st.frame_batch):
                        ids = list(range(s, min(s + st.frame_batch, F_)))
                        out[ids] = run(ids)
                        done += 1
                        report(progress, done, total)
                else:
                    state.mode = "keyframe"
                    for group, keep in kf_batches:
                        state.store_frames = keep
                        m = run(group)
                        for p, f in enumerate(group):
                            if f in keep:
                                out[f] = m[p]
                        done += 1
                        report(progress, done, total)
                    store_peak = max(store_peak, state.store_bytes())
                    state.mode = "propagate"
                    state.store_frames = set()
                    for ids in prop_batches:
                        out[ids] = run(ids)
                        done += 1
                        report(progress, done, total)
                x = sched.step(i, x, out)
                if not bool(torch.isfinite(x).all()):
                    raise InputError(f"Sampling produced NaN/Inf at step {i} (timestep {t}); lower the guidance or "
                                     "check the model files.")
    finally:
        models.release("unet", "controlnets")
    base = done

    def decode_progress(d, tot):
        report(progress, base + d, total)

    imgs = decode_latents(models, x, batch=st.vae_batch, progress=decode_progress)
    if st.output_size == "input" and tuple(imgs.shape[-2:]) != tuple(inversion.input_size):
        imgs = F.interpolate(imgs, size=tuple(inversion.input_size), mode="bicubic", align_corners=False).clamp(0, 1)
    frames = imgs.permute(0, 2, 3, 1).contiguous()
    return EnhanceResult(frames=frames, latents=x.float().cpu(), keyframes=keyframes, settings=st, memory=est,
                         seconds=time.monotonic() - t0, events=list(state.events), notes=reductions, store_peak=store_peak)
