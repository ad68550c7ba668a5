"""Monocular depth and hard-depth refinement nodes."""

from __future__ import annotations

from ._gaussian_io import GAUSSIANS_INPUT, GAUSSIANS_TOOLTIP_SUFFIX, SPLAT_AXES_INPUT, as_pm_gaussians
from ._util import (CATEGORY, first_image, first_mask, log, preview_images, progress_with_previews, require_batch,
                    save_ply_output)


class PhysMotionDepthLoader:
    """Load a transformers depth model (DPT / MiDaS, Depth Anything) from models/physmotion/depth/."""

    DESCRIPTION = ("Loads a monocular depth model folder (e.g. Intel/dpt-hybrid-midas or "
                   "depth-anything/Depth-Anything-V2-Small-hf, the whole Hugging Face folder) from "
                   "models/physmotion/depth/. Nothing is downloaded.")

    @classmethod
    def INPUT_TYPES(cls):
        from ._util import model_choices

        return {"required": {"model_name": (model_choices("depth", dirs=True),
                                            {"tooltip": "A model folder in models/physmotion/depth/."})}}

    RETURN_TYPES = ("PM_DEPTH_MODEL",)
    RETURN_NAMES = ("depth_model",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/refine"

    def run(self, model_name):
        from physmotion_core.depth import load_depth_model
        from physmotion_core.depth.monocular import EXPECTED

        from ._memory import manage
        from ._util import model_path, offload_device

        folder = model_path("depth", model_name, expected=EXPECTED)
        return (manage(load_depth_model(str(folder), device=offload_device()), "depth model"),)


class PhysMotionDepth:
    """Monocular depth of an image (near = bright), for preview and for refinement."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "depth_model": ("PM_DEPTH_MODEL", {"tooltip": "From PhysMotion Depth Loader."}),
            "image": ("IMAGE", {"tooltip": "Image(s) to estimate depth for (every image of the batch)."}),
        }, "optional": {
            "mask": ("MASK", {"tooltip": "Optional: normalise the preview over the object only."}),
        }}

    RETURN_TYPES = ("IMAGE",)
    RETURN_NAMES = ("depth_preview",)
    OUTPUT_TOOLTIPS = ("Relative depth, near = bright, 2..98 % range stretched.",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/refine"

    def run(self, depth_model, image, mask=None):
        import torch

        from physmotion_core.depth import estimate_depth

        from ._memory import models_on_device

        require_batch(image, "image")
        if mask is not None:
            require_batch(mask, "mask", "MASK")
        out = []
        with models_on_device(depth_model, what="Monocular Depth"):
            for b in range(image.shape[0]):
                m = None if mask is None else mask[min(b, mask.shape[0] - 1)].float().cpu()
                d = estimate_depth(depth_model, image[b, ..., :3].float().cpu())
                if m is not None and tuple(m.shape) != tuple(d.values.shape):
                    m = None
                out.append(d.preview(m))
        return (torch.stack(out),)


class PhysMotionHardDepthRefine:
    """Refine lifted Gaussians: colour loss on the input view, hard-depth loss on every view."""

    DESCRIPTION = ("Polishes the lifted Gaussians (PhysMotion §3.2): a colour loss (L1 + 0.2 D-SSIM) on the input "
                   "photo and, with a depth model, DNGaussian's hard-depth loss on the input view and the "
                   "generated views, which pulls floating Gaussians back onto the surface. Without a depth model "
                   "only the colour loss runs (the log says so).")

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "gaussians": (GAUSSIANS_INPUT, {"tooltip": "Lifted Gaussians (LGM Lift or Silhouette Lift)."
                                                           + GAUSSIANS_TOOLTIP_SUFFIX}),
                "camera": ("PM_CAMERA", {"tooltip": "The input camera from the lift node."}),
                "image": ("IMAGE", {"tooltip": "The input photo."}),
                "mask": ("MASK", {"tooltip": "The object mask."}),
                "iterations": ("INT", {"default": 3000, "min": 0, "max": 100000, "step": 100,
                                       "tooltip": "Paper: 3000. The schedule (decay at half, depth from 1/6) "
                                                  "scales with this. About 2-5 it/s on a CPU at 20k Gaussians."}),
                "hard_depth_every": ("INT", {"default": 10, "min": 1, "max": 1000,
                                             "tooltip": "A hard-depth step every N iterations (paper: 10)."}),
                "learning_rate": ("FLOAT", {"default": 1e-3, "min": 0.0, "max": 0.1, "step": 1e-4,
                                            "tooltip": "Colour-step learning rate (paper: 1e-4..1e-3); positions "
                                                       "in object heights per step."}),
                "prune_floaters": ("BOOLEAN", {"default": True,
                                               "tooltip": "Remove Gaussians that fall outside a view's mask."}),
                "max_render_side": ("INT", {"default": 512, "min": 64, "max": 4096, "step": 64,
                                            "tooltip": "Views are compared at most this large (speed)."}),
                "time_limit_s": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 36000.0,
                                           "tooltip": "Stop after this many seconds (0 = no limit)."}),
                "seed": ("INT", {"default": 0, "min": 0, "max": 2 ** 31 - 1, "tooltip": "Patch-size draws."}),
            },
            "optional": {
                "views": ("PM_VIEWS", {"tooltip": "Generated views with cameras (from LGM Lift)."}),
                "depth_model": ("PM_DEPTH_MODEL", {"tooltip": "Monocular depth model; without it, colour loss only."}),
                "filename_prefix": ("STRING", {"default": "PhysMotion/refined",
                                               "tooltip": "The refined Gaussians are saved as a 3DGS .ply with this "
                                                          "prefix in the output folder (for Load3D / Preview3D); "
                                                          "empty = do not save."}),
                "splat_axes": SPLAT_AXES_INPUT,
            },
        }

    RETURN_TYPES = ("PM_GAUSSIANS", "IMAGE", "STRING")
    RETURN_NAMES = ("gaussians", "preview", "ply_path")
    OUTPUT_TOOLTIPS = ("Refined Gaussians.", "Render of the result from the input camera beside the photo.",
                       "The saved .ply relative to the output folder (connect to Preview3D's model_file); "
                       "empty when filename_prefix is empty.")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/refine"

    def run(self, gaussians, camera, image, mask, iterations, hard_depth_every, learning_rate, prune_floaters,
            max_render_side, time_limit_s, seed, views=None, depth_model=None, filename_prefix="PhysMotion/refined",
            splat_axes="y_down"):
        import torch

        from physmotion_core.refine import RefineSettings, build_views, refine_gaussians
        from physmotion_core.render.rasterize import rasterize

        from ._memory import models_on_device
        from ._util import torch_device

        dev = torch_device()
        img = first_image(image)
        m = first_mask(mask)
        if depth_model is None:
            log.info("Hard-Depth Refine: no depth model connected, running the colour loss only")
        with models_on_device(depth_model, what="Hard-Depth Refine"):
            rviews = build_views(camera, img, m, list(views or []), depth_model)
        st = RefineSettings(iterations=int(iterations), depth_every=int(hard_depth_every),
                            lr_position=float(learning_rate), lr_colour=float(learning_rate),
                            lr_opacity=float(learning_rate), lr_scale=float(learning_rate),
                            lr_rotation=float(learning_rate), prune_floaters=bool(prune_floaters),
                            max_render_side=int(max_render_side), max_seconds=float(time_limit_s), seed=int(seed))
        # The progress bar shows the current render beside the photo (every 50 iterations).
        progress, preview = progress_with_previews()
        res = refine_gaussians(as_pm_gaussians(gaussians, axes=splat_axes).to(dev), rviews, st, progress=progress, preview=preview)
        for note in res.notes:
            log.info("Hard-Depth Refine: %s", note)
        log.info("Hard-Depth Refine: %d iterations in %.1f s (%.2f it/s), %d pruned", res.iterations_done,
                 res.seconds, res.iterations_per_second, res.pruned)
        out = res.gaussians.to("cpu")
        cam = rviews[0].camera
        with torch.no_grad():
            r = rasterize(out, cam)
        tgt = rviews[0].image * (rviews[0].mask[..., None] if rviews[0].mask is not None else 1.0)
        preview = torch.cat([r.rgb.clamp(0, 1), tgt], dim=1)[None]
        ply = save_ply_output(out, filename_prefix) if (filename_prefix or "").strip() else ""
        ui = preview_images(preview, "PhysMotion_refine")
        if ply:
            ui["text"] = [ply]
        return {"ui": ui, "result": (out, preview, ply)}


NODE_CLASS_MAPPINGS = {
    "PhysMotionDepthLoader": PhysMotionDepthLoader,
    "PhysMotionDepth": PhysMotionDepth,
    "PhysMotionHardDepthRefine": PhysMotionHardDepthRefine,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PhysMotionDepthLoader": "PhysMotion Depth Loader",
    "PhysMotionDepth": "PhysMotion Monocular Depth",
    "PhysMotionHardDepthRefine": "PhysMotion Hard-Depth Refine",
}
