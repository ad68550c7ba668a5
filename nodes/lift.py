"""Lifting nodes (image + mask → 3D Gaussians) and Gaussian file I/O."""

from __future__ import annotations

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
            "gaussians": ("PM_GAUSSIANS", {"tooltip": "Gaussians to save."}),
            "filename_prefix": ("STRING", {"default": "PhysMotion/gaussians",
                                           "tooltip": "File name prefix inside the output folder."}),
        }}

    RETURN_TYPES = ("STRING",)
    RETURN_NAMES = ("ply_path",)
    OUTPUT_TOOLTIPS = ("Path of the .ply relative to the output folder (feed it to Preview3D).",)
    OUTPUT_NODE = True
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/io"

    def run(self, gaussians, filename_prefix):
        from physmotion_core.ply import write_ply

        path, filename, subfolder = output_path(filename_prefix, "ply")
        write_ply(path, gaussians)
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


NODE_CLASS_MAPPINGS = {
    "PhysMotionSilhouetteLift": PhysMotionSilhouetteLift,
    "PhysMotionSaveGaussians": PhysMotionSaveGaussians,
    "PhysMotionLoadGaussians": PhysMotionLoadGaussians,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PhysMotionSilhouetteLift": "PhysMotion Silhouette Lift (no model)",
    "PhysMotionSaveGaussians": "PhysMotion Save Gaussians (.ply)",
    "PhysMotionLoadGaussians": "PhysMotion Load Gaussians (.ply)",
}
