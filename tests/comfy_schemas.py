"""Node schemas for checking templates without a ComfyUI: what ``GET /object_info`` of a real ComfyUI
0.3.64 returned (tests/data/object_info-0.3.64.json, a copy of ../shared/comfy/), the upstream nodes
newer than 0.3.64 typed from their source (tests/data/comfy_upstream_nodes.json, commits inside), and
this pack's own nodes built from their classes (the captured PhysMotion entries are dropped: the
classes are the truth). Use with physmotion_core.workflow.validate_prompt_against_schemas.
"""

from __future__ import annotations

import importlib
import json
from functools import lru_cache

from comfy_harness import ROOT, load_pack

from physmotion_core.comfy.workflow import node_schemas

DATA = ROOT / "tests" / "data"
OBJECT_INFO = DATA / "object_info-0.3.64.json"
UPSTREAM = DATA / "comfy_upstream_nodes.json"


def pack_classes() -> dict:
    """Every PhysMotion node class, also those registered only on a ComfyUI that has what they need
    (the GAUSSIAN converters are absent on 0.3.64 and outside ComfyUI, yet templates use them)."""
    pack = load_pack()
    classes = dict(pack.NODE_CLASS_MAPPINGS)
    for path in sorted((ROOT / "nodes").glob("*.py")):
        if path.stem.startswith("_"):
            continue
        try:
            mod = importlib.import_module(f"{pack.__name__}.nodes.{path.stem}")
        except Exception:  # noqa: BLE001 - a module the pack could not load is reported by test_nodes
            continue
        for name, obj in vars(mod).items():
            if name.startswith("PhysMotion") and isinstance(obj, type) and hasattr(obj, "INPUT_TYPES"):
                classes.setdefault(name, obj)
    return classes


@lru_cache(maxsize=1)
def _native() -> dict:
    info = json.loads(OBJECT_INFO.read_text())
    native = {k: v for k, v in info.items() if not k.startswith("PhysMotion")}
    native.update(json.loads(UPSTREAM.read_text())["nodes"])
    return native


def all_schemas() -> dict:
    """ComfyUI 0.3.64's nodes + the newer upstream nodes + this pack's nodes."""
    return {**_native(), **node_schemas(pack_classes())}


def native_schemas() -> dict:
    return dict(_native())


#: The model files the weight-needing templates name (README: "Needs ..."): a model dropdown lists only
#: the files found on the machine, so these are accepted there in addition.
TEMPLATE_MODEL_FILES = {
    "PhysMotionSAMLoader.sam_name": ["sam_vit_h_4b8939.pth"],
    "PhysMotionImageDreamLoader.model_name": ["imagedream-ipmv-diffusers"],
    "PhysMotionLGMLoader.lgm_name": ["model_fp16_fixrot.safetensors"],
    "PhysMotionDiffusionLoader.model": ["stable-diffusion-2-1"],
    "PhysMotionDiffusionLoader.controlnet_depth": ["controlnet-sd21-depth-diffusers"],
    "PhysMotionDiffusionLoader.controlnet_canny": ["controlnet-sd21-canny-diffusers"],
    # TripoSplat (docs/comfyui.md "TripoSplat -> physics"): the DINOv3 ViT-H encoder, the Flux2 VAE, the
    # TripoSplat VAE decoder and the TripoSplat diffusion model, as the native nodes' users name them.
    "CLIPVisionLoader.clip_name": ["dino_v3_vit_h.safetensors"],
    "VAELoader.vae_name": ["flux2-vae.safetensors", "triposplat_vae_decoder_fp16.safetensors"],
    "UNETLoader.unet_name": ["triposplat_fp16.safetensors"],
}
# The Wan templates (README "Where weights go"): Comfy-Org/Wan_2.1_ComfyUI_repackaged's text encoder, VAE,
# CLIP vision and VACE 14B files, and the ATI 14B model (Kijai/WanVideo_comfy, as bytedance/ATI links it).
for _key, _files in {"UNETLoader.unet_name": ["Wan2_1-I2V-ATI-14B_fp8_e4m3fn.safetensors",
                                              "wan2.1_vace_14B_fp16.safetensors"],
                     "CLIPLoader.clip_name": ["umt5_xxl_fp8_e4m3fn_scaled.safetensors"],
                     "VAELoader.vae_name": ["wan_2.1_vae.safetensors"],
                     "CLIPVisionLoader.clip_name": ["clip_vision_h.safetensors"]}.items():
    TEMPLATE_MODEL_FILES.setdefault(_key, []).extend(_files)
