"""Gradients wherever the caller runs us.

ComfyUI executes every node inside ``torch.inference_mode()`` (0.3.64: ``execution.py``), where no
autograd graph is recorded and ``backward()`` fails; the tensors it passes between nodes are then
"inference tensors", which an autograd graph may not save. The stages that optimise (Fit Gaussians
to Photo, Hard-Depth Refine, LoRA Personalize) run inside ``with_autograd``: gradients on, and every
inference tensor among their arguments (also inside dataclasses, lists and tuples) replaced by a
normal copy. Anything else is passed through untouched, and the caller's mode is restored after.
"""

from __future__ import annotations

import dataclasses
import functools

import torch


def normal_copy(value):
    """``value`` with each inference tensor in it (tensors, dataclass fields, lists, tuples, dict
    values) replaced by a normal copy; call with inference mode off."""
    if torch.is_tensor(value):
        return value.clone() if value.is_inference() else value
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        changes = {}
        for f in dataclasses.fields(value):
            if f.init:
                old = getattr(value, f.name)
                new = normal_copy(old)
                if new is not old:
                    changes[f.name] = new
        return dataclasses.replace(value, **changes) if changes else value
    if isinstance(value, (list, tuple)):
        items = [normal_copy(v) for v in value]
        if all(a is b for a, b in zip(items, value)):
            return value
        return type(value)(items) if isinstance(value, list) else tuple(items)
    if isinstance(value, dict):
        items = {k: normal_copy(v) for k, v in value.items()}
        return value if all(items[k] is value[k] for k in value) else items
    return value


def with_autograd(fn):
    """Run ``fn`` with gradients on and its arguments free of inference tensors (see the module doc)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with torch.inference_mode(False), torch.enable_grad():
            args = tuple(normal_copy(a) for a in args)
            kwargs = {k: normal_copy(v) for k, v in kwargs.items()}
            return fn(*args, **kwargs)

    return wrapper


def normal_parameters(module: torch.nn.Module) -> int:
    """Replace ``module``'s parameters and buffers that are inference tensors (a model loaded or moved
    to its device inside ComfyUI's inference mode) by normal copies, in place, so gradients can flow
    through it. Returns how many were replaced; call with inference mode off."""
    replaced = 0
    for sub in module.modules():
        for name, p in list(sub._parameters.items()):
            if p is not None and p.is_inference():
                sub._parameters[name] = torch.nn.Parameter(p.detach().clone(), requires_grad=p.requires_grad)
                replaced += 1
        for name, b in list(sub._buffers.items()):
            if b is not None and b.is_inference():
                sub._buffers[name] = b.clone()
                replaced += 1
    return replaced
