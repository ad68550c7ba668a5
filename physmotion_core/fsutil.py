"""Atomic file output: write to a temporary file beside the target, then rename over it.

A crash or a Cancel mid-write leaves the previous file (or none), never a half-written one that
a later run would trust.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path``, on error it is removed."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp makes the file private (0600); give it the mode a plain open() would have given it
        # (an existing file's mode, else 0666 minus the umask), so servers and viewers can read it.
        try:
            mode = target.stat().st_mode & 0o7777
        except FileNotFoundError:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def tensors_digest(tensors: dict) -> str:
    """SHA-256 over a dict of tensors (names, dtypes, shapes and bytes, in name order): stored in a
    cache file's metadata when it is written and recomputed when it is read, so a cache file that
    was damaged after writing (a bad disk, a copy cut short that still parses) is never trusted."""
    import hashlib

    import torch

    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(name.encode())
        h.update(str(t.dtype).encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def load_verified_safetensors(path: str | os.PathLike, key: str | None = None) -> tuple[dict, dict]:
    """(tensors, metadata) of a cache file written with ``content_sha256`` (and ``cache_key``) in its
    metadata. Raises ValueError when the file does not parse, lacks the digest, was written for
    another key, or its tensors no longer match the digest."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as fh:
        meta = dict(fh.metadata() or {})
        # Copies, not views of the file's memory map: the caller keeps them after the file is replaced.
        tensors = {k: fh.get_tensor(k).clone() for k in fh.keys()}
    if "content_sha256" not in meta:
        raise ValueError("no content digest in the metadata (not written by this version)")
    if key is not None and meta.get("cache_key") != key:
        raise ValueError("written for other inputs")
    if tensors_digest(tensors) != meta["content_sha256"]:
        raise ValueError("contents do not match the digest written with them (damaged)")
    return tensors, meta
