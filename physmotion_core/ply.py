"""Gaussian splat .ply files in the standard 3DGS layout.

Vertex properties: x y z, nx ny nz (zeros), f_dc_0..2, f_rest_* (channel-major, as 3DGS writes
them), opacity (logit), scale_0..2 (log), rot_0..3 (wxyz, unnormalised allowed). Splat viewers and
ComfyUI's Load3D/Preview3D read this layout.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from .errors import InputError
from .fsutil import atomic_output
from .types import Gaussians

_PLY_TYPES = {
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
    "uchar": "u1", "uint8": "u1", "char": "i1", "int8": "i1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
}


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-7, 1 - 1e-7)
    return np.log(p / (1 - p))


def write_ply(path: str | os.PathLike, gaussians: Gaussians) -> Path:
    """Write Gaussians as a binary little-endian 3DGS .ply (atomically: temp file + rename)."""
    g = gaussians.with_covariance_as_rotscale().detach().to("cpu")
    g.validate("Gaussians to save")
    n, k = len(g), g.sh.shape[1]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.empty(n, dtype=[(name, "<f4") for name in names])
    means = g.means.float().numpy()
    data["x"], data["y"], data["z"] = means[:, 0], means[:, 1], means[:, 2]
    data["nx"] = data["ny"] = data["nz"] = 0.0
    sh = g.sh.float().numpy()
    for c in range(3):
        data[f"f_dc_{c}"] = sh[:, 0, c]
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)  # (N, 3*(K-1)), channel-major
    for i in range(rest.shape[1]):
        data[f"f_rest_{i}"] = rest[:, i]
    data["opacity"] = _logit(g.opacities.double().numpy())
    log_scales = np.log(g.scales.double().numpy().clip(1e-30))
    quats = g.quats.float().numpy()
    for i in range(3):
        data[f"scale_{i}"] = log_scales[:, i]
    for i in range(4):
        data[f"rot_{i}"] = quats[:, i]

    header = "ply\nformat binary_little_endian 1.0\n"
    header += "comment written by physmotion (3DGS layout)\n"
    header += f"element vertex {n}\n" + "".join(f"property float {name}\n" for name in names) + "end_header\n"
    path = Path(path)
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(data.tobytes())
    return path


def _parse_header(fh, path) -> tuple[str, int, list[tuple[str, str]], int]:
    first = fh.readline()
    if first.strip() != b"ply":
        raise InputError(f"{path} is not a .ply file (it does not start with 'ply')")
    fmt, count, props, in_vertex = None, None, [], False
    while True:
        line = fh.readline()
        if not line:
            raise InputError(f"{path}: the .ply header has no end_header line (truncated file?)")
        text = line.decode("ascii", errors="replace").strip()
        if text == "end_header":
            break
        parts = text.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                count = int(parts[2])
        elif parts[0] == "property" and in_vertex:
            if parts[1] == "list":
                raise InputError(f"{path}: list properties in the vertex element are not a Gaussian splat layout")
            if parts[1] not in _PLY_TYPES:
                raise InputError(f"{path}: unsupported property type '{parts[1]}'")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt is None or count is None:
        raise InputError(f"{path}: the .ply header lacks a format line or a vertex element")
    return fmt, count, props, fh.tell()


def read_ply(path: str | os.PathLike) -> Gaussians:
    """Read a 3DGS-layout .ply (binary little/big endian) into Gaussians."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"No .ply file at {path}")
    with open(path, "rb") as fh:
        fmt, count, props, offset = _parse_header(fh, path)
        if fmt == "ascii":
            raise InputError(f"{path}: ASCII .ply is not supported for Gaussian splats; save it as binary")
        order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
        if order is None:
            raise InputError(f"{path}: unknown .ply format '{fmt}'")
        dtype = np.dtype([(name, order + t) for name, t in props])
        raw = fh.read()
    if len(raw) < count * dtype.itemsize:
        raise InputError(f"{path} is truncated: the header promises {count} vertices "
                         f"({count * dtype.itemsize} bytes) but only {len(raw)} bytes follow")
    data = np.frombuffer(raw, dtype=dtype, count=count)
    names = set(dtype.names)
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [r for r in required if r not in names]
    if missing:
        raise InputError(f"{path} is not a Gaussian-splat .ply: missing properties {missing}. "
                         "It may be a mesh or point cloud; Gaussian splats need the 3DGS layout.")

    def col(name):
        return np.asarray(data[name], dtype=np.float64)

    rest_names = sorted((nm for nm in names if re.fullmatch(r"f_rest_\d+", nm)), key=lambda s: int(s[7:]))
    if len(rest_names) % 3:
        raise InputError(f"{path}: {len(rest_names)} f_rest properties is not a multiple of 3")
    k = 1 + len(rest_names) // 3
    sh = np.zeros((count, k, 3), dtype=np.float32)
    sh[:, 0, :] = np.stack([col(f"f_dc_{c}") for c in range(3)], axis=-1)
    if rest_names:
        rest = np.stack([col(nm) for nm in rest_names], axis=-1).reshape(count, 3, k - 1)
        sh[:, 1:, :] = rest.transpose(0, 2, 1)
    means = np.stack([col("x"), col("y"), col("z")], axis=-1)
    scales = np.exp(np.stack([col(f"scale_{i}") for i in range(3)], axis=-1))
    quats = np.stack([col(f"rot_{i}") for i in range(4)], axis=-1)
    norm = np.linalg.norm(quats, axis=-1, keepdims=True)
    quats = np.where(norm > 0, quats / np.where(norm > 0, norm, 1), np.array([1.0, 0, 0, 0]))
    opacities = 1.0 / (1.0 + np.exp(-col("opacity")))
    g = Gaussians(
        means=torch.from_numpy(means).float(),
        quats=torch.from_numpy(quats).float(),
        scales=torch.from_numpy(scales).float(),
        opacities=torch.from_numpy(opacities).float(),
        sh=torch.from_numpy(sh),
    )
    if not all(bool(torch.isfinite(t).all()) for t in (g.means, g.scales, g.sh, g.quats)):
        raise InputError(f"{path} contains NaN/Inf values; the file is corrupt")
    return g


def write_ply_sequence(folder: str | os.PathLike, sim, every: int = 1, progress=None) -> list[Path]:
    """One 3DGS .ply per simulated frame (every ``every``-th), named frame_00000.ply, ... in ``folder``."""
    from .progress import report

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    frames = list(range(0, sim.num_frames, max(1, int(every))))
    out = []
    for i, k in enumerate(frames):
        out.append(write_ply(folder / f"frame_{k:05d}.ply", sim.gaussians_at(k)))
        report(progress, i + 1, len(frames))
    return out
