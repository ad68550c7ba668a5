"""Conversion between our Gaussians and ComfyUI's native ``GAUSSIAN`` splat batch.

The library never imports ComfyUI: a native object is read through its attributes (duck typing) and
built by calling the class the caller passes in. The layout matched is the one of
comfyanonymous/ComfyUI ``comfy_api/latest/_util/geometry_types.py`` (class ``GAUSSIAN`` at commit
2c682860a5709b96fd8a891cb6c4b4eaefeb856f, renamed ``SPLAT`` with the same constructor and fields at
0b5657d47bcf0a024cc391839713922e44839ef8) and its users in ``comfy_extras/nodes_gaussian.py``
(commit dd4c7d7661709ddd58d0e942ce6cf69c32993c89)::

    GAUSSIAN(positions, scales, rotations, opacities, sh, counts=None)
    positions (B, N, 3)   world-space centres
    scales    (B, N, 3)   linear per-axis standard deviations
    rotations (B, N, 4)   unit quaternions, w x y z
    opacities (B, N, 1)   in [0, 1]
    sh        (B, N, K, 3) SH coefficients, K = (degree + 1)², DC = sh[..., 0, :] (rgb = 0.5 + C0 * DC)
    counts    (B,) int    real length of each item (rows beyond it are zero padding), or None

Activations, quaternion order and SH layout are ours already (README.md, "Conventions"), so those fields are copied
bit for bit. Only the axes differ: upstream's renderer (``_render_gaussian``) projects with the camera
looking down +z and image rows growing with +y (the OpenCV / 3DGS frame: y down, z away from the
viewer), while our world is +y up with the camera looking down -z. ``axes="y_down"`` (the default)
converts with the 180° rotation about x, D = diag(1, -1, -1): positions D·p, quaternions
q_x(180°) ⊗ q, SH coefficient (l, m) times its parity under D. It is a proper rotation (both frames
are right-handed) and every step is a sign flip or a permutation, so a round trip is exact.
``axes="as_is"`` copies positions unchanged (what .ply files do: ours and upstream's
File3DToGaussian both read and write x y z as stored).

Our ``covars`` (the simulator's deformed shapes, Σ = F Σ₀ Fᵀ) have no native field: they are
converted to rotation + scales by ``Gaussians.with_covariance_as_rotscale`` (an eigen-decomposition
in float64), which reproduces Σ to float32 rounding (about 1e-6 relative), not bit for bit.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Optional, Sequence

import torch

from .errors import InputError
from .memory import host_available_bytes
from .types.gaussians import Gaussians
from .types.results import SimResult

AXES = ("y_down", "as_is")
NATIVE_FIELDS = ("positions", "scales", "rotations", "opacities", "sh")

#: D = diag(1, -1, -1): our +y-up / camera-looks-down--z frame <-> the native y-down / +z-forward frame.
_FLIP = (1.0, -1.0, -1.0)


def is_native_gaussian(value: Any) -> bool:
    """True for an object with the native GAUSSIAN fields (whatever its class is called)."""
    return not isinstance(value, Gaussians) and all(hasattr(value, f) for f in NATIVE_FIELDS)


def check_splat_values(where: str, means, scales, quats, opacities, sh) -> None:
    """The checks every entry of splats into the library makes (the .ply reader, both converters): no
    NaN or infinite value in any field, positive scales (linear, not log), opacities in [0, 1] (not
    logits), quaternions that are not all zero. ``where`` names the input in the message."""
    n = int(means.shape[0])
    for name, t in (("positions", means), ("scales", scales), ("rotations", quats), ("opacities", opacities),
                    ("sh", sh)):
        if t.numel() and not bool(torch.isfinite(t).all()):
            rows = t.reshape(t.shape[0], -1) if t.ndim > 1 else t[:, None]
            bad = int((~torch.isfinite(rows)).any(dim=1).sum())
            raise InputError(f"{where}: {bad} of {n} splats have a NaN or infinite {name} value; the splat is "
                             "damaged or came from a diverged optimisation. Re-create or re-export it (the .ply "
                             "reader refuses the same values).")
    if scales.numel() and bool((scales <= 0).any()):
        bad = int((scales <= 0).any(dim=-1).sum())
        raise InputError(f"{where}: {bad} of {n} splats have a scale <= 0; scales must be positive linear sizes in "
                         "metres (log-scales, as a .ply stores them, must be exponentiated first).")
    if opacities.numel() and bool(((opacities < 0) | (opacities > 1)).any()):
        bad = int(((opacities < 0) | (opacities > 1)).reshape(n, -1).any(dim=-1).sum())
        raise InputError(f"{where}: {bad} of {n} splats have an opacity outside [0, 1]; opacities must be "
                         "probabilities (logits, as a .ply stores them, must go through a sigmoid first).")
    if quats.numel() and bool((quats.abs().sum(dim=-1) == 0).any()):
        bad = int((quats.abs().sum(dim=-1) == 0).sum())
        raise InputError(f"{where}: {bad} of {n} splats have an all-zero rotation quaternion, which is no "
                         "rotation; the splat is damaged. Re-create it (unit quaternions, w x y z).")


def _check_axes(axes: str) -> None:
    if axes not in AXES:
        raise InputError(f"axes must be one of {AXES}; got {axes!r}")


def sh_flip_signs(k: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(K,) signs of the SH coefficients under D = diag(1, -1, -1) (a 180° turn about x).

    Real SH basis (l, m) in the 3DGS order m = -l..l is a polynomial whose parity in (y, z) is
    (-1)^(l+m) for m >= 0 and (-1)^(l+m+1) for m < 0 (e.g. l=1: -y, z, -x -> -1, -1, +1).
    """
    degree = int(round(math.sqrt(k))) - 1
    if (degree + 1) ** 2 != k:
        raise InputError(f"the SH coefficients have K={k} per channel, which is not (degree+1)² "
                         "(1, 4, 9, 16, ...); cannot turn them into the other axes")
    signs = []
    for ell in range(degree + 1):
        for m in range(-ell, ell + 1):
            p = ell + m + (1 if m < 0 else 0)
            signs.append(-1.0 if p % 2 else 1.0)
    return torch.tensor(signs, dtype=dtype, device=device)


def _quat_flip(q: torch.Tensor) -> torch.Tensor:
    """q_x(180°) ⊗ q for wxyz quaternions: (w, x, y, z) -> (-x, w, -z, y) (exact)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([-x, w, -z, y], dim=-1)


def _quat_unflip(q: torch.Tensor) -> torch.Tensor:
    """The inverse of ``_quat_flip`` (exact): (a, b, c, d) -> (b, -a, d, -c)."""
    a, b, c, d = q.unbind(-1)
    return torch.stack([b, -a, d, -c], dim=-1)


def _to_native_axes(means, quats, sh):
    f = torch.tensor(_FLIP, dtype=means.dtype, device=means.device)
    s = sh_flip_signs(sh.shape[-2], sh.dtype, sh.device)
    return means * f, _quat_flip(quats), sh * s[:, None]


def _from_native_axes(pos, rot, sh):
    f = torch.tensor(_FLIP, dtype=pos.dtype, device=pos.device)
    s = sh_flip_signs(sh.shape[-2], sh.dtype, sh.device)
    return pos * f, _quat_unflip(rot), sh * s[:, None]


# ----------------------------------------------------------------------------------------------
# ours -> native
# ----------------------------------------------------------------------------------------------


def split_objects(g: Gaussians) -> list[Gaussians]:
    """One Gaussians per object id (0, 1, ...; order kept inside each); a scene without ids is one item."""
    if g.object_ids is None:
        return [g]
    ids = g.object_ids
    out = []
    for k in sorted(int(i) for i in torch.unique(ids).tolist()):
        sub = g.subset(torch.nonzero(ids == k).flatten())
        out.append(Gaussians(means=sub.means, quats=sub.quats, scales=sub.scales, opacities=sub.opacities,
                             sh=sub.sh, covars=sub.covars, object_ids=None))
    return out


def to_native_tensors(items: Gaussians | Sequence[Gaussians], *, axes: str = "y_down",
                      split: bool = False) -> dict[str, Optional[torch.Tensor]]:
    """The native fields for one set of Gaussians (one batch item; ``split``: one item per object)
    or a list of sets (one item each). Shorter items are zero-padded, ``counts`` gives their
    lengths (None when all are equally long); SH of lower degree are zero-padded to the highest K.
    """
    _check_axes(axes)
    if isinstance(items, Gaussians):
        items = split_objects(items) if split else [items]
    items = list(items)
    if not items:
        raise InputError("no Gaussians to convert (an empty list)")
    rows = []
    for i, g in enumerate(items):
        if not isinstance(g, Gaussians):
            raise InputError(f"expected physmotion Gaussians, got {type(g).__name__}")
        where = "the Gaussians to convert" + (f" (item {i} of {len(items)})" if len(items) > 1 else "")
        g = g.with_covariance_as_rotscale()
        check_splat_values(where, g.means, g.scales, g.quats, g.opacities, g.sh)
        means, quats, sh = g.means, g.quats, g.sh
        if axes == "y_down":
            means, quats, sh = _to_native_axes(means, quats, sh)
        rows.append((means, g.scales, quats, g.opacities[:, None], sh))
    n = max(r[0].shape[0] for r in rows)
    if n == 0:  # an empty item among others is a real (zero-length) batch item; nothing at all is not
        raise InputError(f"the Gaussians to convert hold no splats ({'every item is empty' if len(rows) > 1 else '0 Gaussians'}):"
                         " a GAUSSIAN needs at least one splat. The lift, fit or selection upstream produced "
                         "nothing; check its mask or settings.")
    k = max(r[4].shape[1] for r in rows)
    lengths = [r[0].shape[0] for r in rows]
    ref = rows[0][0]

    def stack(idx: int, tail: tuple[int, ...]) -> torch.Tensor:
        out = torch.zeros((len(rows), n) + tail, dtype=rows[0][idx].dtype, device=ref.device)
        for b, r in enumerate(rows):
            t = r[idx].to(ref.device)
            if idx == 4:
                out[b, : t.shape[0], : t.shape[1]] = t
            else:
                out[b, : t.shape[0]] = t
        return out

    uniform = len(set(lengths)) == 1
    return {
        "positions": stack(0, (3,)),
        "scales": stack(1, (3,)),
        "rotations": stack(2, (4,)),
        "opacities": stack(3, (1,)),
        "sh": stack(4, (k, 3)),
        "counts": None if uniform else torch.tensor(lengths, dtype=torch.int64, device=ref.device),
    }


def to_native(items: Gaussians | Sequence[Gaussians], native_cls: Callable, *, axes: str = "y_down",
              split: bool = False):
    """A native GAUSSIAN built by ``native_cls(positions, scales, rotations, opacities, sh, counts=...)``."""
    t = to_native_tensors(items, axes=axes, split=split)
    return native_cls(t["positions"], t["scales"], t["rotations"], t["opacities"], t["sh"], counts=t["counts"])


def sim_to_native_tensors(sim: SimResult, *, axes: str = "y_down", every: int = 1,
                          progress=None) -> dict[str, Optional[torch.Tensor]]:
    """One batch item per simulated frame (every ``every``-th): the Gaussians exactly as the renderer
    draws them (``SimResult.gaussians_at``), their covariances as rotation + scales."""
    if not isinstance(sim, SimResult):
        raise InputError(f"expected a PhysMotion simulation (PM_SIM), got {type(sim).__name__}")
    if not (isinstance(every, int) and every >= 1):
        raise InputError(f"every must be a positive whole number of frames; got {every!r}")
    frames = list(range(0, sim.num_frames, every))
    n, k = len(sim.rest), sim.rest.sh.shape[1]
    need = len(frames) * n * (3 + 3 + 4 + 1 + 3 * k) * sim.rest.means.element_size()
    have = host_available_bytes()
    if need > 0.5 * have:  # the per-frame items and the stacked batch exist at once for a moment
        from .memory import over_limit_message

        raise InputError(f"A GAUSSIAN batch of {len(frames)} frames x {n} splats "
                         f"{over_limit_message(need, have, 0.5)} (the frames and the stacked batch exist at once); "
                         f"raise every_nth_frame (at most about {max(int(0.5 * have // max(need // len(frames), 1)), 0)} "
                         "frames fit), or free memory.")
    items = []
    for i, f in enumerate(frames):
        items.append(sim.gaussians_at(f).detach().to("cpu").with_covariance_as_rotscale())
        if progress is not None:
            progress(i + 1, len(frames))
    return to_native_tensors(items, axes=axes)


# ----------------------------------------------------------------------------------------------
# native -> ours
# ----------------------------------------------------------------------------------------------


def _field(obj, name: str) -> torch.Tensor:
    t = getattr(obj, name, None)
    if not isinstance(t, torch.Tensor):
        raise InputError(f"the GAUSSIAN's {name} is not a tensor (got {type(t).__name__}); "
                         "connect a GAUSSIAN from ComfyUI's own nodes (e.g. 3D File to Gaussian Splat)")
    return t


def from_native(obj, *, axes: str = "y_down") -> list[Gaussians]:
    """Each batch item of a native GAUSSIAN as our Gaussians (its real length, per ``counts``).

    float32 fields are taken bit for bit; other floating types (half, bfloat16, double) become float32,
    the precision the rest of the pipeline works in. The tensors stay on their device.
    """
    _check_axes(axes)
    pos, scl, rot = _field(obj, "positions"), _field(obj, "scales"), _field(obj, "rotations")
    opa, sh = _field(obj, "opacities"), _field(obj, "sh")
    pos, scl, rot, opa, sh = (t.float() if t.dtype != torch.float32 else t for t in (pos, scl, rot, opa, sh))
    if pos.ndim == 2:  # an unbatched item: accept it as a batch of one
        pos, scl, rot, opa, sh = pos[None], scl[None], rot[None], opa[None], sh[None]
    if pos.ndim != 3 or pos.shape[-1] != 3:
        raise InputError(f"GAUSSIAN.positions must be (B, N, 3); got {tuple(pos.shape)}")
    b, n = pos.shape[:2]
    if opa.ndim == 2:
        opa = opa[..., None]
    expect = {"scales": (scl, (b, n, 3)), "rotations": (rot, (b, n, 4)), "opacities": (opa, (b, n, 1))}
    for name, (t, shape) in expect.items():
        if tuple(t.shape) != shape:
            raise InputError(f"GAUSSIAN.{name} must have shape {shape} (like positions {tuple(pos.shape)}); "
                             f"got {tuple(t.shape)}")
    if sh.ndim == 3 and sh.shape[-1] == 3:  # (B, N, 3): a bare DC colour
        sh = sh[:, :, None, :]
    if sh.ndim != 4 or tuple(sh.shape[:2]) != (b, n) or sh.shape[-1] != 3:
        raise InputError(f"GAUSSIAN.sh must be (B, N, K, 3) with B, N = {b}, {n}; got {tuple(sh.shape)}")
    counts = getattr(obj, "counts", None)
    if counts is None:
        lengths = [n] * b
    else:
        lengths = [int(c) for c in torch.as_tensor(counts).reshape(-1).tolist()]
        if len(lengths) != b or any(not (0 <= c <= n) for c in lengths):
            raise InputError(f"GAUSSIAN.counts must hold {b} lengths between 0 and {n}; got {lengths}")
    out = []
    for i, c in enumerate(lengths):
        p, r, s = pos[i, :c], rot[i, :c], sh[i, :c]
        check_splat_values(f"the GAUSSIAN's item {i}" if b > 1 else "the GAUSSIAN", p, scl[i, :c], r, opa[i, :c, 0], s)
        if axes == "y_down":
            p, r, s = _from_native_axes(p, r, s)
        out.append(Gaussians(means=p, quats=r, scales=scl[i, :c], opacities=opa[i, :c, 0], sh=s))
    return out


def frame_batch_reason(obj) -> Optional[str]:
    """Why a native batch looks like one object's frames rather than independent splats, or None.

    PhysMotion Simulation to SPLAT marks its output (``physmotion_frame_batch``); a batch that lost the mark
    (an upstream node made a new object) is still recognised: the frames of one simulation keep every
    splat's colour and opacity, so all items have the same length and identical ``sh`` and ``opacities``,
    which independent splats (one per image, one per seed) do not.
    """
    if getattr(obj, "physmotion_frame_batch", False):
        return "it is the output of PhysMotion Simulation to SPLAT/GAUSSIAN (one item per simulated frame)"
    pos, sh, opa = (getattr(obj, f, None) for f in ("positions", "sh", "opacities"))
    if not all(isinstance(t, torch.Tensor) for t in (pos, sh, opa)) or pos.ndim != 3 or pos.shape[0] < 2:
        return None
    counts = getattr(obj, "counts", None)
    if counts is not None and len(set(int(c) for c in torch.as_tensor(counts).reshape(-1).tolist())) > 1:
        return None
    if pos.shape[1] == 0 or bool(torch.equal(pos[0], pos[1])):
        return None  # the same splat repeated is not a trajectory (and is refused as a batch anyway)
    if all(torch.equal(sh[0], sh[i]) and torch.equal(opa[0], opa[i]) for i in range(1, pos.shape[0])):
        return ("its items hold the same splats with the same colours and opacities at different positions: "
                "the frames of one simulation")
    return None


def _frame_batch_message(where: str, b: int, reason: str) -> str:
    return (f"{where}: this {b}-item splat batch looks like frames of one motion ({reason}). Fed back as objects "
            f"they would be {b} copies of the object overlapping in one scene. Simulate the rest state instead "
            "(the Gaussians that went into MPM Simulate), or to start from a later frame, pick that one frame "
            "(PhysMotion Simulation to SPLAT with every_nth_frame, then one item of it).")


def from_native_one(obj, *, axes: str = "y_down", where: str = "the splat input") -> Gaussians:
    """A native splat batch at an input that takes one scene: upstream's meaning of a batch item (an
    independent splat: one per input image, one per decode), so exactly one item is accepted. A batch of
    several is refused with what to do; a frame batch fed back is named as such."""
    b = _batch_size(obj)
    if b > 1:
        reason = frame_batch_reason(obj)
        if reason is not None:
            raise InputError(_frame_batch_message(where, b, reason))
        raise InputError(f"{where}: the splat batch holds {b} items. In ComfyUI each item of a SPLAT/GAUSSIAN batch "
                         "is an independent splat (TripoSplat decodes one per input image; Render Splat renders "
                         "each), and this input takes one scene. Use one image (one item), or Merge Splats to put "
                         "them into one splat, or PhysMotion SPLAT to PhysMotion Gaussians to make each item one "
                         "object of a scene.")
    (item,) = from_native(obj, axes=axes)
    if len(item) == 0:
        raise InputError(f"{where}: the splat holds no Gaussians (its only item is empty)")
    return item


def _batch_size(obj) -> int:
    pos = getattr(obj, "positions", None)
    if isinstance(pos, torch.Tensor) and pos.ndim == 3:
        return int(pos.shape[0])
    return 1


def from_native_scene(obj, *, axes: str = "y_down") -> Gaussians:
    """A native GAUSSIAN as one scene: a single item as it is, several items as one object each
    (object_ids 0, 1, ... in batch order, as Combine Objects numbers them; empty items are skipped).
    A batch of one motion's frames (``frame_batch_reason``) is refused: its items are not objects."""
    b = _batch_size(obj)
    if b > 1:
        reason = frame_batch_reason(obj)
        if reason is not None:
            raise InputError(_frame_batch_message("SPLAT to PhysMotion Gaussians", b, reason))
    items = from_native(obj, axes=axes)
    if all(len(g) == 0 for g in items):
        raise InputError("the GAUSSIAN holds no splats (every batch item is empty)")
    if len(items) == 1:
        return items[0]
    kept = [g for g in items if len(g)]  # empty items hold no object: the ids stay consecutive
    tagged = [Gaussians(means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities, sh=g.sh,
                        object_ids=torch.full((len(g),), i, dtype=torch.int64, device=g.device))
              for i, g in enumerate(kept)]
    return Gaussians.cat(tagged)


# ----------------------------------------------------------------------------------------------
# whole Gaussians between the two frames (used by the .ply writer and reader)
# ----------------------------------------------------------------------------------------------


def turn_axes(g: Gaussians, to: str) -> Gaussians:
    """``g`` turned 180° about x: ``to="y_down"`` from our +y-up frame into the native/3DGS one (y down,
    z away from the camera), ``to="y_up"`` back. Exact (sign flips and a permutation); object ids kept,
    covariances (when present) turned as D Σ D."""
    if to not in ("y_down", "y_up"):
        raise InputError(f"turn_axes: to must be 'y_down' or 'y_up'; got {to!r}")
    fn = _to_native_axes if to == "y_down" else _from_native_axes
    means, quats, sh = fn(g.means, g.quats, g.sh)
    covars = None
    if g.covars is not None:
        f = torch.tensor(_FLIP, dtype=g.covars.dtype, device=g.covars.device)
        covars = g.covars * f[:, None] * f[None, :]
    return Gaussians(means=means, quats=quats, scales=g.scales, opacities=g.opacities, sh=sh, covars=covars,
                     object_ids=g.object_ids)
