"""Our learned models under ComfyUI's memory manager (comfy.model_management).

Inside ComfyUI a loader node hands its model to ``manage``: the model's torch modules are put in one
``torch.nn.ModuleDict`` (a plain container: ModelPatcher records ``.device`` and its load counters on
the module it wraps, which our modules and diffusers' expose as read-only properties) and wrapped in a
``comfy.model_patcher.ModelPatcher(container, load_device, offload_device)``, kept on the model object.
A node that runs the model enters ``models_on_device(...)``, which calls
``comfy.model_management.load_models_gpu(patchers, force_full_load=True)``: ComfyUI makes room (evicting
the least recently used of its own models and ours), moves the weights in and lists the model among
its loaded models. After the node the weights stay on the device, like ComfyUI's own models, until
the manager needs the room (it then moves them to the offload device: ``ModelPatcher.detach``) or
"Unload models" is pressed. ``force_full_load``: our modules are plain torch modules without ComfyUI's
cast-on-the-fly layers, so a partial (low-VRAM) load would leave some weights on the CPU.

Outside ComfyUI (the CLI, the tests without ComfyUI) nothing changes: the weights move to the device
for the node and back to the offload device after it, with the clear "does not fit" refusal first.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Callable, Iterator, Mapping, Optional

import torch

from ._util import free_memory_for, log, offload_device, torch_device

PATCHER_ATTR = "_physmotion_model_patcher"


def make_room(need_bytes: int, device) -> None:
    """Ask ComfyUI to evict cached models (its own and ours) until ``need_bytes`` are free on a CUDA
    ``device``, for work it does not manage (the simulation). A no-op outside ComfyUI or on the CPU."""
    dev = torch.device(device)
    if dev.type != "cuda":
        return
    try:
        import comfy.model_management as mm
    except ImportError:
        return
    mm.free_memory(int(need_bytes * 1.1) + (256 << 20), dev)


def model_modules(obj) -> dict[str, torch.nn.Module]:
    """The torch modules of one of our model objects (SAM, depth, LGM, ImageDream, the diffusion stack)."""
    if isinstance(obj, torch.nn.Module):
        return {"model": obj}
    if hasattr(obj, "MODULES"):  # ImageDreamPipeline
        return {n: getattr(obj, n) for n in obj.MODULES}
    mods = getattr(obj, "modules", None)
    if callable(mods):  # DiffusionModels.modules() -> {name: module}
        out = mods()
        if isinstance(out, Mapping):
            return dict(out)
    model = getattr(obj, "model", None)  # SamModel, DepthModel
    if isinstance(model, torch.nn.Module):
        return {"model": model}
    raise TypeError(f"no torch modules found in {type(obj).__name__}")


def parameter_bytes(obj) -> int:
    return sum(t.numel() * t.element_size() for m in model_modules(obj).values()
               for t in list(m.parameters()) + list(m.buffers()))


def manage(obj, what: str = "model"):
    """Wrap ``obj``'s modules in a ComfyUI ModelPatcher (inside ComfyUI; a no-op outside). Returns ``obj``."""
    try:
        import comfy.model_management as mm
        import comfy.model_patcher
    except ImportError:
        return obj
    container = torch.nn.ModuleDict(model_modules(obj))
    patcher = comfy.model_patcher.ModelPatcher(container, load_device=mm.get_torch_device(),
                                               offload_device=mm.unet_offload_device())
    object.__setattr__(obj, PATCHER_ATTR, patcher)
    log.debug("PhysMotion: %s is managed by ComfyUI (%d bytes)", what, parameter_bytes(obj))
    return obj


def patcher_of(obj):
    """The ModelPatcher ``manage`` attached to ``obj``, or None."""
    return getattr(obj, PATCHER_ATTR, None) if obj is not None else None


def load_managed(*objs, what: str = "This node") -> torch.device:
    """Load the managed models among ``objs`` through ComfyUI (``load_models_gpu``); returns the device."""
    dev = torch_device()
    patchers = [p for p in (patcher_of(o) for o in objs) if p is not None]
    if not patchers:
        return dev
    import comfy.model_management as mm

    missing = sum(p.model_size() for p in patchers if p.current_loaded_device() != dev)
    if missing:
        free_memory_for(missing, dev, what)  # a clear refusal when the weights cannot fit at all
    mm.load_models_gpu(patchers, force_full_load=True)
    return dev


@contextmanager
def models_on_device(*objs, what: str = "This node", move_in: Optional[Callable] = None,
                     move_out: Optional[Callable] = None) -> Iterator[torch.device]:
    """Have the models ``objs`` (None entries are skipped) on ComfyUI's device for the ``with`` body.

    Managed models are loaded through ``load_models_gpu`` and stay loaded afterwards; the others are
    moved in with ``move_in(dev)`` (default: ``obj.to(dev)``) and out with ``move_out()`` (default:
    ``obj.to(offload_device())``) around the body, as before.
    """
    dev = torch_device()
    objs = [o for o in objs if o is not None]
    managed = [o for o in objs if patcher_of(o) is not None]
    plain = [o for o in objs if patcher_of(o) is None]
    if managed:
        load_managed(*managed, what=what)
    if plain:
        free_memory_for(sum(parameter_bytes(o) for o in plain), dev, what)
    try:
        if plain:
            if move_in is not None:
                move_in(dev)
            else:
                for o in plain:
                    o.to(dev)
        yield dev
    finally:
        if plain:
            if move_out is not None:
                move_out()
            else:
                for o in plain:
                    o.to(offload_device())
