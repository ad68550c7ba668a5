"""Gaussian splat .ply files in the standard 3DGS layout.

Vertex properties: x y z, nx ny nz (zeros), f_dc_0..2, f_rest_* (channel-major, as 3DGS writes
them), opacity (logit), scale_0..2 (log), rot_0..3 (wxyz, unnormalised allowed). Splat viewers and
ComfyUI's Load3D/Preview3D read this layout.

Axes. The file is written in the 3DGS frame (x right, y down, z away from the camera), the frame of
ComfyUI's own splat nodes and of files from 3DGS tools, so ComfyUI's *Get Splat* / *3D File to Gaussian
Splat* (which copy x y z as stored) gives a SPLAT that PhysMotion's inputs turn upright with their
default ``y_down``. The header records it (``comment physmotion_axes y_down``) and ``read_ply`` honours
the record, turning such a file back to our +y-up frame; a file without the record (from another tool,
or written by PhysMotion before the record existed, then +y up) is read as stored unless told otherwise.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import torch

from .errors import InputError
from .fsutil import atomic_output
from .types.gaussians import Gaussians

_PLY_TYPES = {
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
    "uchar": "u1", "uint8": "u1", "char": "i1", "int8": "i1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
}


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-7, 1 - 1e-7)
    return np.log(p / (1 - p))


#: The header comment that records the file's axes: ``comment physmotion_axes y_down`` or ``... y_up``.
AXES_COMMENT = "physmotion_axes"
PLY_AXES = ("y_down", "y_up")
_AXES_RE = re.compile(rb"^comment\s+" + AXES_COMMENT.encode() + rb"\s+(\S+)", re.MULTILINE)


def write_ply(path: str | os.PathLike, gaussians: Gaussians, axes: str = "y_down") -> Path:
    """Write Gaussians (our frame, +y up) as a binary little-endian 3DGS .ply (atomically: temp file +
    rename). ``axes="y_down"`` (default) stores them turned into the 3DGS frame, ``"y_up"`` as they are;
    either way the header records which, and ``read_ply`` turns the file back."""
    if axes not in PLY_AXES:
        raise InputError(f"write_ply: axes must be one of {PLY_AXES}; got {axes!r}")
    g = gaussians.with_covariance_as_rotscale().detach().to("cpu")
    g.validate("Gaussians to save")
    if axes == "y_down":
        from .interop_gaussian import turn_axes

        g = turn_axes(g, "y_down")
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
    header += (f"comment {AXES_COMMENT} {axes} (written by physmotion, 3DGS layout; "
               + ("x right, y down, z away from the camera: the 3DGS frame)" if axes == "y_down"
                  else "+y up, the camera looking down -z)") + "\n")
    header += f"element vertex {n}\n" + "".join(f"property float {name}\n" for name in names) + "end_header\n"
    path = Path(path)
    head = header.encode("ascii")
    with atomic_output(path, need_bytes=len(head) + data.nbytes) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(head)
            fh.write(memoryview(data).cast("B"))
    return path


_MAX_HEADER_LINES = 10_000
#: The longest header line read in one piece; longer comment lines are skipped to their end (a tool
#: may store its settings or a licence in one), any other keyword line that long is refused.
_MAX_LINE_BYTES = 4096
#: A header larger than this (comments included) is refused: no real file comes near it.
_MAX_HEADER_BYTES = 16 << 20


def _header_line(fh, path, lineno: int, start: int) -> bytes:
    """The next header line, with a comment or obj_info line of any length cut to its first
    _MAX_LINE_BYTES bytes (the rest is read and dropped, within _MAX_HEADER_BYTES)."""
    line = fh.readline(_MAX_LINE_BYTES)
    if line.endswith(b"\n") or len(line) < _MAX_LINE_BYTES:
        return line
    if line.split(None, 1)[:1] not in ([b"comment"], [b"obj_info"]):
        raise InputError(f"{path}, header line {lineno}: longer than {_MAX_LINE_BYTES} bytes and not a comment; "
                         "the header is damaged (or this is not a .ply file)")
    while True:
        rest = fh.readline(1 << 16)
        if fh.tell() - start > _MAX_HEADER_BYTES:
            raise InputError(f"{path}: the .ply header is larger than {_MAX_HEADER_BYTES >> 20} MiB; the file is "
                             "damaged")
        if not rest or rest.endswith(b"\n"):
            return line


def _parse_header(fh, path) -> tuple[str, int, list[tuple[str, str]], int]:
    """(format, vertex count, vertex properties, byte offset of the vertex data). Every malformed
    header (a format line without a value, a missing, negative or non-numeric count, a property
    given twice, an element before the vertices that cannot be skipped) is refused naming the
    file and the line."""
    first = fh.readline(64)
    if first.strip() != b"ply":
        raise InputError(f"{path} is not a .ply file (it does not start with 'ply')")
    fmt, count, props, in_vertex = None, None, [], False
    pre, current, seen_vertex = [], None, False  # [count, bytes per item] of elements before the vertices
    start = fh.tell()
    for lineno in range(2, _MAX_HEADER_LINES):
        line = _header_line(fh, path, lineno, start)
        if not line:
            raise InputError(f"{path}: the .ply header has no end_header line (truncated file?)")
        text = line.decode("ascii", errors="replace").strip()
        if text == "end_header":
            break
        parts = text.split()
        where = f"{path}, header line {lineno} ('{text[:60]}')"
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if len(parts) < 2:
                raise InputError(f"{where}: the format line has no value; expected 'format binary_little_endian 1.0'")
            if fmt is not None:
                raise InputError(f"{where}: a second format line")
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3:
                raise InputError(f"{where}: an element line needs a name and a count, e.g. 'element vertex 1000'")
            try:
                n = int(parts[2])
            except ValueError:
                raise InputError(f"{where}: the element count '{parts[2]}' is not a whole number") from None
            if n < 0:
                raise InputError(f"{where}: the element count {n} is negative")
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                if seen_vertex:
                    raise InputError(f"{where}: a second vertex element")
                seen_vertex, count = True, n
            elif not seen_vertex:
                current = [n, 0]
                pre.append(current)
            else:
                current = None
        elif parts[0] == "property":
            if len(parts) < 3 or (parts[1] == "list" and len(parts) < 5):
                raise InputError(f"{where}: a property line needs a type and a name, e.g. 'property float x'")
            if parts[1] == "list":
                if in_vertex:
                    raise InputError(f"{path}: list properties in the vertex element are not a Gaussian splat layout")
                if current is not None and current[0] > 0:
                    raise InputError(f"{where}: an element with list properties comes before the vertices; "
                                     "re-save the file with the vertex element first")
                continue
            if parts[1] not in _PLY_TYPES:
                raise InputError(f"{where}: unsupported property type '{parts[1]}'; expected one of "
                                 f"{sorted(set(_PLY_TYPES))}")
            if in_vertex:
                if any(name == parts[2] for name, _ in props):
                    raise InputError(f"{where}: the vertex property '{parts[2]}' is given twice")
                props.append((parts[2], _PLY_TYPES[parts[1]]))
            elif current is not None:
                current[1] += np.dtype(_PLY_TYPES[parts[1]]).itemsize
        else:
            raise InputError(f"{where}: unknown header keyword '{parts[0]}'")
    else:
        raise InputError(f"{path}: the .ply header is longer than {_MAX_HEADER_LINES} lines; the file is damaged")
    if fmt is None:
        raise InputError(f"{path}: the .ply header has no format line")
    if count is None:
        raise InputError(f"{path}: the .ply header has no vertex element (it holds no points)")
    if not props:
        raise InputError(f"{path}: the vertex element has no properties")
    return fmt, count, props, fh.tell() + sum(n * size for n, size in pre)


#: Bytes read_ply holds per Gaussian at its peak besides the file's own bytes: a float64 column
#: at a time for the checks, float64 means / scales / quaternions / opacities (and their norms), the
#: float32 tensors of the result. Rounded up from counting the arrays (see read_ply).
PLY_BYTES_PER_GAUSSIAN = 24 * 3 + 32 + 8 + 8 + 48 + 16
PLY_BYTES_PER_SH_COEFF = 4 + 8  # the float32 SH array, plus the float64 rest block it is built from


def _sh_k(names) -> int:
    rest = sum(1 for nm in names if re.fullmatch(r"f_rest_\d+", nm))
    return 1 + rest // 3


def ply_need_bytes(count: int, itemsize: int, k: int = 1) -> int:
    """Bytes of RAM reading ``count`` Gaussians of ``itemsize`` bytes each (SH of ``k`` coefficients
    per channel) needs at its peak."""
    return int(count) * (int(itemsize) + PLY_BYTES_PER_GAUSSIAN + 3 * int(k) * PLY_BYTES_PER_SH_COEFF)


def check_ply_fits(path, count: int, itemsize: int, k: int = 1, fraction: float = 0.8) -> None:
    """Refuse, before reading, a .ply whose Gaussians would not fit in the RAM available now."""
    from .memory import host_available_bytes, over_limit_message

    need, have = ply_need_bytes(count, itemsize, k), host_available_bytes()
    if need > fraction * have:
        raise InputError(f"{path}: reading its {count:,} Gaussians {over_limit_message(need, have, fraction)}. "
                         "Use a smaller splat (fewer Gaussians: prune or downsample it in the tool that made it), "
                         "or free memory (close other programs or models) and try again.")


def ply_axes(path: str | os.PathLike) -> str | None:
    """The axes a .ply's header records (``y_down`` / ``y_up``), or None when it records none."""
    with open(path, "rb") as fh:
        _fmt, _count, _props, offset = _parse_header(fh, Path(path))
        fh.seek(0)
        head = fh.read(offset)
    m = _AXES_RE.search(head)
    return m.group(1).decode("ascii", errors="replace") if m else None


def read_ply(path: str | os.PathLike, axes: str = "auto") -> Gaussians:
    """Read a 3DGS-layout .ply (binary little/big endian) into Gaussians (our frame, +y up).

    ``axes``: ``auto`` honours the header's ``physmotion_axes`` record (a file without one is read as
    stored); ``y_down`` turns a file stored in the 3DGS frame upright whatever it records; ``as_is``
    copies x y z as stored."""
    if axes not in ("auto", "y_down", "as_is"):
        raise InputError(f"read_ply: axes must be 'auto', 'y_down' or 'as_is'; got {axes!r}")
    g = _read_ply_as_stored(path)
    turn = ply_axes(path) == "y_down" if axes == "auto" else axes == "y_down"
    if turn:
        from .interop_gaussian import turn_axes

        g = turn_axes(g, "y_up")
    return g


def _read_ply_as_stored(path: str | os.PathLike) -> Gaussians:
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
        if count == 0:
            raise InputError(f"{path} holds no Gaussians (its header says 0 vertices)")
        available = max(os.fstat(fh.fileno()).st_size - offset, 0)
        # Never read more than the file holds: a header may promise any count. And never start reading
        # what will not fit in memory (the file's bytes plus the columns and tensors made from them).
        if available >= count * dtype.itemsize:
            check_ply_fits(path, count, dtype.itemsize, _sh_k(dtype.names))
        raw = b"" if available < count * dtype.itemsize else (fh.seek(offset), fh.read(count * dtype.itemsize))[1]
    if len(raw) < count * dtype.itemsize:
        raise InputError(f"{path} is truncated: the header promises {count} vertices "
                         f"({count * dtype.itemsize} bytes) but only {available} bytes follow the header")
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

    for name in required + [nm for nm in names if re.fullmatch(r"f_rest_\d+", nm)]:
        bad = int(np.count_nonzero(~np.isfinite(col(name))))
        if bad:
            raise InputError(f"{path}: {bad} of {count} Gaussians have a NaN or infinite '{name}' value; the file "
                             "is damaged or was written by a diverged optimisation. Re-export it.")

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
    if not all(bool(torch.isfinite(t).all()) for t in (g.means, g.scales, g.sh, g.quats, g.opacities)):
        raise InputError(f"{path}: a scale overflows (scale_* log values above 88); the file is damaged")
    return g


def write_ply_sequence(folder: str | os.PathLike, sim, every: int = 1, progress=None) -> list[Path]:
    """One 3DGS .ply per simulated frame (every ``every``-th), named frame_00000.ply, ... in ``folder``
    (all or nothing: see below)."""
    from .progress import report

    from .fsutil import atomic_folder

    folder = Path(folder)
    frames = list(range(0, sim.num_frames, max(1, int(every))))
    # Every file's size is known before the first is written: refuse a sequence the disk cannot hold.
    from .fsutil import check_free_space

    first = sim.gaussians_at(frames[0]) if frames else None
    if first is not None:
        props = 17 + 3 * (first.sh.shape[1] - 1)
        check_free_space(folder.parent, len(frames) * (1024 + len(first) * props * 4),
                         f"The .ply sequence ({len(frames)} files of {len(first):,} Gaussians)")
    # Written into a hidden temporary folder that is renamed to ``folder`` only when every frame is
    # there: a Cancel half-way leaves no folder under that name that a later run would take as a
    # complete sequence.
    with atomic_folder(folder) as tmp:
        for i, k in enumerate(frames):
            write_ply(tmp / f"frame_{k:05d}.ply", first if i == 0 else sim.gaussians_at(k))
            report(progress, i + 1, len(frames))
    return [folder / f"frame_{k:05d}.ply" for k in frames]
