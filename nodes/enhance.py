"""Generative enhancement nodes: Diffusion Loader, LoRA Personalize, DDIM+ Invert, Keyframe-Shared Sample."""

from __future__ import annotations

from pathlib import Path

from ._util import CATEGORY, log, progress_callback, require_batch

NONE = "(none)"
_WEIGHT_SUFFIXES = (".safetensors", ".ckpt", ".pt", ".pth", ".bin")


def _entries(kind: str, *, dirs: bool = True, files: bool = True) -> list[str]:
    """Top-level sub-folders and weight files of every folder of ``kind``."""
    from ._util import comfy_file_list, model_folders

    names: set[str] = set()
    listed = comfy_file_list(kind, _WEIGHT_SUFFIXES) if files else None
    if listed is not None:  # inside ComfyUI: its folder_paths lists the files (top level: not a model folder's)
        names.update(f for f in listed if not (dirs and ("/" in f or "\\" in f)))
    for folder in model_folders(kind):
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            if p.name.startswith("."):
                continue
            if (dirs and p.is_dir()) or (listed is None and files and p.is_file()
                                         and p.name.lower().endswith(_WEIGHT_SUFFIXES)):
                names.add(p.name)
    return sorted(names)


def _find(kinds: tuple, name: str, expected: str) -> Path:
    from physmotion_core.errors import MissingModelError
    from physmotion_core.models import describe_folder, safe_child, trust_folder

    from ._util import comfy_full_path, model_folders

    folders = [f for k in kinds for f in model_folders(k)]
    if name and name not in (NONE, "(none found)"):
        for k in kinds:  # a file, resolved by ComfyUI's folder_paths
            found = comfy_full_path(k, name)
            if found is not None:
                return found
        # names come from the drop-down or an API client: they must stay inside the model folders
        for f in folders:
            cand = safe_child(f, name, "model")
            if cand.exists():
                trust_folder(f)  # a model folder: its .ckpt files may load (weights_only)
                return cand
    where = "; ".join(f"{f} ({describe_folder(f)})" for f in folders)
    raise MissingModelError(f"{name!r} not found. Expected {expected} in: {where}. Weights are never downloaded: put "
                            "them there and refresh the node list (press R).")


def _default(choices: list[str], word: str) -> str:
    return next((c for c in choices if word in c.lower()), choices[0])


def _make_room(models, names) -> None:
    """Ask ComfyUI for room, then put the stage's modules on the device (a stack under ComfyUI's memory
    manager is loaded through it whole; otherwise the library places each module when its stage runs)."""
    from ._memory import load_managed, patcher_of
    from ._util import free_memory_for

    if patcher_of(models) is not None:
        load_managed(models, what="The diffusion models")
        return
    free_memory_for(models.parameter_bytes(names), models.device)


def _offload(models) -> None:
    """Back to the offload device after a node; a managed stack stays until ComfyUI needs the room."""
    from ._memory import patcher_of
    from ._util import offload_device

    if patcher_of(models) is not None:
        return
    models.offload(None, offload_device())


class PhysMotionDiffusionLoader:
    """SD 2.1 + ControlNet depth/canny (+ LoRA) from the model folders; nothing is downloaded."""

    DESCRIPTION = ("Loads Stable Diffusion 2.1 (a diffusers folder in models/diffusers/ or a single checkpoint in "
                   "models/checkpoints/, read offline with the configs shipped in the pack) and the SD 2.1 depth and "
                   "canny ControlNets (folders or single files in models/controlnet/), used together. fp16 on CUDA, "
                   "fp32 on the CPU; kept on the CPU between stages.")

    @classmethod
    def INPUT_TYPES(cls):
        models = _entries("diffusers", files=False) + _entries("checkpoints", dirs=False)
        models = models or ["(none found)"]
        cns = [NONE] + _entries("controlnet")
        loras = [NONE] + _entries("loras", dirs=False)
        return {
            "required": {
                "model": (models, {"default": _default(models, "2-1"),
                                   "tooltip": "SD 2.1: a diffusers folder (models/diffusers/) or a single .safetensors/"
                                              ".ckpt (models/checkpoints/), e.g. v2-1_768-ema-pruned.safetensors."}),
                "controlnet_depth": (cns, {"default": _default(cns, "depth"),
                                           "tooltip": "SD 2.1 depth ControlNet (folder or file in models/controlnet/), "
                                                      "e.g. control_v11p_sd21_depth. (none) = no depth conditioning."}),
                "controlnet_canny": (cns, {"default": _default(cns, "canny"),
                                           "tooltip": "SD 2.1 canny ControlNet (folder or file in models/controlnet/), "
                                                      "e.g. control_v11p_sd21_canny. (none) = no edge conditioning."}),
                "prediction_type": (["auto", "v_prediction", "epsilon"], {
                    "default": "auto", "tooltip": "auto: from the model's scheduler config (single files: SD 2.1 768 = "
                                                  "v_prediction). Use epsilon for SD 2.1-base (512) single files."}),
                "cpu_offload": ("BOOLEAN", {"default": False,
                                            "tooltip": "Keep only the module in use on the GPU (slower, less VRAM)."}),
            },
            "optional": {
                "lora": (loras, {"default": NONE, "tooltip": "Optional LoRA from models/loras/ (e.g. one written by "
                                                            "LoRA Personalize)."}),
                "lora_strength": ("FLOAT", {"default": 1.0, "min": -4.0, "max": 4.0, "step": 0.05,
                                            "tooltip": "Scale of the LoRA (1 = as trained)."}),
            },
        }

    RETURN_TYPES = ("PM_DIFFUSION",)
    RETURN_NAMES = ("diffusion",)
    OUTPUT_TOOLTIPS = ("SD 2.1 + ControlNets (+ LoRA), for LoRA Personalize, DDIM+ Invert and Keyframe-Shared Sample.",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/enhance"

    def run(self, model, controlnet_depth, controlnet_canny, prediction_type, cpu_offload, lora=NONE,
            lora_strength=1.0):
        from physmotion_core.enhance import load_diffusion
        from physmotion_core.enhance.loader import EXPECTED_CONTROLNET, EXPECTED_SD_FILE, EXPECTED_SD_FOLDER
        from physmotion_core.models import default_dtype

        from ._util import torch_device

        dev = torch_device()
        path = _find(("diffusers", "checkpoints"), model, f"{EXPECTED_SD_FOLDER} or {EXPECTED_SD_FILE}")
        cn = {k: (str(_find(("controlnet",), v, EXPECTED_CONTROLNET)) if v not in (NONE, "", None) else None)
              for k, v in (("depth", controlnet_depth), ("canny", controlnet_canny))}
        lora_path = str(_find(("loras",), lora, "a LoRA .safetensors")) if lora not in (NONE, "", None) else None
        models = load_diffusion(str(path), controlnet_depth=cn["depth"], controlnet_canny=cn["canny"], lora=lora_path,
                                lora_strength=float(lora_strength), device=dev, dtype=default_dtype(dev),
                                cpu_offload=bool(cpu_offload), prediction_type=prediction_type)
        _offload(models)
        if not cpu_offload:  # with cpu_offload the library moves one module at a time itself
            from ._memory import manage

            manage(models, "SD 2.1 + ControlNets")
        return (models,)


class PhysMotionLoRAPersonalize:
    """DreamBooth-style LoRA on the segmented object + its multi-view images (trained once, cached)."""

    DESCRIPTION = ("Fine-tunes a LoRA on the UNet's attention (peft) with the object cut-out and its generated views "
                   "under one instance prompt, so the enhancement keeps the object's look (paper: 1500 steps at "
                   "lr 1e-6). The adapter is saved in models/loras/ named by a hash of its inputs: the same inputs "
                   "load it instead of training again.")

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "diffusion": ("PM_DIFFUSION", {"tooltip": "From PhysMotion Diffusion Loader."}),
                "object_image": ("IMAGE", {"tooltip": "The segmented object (PhysMotion Segment's foreground); every "
                                                      "image of the batch is used."}),
                "instance_prompt": ("STRING", {"default": "a photo of sks object", "multiline": False,
                                               "tooltip": "Prompt with a rare token for the object; use the same "
                                                          "words in the sampling prompt (e.g. 'a photo of sks jelly')."}),
                "steps": ("INT", {"default": 1500, "min": 0, "max": 20000, "step": 50,
                                  "tooltip": "Training steps (paper: 1500). 0 = an untrained (identity) adapter."}),
                "learning_rate": ("FLOAT", {"default": 1e-6, "min": 1e-8, "max": 1e-2, "step": 1e-7, "round": False,
                                            "tooltip": "AdamW learning rate (paper: 1e-6; LoRA often needs ~1e-4 to "
                                                       "change much in 1500 steps)."}),
                "rank": ("INT", {"default": 4, "min": 1, "max": 128, "tooltip": "LoRA rank."}),
                "resolution": ("INT", {"default": 512, "min": 64, "max": 1024, "step": 64,
                                       "tooltip": "Training images are padded square and resized to this."}),
                "seed": ("INT", {"default": 0, "min": 0, "max": 2 ** 31 - 1,
                                 "tooltip": "Noise, timesteps and image order of training."}),
                "lora_strength": ("FLOAT", {"default": 1.0, "min": -4.0, "max": 4.0, "step": 0.05,
                                            "tooltip": "Scale the adapter is applied with downstream."}),
            },
            "optional": {
                "object_mask": ("MASK", {"tooltip": "Object mask: the background becomes white for training."}),
                "multiview_images": ("IMAGE", {"tooltip": "More views of the object (e.g. Multi-View Generate)."}),
                "views": ("PM_VIEWS", {"tooltip": "Generated views with cameras (from LGM Lift); their images are used."}),
            },
        }

    RETURN_TYPES = ("PM_DIFFUSION", "STRING")
    RETURN_NAMES = ("diffusion", "lora_name")
    OUTPUT_TOOLTIPS = ("The same models, applying the personalised LoRA.", "The adapter's file name in models/loras/.")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/enhance"

    def run(self, diffusion, object_image, instance_prompt, steps, learning_rate, rank, resolution, seed,
            lora_strength, object_mask=None, multiview_images=None, views=None):
        from physmotion_core.enhance import LoraSettings, personalize

        from ._util import model_folders

        require_batch(object_image, "object_image")
        if object_mask is not None:
            require_batch(object_mask, "object_mask", "MASK")
        images, masks = [], []
        for b in range(object_image.shape[0]):
            images.append(object_image[b, ..., :3].float().cpu())
            masks.append(None if object_mask is None else object_mask[min(b, object_mask.shape[0] - 1)].float().cpu())
        if multiview_images is not None:
            for b in range(multiview_images.shape[0]):
                images.append(multiview_images[b, ..., :3].float().cpu())
                masks.append(None)
        for v in list(views or []):
            if getattr(v, "image", None) is not None:
                images.append(v.image.float().cpu())
                masks.append(v.mask.float().cpu() if getattr(v, "mask", None) is not None else None)
        st = LoraSettings(steps=int(steps), learning_rate=float(learning_rate), rank=int(rank),
                          resolution=int(resolution), prompt=str(instance_prompt), seed=int(seed))
        _make_room(diffusion, ["unet", "vae", "text_encoder"])
        try:
            res = personalize(diffusion, images, masks, st, folder=model_folders("loras")[0],
                              progress=progress_callback())
        finally:
            _offload(diffusion)
        if res.trained and res.losses:
            log.info("LoRA Personalize: loss %.4g -> %.4g over %d steps", res.losses[0], res.losses[-1], len(res.losses))
        return (diffusion.with_lora(res.path, float(lora_strength)), res.path.name)


class PhysMotionDDIMInvert:
    """DDIM+ inversion of the coarse frames, conditioned on depth + canny edges and a prompt."""

    DESCRIPTION = ("Encodes the blended coarse frames and inverts them deterministically along the DDIM timesteps "
                   "(paper: 1000 training steps, step 20 = 50 steps, CFG 1), conditioned on the rendered depth and "
                   "OpenCV canny edges through the ControlNets and on the prompt. Keeps the latent of every step for "
                   "the sampler's source branch. Outputs a preview of the edges the ControlNet sees.")

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "diffusion": ("PM_DIFFUSION", {"tooltip": "From Diffusion Loader or LoRA Personalize (use the same one "
                                                          "for the sampler)."}),
                "frames": ("IMAGE", {"tooltip": "The coarse video (PhysMotion Blend): blended in image space."}),
                "depth": ("IMAGE", {"tooltip": "Rendered depth per frame (PhysMotion Render's depth, near = bright)."}),
                "prompt": ("STRING", {"default": "a photo of sks object", "multiline": True,
                                      "tooltip": "A short description of the scene (with the LoRA's token)."}),
                "steps": ("INT", {"default": 50, "min": 1, "max": 1000,
                                  "tooltip": "DDIM steps (paper: 50 = 1000 training steps / 20); the sampler uses the "
                                             "same timesteps."}),
                "resolution": ("INT", {"default": 768, "min": 64, "max": 2048, "step": 64,
                                       "tooltip": "Long side of the working size (paper: 768); both sides are rounded "
                                                  "to a multiple of 64."}),
                "refine_iterations": ("INT", {"default": 1, "min": 0, "max": 10,
                                              "tooltip": "Fixed-point refinements per inversion step (DDIM+); each "
                                                         "costs one more UNet call and makes sampling reproduce the "
                                                         "frames more exactly. 0 = classic DDIM inversion."}),
                "canny_low": ("INT", {"default": 100, "min": 0, "max": 1000, "tooltip": "OpenCV Canny low threshold."}),
                "canny_high": ("INT", {"default": 200, "min": 0, "max": 1000,
                                       "tooltip": "OpenCV Canny high threshold."}),
                "depth_strength": ("FLOAT", {"default": 1.0, "min": 0.0, "max": 2.0, "step": 0.05,
                                             "tooltip": "Depth ControlNet conditioning scale."}),
                "canny_strength": ("FLOAT", {"default": 1.0, "min": 0.0, "max": 2.0, "step": 0.05,
                                             "tooltip": "Canny ControlNet conditioning scale."}),
                "frame_batch": ("INT", {"default": 4, "min": 1, "max": 64,
                                        "tooltip": "Frames inverted together (memory vs speed)."}),
            },
        }

    RETURN_TYPES = ("PM_INVERSION", "IMAGE")
    RETURN_NAMES = ("inversion", "edges")
    OUTPUT_TOOLTIPS = ("Inverted latents at every timestep + the conditions, for Keyframe-Shared Sample.",
                       "The canny edges (or depth) given to the ControlNets, at the working size.")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/enhance"

    def run(self, diffusion, frames, depth, prompt, steps, resolution, refine_iterations, canny_low, canny_high,
            depth_strength, canny_strength, frame_batch):
        from physmotion_core.enhance import invert_frames

        from ._util import temp_directory

        require_batch(frames, "frames")
        require_batch(depth, "depth")
        _make_room(diffusion, ["unet", "vae", "text_encoder"] + [f"controlnet_{k}" for k in diffusion.controlnets])
        try:
            inv = invert_frames(diffusion, frames, depth, prompt=str(prompt), steps=int(steps),
                                resolution=int(resolution), canny_low=float(canny_low), canny_high=float(canny_high),
                                depth_scale=float(depth_strength), canny_scale=float(canny_strength),
                                frame_batch=int(frame_batch), refine_iterations=int(refine_iterations),
                                cache_dir=temp_directory() / "physmotion_inversion", progress=progress_callback())
        finally:
            _offload(diffusion)
        return (inv, inv.preview())


class PhysMotionKeyframeSharedSample:
    """Enhanced frames: PnP injection + keyframe extended attention + TokenFlow propagation."""

    DESCRIPTION = ("Runs a source branch (the inverted latents, empty prompt) and the enhanced branch together. For "
                   "the first feature_injection of the steps the enhanced branch takes the source's residual features "
                   "(up block 1, resnet 1), for the first attention_injection its decoder self-attention queries and "
                   "keys. Keyframes attend jointly; the other frames take their keyframes' attention through "
                   "nearest-neighbour correspondences, blended by frame distance (TokenFlow). The memory is estimated "
                   "first; a run that cannot fit is refused (or reduced, with memory = reduce).")

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "diffusion": ("PM_DIFFUSION", {"tooltip": "The same models the inversion used."}),
                "inversion": ("PM_INVERSION", {"tooltip": "From PhysMotion DDIM+ Invert."}),
                "prompt": ("STRING", {"default": "", "multiline": True,
                                      "tooltip": "What the enhanced video shows; empty = the inversion prompt."}),
                "negative_prompt": ("STRING", {"default": "", "multiline": True,
                                               "tooltip": "Classifier-free guidance's negative prompt."}),
                "guidance": ("FLOAT", {"default": 7.5, "min": 0.0, "max": 30.0, "step": 0.1,
                                       "tooltip": "Classifier-free guidance scale (paper: 7.5; 1 = no guidance)."}),
                "feature_injection": ("FLOAT", {"default": 0.8, "min": 0.0, "max": 1.0, "step": 0.05,
                                                "tooltip": "τ_f: fraction of the steps that take the source's residual "
                                                           "features (structure). Paper/PnP: 0.8."}),
                "attention_injection": ("FLOAT", {"default": 0.5, "min": 0.0, "max": 1.0, "step": 0.05,
                                                  "tooltip": "τ_A: fraction of the steps that take the source's decoder "
                                                             "self-attention Q and K (layout). Paper/PnP: 0.5."}),
                "keyframe_interval": ("INT", {"default": 5, "min": 1, "max": 100,
                                              "tooltip": "A keyframe every N frames (the first frame always)."}),
                "attention": (["tokenflow", "per_frame"], {
                    "default": "tokenflow", "tooltip": "tokenflow: shared keyframe attention + propagation (temporally "
                                                       "consistent). per_frame: each frame alone (ablation)."}),
                "frame_batch": ("INT", {"default": 4, "min": 1, "max": 64,
                                        "tooltip": "Non-keyframes per UNet call (memory vs speed)."}),
                "keyframe_batch": ("INT", {"default": 8, "min": 1, "max": 64,
                                           "tooltip": "Keyframes attending jointly in one call; more keyframes run in "
                                                      "batches that all include the first keyframe."}),
                "attention_chunk": ("INT", {"default": 4096, "min": 0, "max": 1 << 20, "step": 256,
                                            "tooltip": "Query tokens per attention / correspondence call (0 = all at "
                                                       "once); bounds memory on long clips."}),
                "memory": (["refuse", "reduce"], {
                    "default": "refuse", "tooltip": "When the up-front estimate exceeds free memory: refuse with the "
                                                    "numbers, or reduce the batches/chunks (logged)."}),
                "output_size": (["input", "diffusion"], {
                    "default": "input", "tooltip": "input: resize to the coarse frames' size. diffusion: keep the "
                                                   "working resolution (e.g. 768)."}),
            },
        }

    RETURN_TYPES = ("IMAGE",)
    RETURN_NAMES = ("frames",)
    OUTPUT_TOOLTIPS = ("The enhanced video frames.",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/enhance"

    def run(self, diffusion, inversion, prompt, negative_prompt, guidance, feature_injection, attention_injection,
            keyframe_interval, attention, frame_batch, keyframe_batch, attention_chunk, memory, output_size):
        from physmotion_core.enhance import SampleSettings, keyframe_shared_sample

        from ._util import preview_video

        st = SampleSettings(prompt=str(prompt), negative_prompt=str(negative_prompt), guidance=float(guidance),
                            tau_features=float(feature_injection), tau_attention=float(attention_injection),
                            keyframe_interval=int(keyframe_interval), attention=attention,
                            frame_batch=int(frame_batch), keyframe_batch=int(keyframe_batch),
                            attention_chunk=int(attention_chunk), memory=memory, output_size=output_size)
        _make_room(diffusion, ["unet", "vae", "text_encoder"] + [f"controlnet_{k}" for k in diffusion.controlnets])
        try:
            res = keyframe_shared_sample(diffusion, inversion, st, progress=progress_callback())
        finally:
            _offload(diffusion)
        log.info("Keyframe-Shared Sample: %d frames in %.1f s (%.2f s/frame), keyframes %s", res.frames.shape[0],
                 res.seconds, res.seconds / max(res.frames.shape[0], 1), res.keyframes)
        return {"ui": preview_video(res.frames, 24.0, "PhysMotion_enhanced"), "result": (res.frames,)}


NODE_CLASS_MAPPINGS = {
    "PhysMotionDiffusionLoader": PhysMotionDiffusionLoader,
    "PhysMotionLoRAPersonalize": PhysMotionLoRAPersonalize,
    "PhysMotionDDIMInvert": PhysMotionDDIMInvert,
    "PhysMotionKeyframeSharedSample": PhysMotionKeyframeSharedSample,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PhysMotionDiffusionLoader": "PhysMotion Diffusion Loader (SD 2.1 + ControlNets)",
    "PhysMotionLoRAPersonalize": "PhysMotion LoRA Personalize",
    "PhysMotionDDIMInvert": "PhysMotion DDIM+ Invert",
    "PhysMotionKeyframeSharedSample": "PhysMotion Keyframe-Shared Sample",
}
