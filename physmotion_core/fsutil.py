"""Output files, in one place: where they may go, and how they are written.

``check_outputs`` plans every output of a run before any work starts: each location must be a
writable folder (created if missing), a file name the file system accepts, not an input of the
same run (compared by inode, so symlinks and hard links count), not anything but a regular file
(a folder, a device such as /dev/null, a pipe), and no two outputs may share a path.

``atomic_output`` / ``atomic_folder`` write to a temporary name beside the target and rename it
over the target only when complete: a crash, Ctrl-C, SIGTERM (the CLI turns it into an exception)
or a Cancel mid-write leaves the previous file (or none), never a half-written one that a later run
would trust. They re-check the target right before the rename, and refuse to replace an input
registered with ``protect_inputs``. Temporary names are short (bounded), so any file name the
file system accepts can be written.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import shutil
import stat
import tempfile
from pathlib import Path
from typing import Iterable, Iterator, Mapping, Optional

from .errors import InputError


class OutputLocationError(InputError):
    """An output's folder cannot be created or written (permissions, a read-only disk, a path
    through a file): a file-system problem the user fixes outside the program."""


class DiskFullError(OutputLocationError):
    """An output does not fit on its disk (found before writing where its size is known, or when a
    write fails with "no space left"): nothing under the output's name was written."""


#: errno values that mean "the disk (or the user's quota, or the file-size limit) is full".
_FULL_ERRNOS = {getattr(errno, n) for n in ("ENOSPC", "EDQUOT", "EFBIG") if hasattr(errno, n)}


def free_bytes(folder) -> Optional[int]:
    """Bytes free to this user in ``folder`` (or the nearest existing folder above it); None when the
    file system does not say."""
    try:
        return int(shutil.disk_usage(_nearest_existing(Path(folder))).free)
    except (OSError, ValueError):
        return None


def _fmt(n: float) -> str:
    from .memory import fmt_bytes

    return fmt_bytes(n)


def check_free_space(folder, need_bytes: int, what: str) -> None:
    """Refuse (DiskFullError) before writing ``need_bytes`` into ``folder`` when its disk has less free."""
    free = free_bytes(folder)
    if free is not None and int(need_bytes) > free:
        raise DiskFullError(f"{what} needs about {_fmt(need_bytes)} of disk space in '{folder}' but only "
                            f"{_fmt(free)} is free there. Free at least {_fmt(int(need_bytes) - free)} on that disk, "
                            "or write to a folder on another disk.")


def is_disk_full(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and getattr(exc, "errno", None) in _FULL_ERRNOS


def disk_full_error(target, written: int, exc: Optional[BaseException] = None,
                    need_bytes: Optional[int] = None) -> DiskFullError:
    """The error for an output that ran out of disk space after ``written`` bytes."""
    target = Path(target)
    free = free_bytes(target.parent)
    need = f"about {_fmt(need_bytes)}" if need_bytes else f"more than the {_fmt(written)} written before the disk filled"
    why = f" ({exc.strerror or exc})" if isinstance(exc, OSError) else ""
    return DiskFullError(f"'{target}' could not be written: its disk is full{why}. It needs {need}; "
                         f"{_fmt(free) if free is not None else 'an unknown amount'} is free in '{target.parent}'. "
                         "Nothing was written under that name (the partial file was removed). Free space on that "
                         "disk, or write to a folder on another disk.")


#: Inputs of the run in progress (device, inode) -> path: no output may replace them.
_PROTECTED: contextvars.ContextVar[tuple] = contextvars.ContextVar("physmotion_protected_inputs", default=())

#: How much of the target's name a temporary name keeps (bytes), and the longest suffix it gets.
_TMP_NAME_BYTES = 32
_TMP_SUFFIX_CHARS = 16


def _file_id(path: Path) -> Optional[tuple[int, int]]:
    try:
        # realpath first: follows symlinks (a link to the photo is the photo) and resolves '..' after
        # folders that do not exist yet ('new/../photo.png' is the photo once 'new' is created).
        st = os.stat(os.path.realpath(path))
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


@contextlib.contextmanager
def protect_inputs(*paths) -> Iterator[None]:
    """While the block runs, ``atomic_output`` refuses to replace any of ``paths`` (or a link to
    one): the inputs of a run are never overwritten by its outputs."""
    entries = []
    for p in paths:
        if p is None or not isinstance(p, (str, os.PathLike)):
            continue
        fid = _file_id(Path(p))
        if fid is not None:
            entries.append((fid, str(p)))
    token = _PROTECTED.set(_PROTECTED.get() + tuple(entries))
    try:
        yield
    finally:
        _PROTECTED.reset(token)


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return 255


def _nearest_existing(folder: Path) -> Path:
    p = folder
    while not p.exists() and p.parent != p:
        p = p.parent
    return p


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISFIFO(mode):
        return "a named pipe"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _check_replaceable(target: Path, what: str) -> None:
    """Refuse when ``target`` exists and is anything but a regular file (or a link to one), or is
    a protected input."""
    try:
        st = os.stat(os.path.realpath(target))
    except FileNotFoundError:
        return  # absent, or a dangling link: nothing to lose
    except OSError as exc:
        raise OutputLocationError(f"{what} '{target}' cannot be checked ({exc.strerror}); choose another path") from exc
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{what} '{target}' is {_kind(st.st_mode)}, not a regular file: refusing to replace it. "
                         "Give a file path (e.g. a name ending in the output's extension) in a folder you own.")
    for fid, src in _PROTECTED.get():
        if (st.st_dev, st.st_ino) == fid:
            raise InputError(f"{what} '{target}' is the input '{src}' of this run (the same file): writing it would "
                             "destroy the input. Choose another output name.")


def _tmp_name_parts(target: Path, suffix: str) -> tuple[str, str]:
    """(prefix, suffix) of a temporary name beside ``target``: short whatever the target's length,
    so a name the file system accepts never fails because of its temporary twin."""
    stem = target.name.encode("utf-8", "surrogateescape")[:_TMP_NAME_BYTES].decode("utf-8", "ignore")
    suffix = "".join(c for c in suffix if c.isalnum() or c in "._-")[-_TMP_SUFFIX_CHARS:]
    return f".{stem}.", suffix


def check_output_path(path, what: str = "output", *, folder: bool = False) -> Path:
    """Check one output location now, before any work: see ``check_outputs``. Returns the path."""
    return check_outputs({what: path}, folders=(what,) if folder else ())[what]


def check_outputs(outputs: Mapping[str, object], inputs: Iterable = (), *, folders: Iterable[str] = ()) -> dict:
    """Check every output of a run before it starts; returns {label: Path} of those given.

    ``outputs``: label (how the user named it, e.g. "-o" or "--stats") -> path or None (not
    wanted). ``inputs``: the run's input files. ``folders``: labels whose output is a folder
    (written with ``atomic_folder``). Raises InputError (or OutputLocationError for a folder that
    cannot be created or written) naming the option and the fix. Missing parent folders are
    created (the run would create them anyway), and a temporary file is created and removed in
    each one to prove it is writable.
    """
    folders = set(folders)
    planned: dict[str, Path] = {}
    ids: dict[tuple, str] = {}
    input_ids = {}
    for inp in inputs:
        if inp is None or not isinstance(inp, (str, os.PathLike)):
            continue
        fid = _file_id(Path(inp))
        if fid is not None:
            input_ids[fid] = str(inp)
    for label, raw in outputs.items():
        if raw is None:
            continue
        text = os.fspath(raw)
        if "\x00" in text:
            raise InputError(f"{label} {text!r} contains a NUL byte, which no file name may hold; remove it")
        if not text.strip():
            raise InputError(f"{label} is an empty path; give a file name")
        path = Path(text).expanduser()
        if path.name in ("", ".", ".."):
            raise InputError(f"{label} '{text}' names a folder, not a file; add a file name")
        parent = path.parent if str(path.parent) else Path(".")
        nbytes = len(path.name.encode("utf-8", "surrogateescape"))
        limit = _name_max(_nearest_existing(parent))
        if nbytes > limit:
            raise InputError(f"{label}: the file name '{path.name[:40]}...' is {nbytes} bytes long; this file system "
                             f"allows at most {limit}. Choose a shorter name.")
        if label in folders:
            if path.exists() and not path.is_dir():
                raise InputError(f"{label} '{path}' exists and is not a folder; choose another name")
        else:
            _check_replaceable(path, label)
        fid = _file_id(path)
        if fid is not None and fid in input_ids:
            raise InputError(f"{label} '{text}' is the input '{input_ids[fid]}' of this run (the same file): writing "
                             "it would destroy the input. Choose another output name.")
        key = fid or ("path", os.path.realpath(path))
        if key in ids:
            raise InputError(f"{label} and {ids[key]} are the same file '{text}'; give each output its own name")
        ids[key] = label
        existing = _nearest_existing(parent)
        if not existing.is_dir():
            raise OutputLocationError(f"{label} '{text}': '{existing}' is a file, not a folder, so the output folder "
                                      f"'{parent}' cannot be created. Choose an output in a writable folder.")
        try:
            parent.mkdir(parents=True, exist_ok=True)
            prefix, suffix = _tmp_name_parts(path, ".probe")
            fd, probe = tempfile.mkstemp(dir=parent, prefix=prefix, suffix=suffix)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise OutputLocationError(
                f"{label} '{text}': the folder '{parent}' is not writable ({exc.strerror or exc}). Check that the "
                "output folder exists, is writable and has free space, or choose another output path.") from exc
        planned[label] = path
    return planned


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, suffix: str = ".tmp", need_bytes: Optional[int] = None) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path``, on error it is removed.

    Refuses (InputError) when ``path`` is a folder, a device, a pipe or a socket, or an input
    protected by ``protect_inputs``: checked before the write and again right before the rename.
    ``need_bytes`` (the file's size, where the writer knows it): refused up front (DiskFullError)
    when the disk has less free, and the written file must have at least that size. A write that
    fails because the disk is full becomes a DiskFullError naming the file and the space.
    """
    target = Path(path)
    _check_replaceable(target, "output")
    target.parent.mkdir(parents=True, exist_ok=True)
    if need_bytes is not None:
        check_free_space(target.parent, need_bytes, f"'{target.name}'")
    prefix, suffix = _tmp_name_parts(target, suffix)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=prefix, suffix=suffix)
    os.close(fd)
    try:
        try:
            yield Path(tmp)
            if need_bytes is not None and os.path.getsize(tmp) < need_bytes:
                raise OSError(errno.ENOSPC, f"only {os.path.getsize(tmp)} of {need_bytes} bytes reached the disk")
        except OSError as exc:
            if not is_disk_full(exc):
                raise
            try:
                written = os.path.getsize(tmp)
            except OSError:
                written = 0
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise disk_full_error(target, written, exc, need_bytes) from exc
        # mkstemp makes the file private (0600); give it the mode a plain open() would have given it
        # (an existing file's mode, else 0666 minus the umask), so servers and viewers can read it.
        try:
            mode = target.stat().st_mode & 0o7777
        except FileNotFoundError:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        os.chmod(tmp, mode)
        _check_replaceable(target, "output")
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write a text file atomically (see ``atomic_output``)."""
    with atomic_output(path, suffix=".tmp" + Path(path).suffix) as tmp:
        tmp.write_text(text)
    return Path(path)


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside ``path`` to fill; when the block completes it becomes
    ``path`` (an existing folder there is replaced), on error it is removed. A Cancel half-way
    never leaves a folder under the final name that looks complete to a later run."""
    target = Path(path)
    if target.exists() and not target.is_dir():
        raise InputError(f"output folder '{target}' exists and is not a folder; choose another name")
    target.parent.mkdir(parents=True, exist_ok=True)
    prefix, _ = _tmp_name_parts(target, "")
    tmp = Path(tempfile.mkdtemp(dir=target.parent, prefix=prefix, suffix=".partial"))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())
        old = None
        if target.exists():
            old = Path(tempfile.mkdtemp(dir=target.parent, prefix=prefix, suffix=".old"))
            os.replace(target, old / "x")
        try:
            os.replace(tmp, target)
        except BaseException:
            if old is not None:
                os.replace(old / "x", target)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes, read in 1 MiB blocks (inputs' identities, outputs' checks)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


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
