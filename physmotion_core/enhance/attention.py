"""Keyframe-shared self-attention, PnP injection and TokenFlow propagation as diffusers attention
processors and a forward hook (no patched forwards).

One UNet call runs a batch laid out branch-major: ``[source frames | (unconditional frames) |
conditional frames]``, each branch holding the same ``n`` frames. The source branch runs on the
inverted latents with the source (empty) prompt and only provides features; the enhanced branches
are the ones that are denoised. :class:`SharedAttention` says what the current call is; every
self-attention layer (``attn1``) of the UNet gets a :class:`SharedSelfAttnProcessor` reading it:

* ``mode="frame"``: ordinary per-sample self-attention.
* ``mode="keyframe"``: extended attention — within each branch, every frame's queries attend over
  the keys and values of all frames of the batch (the keyframes), and the outputs of the keyframes
  are stored together with the source branch's input tokens.
* ``mode="propagate"`` (TokenFlow): a frame's attention output is not computed; each of its tokens
  takes the stored output of its nearest neighbour (cosine similarity of the source branch's input
  tokens) in the previous and the next keyframe, blended linearly by frame distance.

PnP injection, for the first τ_A of the steps, replaces the enhanced branches' queries and keys by
the source branch's on the decoder (``up_blocks.*``) self-attention layers; for the first τ_f of the
steps a forward hook on ``up_blocks[1].resnets[1]`` replaces the enhanced branches' residual-block
output by the source branch's. Every injection is appended to ``SharedAttention.events`` when
``record`` is set (for tests and diagnostics).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Optional

import torch
import torch.nn.functional as F

FEATURE_LAYER = "up_blocks.1.resnets.1"


def attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, scale: float, chunk: int = 0) -> torch.Tensor:
    """softmax(q kᵀ · scale) v over the last two dims, the queries in chunks of ``chunk`` (0 = all)."""
    n = q.shape[-2]
    if chunk <= 0 or n <= chunk:
        return F.scaled_dot_product_attention(q, k, v, scale=scale)
    return torch.cat([F.scaled_dot_product_attention(q[..., s:s + chunk, :], k, v, scale=scale)
                      for s in range(0, n, chunk)], dim=-2)


def nearest_neighbours(query: torch.Tensor, keys: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """For each row of ``query`` (N,C) the index of the row of ``keys`` (M,C) with the highest cosine
    similarity; computed in chunks of ``chunk`` queries so the N×M matrix never exists whole."""
    qn = F.normalize(query.float(), dim=-1)
    kn = F.normalize(keys.float(), dim=-1)
    step = chunk if chunk > 0 else qn.shape[0]
    return torch.cat([(qn[s:s + step] @ kn.T).argmax(-1) for s in range(0, qn.shape[0], step)])


@dataclass
class SharedAttention:
    """What the next UNet call is; read by every processor and the feature hook."""

    mode: str = "frame"                      # "frame" | "keyframe" | "propagate"
    branches: int = 1                        # samples per frame in the batch (source first when > 1 and has_source)
    frames: list = field(default_factory=list)  # frame index of each of the n samples of a branch
    has_source: bool = False
    store_frames: set = field(default_factory=set)   # keyframe mode: frames whose outputs are kept
    neighbours: dict = field(default_factory=dict)   # propagate mode: frame -> (prev kf, next kf, w_prev, w_next)
    inject_qk: bool = False
    inject_features: bool = False
    step: int = -1
    chunk: int = 0                           # attention / correspondence query chunk (0 = no chunking)
    store_device: Optional[torch.device] = None
    record: bool = False
    events: list = field(default_factory=list)
    store: dict = field(default_factory=dict)  # layer -> frame -> (source tokens (N,C), outputs (branches,N,C))

    def clear_store(self) -> None:
        self.store.clear()

    def log(self, *event) -> None:
        if self.record:
            self.events.append((self.step,) + event)

    def store_bytes(self) -> int:
        return sum(s.numel() * s.element_size() + o.numel() * o.element_size()
                   for layer in self.store.values() for s, o in layer.values())


class SharedSelfAttnProcessor:
    """Self-attention (``attn1``) processor implementing the modes of :class:`SharedAttention`."""

    def __init__(self, state: SharedAttention, name: str, decoder: bool):
        self.state, self.name, self.decoder = state, name, decoder

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states: Optional[torch.Tensor] = None,
                 attention_mask: Optional[torch.Tensor] = None, temb: Optional[torch.Tensor] = None, *args, **kwargs):
        if (encoder_hidden_states is not None or attention_mask is not None or hidden_states.ndim != 3
                or attn.spatial_norm is not None or attn.group_norm is not None):
            from diffusers.models.attention_processor import AttnProcessor2_0

            return AttnProcessor2_0()(attn, hidden_states, encoder_hidden_states, attention_mask, temb)
        st = self.state
        B, N, C = hidden_states.shape
        nb = max(st.branches, 1)
        n = B // nb
        if n * nb != B or (st.frames and len(st.frames) != n):
            raise RuntimeError(f"{self.name}: batch {B} does not match {nb} branches x {len(st.frames)} frames")
        residual = hidden_states
        if st.mode == "propagate":
            out = self._propagate(hidden_states.view(nb, n, N, C))
        else:
            out = self._attend(attn, hidden_states, nb, n)
        if attn.residual_connection:
            out = out + residual
        return out / attn.rescale_output_factor

    # -- attention computed here ------------------------------------------------------------
    def _attend(self, attn, x: torch.Tensor, nb: int, n: int) -> torch.Tensor:
        st = self.state
        B, N, C = x.shape
        heads = attn.heads
        q, k, v = attn.to_q(x), attn.to_k(x), attn.to_v(x)
        inner = k.shape[-1]
        d = inner // heads
        q, k, v = (t.view(nb, n, N, heads, d) for t in (q, k, v))
        if attn.norm_q is not None or attn.norm_k is not None:
            raise RuntimeError("qk-norm attention is not part of SD 2.1")
        if st.inject_qk and self.decoder and st.has_source and nb > 1:
            q = torch.cat([q[:1], q[:1].expand(nb - 1, -1, -1, -1, -1)], 0)
            k = torch.cat([k[:1], k[:1].expand(nb - 1, -1, -1, -1, -1)], 0)
            st.log("qk", self.name)
        if st.mode == "keyframe":
            # (nb, heads, n*N, d): each branch's frames form one sequence
            qh, kh, vh = (t.permute(0, 3, 1, 2, 4).reshape(nb, heads, n * N, d) for t in (q, k, v))
            o = attend(qh, kh, vh, attn.scale, st.chunk)
            o = o.view(nb, heads, n, N, d).permute(0, 2, 3, 1, 4).reshape(B, N, inner)
            st.log("extended", self.name, n)
        else:
            qh, kh, vh = (t.reshape(B, N, heads, d).transpose(1, 2) for t in (q, k, v))
            o = attend(qh, kh, vh, attn.scale, st.chunk)
            o = o.transpose(1, 2).reshape(B, N, inner)
        o = attn.to_out[1](attn.to_out[0](o.to(x.dtype)))
        if st.mode == "keyframe" and st.store_frames:
            layer = st.store.setdefault(self.name, {})
            src = x.view(nb, n, N, C)[0]
            ov = o.view(nb, n, N, -1)
            dev = st.store_device
            for p, f in enumerate(st.frames):
                if f in st.store_frames:
                    layer[f] = (src[p].detach().to(dev) if dev is not None else src[p].detach(),
                                ov[:, p].detach().to(dev) if dev is not None else ov[:, p].detach())
        return o

    # -- TokenFlow propagation ----------------------------------------------------------------
    def _propagate(self, x: torch.Tensor) -> torch.Tensor:
        st = self.state
        nb, n, N, C = x.shape
        layer = st.store.get(self.name)
        if layer is None:
            raise RuntimeError(f"{self.name}: no keyframe outputs stored before propagation")
        src = x[0]
        outs = []
        for p, f in enumerate(st.frames):
            if f in layer:
                outs.append(layer[f][1].to(x.device, x.dtype))
                continue
            a, b, wa, wb = st.neighbours[f]
            sa, oa = layer[a]
            ia = nearest_neighbours(src[p], sa.to(x.device), st.chunk)
            o = oa.to(x.device, x.dtype)[:, ia] * wa
            if b != a and wb > 0:
                sb, ob = layer[b]
                ib = nearest_neighbours(src[p], sb.to(x.device), st.chunk)
                o = o + ob.to(x.device, x.dtype)[:, ib] * wb
            outs.append(o)
        st.log("propagate", self.name, n)
        return torch.stack(outs, 1).reshape(nb * n, N, -1)


class FeatureInjectionHook:
    """Forward hook: the enhanced branches take the source branch's output of this module."""

    def __init__(self, state: SharedAttention, name: str = FEATURE_LAYER):
        self.state, self.name = state, name

    def __call__(self, module, inputs, output):
        st = self.state
        if not (st.inject_features and st.has_source and st.branches > 1):
            return None
        o = output.view(st.branches, -1, *output.shape[1:])
        new = torch.cat([o[:1], o[:1].expand(st.branches - 1, *o.shape[1:])], 0).reshape(output.shape)
        st.log("features", self.name)
        return new


def self_attention_layers(unet) -> dict[str, bool]:
    """Name of every UNet self-attention module -> whether it is a decoder (up block) layer."""
    return {name[: -len(".processor")]: name.startswith("up_blocks.")
            for name in unet.attn_processors if name.endswith("attn1.processor")}


@contextlib.contextmanager
def shared_attention(unet, state: SharedAttention, feature_layer: str = FEATURE_LAYER):
    """Install the processors (self-attention layers only) and the feature hook; restore on exit."""
    original = dict(unet.attn_processors)
    layers = self_attention_layers(unet)
    procs = {}
    for name, proc in original.items():
        base = name[: -len(".processor")]
        procs[name] = SharedSelfAttnProcessor(state, base, layers[base]) if base in layers else proc
    unet.set_attn_processor(procs)
    handle = unet.get_submodule(feature_layer).register_forward_hook(FeatureInjectionHook(state, feature_layer))
    try:
        yield state
    finally:
        handle.remove()
        unet.set_attn_processor(original)
        state.clear_store()
