"""A stand-in ``comfy`` package with the parts of ComfyUI's API the nodes call (progress bar,
interruption, devices, memory), for testing progress and Cancel without ComfyUI."""

from __future__ import annotations

import sys
import time
import types

import torch


class InterruptProcessingException(Exception):
    """What ComfyUI raises from throw_exception_if_processing_interrupted()."""


def install_fake_comfy(monkeypatch, cancel_after_checks=None) -> types.SimpleNamespace:
    """Put ``comfy``, ``comfy.model_management`` and ``comfy.utils`` in sys.modules for the test.

    The returned state records every progress update (``updates``: (value, total)), counts the
    interruption checks (``checks``), and raises InterruptProcessingException once ``interrupt`` is
    set or more than ``cancel_after`` checks were made (``raised_at``: when, by time.monotonic()).
    """
    state = types.SimpleNamespace(interrupt=False, updates=[], checks=0, cancel_after=cancel_after_checks,
                                  raised_at=None)
    mm = types.ModuleType("comfy.model_management")

    def throw_exception_if_processing_interrupted():
        state.checks += 1
        if state.interrupt or (state.cancel_after is not None and state.checks > state.cancel_after):
            state.raised_at = time.monotonic()
            raise InterruptProcessingException()

    mm.throw_exception_if_processing_interrupted = throw_exception_if_processing_interrupted
    mm.InterruptProcessingException = InterruptProcessingException
    mm.get_torch_device = lambda: torch.device("cpu")
    mm.unet_offload_device = lambda: torch.device("cpu")
    mm.free_memory = lambda *a, **k: None
    utils = types.ModuleType("comfy.utils")

    class ProgressBar:
        def __init__(self, total):
            self.total = total

        def update_absolute(self, value, total=None, preview=None):
            state.updates.append((value, total))

    utils.ProgressBar = ProgressBar
    comfy = types.ModuleType("comfy")
    comfy.model_management, comfy.utils = mm, utils
    for name, mod in (("comfy", comfy), ("comfy.model_management", mm), ("comfy.utils", utils)):
        monkeypatch.setitem(sys.modules, name, mod)
    return state
