"""Learned models under ComfyUI's memory manager (ModelPatcher + load_models_gpu) and model files listed and
resolved through folder_paths, checked with stand-ins of both (tests/fake_comfy.py); and, when COMFYUI_DIR
points at a ComfyUI checkout, with the real ModelPatcher and load_models_gpu on the CPU."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from comfy_harness import ROOT, load_pack
from fake_comfy import install_fake_comfy, install_fake_folder_paths

PACK = load_pack()
NODES = PACK.NODE_CLASS_MAPPINGS
MEMORY = importlib.import_module(f"{PACK.__name__}.nodes._memory")
UTIL = importlib.import_module(f"{PACK.__name__}.nodes._util")


@pytest.fixture
def comfy(monkeypatch, tmp_path):
    """A ComfyUI stand-in with the memory manager and folder_paths; the pack's folders registered."""
    state = install_fake_comfy(monkeypatch, model_manager=True)
    state.fp = install_fake_folder_paths(monkeypatch, tmp_path)
    state.models = tmp_path / "models"
    UTIL.register_model_folders()
    return state


def _photo():
    rng = np.random.default_rng(0)
    img = 0.5 + 0.05 * rng.standard_normal((96, 128, 3))
    yy, xx = np.mgrid[:96, :128]
    img[(xx - 70) ** 2 + (yy - 50) ** 2 < 22 ** 2] = [0.9, 0.1, 0.1]
    return torch.from_numpy(np.clip(img, 0, 1).astype(np.float32))[None]


def test_sam_files_come_from_folder_paths_and_the_model_from_load_models_gpu(comfy):
    pytest.importorskip("segment_anything")
    from test_sam import tiny_sam

    (comfy.models / "sams" / "sub").mkdir(parents=True)
    torch.save(tiny_sam().state_dict(), comfy.models / "sams" / "sub" / "sam_tiny.pth")
    loader, seg = NODES["PhysMotionSAMLoader"], NODES["PhysMotionSAMSegment"]
    assert loader.INPUT_TYPES()["required"]["sam_name"][0] == ["sub/sam_tiny.pth"]
    assert ("get_filename_list", "sams", None) in comfy.fp.calls
    (sam,) = loader().run("sub/sam_tiny.pth")
    assert ("get_full_path", "sams", "sub/sam_tiny.pth") in comfy.fp.calls

    patcher = MEMORY.patcher_of(sam)
    assert patcher is not None and patcher in comfy.patchers
    assert isinstance(patcher.model, torch.nn.ModuleDict) and patcher.model["model"] is sam.model
    out = seg().run(sam, _photo(), "0.55, 0.52", "", "fraction", True)
    assert comfy.load_calls == [([patcher], True)]  # loaded through ComfyUI, whole (plain torch modules)
    mm = sys.modules["comfy.model_management"]
    assert mm.current_loaded_models == [patcher]  # still loaded after the node: ComfyUI evicts it when it needs room
    mm.unload_all_models()
    assert patcher.model.model_loaded_weight_memory == 0 and mm.current_loaded_models == []
    out2 = seg().run(sam, _photo(), "0.55, 0.52", "", "fraction", True)
    assert len(comfy.load_calls) == 2 and mm.current_loaded_models == [patcher]  # loaded again after eviction
    assert torch.equal(out["result"][1], out2["result"][1])
    # a name that climbs out is kept inside by folder_paths (not found there), then refused clearly
    from physmotion_core.errors import InputError

    with pytest.raises(InputError, match="no '..'"):
        loader().run("../../etc/passwd")


def test_lgm_with_a_read_only_device_property_is_managed_through_a_container(comfy):
    from tiny_models import LGM_INPUT_SIZE, LGM_NAME, write_tiny_lgm

    write_tiny_lgm(comfy.models)
    assert NODES["PhysMotionLGMLoader"].INPUT_TYPES()["required"]["lgm_name"][0] == [LGM_NAME]
    (net,) = NODES["PhysMotionLGMLoader"]().run(LGM_NAME, "auto", LGM_INPUT_SIZE)
    patcher = MEMORY.patcher_of(net)
    assert patcher.model["model"] is net
    with MEMORY.models_on_device(net, what="LGM") as dev:  # the stand-in sets .device as upstream does
        assert net.device == dev
    assert comfy.load_calls[-1] == ([patcher], True)
    assert patcher.current_loaded_device() == torch.device("cpu")


def test_the_diffusion_stack_is_one_managed_model_unless_cpu_offload(comfy):
    from physmotion_core.enhance.loader import DiffusionModels

    enhance = importlib.import_module(f"{PACK.__name__}.nodes.enhance")
    lin = lambda: torch.nn.Linear(4, 4)  # noqa: E731
    models = DiffusionModels(unet=lin(), vae=lin(), text_encoder=lin(), tokenizer=None, controlnets={"depth": lin()},
                             scheduler_config={}, prediction_type="epsilon", device=torch.device("cpu"),
                             dtype=torch.float32, name="tiny")
    MEMORY.manage(models, "SD")
    patcher = MEMORY.patcher_of(models)
    assert set(patcher.model.keys()) == {"unet", "vae", "text_encoder", "controlnet_depth"}
    enhance._make_room(models, ["unet"])
    assert comfy.load_calls == [([patcher], True)]
    enhance._offload(models)  # a managed stack stays loaded after the node
    assert sys.modules["comfy.model_management"].current_loaded_models == [patcher]
    assert MEMORY.patcher_of(models.with_lora(None)) is patcher  # LoRA copies share the modules and the patcher


def test_outside_comfyui_models_are_not_wrapped_and_move_back_after_use():
    assert "comfy.model_patcher" not in sys.modules
    net = torch.nn.Linear(3, 3)
    assert MEMORY.manage(net) is net and MEMORY.patcher_of(net) is None
    moves = []
    with MEMORY.models_on_device(net, move_in=lambda d: moves.append(("in", d)), move_out=lambda: moves.append("out")):
        pass
    assert moves == [("in", torch.device("cpu")), "out"]


@pytest.mark.skipif(not os.environ.get("COMFYUI_DIR"), reason="needs a ComfyUI checkout in COMFYUI_DIR")
def test_real_model_patcher_loads_and_evicts_our_modules():
    script = textwrap.dedent(f"""
        import sys, importlib.util
        import comfy.options
        comfy.options.enable_args_parsing()
        sys.argv = ["x", "--cpu"]
        import torch
        import comfy.model_management as mm
        spec = importlib.util.spec_from_file_location("pm", {str(ROOT / "__init__.py")!r},
                                                      submodule_search_locations=[{str(ROOT)!r}])
        pack = importlib.util.module_from_spec(spec); sys.modules["pm"] = pack; spec.loader.exec_module(pack)
        from pm.nodes._memory import manage, models_on_device, patcher_of

        class Net(torch.nn.Module):  # a read-only device property, like LGM's and diffusers'
            def __init__(self):
                super().__init__()
                self.conv = torch.nn.Conv2d(3, 3, 1)
            @property
            def device(self):
                return self.conv.weight.device

        net = manage(Net())
        with models_on_device(net):
            assert [m.model for m in mm.current_loaded_models] == [patcher_of(net)]
        assert len(mm.current_loaded_models) == 1
        mm.unload_all_models()
        assert mm.current_loaded_models == []
        with models_on_device(net):
            pass
        print("OK", patcher_of(net).model_size())
    """)
    python = os.environ.get("COMFYUI_PYTHON") or sys.executable  # the checkout's own environment (einops, ...)
    out = subprocess.run([python, "-c", script], cwd=os.environ["COMFYUI_DIR"], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0 and "OK 48" in out.stdout, out.stderr[-3000:]


def test_make_room_asks_comfyui_to_free_cuda_memory_only(comfy, monkeypatch):
    calls = []
    monkeypatch.setattr(sys.modules["comfy.model_management"], "free_memory", lambda need, dev: calls.append((need, dev)))
    MEMORY.make_room(10 << 20, "cpu")
    assert calls == []
    MEMORY.make_room(10 << 20, "cuda:1")
    assert len(calls) == 1 and calls[0][1] == torch.device("cuda:1") and calls[0][0] >= 10 << 20
