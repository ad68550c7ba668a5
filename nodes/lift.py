"""Lifting nodes (image + mask → 3D Gaussians: silhouette, or ImageDream + LGM) and Gaussian file I/O."""

from __future__ import annotations

from ._gaussian_io import GAUSSIANS_INPUT, GAUSSIANS_TOOLTIP_SUFFIX, SPLAT_AXES_INPUT, as_pm_gaussians
from ._util import CATEGORY, first_image, first_mask, output_path


class PhysMotionSilhouetteLift:
    """The no-weights lift: a closed, rounded solid whose outline is the mask."""

    DESCRIPTION = ("Turns the segmented object into a closed solid of 3D Gaussians (front coloured from the photo, "
                   "back from a mirrored copy), scaled to the object's real height and resting on the ground, "
                   "seen by a camera that reproduces the input view. Needs no model weights.")

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "image": ("IMAGE", {"tooltip": "The photo (or the foreground) the object's colours come from."}),
                "mask": ("MASK", {"tooltip": "Object mask from PhysMotion Segment (1 on the object)."}),
                "object_height": ("FLOAT", {"default": 0.3, "min": 0.001, "max": 1000.0, "step": 0.01,
                                            "tooltip": "Real height of the object in metres. It sets the time "
                                                       "scale of everything physical (a 3 m object falls slower "
                                                       "in image space than a 3 cm one)."}),
                "fov_y": ("FLOAT", {"default": 40.0, "min": 1.0, "max": 170.0, "step": 0.5,
                                    "tooltip": "Vertical field of view of the photo in degrees (phone main "
                                               "camera ≈ 50-60, telephoto ≈ 20)."}),
                "thickness": ("FLOAT", {"default": 1.0, "min": 0.05, "max": 5.0, "step": 0.05,
                                        "tooltip": "Depth of the solid relative to a round cross-section "
                                                   "(1 = as deep as wide near the edges)."}),
                "max_gaussians": ("INT", {"default": 60000, "min": 1000, "max": 2000000, "step": 1000,
                                          "tooltip": "Upper bound on the number of Gaussians (render cost)."}),
                "on_ground": ("BOOLEAN", {"default": True,
                                          "tooltip": "Place the object's lowest point on the ground plane y=0."}),
            },
        }

    RETURN_TYPES = ("PM_GAUSSIANS", "PM_CAMERA")
    RETURN_NAMES = ("gaussians", "camera")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/lift"

    def run(self, image, mask, object_height, fov_y, thickness, max_gaussians, on_ground):
        from physmotion_core.lift import silhouette_lift

        m = first_mask(mask)
        res = silhouette_lift(first_image(image), m, object_height=float(object_height), fov_y_deg=float(fov_y),
                              thickness=float(thickness), max_gaussians=int(max_gaussians),
                              on_ground=bool(on_ground))
        return (res.gaussians, res.camera)


class PhysMotionSaveGaussians:
    """Save Gaussians as a standard 3DGS .ply in ComfyUI's output folder (for Load3D / Preview3D)."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "gaussians": (GAUSSIANS_INPUT, {"tooltip": "Gaussians to save." + GAUSSIANS_TOOLTIP_SUFFIX}),
            "filename_prefix": ("STRING", {"default": "PhysMotion/gaussians",
                                           "tooltip": "File name prefix inside the output folder."}),
        }, "optional": {"splat_axes": SPLAT_AXES_INPUT}}

    RETURN_TYPES = ("STRING",)
    RETURN_NAMES = ("ply_path",)
    OUTPUT_TOOLTIPS = ("Path of the .ply relative to the output folder (feed it to Preview3D).",)
    OUTPUT_NODE = True
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/io"

    def run(self, gaussians, filename_prefix, splat_axes="y_down"):
        from physmotion_core.ply import write_ply

        path, filename, subfolder = output_path(filename_prefix, "ply")
        write_ply(path, as_pm_gaussians(gaussians, axes=splat_axes))
        rel = f"{subfolder}/{filename}" if subfolder else filename
        return {"ui": {"text": [rel]}, "result": (rel,)}


class PhysMotionLoadGaussians:
    """Load a 3DGS .ply (from the output or input folder, or an absolute path)."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "ply_path": ("STRING", {"default": "", "tooltip": "A .ply path: relative to ComfyUI's output "
                                                               "folder, or absolute."}),
        }}

    RETURN_TYPES = ("PM_GAUSSIANS",)
    RETURN_NAMES = ("gaussians",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/io"

    def run(self, ply_path):
        from pathlib import Path

        from physmotion_core.ply import read_ply

        from ._util import output_directory

        p = Path(ply_path)
        if not p.is_absolute():
            p = output_directory() / p
        return (read_ply(p),)


# ----------------------------------------------------------------------------------------------
# The learned lift: ImageDream (4 views) + LGM (Gaussians)
# ----------------------------------------------------------------------------------------------

def _cancel_check():
    """ComfyUI's Cancel check, or None outside ComfyUI."""
    try:
        import comfy.model_management as mm
    except ImportError:
        return None
    return mm.throw_exception_if_processing_interrupted


class PhysMotionLGMLoader:
    """Load the official LGM weights from models/physmotion/lgm/."""

    DESCRIPTION = ("Loads LGM (Large Multi-View Gaussian Model) from models/physmotion/lgm/: the official "
                   "model_fp16_fixrot.safetensors (recommended) or model_fp16.safetensors from "
                   "huggingface.co/ashawkey/LGM. The network layout is read from the file and every key must "
                   "match. Nothing is downloaded.")

    @classmethod
    def INPUT_TYPES(cls):
        from ._util import model_choices

        return {"required": {
            "lgm_name": (model_choices("lgm", suffixes=(".safetensors", ".pth", ".pt", ".bin")),
                         {"tooltip": "A weight file in models/physmotion/lgm/."}),
            "rotation": (["auto", "per_gaussian", "across_gaussians"], {
                "default": "auto",
                "tooltip": "How the checkpoint normalises its Gaussians' rotations. auto: from the file name "
                           "(*fixrot* = per_gaussian, the fixed code; otherwise across_gaussians, the quirk "
                           "model_fp16.safetensors was trained with). Override only for renamed files."}),
            "input_size": ("INT", {"default": 256, "min": 32, "max": 1024, "step": 32,
                                   "tooltip": "Resolution the 4 views are fed to LGM at (the released model was "
                                              "trained at 256; it makes 4 x (size/2)² Gaussians)."}),
        }}

    RETURN_TYPES = ("PM_LGM",)
    RETURN_NAMES = ("lgm",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/lift"

    def run(self, lgm_name, rotation, input_size):
        from physmotion_core.lift.lgm import LGM_EXPECTED, load_lgm
        from physmotion_core.models import default_dtype

        from ._memory import manage
        from ._util import model_path, offload_device, torch_device

        path = model_path("lgm", lgm_name, expected=LGM_EXPECTED)
        return (manage(load_lgm(str(path), device=offload_device(), dtype=default_dtype(torch_device()),
                                rotation=rotation, input_size=int(input_size)), "LGM"),)


class PhysMotionImageDreamLoader:
    """Load ImageDream (image-prompted multi-view diffusion) from models/physmotion/imagedream/."""

    DESCRIPTION = ("Loads the diffusers folder of ashawkey/imagedream-ipmv-diffusers (the whole folder: unet, vae, "
                   "text_encoder, tokenizer, image_encoder, feature_extractor, scheduler) from "
                   "models/physmotion/imagedream/. Nothing is downloaded.")

    @classmethod
    def INPUT_TYPES(cls):
        from ._util import model_choices

        return {"required": {
            "model_name": (model_choices("imagedream", dirs=True),
                           {"tooltip": "A model folder in models/physmotion/imagedream/."}),
        }}

    RETURN_TYPES = ("PM_IMAGEDREAM",)
    RETURN_NAMES = ("imagedream",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/lift"

    def run(self, model_name):
        from physmotion_core.lift.imagedream import IMAGEDREAM_LAYOUT, load_imagedream
        from physmotion_core.models import default_dtype

        from ._memory import manage
        from ._util import model_path, offload_device, torch_device

        folder = model_path("imagedream", model_name, expected=IMAGEDREAM_LAYOUT)
        return (manage(load_imagedream(str(folder), device=offload_device(), dtype=default_dtype(torch_device())),
                       "ImageDream"),)


def _imagedream_inputs(d: dict) -> dict:
    d.update({
        "seed": ("INT", {"default": 0, "min": 0, "max": 2 ** 31 - 1,
                         "tooltip": "Noise seed of the view generation (same seed, same views)."}),
        "steps": ("INT", {"default": 30, "min": 1, "max": 200,
                          "tooltip": "DDIM steps of ImageDream (30 as LGM's demo)."}),
        "guidance": ("FLOAT", {"default": 5.0, "min": 1.0, "max": 30.0, "step": 0.5,
                               "tooltip": "Classifier-free guidance scale (5 as LGM's demo; 1 = off)."}),
        "border_ratio": ("FLOAT", {"default": 0.2, "min": 0.0, "max": 0.8, "step": 0.05,
                                   "tooltip": "Empty border round the recentred object: it fills 1 - this of "
                                              "the views (0.2 as LGM)."}),
    })
    return d


class PhysMotionMultiViewGenerate:
    """Four views of the segmented object (ImageDream), front first."""

    DESCRIPTION = ("Recentres the object on white and generates four views of it with ImageDream, in LGM's order: "
                   "the front (input side), then the camera orbited 90°, 180° and 270° to the right. Feed them "
                   "to LGM Lift's views input to try LGM settings without generating again.")

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": _imagedream_inputs({
            "imagedream": ("PM_IMAGEDREAM", {"tooltip": "From PhysMotion ImageDream Loader."}),
            "image": ("IMAGE", {"tooltip": "The photo (the first image of a batch is used)."}),
            "mask": ("MASK", {"tooltip": "The object mask (1 on the object), e.g. from SAM Segment."}),
        })}

    RETURN_TYPES = ("IMAGE",)
    RETURN_NAMES = ("views",)
    OUTPUT_TOOLTIPS = ("4 views [4, 256, 256, 3]: azimuth 0 (front), 90, 180, 270 degrees.",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/lift"

    def run(self, imagedream, image, mask, seed, steps, guidance, border_ratio):
        from physmotion_core.lift.imagedream import generate_views, views_for_lgm
        from physmotion_core.lift.learned import recenter
        from physmotion_core.memory import oom_as_input_error

        from ._memory import models_on_device
        from ._util import progress_callback

        canvas, _, _ = recenter(first_image(image), first_mask(mask), border_ratio=float(border_ratio),
                                size=imagedream.image_size)
        with models_on_device(imagedream, what="ImageDream"):
            with oom_as_input_error("Multi-View Generate", "Free GPU memory (unload other models) or run on the CPU."):
                views = generate_views(imagedream, canvas, guidance_scale=float(guidance),
                                       num_inference_steps=int(steps), seed=int(seed), progress=progress_callback(),
                                       cancel=_cancel_check())
        ordered = views_for_lgm(views).float().cpu()
        return {"ui": _views_grid_preview(ordered, "PhysMotion_views"), "result": (ordered,)}


def _views_grid_preview(views, stem: str) -> dict:
    """The 4 views as one 2x2 grid shown in the node (front, 90° / 180°, 270°)."""
    import torch

    from ._util import preview_images

    v = views.float().clamp(0, 1)
    if v.shape[0] != 4:
        return preview_images(v, stem)
    grid = torch.cat([torch.cat([v[0], v[1]], dim=1), torch.cat([v[2], v[3]], dim=1)], dim=0)
    return preview_images(grid[None], stem)


class PhysMotionLGMLift:
    """The learned lift: ImageDream's 4 views → LGM's Gaussians, scaled and placed in the scene."""

    DESCRIPTION = ("Lifts the segmented object to 3D Gaussians as in the paper: recentre on white, ImageDream's "
                   "4 views (or the connected views), LGM, pruning of near-transparent Gaussians, then LGM's "
                   "frame is scaled to the object's real height and put on the ground. The camera output "
                   "reproduces the input photo; the views output feeds Hard-Depth Refine.")

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": _imagedream_inputs({
                "lgm": ("PM_LGM", {"tooltip": "From PhysMotion LGM Loader."}),
                "image": ("IMAGE", {"tooltip": "The photo (the first image of a batch is used)."}),
                "mask": ("MASK", {"tooltip": "The object mask (1 on the object), e.g. from SAM Segment."}),
                "object_height": ("FLOAT", {"default": 0.3, "min": 0.001, "max": 1000.0, "step": 0.01,
                                            "tooltip": "Real height of the object in metres. It sets the time "
                                                       "scale of everything physical."}),
                "on_ground": ("BOOLEAN", {"default": True,
                                          "tooltip": "Place the object's lowest Gaussian on the ground plane y=0."}),
                "prune_opacity": ("FLOAT", {"default": 0.005, "min": 0.0, "max": 0.99, "step": 0.005,
                                            "tooltip": "Drop Gaussians less opaque than this (0.005 as LGM)."}),
                "max_gaussians": ("INT", {"default": 0, "min": 0, "max": 2000000, "step": 1000,
                                          "tooltip": "Keep at most this many (the most opaque); 0 = all "
                                                     "(up to 65536 at input size 256)."}),
            }),
            "optional": {
                "imagedream": ("PM_IMAGEDREAM", {"tooltip": "From PhysMotion ImageDream Loader: generates the "
                                                            "4 views (not needed when views are connected)."}),
                "views": ("IMAGE", {"tooltip": "4 views from Multi-View Generate (same image, mask and "
                                               "border_ratio); ImageDream is then not run."}),
            },
        }

    RETURN_TYPES = ("PM_GAUSSIANS", "PM_CAMERA", "PM_VIEWS", "IMAGE")
    RETURN_NAMES = ("gaussians", "camera", "views", "view_images")
    OUTPUT_TOOLTIPS = ("Gaussians in metres, +y up.", "The input camera (reproduces the photo).",
                       "The generated side and back views with their cameras, for Hard-Depth Refine.",
                       "The 4 views LGM saw (front, 90, 180, 270 degrees).")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/lift"

    def run(self, lgm, image, mask, object_height, on_ground, prune_opacity, max_gaussians, seed, steps, guidance,
            border_ratio, imagedream=None, views=None):
        from physmotion_core.lift.learned import learned_lift, views_for_refine
        from physmotion_core.memory import oom_as_input_error

        from ._memory import models_on_device
        from ._util import progress_callback

        if imagedream is None and views is None:
            raise ValueError("LGM Lift: connect an ImageDream Loader (imagedream) or 4 views (views)")
        with models_on_device(lgm, imagedream if views is None else None, what="LGM Lift"):
            with oom_as_input_error("LGM Lift", "Free GPU memory (unload other models), connect pre-generated "
                                                "views instead of ImageDream, or run on the CPU."):
                res = learned_lift(first_image(image), first_mask(mask), lgm=lgm,
                                   imagedream=imagedream if views is None else None, views=views,
                                   object_height=float(object_height), on_ground=bool(on_ground),
                                   border_ratio=float(border_ratio), seed=int(seed), steps=int(steps),
                                   guidance_scale=float(guidance), prune_opacity=float(prune_opacity),
                                   max_gaussians=int(max_gaussians), progress=progress_callback(),
                                   cancel=_cancel_check())
        return {"ui": _views_grid_preview(res.view_images, "PhysMotion_lgm_views"),
                "result": (res.gaussians, res.camera, views_for_refine(res.views), res.view_images)}


NODE_CLASS_MAPPINGS = {
    "PhysMotionSilhouetteLift": PhysMotionSilhouetteLift,
    "PhysMotionSaveGaussians": PhysMotionSaveGaussians,
    "PhysMotionLoadGaussians": PhysMotionLoadGaussians,
    "PhysMotionLGMLoader": PhysMotionLGMLoader,
    "PhysMotionImageDreamLoader": PhysMotionImageDreamLoader,
    "PhysMotionMultiViewGenerate": PhysMotionMultiViewGenerate,
    "PhysMotionLGMLift": PhysMotionLGMLift,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PhysMotionSilhouetteLift": "PhysMotion Silhouette Lift (no model)",
    "PhysMotionSaveGaussians": "PhysMotion Save Gaussians (.ply)",
    "PhysMotionLoadGaussians": "PhysMotion Load Gaussians (.ply)",
    "PhysMotionLGMLoader": "PhysMotion LGM Loader",
    "PhysMotionImageDreamLoader": "PhysMotion ImageDream Loader",
    "PhysMotionMultiViewGenerate": "PhysMotion Multi-View Generate (ImageDream)",
    "PhysMotionLGMLift": "PhysMotion LGM Lift",
}
