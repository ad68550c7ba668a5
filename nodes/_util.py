"""Glue between ComfyUI and physmotion_core. ComfyUI modules are imported lazily, so the node
classes also load (and are tested) without ComfyUI."""

from __future__ import annotations

import logging
import math
import os
import re
from pathlib import Path
from typing import Optional

import torch

from physmotion_core.errors import InputError

log = logging.getLogger("physmotion.nodes")

CATEGORY = "PhysMotion"


def progress_callback():
    """A physmotion progress callback driving ComfyUI's progress bar and honouring Cancel.

    Outside ComfyUI it returns None (no progress, no interruption).
    """
    try:
        import comfy.model_management as mm
        import comfy.utils
    except ImportError:
        return None
    bar: Optional[comfy.utils.ProgressBar] = None

    def callback(done: int, total: int, preview=None) -> None:
        nonlocal bar
        mm.throw_exception_if_processing_interrupted()
        if bar is None:
            bar = comfy.utils.ProgressBar(total)
        bar.update_absolute(done, total, preview)

    return callback


def node_text(unique_id, lines) -> None:
    """Show ``lines`` as text on the running node in ComfyUI (``PromptServer.send_progress_text``, which the
    frontend draws under the node, as for the core Get Image Size node; each call replaces the text).
    Nothing outside ComfyUI, without the node's id, or on a server without it."""
    if unique_id is None:
        return
    try:
        from server import PromptServer
    except ImportError:
        return
    send = getattr(getattr(PromptServer, "instance", None), "send_progress_text", None)
    if send is not None:
        send("\n".join(str(t) for t in lines), str(unique_id))


def preview_payload(image: torch.Tensor, max_side: int = 512):
    """An (H, W, 3) image in 0..1 as the preview ComfyUI's progress bar shows beside it
    (``ProgressBar.update_absolute(value, total, preview)``): ("JPEG", PIL image, max size)."""
    import numpy as np
    from PIL import Image

    arr = (image.detach().float().cpu().clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    return ("JPEG", Image.fromarray(arr), int(max_side))


def progress_with_previews():
    """(progress, preview) callbacks for a library loop that reports progress every step and a
    preview image now and then: the latest preview rides along with the next progress update."""
    cb = progress_callback()
    if cb is None:
        return None, None
    latest: dict = {}

    def preview(_step, image) -> None:
        latest["image"] = image

    def progress(done, total) -> None:
        img = latest.pop("image", None)
        cb(done, total, preview_payload(img) if img is not None else None)

    return progress, preview


def temp_directory() -> Path:
    """ComfyUI's temp folder (previews, cleared on restart); outside ComfyUI $PHYSMOTION_TEMP_DIR or
    ``.previews`` in the output folder."""
    try:
        import folder_paths

        return Path(folder_paths.get_temp_directory())
    except ImportError:
        return Path(os.environ.get("PHYSMOTION_TEMP_DIR") or output_directory() / ".previews")


#: Longest side of the preview clips shown in the nodes (full-size frames go to Save Video).
PREVIEW_MAX_SIDE = 512


def _preview_frames(frames: torch.Tensor) -> torch.Tensor:
    """(T,H,W,3) or (T,H,W) frames shrunk to PREVIEW_MAX_SIDE, as (T,h,w,3) float in 0..1."""
    f = frames.detach().float().cpu()
    grey = f.ndim == 3
    if not grey:
        f = f[..., :3]
    scale = PREVIEW_MAX_SIDE / max(f.shape[1], f.shape[2])
    if scale < 1:
        import cv2
        import numpy as np

        # Area averaging (OpenCV's INTER_AREA, frame by frame: several times faster than torch's "area" mode,
        # adaptive average pooling, on the CPU at non-integer ratios), before the clamp and the grey frames'
        # three channels, so those passes run over the small frames (the same values for frames in 0..1, what
        # every previewed clip holds; the full-size clip is hundreds of MB).
        size = (max(2, round(f.shape[2] * scale)), max(2, round(f.shape[1] * scale)))  # (w, h)
        a = f.contiguous().numpy()
        f = torch.from_numpy(np.stack([cv2.resize(a[t], size, interpolation=cv2.INTER_AREA)
                                       for t in range(a.shape[0])]))
    if grey:
        f = f[..., None].expand(*f.shape, 3)
    return f.clamp(0, 1)


def preview_video(frames: torch.Tensor, fps: float, stem: str = "PhysMotion_preview") -> dict:
    """A node's video preview: an mp4 in the temp folder, returned as the ``ui`` dict ComfyUI's own
    video nodes return ({"images": [file], "animated": (True,)}); a single frame is a still PNG."""
    from physmotion_core.errors import InputError
    from physmotion_core.video import write_mp4

    folder = temp_directory()
    folder.mkdir(parents=True, exist_ok=True)
    f = _preview_frames(frames)
    if f.shape[0] == 1:
        return preview_images(f, stem)
    if not math.isfinite(float(f.sum())):  # clamped to 0..1: only a NaN can make the sum non-finite
        raise InputError("The frames to preview contain NaN values: the node (or one upstream of it) produced "
                         "invalid numbers. Check that node's inputs (e.g. a simulation that reported an error).")
    # To 8 bits here, as write_mp4 would (round to nearest), in one pass of torch's threads over the small frames.
    f8 = f.mul(255.0).add_(0.5).to(torch.uint8)
    name = f"{stem}_{os.urandom(4).hex()}.mp4"
    # A preview: the fastest x264 preset (on a 33-frame 512x288 clip 0.08 s instead of 0.21-0.24 s for "medium";
    # three previews in a Wan controls prompt), in a larger temp file.
    write_mp4(folder / name, f8, fps=float(min(max(fps, 1.0), 240.0)), crf=28, preset="ultrafast")
    return {"images": [{"filename": name, "subfolder": "", "type": "temp"}], "animated": (True,)}


def preview_images(images: torch.Tensor, stem: str = "PhysMotion_preview") -> dict:
    """Still previews (PNG in the temp folder) in the form ComfyUI's PreviewImage returns."""
    import cv2
    import numpy as np

    folder = temp_directory()
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for img in _preview_frames(images):
        name = f"{stem}_{os.urandom(4).hex()}.png"
        arr = (img.numpy() * 255 + 0.5).astype(np.uint8)[..., ::-1]
        if not cv2.imwrite(str(folder / name), arr, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OSError(f"could not write the preview {folder / name}")
        out.append({"filename": name, "subfolder": "", "type": "temp"})
    return {"images": out, "animated": (False,)}


def save_ply_output(gaussians, prefix: str) -> str:
    """Save Gaussians as a 3DGS .ply in the output folder; returns its path relative to the output
    folder (what Preview3D's model_file takes)."""
    from physmotion_core.ply import write_ply

    path, filename, subfolder = output_path(prefix, "ply")
    write_ply(path, gaussians)
    return f"{subfolder}/{filename}" if subfolder else filename


def torch_device() -> torch.device:
    try:
        import comfy.model_management as mm

        return mm.get_torch_device()
    except ImportError:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def sim_device(choice: str) -> str:
    """'auto' follows ComfyUI's device (a CUDA device index) or falls back to the simulator's own choice."""
    if choice != "auto":
        return choice
    dev = torch_device()
    if dev.type == "cuda":
        return f"cuda:{dev.index or 0}"
    if dev.type == "cpu":
        return "cpu"
    return "auto"


def output_directory() -> Path:
    try:
        import folder_paths

        return Path(folder_paths.get_output_directory())
    except ImportError:
        return Path(os.environ.get("PHYSMOTION_OUTPUT_DIR", "output")).resolve()


def output_path(prefix: str, extension: str) -> tuple[Path, str, str]:
    """A new file ``<output>/<prefix>_NNNNN_.<ext>`` (or, with extension "", a new folder
    ``<output>/<prefix>_NNNNN_``); returns (path, name, subfolder).

    The prefix may contain sub-folders but never leaves the output directory.
    """
    root = output_directory().resolve()
    if prefix and any(c == "\x00" or ord(c) < 32 for c in prefix):
        raise InputError(f"filename_prefix {prefix!r} contains a NUL byte or a control character, which file names "
                         "cannot hold; remove it")
    prefix = (prefix or "PhysMotion").strip().replace("\\", "/")
    target = (root / prefix).resolve()
    if os.path.commonpath([root, target]) != str(root):
        raise InputError(f"filename_prefix '{prefix}' points outside the output folder; use a relative name")
    folder, stem = target.parent, target.name or "PhysMotion"
    folder.mkdir(parents=True, exist_ok=True)
    suffix = f".{extension}" if extension else ""
    pattern = re.compile(re.escape(stem) + r"_(\d{5})_" + re.escape(suffix) + "$")
    taken = [int(m.group(1)) for p in folder.iterdir() if (m := pattern.match(p.name))]
    counter = max(taken, default=0) + 1
    name = f"{stem}_{counter:05d}_{suffix}"
    if len(name.encode("utf-8", "surrogateescape")) > 255:
        raise InputError(f"filename_prefix ends in a name of {len(stem.encode())} bytes; with the counter and extension "
                         "the file name would exceed the 255 bytes file systems allow. Use a shorter prefix.")
    subfolder = os.path.relpath(folder, root)
    return folder / name, name, "" if subfolder == "." else subfolder


def first_image(image: torch.Tensor, name: str = "image") -> torch.Tensor:
    """(H,W,3) from a ComfyUI IMAGE batch, warning when frames beyond the first are ignored."""
    if image.ndim == 3:
        image = image[None]
    if image.ndim != 4 or image.shape[-1] not in (3, 4):
        raise InputError(f"{name} must be an IMAGE [B,H,W,3]; got shape {tuple(image.shape)}")
    require_batch(image, name, "IMAGE")
    if image.shape[0] > 1:
        log.warning("%s: a batch of %d images was given; using the first", name, image.shape[0])
    return image[0, ..., :3].float().cpu()


def first_mask(mask: Optional[torch.Tensor]) -> Optional[torch.Tensor]:
    if mask is None:
        return None
    if mask.ndim == 3:
        require_batch(mask, "mask", "MASK")
        mask = mask[0]
    if mask.ndim != 2:
        raise InputError(f"mask must be a MASK [B,H,W]; got shape {tuple(mask.shape)}")
    if mask.numel() == 0:
        raise InputError(f"mask is empty (shape {tuple(mask.shape)}); connect a mask with pixels")
    return mask.float().cpu()


def require_batch(tensor: torch.Tensor, name: str, kind: str = "IMAGE") -> torch.Tensor:
    """Refuse an empty IMAGE/MASK batch (no images, or images of 0 pixels), e.g. from a filter or
    a batch split upstream that let nothing through, before any index into it fails."""
    if not isinstance(tensor, torch.Tensor):
        raise InputError(f"{name} must be an {kind} tensor; got {type(tensor).__name__}")
    if tensor.ndim >= 1 and tensor.shape[0] == 0:
        raise InputError(f"{name} is an empty {kind} batch (0 images, shape {tuple(tensor.shape)}): the node "
                         "upstream produced nothing; check it (a filter, a batch split or a load that matched no file)")
    if tensor.numel() == 0:
        raise InputError(f"{name} has images of 0 pixels (shape {tuple(tensor.shape)}); check the node upstream")
    return tensor


# ----------------------------------------------------------------------------------------------
# Model folders: ComfyUI's models/<sub> when inside ComfyUI, $PHYSMOTION_MODELS/<sub> outside.
# ----------------------------------------------------------------------------------------------

#: ComfyUI folder name -> physmotion_core.models kind
COMFY_FOLDERS = {"sams": "sams", "physmotion_lgm": "lgm", "physmotion_imagedream": "imagedream",
                 "physmotion_depth": "depth"}
#: ComfyUI's own folder names for kinds it already knows (looked up, never re-registered)
COMFY_CORE_FOLDERS = {"diffusers": "diffusers", "controlnet": "controlnet", "loras": "loras",
                      "checkpoints": "checkpoints"}


def register_model_folders() -> None:
    """Add our model folders to ComfyUI's folder_paths (keeping any the user configured)."""
    try:
        import folder_paths
    except ImportError:
        return
    from physmotion_core.models import MODEL_FOLDERS

    for name, kind in COMFY_FOLDERS.items():
        path = os.path.join(folder_paths.models_dir, *MODEL_FOLDERS[kind].split("/"))
        if name not in folder_paths.folder_names_and_paths:
            folder_paths.folder_names_and_paths[name] = ([path], set(folder_paths.supported_pt_extensions))
        else:
            folder_paths.add_model_folder_path(name, path)


def model_folders(kind: str) -> list[Path]:
    """Every folder holding weights of ``kind`` (ComfyUI's list, or the library's single folder)."""
    from physmotion_core.models import model_dir

    name = next((n for n, k in {**COMFY_FOLDERS, **COMFY_CORE_FOLDERS}.items() if k == kind), None)
    try:
        import folder_paths

        if name is not None and name in folder_paths.folder_names_and_paths:
            return [Path(p) for p in folder_paths.get_folder_paths(name)]
    except ImportError:
        pass
    return [model_dir(kind)]


def _comfy_folder_name(kind: str) -> Optional[str]:
    """ComfyUI's folder_paths name for ``kind`` when running inside ComfyUI and it is registered."""
    name = next((n for n, k in {**COMFY_FOLDERS, **COMFY_CORE_FOLDERS}.items() if k == kind), None)
    try:
        import folder_paths
    except ImportError:
        return None
    return name if name is not None and name in folder_paths.folder_names_and_paths else None


def comfy_file_list(kind: str, suffixes) -> Optional[list[str]]:
    """``folder_paths.get_filename_list`` of ``kind``'s folder (names relative to it, sub-folders with
    "/"), the weight files among them; None outside ComfyUI or when the folder is not registered."""
    comfy_name = _comfy_folder_name(kind)
    if comfy_name is None:
        return None
    import folder_paths

    return [f for f in folder_paths.get_filename_list(comfy_name) if f.lower().endswith(tuple(suffixes))]


def comfy_full_path(kind: str, name: str) -> Optional[Path]:
    """``folder_paths.get_full_path`` of a file name of ``kind`` (it keeps the name inside the folders);
    the folder it was found in becomes trusted for checkpoints. None when not found that way."""
    comfy_name = _comfy_folder_name(kind)
    if comfy_name is None or not name:
        return None
    import folder_paths

    from physmotion_core.models import trust_folder

    found = folder_paths.get_full_path(comfy_name, name)
    if not found:
        return None
    for folder in model_folders(kind):
        if _within(Path(found), folder):
            trust_folder(folder)  # a ComfyUI model folder: its checkpoints may load
            return Path(found)
    return None


def model_choices(kind: str, *, dirs: bool = False, suffixes=(".safetensors", ".pth", ".pt", ".bin")) -> list[str]:
    """Names to offer in a loader's drop-down: files (or sub-folders with ``dirs``) of every folder.

    Inside ComfyUI files are listed by ``folder_paths.get_filename_list`` (its cache, its refresh);
    folder_paths lists no folders, so sub-folder models are found in ``get_folder_paths``.
    """
    files = None if dirs else comfy_file_list(kind, suffixes)
    if files is not None:
        return sorted(files) or ["(none found)"]
    names: set[str] = set()
    for folder in model_folders(kind):
        if not folder.is_dir():
            continue
        if dirs:
            names.update(p.name for p in folder.iterdir() if p.is_dir())
        else:
            names.update(str(p.relative_to(folder)) for p in folder.rglob("*")
                         if p.is_file() and p.name.lower().endswith(tuple(suffixes)))
    return sorted(names) or ["(none found)"]


def model_path(kind: str, name: str, *, expected: str) -> Path:
    """The full path of a drop-down choice; a clear error naming the folders when it is absent."""
    from physmotion_core.errors import MissingModelError
    from physmotion_core.models import describe_folder

    from physmotion_core.models import safe_child, trust_folder

    folders = model_folders(kind)
    found = comfy_full_path(kind, name) if name and name != "(none found)" else None
    if found is not None:  # a file, resolved by ComfyUI's folder_paths
        return found
    if name and name != "(none found)":  # a model folder (folder_paths resolves files only), or outside ComfyUI
        # Names come from the drop-down, or from an API client: they must stay inside the folders.
        for folder in folders:
            cand = safe_child(folder, name, f"{kind} model")
            if cand.exists():
                trust_folder(folder)  # a ComfyUI model folder: its checkpoints may load
                return cand
    where = "; ".join(f"{f} ({describe_folder(f)})" for f in folders)
    raise MissingModelError(f"{kind} model {name!r} not found. Expected {expected} in: {where}. "
                            "Weights are never downloaded: put the file there and refresh the node (press R).")


def _within(path: Path, folder: Path) -> bool:
    try:
        return os.path.commonpath([os.path.abspath(path), os.path.abspath(folder)]) == os.path.abspath(folder)
    except ValueError:  # different drives
        return False


def offload_device() -> torch.device:
    try:
        import comfy.model_management as mm

        return mm.unet_offload_device()
    except ImportError:
        return torch.device("cpu")


def free_memory_for(model_bytes: int, device: torch.device, what: str = "This node") -> None:
    """Ask ComfyUI to make room on ``device`` before one of our models moves there; then refuse
    clearly (InputError naming the sizes and what to do) if the weights still cannot fit, instead
    of failing with a CUDA out-of-memory traceback half-way through the move."""
    if device.type != "cuda":
        return  # the weights already live in RAM (the offload device)
    try:
        import comfy.model_management as mm

        mm.free_memory(int(model_bytes * 1.2) + (512 << 20), device)
    except ImportError:
        pass
    from physmotion_core.memory import check_device_fits

    check_device_fits(int(model_bytes), device, what)
