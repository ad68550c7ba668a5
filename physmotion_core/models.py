"""Where weights live, how they are loaded safely, and the errors when they are not there.

Nothing here downloads anything. Weights sit in ComfyUI's model folders (the nodes resolve those
through ``folder_paths``); outside ComfyUI the same sub-folders live under ``$PHYSMOTION_MODELS``
(default ``./models``):

==============  ==================================  ==========================================
kind            folder under the models root        format
==============  ==================================  ==========================================
``sams``        ``sams/``                           official SAM ``.pth`` (vit_b / vit_l / vit_h)
``lgm``         ``physmotion/lgm/``                 official LGM ``.safetensors`` (fp16)
``imagedream``  ``physmotion/imagedream/<dir>``     diffusers folder (imagedream-ipmv-diffusers)
``depth``       ``physmotion/depth/<dir>``          transformers folder
``diffusers``   ``diffusers/<dir>``                 diffusers folder (SD 2.1)
``controlnet``  ``controlnet/<dir or file>``        diffusers folder or single file
``loras``       ``loras/``                          peft safetensors
==============  ==================================  ==========================================
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Mapping, Optional, Sequence

from .errors import InputError, MissingModelError

if TYPE_CHECKING:  # torch is imported where used, so the module imports without it
    import torch

MODEL_FOLDERS = {
    "sams": "sams",
    "lgm": "physmotion/lgm",
    "imagedream": "physmotion/imagedream",
    "depth": "physmotion/depth",
    "diffusers": "diffusers",
    "controlnet": "controlnet",
    "loras": "loras",
    "checkpoints": "checkpoints",
}

WEIGHT_SUFFIXES = (".safetensors", ".pth", ".pt", ".bin", ".ckpt")


#: Folders whose files the user put there as model weights (the models root and, inside ComfyUI,
#: its model folders): pickled checkpoints (.pth/.pt/.bin/.ckpt) load from these without opt-in.
_TRUSTED_FOLDERS: list[Path] = []
ALLOW_PICKLE_ENV = "PHYSMOTION_ALLOW_PICKLE"


def trust_folder(folder: os.PathLike) -> None:
    """Mark a model folder whose pickled checkpoints may load (still with ``weights_only=True``)."""
    p = Path(os.path.abspath(Path(folder).expanduser()))
    if p not in _TRUSTED_FOLDERS:
        _TRUSTED_FOLDERS.append(p)


def _is_within(path: Path, folder: Path) -> bool:
    try:
        Path(os.path.abspath(path)).relative_to(Path(os.path.abspath(folder)))
        return True
    except ValueError:
        return False


def in_trusted_folder(path: os.PathLike) -> bool:
    return any(_is_within(Path(path), f) for f in [models_root(), *_TRUSTED_FOLDERS])


def safe_child(base: os.PathLike, name: str, what: str) -> Path:
    """``base / name`` for a model *name* (a file or folder inside a model folder). A name that is
    absolute or climbs out with '..' is refused: names from a drop-down or an API call can never
    reach files outside the model folders. (Symbolic links inside the folder are followed, as
    ComfyUI does: users link large files in from other drives.)"""
    p = Path(name)
    if p.is_absolute() or p.drive or any(part == ".." for part in p.parts):
        raise InputError(f"{what} name {name!r} must be a name inside {base} (no absolute paths, no '..'). "
                         "Put the file in that folder and pick it by name.")
    return Path(base) / p


def models_root() -> Path:
    """``$PHYSMOTION_MODELS`` if set, else ``./models`` (ComfyUI's layout)."""
    return Path(os.environ.get("PHYSMOTION_MODELS", "models")).expanduser()


def model_dir(kind: str, root: Optional[os.PathLike] = None) -> Path:
    """The folder that holds weights of ``kind`` (see the module table)."""
    if kind not in MODEL_FOLDERS:
        raise InputError(f"Unknown model kind {kind!r}; expected one of {sorted(MODEL_FOLDERS)}")
    return Path(root) / MODEL_FOLDERS[kind] if root is not None else models_root() / MODEL_FOLDERS[kind]


def list_models(kind: str, *, suffixes: Sequence[str] = WEIGHT_SUFFIXES, dirs: bool = False,
                root: Optional[os.PathLike] = None) -> list[str]:
    """Names (relative to the kind's folder) of weight files, or of sub-folders with ``dirs``."""
    base = model_dir(kind, root)
    if not base.is_dir():
        return []
    if dirs:
        return sorted(p.name for p in base.iterdir() if p.is_dir())
    return sorted(str(p.relative_to(base)) for p in base.rglob("*")
                  if p.is_file() and p.name.lower().endswith(tuple(suffixes)))


def describe_folder(folder: Path, limit: int = 8) -> str:
    """'empty', 'missing' or a short listing, for error messages."""
    folder = Path(folder)
    if not folder.exists():
        return "the folder does not exist"
    if folder.is_file():
        return f"{folder.name} is a file, not a folder"
    names = sorted(p.name + ("/" if p.is_dir() else "") for p in folder.iterdir())
    if not names:
        return "the folder is empty"
    more = f" … and {len(names) - limit} more" if len(names) > limit else ""
    return "found: " + ", ".join(names[:limit]) + more


def resolve_weight_file(kind: str, name: Optional[str], *, expected: str,
                        root: Optional[os.PathLike] = None,
                        suffixes: Sequence[str] = WEIGHT_SUFFIXES) -> Path:
    """The path of a weight file: ``name`` may be absolute, or relative to the kind's folder.

    With ``name`` None the folder must hold exactly one matching file. Raises MissingModelError
    naming the folder, the expected file and what was found.
    """
    base = model_dir(kind, root)
    if name:
        p = Path(name).expanduser()
        # An absolute path is the library caller's own choice of file; a relative name must stay
        # inside the kind's folder.
        cand = p if p.is_absolute() else safe_child(base, name, f"{kind} weights")
        if cand.is_file():
            if not p.is_absolute():
                trust_folder(base)  # the caller named this models root
            return cand
        where = cand.parent
        raise MissingModelError(
            f"{kind} weights {name!r} not found at {cand}. Expected {expected} in {where}; "
            f"{describe_folder(where)}. Weights are never downloaded: place the file there.")
    found = list_models(kind, suffixes=suffixes, root=root)
    if len(found) == 1:
        trust_folder(base)
        return base / found[0]
    if not found:
        raise MissingModelError(
            f"No {kind} weights in {base}. Expected {expected}; {describe_folder(base)}. "
            "Weights are never downloaded: place the file there (or set $PHYSMOTION_MODELS).")
    raise InputError(f"Several {kind} weight files in {base} ({', '.join(found)}); say which one to use.")


def resolve_model_dir(kind: str, name: Optional[str], *, expected: str, required: Iterable[str] = (),
                      root: Optional[os.PathLike] = None) -> Path:
    """A model folder (diffusers/transformers layout) and a check that ``required`` entries exist."""
    base = model_dir(kind, root)
    if name:
        p = Path(name).expanduser()
        folder = p if p.is_absolute() else safe_child(base, name, f"{kind} model folder")
    else:
        subs = list_models(kind, dirs=True, root=root)
        if len(subs) != 1:
            what = "none" if not subs else ", ".join(subs)
            raise MissingModelError(
                f"Say which {kind} model folder to use: {base} holds {what}. Expected {expected}. "
                "Weights are never downloaded.")
        folder = base / subs[0]
    if not folder.is_dir():
        raise MissingModelError(
            f"{kind} model folder {folder} not found. Expected {expected}; in {folder.parent}: "
            f"{describe_folder(folder.parent)}. Weights are never downloaded.")
    if not Path(name or "").expanduser().is_absolute():
        trust_folder(folder)  # inside the models root the caller named
    missing = [r for r in required if not (folder / r).exists()]
    if missing:
        raise MissingModelError(
            f"{kind} model folder {folder} is incomplete: missing {', '.join(missing)}. Expected {expected}; "
            f"{describe_folder(folder)}.")
    return folder


def load_state_dict_file(path: os.PathLike, *, allow_pickle: Optional[bool] = None) -> dict:
    """Tensors from ``.safetensors`` (preferred) or a torch pickle loaded with ``weights_only=True``.

    A pickle (.pth/.pt/.bin/.ckpt) outside the model folders loads only with ``allow_pickle=True``
    or ``$PHYSMOTION_ALLOW_PICKLE=1``: even the restricted unpickler is more attack surface than
    safetensors, so files from arbitrary places must be asked for explicitly.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise MissingModelError(f"Weight file {path} not found; {describe_folder(path.parent)}.")
    if path.suffix != ".safetensors":
        if allow_pickle is None:
            allow_pickle = os.environ.get(ALLOW_PICKLE_ENV, "") in ("1", "true", "yes") or in_trusted_folder(path)
        if not allow_pickle:
            raise InputError(f"{path} is a pickled checkpoint outside the model folders. Move it into the model "
                             f"folder ({models_root()} or ComfyUI's models/), convert it to .safetensors, or opt in "
                             f"with allow_pickle=True / {ALLOW_PICKLE_ENV}=1 (it is then loaded with "
                             "weights_only=True).")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            return load_file(str(path))
        obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except MissingModelError:
        raise
    except Exception as exc:  # corrupt / truncated / not a checkpoint
        raise InputError(f"Could not read weights from {path}: {exc}. The file may be truncated or not a "
                         "checkpoint; re-download it from the official release.") from exc
    if isinstance(obj, Mapping) and "state_dict" in obj and isinstance(obj["state_dict"], Mapping):
        obj = obj["state_dict"]
    if not isinstance(obj, Mapping):
        raise InputError(f"{path} does not hold a state dict (found {type(obj).__name__}).")
    return dict(obj)


def check_state_dict(state: Mapping, expected: Mapping[str, Sequence[int]], what: str,
                     path: Optional[os.PathLike] = None, limit: int = 5, float_keys: Iterable[str] = ()) -> None:
    """Raise InputError unless ``state`` has exactly the keys and shapes of ``expected``, every
    entry is a tensor, and the keys in ``float_keys`` (the model's floating-point parameters) hold
    floating-point tensors (an integer or boolean tensor there is not a weight of this model).

    The message names the file and says how many keys are missing / unexpected / mis-shaped /
    of the wrong dtype with examples, so a user who picked the wrong file (an SD checkpoint in the
    LGM folder, a vit_b in place of vit_h, a quantised or damaged export) sees it at once.
    """
    import torch

    src = f" ({path})" if path else ""
    not_tensors = sorted(k for k, v in state.items() if not isinstance(v, torch.Tensor))
    if not_tensors:
        raise InputError(f"The weights{src} are not a state dict of {what}: {len(not_tensors)} entries are not tensors "
                         f"(e.g. {', '.join(map(str, not_tensors[:limit]))}). Use the official checkpoint file.")
    got = {k: tuple(v.shape) for k, v in state.items()}
    exp = {k: tuple(v) for k, v in expected.items()}
    missing = sorted(set(exp) - set(got))
    unexpected = sorted(set(got) - set(exp))
    shape = sorted(k for k in set(exp) & set(got) if exp[k] != got[k])
    dtype = sorted(k for k in set(float_keys) & set(got) if not state[k].is_floating_point())
    if not (missing or unexpected or shape or dtype):
        return
    parts = []
    if missing:
        parts.append(f"{len(missing)} missing (e.g. {', '.join(missing[:limit])})")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected (e.g. {', '.join(unexpected[:limit])})")
    if shape:
        parts.append(f"{len(shape)} with other shapes (e.g. " + ", ".join(
            f"{k}: file {got[k]} vs model {exp[k]}" for k in shape[:limit]) + ")")
    if dtype:
        parts.append(f"{len(dtype)} not floating-point (e.g. " + ", ".join(
            f"{k}: {str(state[k].dtype).replace('torch.', '')}" for k in dtype[:limit]) + ")")
    raise InputError(f"The weights{src} do not match {what}: " + "; ".join(parts) +
                     f". The checkpoint holds {len(got)} tensors, the model expects {len(exp)}. "
                     "Check that the file is the official release for this model.")


def pick_device(device=None):
    """``device`` if given, else CUDA when available, else CPU."""
    import torch

    if device is not None:
        return torch.device(device)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def default_dtype(device) -> "torch.dtype":
    """fp16 on CUDA, fp32 on CPU (docs/lift.md, docs/enhance.md "Weights")."""
    import torch

    return torch.float16 if torch.device(device).type == "cuda" else torch.float32
