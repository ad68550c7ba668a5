"""A stand-in ``comfy`` package with the parts of ComfyUI's API the nodes call (progress bar,
interruption, devices, memory), for testing progress and Cancel without ComfyUI."""

from __future__ import annotations

import sys
import time
import types

import torch


class InterruptProcessingException(Exception):
    """What ComfyUI raises from throw_exception_if_processing_interrupted()."""


def install_fake_comfy(monkeypatch, cancel_after_checks=None, model_manager=False) -> types.SimpleNamespace:
    """Put ``comfy``, ``comfy.model_management`` and ``comfy.utils`` in sys.modules for the test.

    The returned state records every progress update (``updates``: (value, total)) and every text shown
    on a node (``texts``: (node id, text, how many progress updates came before it), through a stand-in
    ``server.PromptServer``), counts the
    interruption checks (``checks``), and raises InterruptProcessingException once ``interrupt`` is
    set or more than ``cancel_after`` checks were made (``raised_at``: when, by time.monotonic()).

    ``model_manager``: also ``comfy.model_patcher.ModelPatcher`` and ``model_management.load_models_gpu``
    / ``unload_all_models`` / ``current_loaded_models``, reproducing what ComfyUI 0.3.64 does with a
    patcher (it sets ``model.device`` and load counters on the wrapped module, moves it with ``.to``);
    ``state.load_calls`` records (patchers, force_full_load) of every load_models_gpu call.
    """
    state = types.SimpleNamespace(interrupt=False, updates=[], checks=0, cancel_after=cancel_after_checks,
                                  raised_at=None, load_calls=[], patchers=[], texts=[])
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
    # ComfyUI's ``server.PromptServer.instance.send_progress_text(text, node_id)``: text shown on a node
    server = types.ModuleType("server")

    class PromptServer:
        instance = types.SimpleNamespace(send_progress_text=lambda text, node_id, sid=None: state.texts.append(
            (node_id, text, len(state.updates))))

    server.PromptServer = PromptServer
    mods = [("comfy", comfy), ("comfy.model_management", mm), ("comfy.utils", utils), ("server", server)]
    if model_manager:
        comfy.model_patcher = _fake_model_patcher(mm, state)
        mods.append(("comfy.model_patcher", comfy.model_patcher))
    for name, mod in mods:
        monkeypatch.setitem(sys.modules, name, mod)
    return state


def _fake_model_patcher(mm, state) -> types.ModuleType:
    mp = types.ModuleType("comfy.model_patcher")

    class ModelPatcher:
        def __init__(self, model, load_device, offload_device, size=0, weight_inplace_update=False):
            self.model, self.load_device, self.offload_device, self.size = model, load_device, offload_device, size
            if not hasattr(model, "device") or model.device is None:
                model.device = offload_device  # as upstream: an attribute on the wrapped module
            model.model_loaded_weight_memory = 0
            state.patchers.append(self)

        def model_size(self):
            if self.size <= 0:
                self.size = sum(t.nelement() * t.element_size() for t in self.model.state_dict().values())
            return self.size

        def current_loaded_device(self):
            return self.model.device

        def load(self, device_to):
            self.model.to(device_to)
            self.model.device = device_to  # fails on a module whose device is a read-only property
            self.model.model_loaded_weight_memory = self.model_size()

        def detach(self, unpatch_all=True):
            self.model.to(self.offload_device)
            self.model.device = self.offload_device
            self.model.model_loaded_weight_memory = 0
            return self.model

    mm.current_loaded_models = []

    def load_models_gpu(models, memory_required=0, force_patch_weights=False, minimum_memory_required=None,
                        force_full_load=False):
        state.load_calls.append((list(models), force_full_load))
        for m in models:
            if m not in mm.current_loaded_models:
                m.load(m.load_device)
                mm.current_loaded_models.insert(0, m)

    def unload_all_models():
        while mm.current_loaded_models:
            mm.current_loaded_models.pop().detach()

    mm.load_models_gpu, mm.unload_all_models = load_models_gpu, unload_all_models
    mp.ModelPatcher = ModelPatcher
    return mp


def install_fake_folder_paths(monkeypatch, root) -> types.SimpleNamespace:
    """A stand-in ``folder_paths`` (ComfyUI's model, input, output and temp folders under ``root``) with
    the functions the pack calls; ``state.calls`` records (function, folder name, file name)."""
    import os
    from pathlib import Path

    root = Path(root)
    state = types.SimpleNamespace(calls=[])
    fp = types.ModuleType("folder_paths")
    fp.models_dir = str(root / "models")
    fp.supported_pt_extensions = {".ckpt", ".pt", ".pt2", ".bin", ".pth", ".safetensors", ".pkl", ".sft"}
    fp.folder_names_and_paths = {n: ([str(root / "models" / n)], set(fp.supported_pt_extensions))
                                 for n in ("checkpoints", "loras", "controlnet", "diffusers")}

    def add_model_folder_path(name, path, is_default=False):
        paths, exts = fp.folder_names_and_paths.setdefault(name, ([], set()))
        if path not in paths:
            paths.insert(0, path) if is_default else paths.append(path)

    def get_folder_paths(name):
        return list(fp.folder_names_and_paths[name][0])

    def get_filename_list(name):
        state.calls.append(("get_filename_list", name, None))
        paths, exts = fp.folder_names_and_paths[name]
        out = set()
        for base in paths:
            for dirpath, _dirs, files in os.walk(base, followlinks=True):
                for f in files:
                    rel = os.path.relpath(os.path.join(dirpath, f), base).replace(os.sep, "/")
                    if not exts or os.path.splitext(f)[1].lower() in exts:
                        out.add(rel)
        return sorted(out)

    def get_full_path(name, filename):
        state.calls.append(("get_full_path", name, filename))
        if name not in fp.folder_names_and_paths:
            return None
        filename = os.path.relpath(os.path.join("/", filename), "/")  # as upstream: stays inside the folder
        for base in fp.folder_names_and_paths[name][0]:
            full = os.path.join(base, filename)
            if os.path.isfile(full):
                return full
        return None

    for sub in ("input", "output", "temp"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    fp.get_input_directory = lambda: str(root / "input")
    fp.get_output_directory = lambda: str(root / "output")
    fp.get_temp_directory = lambda: str(root / "temp")
    fp.add_model_folder_path, fp.get_folder_paths = add_model_folder_path, get_folder_paths
    fp.get_filename_list, fp.get_full_path = get_filename_list, get_full_path
    monkeypatch.setitem(sys.modules, "folder_paths", fp)
    return state
