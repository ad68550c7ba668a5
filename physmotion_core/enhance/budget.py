"""Memory a keyframe-shared sampling run needs, estimated before it starts.

The estimate is a model of the run, not a measurement:

* weights: the bytes of every module that sits on the device during sampling (exact);
* UNet + ControlNet activations of one call, per sample: the skip connections the UNet keeps for
  its decoder (and the summed ControlNet residuals of the same shapes), plus the largest transient
  of one block (resnet / transformer with its GEGLU feed-forward) — from the UNet config and the
  latent size; times the samples of a call (branches × frames in the batch);
* attention scores: heads × query-chunk × keys of the largest self-attention call, materialised
  only where no fused kernel exists (``fused=False``); chunking the queries bounds it;
* the keyframe store: for every keyframe, every self-attention layer's output for each branch plus
  the source branch's input tokens (exact: tokens × width × bytes);
* correspondences: one chunk of the cosine-similarity matrix (fp32);
* VAE decoding of one batch of frames (fp32);
* host memory: the inverted latents of every step (exact) and the store when it is kept on the CPU.

A safety factor of 1.25 covers the allocator's fragmentation. The constants were chosen from the
architecture, not calibrated on a GPU yet (see docs/enhance.md: GPU measurements are pending).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from typing import Optional

from ..errors import InputError
from ..memory import fmt_bytes

log = logging.getLogger("physmotion.enhance")

SAFETY = 1.25


@dataclass
class RunShape:
    frames: int
    height: int               # image pixels (working resolution)
    width: int
    steps: int
    keyframes: int
    branches: int             # 3 with guidance, 2 without (source + enhanced)
    frame_batch: int
    keyframe_batch: int
    attention_chunk: int
    store_on_cpu: bool = False
    per_frame: bool = False   # attention="per_frame": no keyframe pass, no store
    vae_batch: int = 1


@dataclass
class MemoryEstimate:
    weights: int
    activations: int
    attention_scores: int
    keyframe_store: int
    correspondence: int
    vae_decode: int
    host_latents: int
    host_store: int
    notes: list = field(default_factory=list)

    @property
    def device_peak(self) -> int:
        sampling = self.activations + self.attention_scores + self.correspondence + self.keyframe_store
        return int(SAFETY * (self.weights + max(sampling, self.vae_decode)))

    @property
    def host_peak(self) -> int:
        return int(SAFETY * (self.host_latents + self.host_store))

    def describe(self) -> str:
        parts = [f"weights {fmt_bytes(self.weights)}", f"activations {fmt_bytes(self.activations)}",
                 f"attention scores {fmt_bytes(self.attention_scores)}",
                 f"keyframe store {fmt_bytes(self.keyframe_store or self.host_store)}"
                 + (" (host)" if self.host_store else ""),
                 f"correspondences {fmt_bytes(self.correspondence)}", f"VAE decode {fmt_bytes(self.vae_decode)}",
                 f"inverted latents {fmt_bytes(self.host_latents)} (host)"]
        return (f"device peak ~{fmt_bytes(self.device_peak)} (" + ", ".join(parts) + f"); host ~{fmt_bytes(self.host_peak)}")


def _levels(unet_config: dict) -> list[dict]:
    ch = list(unet_config["block_out_channels"])
    heads = unet_config.get("attention_head_dim", 8)
    heads = list(heads) if isinstance(heads, (list, tuple)) else [heads] * len(ch)
    attn = ["CrossAttn" in t for t in unet_config["down_block_types"]]
    return [{"c": c, "heads": h, "attn": a} for c, h, a in zip(ch, heads, attn)]


def unet_activation_bytes(unet_config: dict, h: int, w: int, dtype_bytes: int, controlnets: int) -> int:
    """Per-sample activation bytes of one UNet (+ ControlNets) call at latent size h×w."""
    lv = _levels(unet_config)
    lpb = int(unet_config.get("layers_per_block", 2))
    skips, transient = 0, 0
    for i, l in enumerate(lv):
        T = (h >> i) * (w >> i)
        skips += l["c"] * T * lpb + (l["c"] * (T >> 2) if i + 1 < len(lv) else 0)
        # decoder block: concat input (2c), resnet internals (3c), transformer: q,k,v,out (4c),
        # GEGLU feed-forward (8c + 4c)
        transient = max(transient, T * l["c"] * (21 if l["attn"] else 7))
    skips += lv[0]["c"] * h * w  # conv_in
    # ControlNets: their own encoder transient is smaller than the UNet decoder's; the summed
    # residuals (MultiControlNet) and the one being computed are skip-sized.
    cn = (2 if controlnets > 1 else 1) * skips if controlnets else 0
    return (skips + cn + transient) * dtype_bytes


def self_attention_widths(unet_config: dict, h: int, w: int) -> list[tuple[int, int, int]]:
    """(tokens, channels, heads) of every self-attention layer of an SD-style UNet."""
    lv = _levels(unet_config)
    lpb = int(unet_config.get("layers_per_block", 2))
    out = []
    for i, l in enumerate(lv):
        if l["attn"]:
            T = (h >> i) * (w >> i)
            out += [(T, l["c"], l["heads"])] * (lpb + (lpb + 1))  # encoder + decoder layers at this level
    deepest = len(lv) - 1
    out.append(((h >> deepest) * (w >> deepest), lv[-1]["c"], lv[-1]["heads"]))  # mid block
    return out


def vae_decode_bytes(vae_config: dict, H: int, W: int, batch: int) -> int:
    ch = list(vae_config["block_out_channels"])
    n = len(ch)
    peak = 0
    for i, c in enumerate(reversed(ch)):  # decoder runs from the deepest level up to full size
        scale = 2 ** (n - 1 - i)
        peak = max(peak, (H // scale) * (W // scale) * c * 6)
    return peak * 4 * batch


def estimate(models, shape: RunShape, *, fused: Optional[bool] = None) -> MemoryEstimate:
    """The memory model of a sampling run (see the module docstring)."""
    import torch

    ucfg = dict(models.unet.config)
    h, w = shape.height // 8, shape.width // 8
    b = torch.tensor([], dtype=models.dtype).element_size()
    if fused is None:
        fused = torch.device(models.device).type == "cuda" and models.dtype in (torch.float16, torch.bfloat16)
    weights = models.parameter_bytes(["unet", "text_encoder"] + [f"controlnet_{k}" for k in models.controlnets]) \
        + models.parameter_bytes(["vae"])
    per_sample = unet_activation_bytes(ucfg, h, w, b, len(models.controlnets))
    kb = min(shape.keyframe_batch, shape.keyframes) if not shape.per_frame else 0
    samples = shape.branches * max(shape.frame_batch, kb)
    activations = per_sample * samples
    layers = self_attention_widths(ucfg, h, w)
    scores = 0
    if not fused:
        for T, c, heads in layers:
            group = kb if kb else 1
            nq = T * group
            q = min(shape.attention_chunk, nq) if shape.attention_chunk > 0 else nq
            scores = max(scores, shape.branches * heads * q * nq * 4)
    per_kf = sum(T * c for T, c, _ in layers) * (shape.branches + 1) * b
    store = 0 if shape.per_frame else per_kf * shape.keyframes
    T0 = layers[0][0] if layers else h * w
    q = min(shape.attention_chunk, T0) if shape.attention_chunk > 0 else T0
    corr = 0 if shape.per_frame else q * T0 * 4 * 2
    vae = vae_decode_bytes(dict(models.vae.config), shape.height, shape.width, shape.vae_batch)
    host_latents = shape.steps * shape.frames * 4 * h * w * 4
    return MemoryEstimate(weights=weights, activations=activations, attention_scores=scores,
                          keyframe_store=0 if shape.store_on_cpu else store, correspondence=corr, vae_decode=vae,
                          host_latents=host_latents, host_store=store if shape.store_on_cpu else 0,
                          notes=[] if fused else ["attention scores counted as materialised (no fused kernel)"])


def plan(models, shape: RunShape, *, device_available: int, host_available: int, allow_reduce: bool,
         fused: Optional[bool] = None) -> tuple[RunShape, MemoryEstimate, list[str]]:
    """The shape to run (``shape``, or a reduced one when ``allow_reduce``) and its estimate; raises
    InputError naming the estimate and what to change when the run cannot fit."""
    warnings: list[str] = []
    est = estimate(models, shape, fused=fused)

    def fits(e: MemoryEstimate) -> bool:
        return e.device_peak <= device_available and e.host_peak <= host_available

    if fits(est):
        return shape, est, warnings
    if allow_reduce:
        cur = shape
        for _ in range(64):
            if fits(est):
                break
            if cur.frame_batch > 1:
                nxt = replace(cur, frame_batch=max(1, cur.frame_batch // 2))
                why = f"frame_batch {cur.frame_batch} -> {nxt.frame_batch}"
            elif not fused and cur.attention_chunk != 256 and (cur.attention_chunk == 0 or cur.attention_chunk > 256):
                nxt = replace(cur, attention_chunk=256 if cur.attention_chunk == 0 else max(256, cur.attention_chunk // 2))
                why = f"attention_chunk {cur.attention_chunk} -> {nxt.attention_chunk}"
            elif cur.keyframe_batch > 2 and not cur.per_frame:
                nxt = replace(cur, keyframe_batch=max(2, cur.keyframe_batch // 2))
                why = f"keyframe_batch {cur.keyframe_batch} -> {nxt.keyframe_batch} (later keyframe batches share " \
                      "attention with the first keyframe only)"
            elif not cur.store_on_cpu and not cur.per_frame and est.keyframe_store > 0:
                nxt = replace(cur, store_on_cpu=True)
                why = "keyframe store moved to host memory (slower)"
            else:
                break
            cur, est = nxt, estimate(models, nxt, fused=fused)
            warnings.append(why)
        if fits(est):
            for w_ in warnings:
                log.warning("Keyframe-Shared Sample: reduced to fit memory: %s", w_)
            return cur, est, warnings
    raise InputError(
        f"This run needs more memory than is available: {est.describe()}; available: device "
        f"{fmt_bytes(device_available)}, host {fmt_bytes(host_available)}. Lower the resolution or the number of "
        "frames, lower frame_batch / keyframe_batch, set attention_chunk (e.g. 2048), or allow the node to reduce "
        "these itself (memory = reduce).")
