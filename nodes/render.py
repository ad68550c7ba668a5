"""Rendering, blending and video output nodes."""

from __future__ import annotations

import torch

from physmotion_core.errors import InputError

from ._util import CATEGORY, first_image, first_mask, log, output_path, preview_video, progress_callback, torch_device


class PhysMotionRender:
    """Render every simulated frame through the input camera."""

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "simulation": ("PM_SIM", {"tooltip": "The simulated trajectory."}),
                "camera": ("PM_CAMERA", {"tooltip": "The camera to render through (the lift's input camera)."}),
                "width": ("INT", {"default": 0, "min": 0, "max": 8192, "step": 8,
                                  "tooltip": "Output width in pixels; 0 = the camera's (the input image's)."}),
                "height": ("INT", {"default": 0, "min": 0, "max": 8192, "step": 8,
                                   "tooltip": "Output height in pixels; 0 = the camera's."}),
            },
            "optional": {
                "photo": ("IMAGE", {"tooltip": "The photo the object was lifted from. Connected, the surface the "
                                               "photo saw shows the photo's own pixels as it moves (frame 0 is the "
                                               "photo); the sides, back and torn faces keep the splats' colours."}),
                "mask": ("MASK", {"tooltip": "The object's mask (soft edges welcome) from the Segment node; "
                                             "without it, the object is where the rest pose renders."}),
                "background": ("IMAGE", {"tooltip": "The background the frames will be blended over (the Segment "
                                                    "node's): a soft edge's colour is unmixed from it, so frame 0 "
                                                    "over it is the photo."}),
                "texture": (["photo", "splat"], {"default": "photo",
                                                 "tooltip": "photo: the photo's pixels where it saw the surface (needs "
                                                            "the photo input); splat: the splats' colours only."}),
            },
        }

    DESCRIPTION = ("Renders the simulated Gaussians through the camera, frame by frame (gsplat on CUDA when it is "
                   "installed, the pack's own PyTorch rasterizer otherwise). With the photo connected, the surface the "
                   "photo saw keeps the photo's own pixels as it moves. The node shows the clip as a preview.")

    RETURN_TYPES = ("IMAGE", "MASK", "IMAGE")
    RETURN_NAMES = ("rgb", "alpha", "depth")
    OUTPUT_TOOLTIPS = ("The object's colour over black (premultiplied).", "Coverage of the object.",
                       "Depth, near = bright, normalised over the clip (for previews and depth ControlNets).")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/render"

    def run(self, simulation, camera, width, height, photo=None, mask=None, background=None, texture="photo"):
        from physmotion_core.render.frames import depth_to_image, render_frames
        from physmotion_core.render.photo_texture import photo_texture_for

        cam = camera
        if width or height:
            w = int(width) or round(camera.width * int(height) / camera.height)
            h = int(height) or round(camera.height * int(width) / camera.width)
            cam = camera.resized(w, h)
        dev = torch_device()
        tex = None
        if photo is not None and texture == "photo":
            tex = photo_texture_for(simulation, camera, first_image(photo, "photo"), first_mask(mask),
                                    None if background is None else first_image(background, "background"))
        frames = render_frames(simulation, cam, device=dev if dev.type == "cuda" else "cpu",
                               progress=progress_callback(), photo=tex)
        result = (frames.rgb, frames.alpha, depth_to_image(frames.depth, frames.alpha))
        return {"ui": preview_video(frames.rgb, frames.fps, "PhysMotion_render"), "result": result}


class PhysMotionBlend:
    """Composite the rendered object over the (inpainted) background in image space."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "rgb": ("IMAGE", {"tooltip": "Rendered frames (premultiplied colour) from PhysMotion Render."}),
            "alpha": ("MASK", {"tooltip": "Rendered coverage from PhysMotion Render."}),
            "background": ("IMAGE", {"tooltip": "The background: PhysMotion Segment's, PhysMotion Fill "
                                                "Background's or any inpainting node's IMAGE (one image, or one "
                                                "per frame)."}),
        }, "optional": {
            "fps": ("FLOAT", {"default": 24.0, "min": 1.0, "max": 1000.0, "step": 1.0,
                              "tooltip": "Frame rate of the preview clip only (the frames themselves carry no rate)."}),
        }}

    DESCRIPTION = "Alpha-composites the rendered frames over the background: the coarse video, shown as a preview."

    RETURN_TYPES = ("IMAGE",)
    RETURN_NAMES = ("frames",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/render"

    def run(self, rgb, alpha, background, fps=24.0):
        from physmotion_core.blend import composite

        if rgb.ndim != 4 or rgb.shape[-1] < 3:
            raise InputError(f"rgb must be an IMAGE batch [T,H,W,3]; got shape {tuple(rgb.shape)}. Connect "
                             "PhysMotion Render's rgb output.")
        if alpha.ndim == 2:
            alpha = alpha[None]
        if alpha.shape[0] != rgb.shape[0] or tuple(alpha.shape[1:3]) != tuple(rgb.shape[1:3]):
            raise InputError(f"alpha {tuple(alpha.shape)} does not match rgb {tuple(rgb.shape[:3])}: connect the "
                             "alpha output of the same PhysMotion Render node as rgb.")
        if background.ndim == 4 and background.shape[0] not in (1, rgb.shape[0]):
            raise InputError(f"background has {background.shape[0]} images but there are {rgb.shape[0]} frames: "
                             "give one background image or one per frame.")
        bg = background if background.shape[0] == rgb.shape[0] else first_image(background, "background")
        if bg.shape[-3:-1] != rgb.shape[1:3]:
            log.warning("background %s resized to the frames' %s", tuple(bg.shape[-3:-1]), tuple(rgb.shape[1:3]))
            b4 = bg if bg.ndim == 4 else bg[None]
            bg = torch.nn.functional.interpolate(b4.permute(0, 3, 1, 2), size=tuple(rgb.shape[1:3]),
                                                 mode="bilinear", align_corners=False).permute(0, 2, 3, 1)
            if bg.shape[0] == 1:
                bg = bg[0]
        out = composite(rgb, alpha, bg)
        return {"ui": preview_video(out, float(fps), "PhysMotion_blend"), "result": (out,)}


class PhysMotionFillBackground:
    """Fill the object's region of the photo from around it: the background the object uncovers."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "image": ("IMAGE", {"tooltip": "The photo (the first image of a batch)."}),
            "mask": ("MASK", {"tooltip": "The object's mask; a soft matte's whole extent is filled."}),
            "method": (["harmonic", "patch", "telea", "ns"], {
                "default": "harmonic",
                "tooltip": "harmonic: smooth membrane fill, closest to the truth on average (docs/quality.md); "
                           "patch: copies the photo's own patches (texture, slower); telea / ns: OpenCV's fills."}),
            "grow_px": ("INT", {"default": -1, "min": -1, "max": 256,
                                "tooltip": "Pixels the hole is grown past the mask (the object's halo); -1 = "
                                           "automatic (0.6 % of the long side)."}),
        }}

    DESCRIPTION = ("Fills the object's region of the photo from the pixels around it, without weights. Its IMAGE "
                   "goes to PhysMotion Blend's background; so can any inpainting node's.")
    RETURN_TYPES = ("IMAGE",)
    RETURN_NAMES = ("background",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/render"

    def run(self, image, mask, method, grow_px):
        from physmotion_core.inpaint import inpaint_background

        m = first_mask(mask)
        out = inpaint_background(first_image(image, "image"), m, method=method,
                                 dilate_px=None if int(grow_px) < 0 else int(grow_px))
        return (out[None],)


class PhysMotionSaveVideo:
    """Save frames as an H.264 mp4 in the output folder, with a preview in the node."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "frames": ("IMAGE", {"tooltip": "The frames to save."}),
            "fps": ("FLOAT", {"default": 24.0, "min": 1.0, "max": 1000.0, "step": 1.0,
                              "tooltip": "Frame rate of the video."}),
            "filename_prefix": ("STRING", {"default": "PhysMotion/video",
                                           "tooltip": "File name prefix inside the output folder."}),
            "crf": ("INT", {"default": 18, "min": 0, "max": 51,
                            "tooltip": "H.264 quality: lower is better and larger (18 ≈ visually lossless)."}),
        }}

    RETURN_TYPES = ("STRING", "VIDEO")
    RETURN_NAMES = ("video_path", "video")
    OUTPUT_TOOLTIPS = ("Absolute path of the saved mp4.",
                       "The saved mp4 as ComfyUI's VIDEO, for the native video nodes (Save Video, Get Video "
                       "Components, ...).")
    DESCRIPTION = ("Writes the frames as an H.264 mp4 (yuv420p, plays everywhere) to the output folder and previews "
                   "it. The templates save with ComfyUI's own Create Video -> Save Video (which embeds the "
                   "workflow in the file); this node is for a chosen crf, and it also returns the file as a VIDEO.")
    OUTPUT_NODE = True
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/io"

    def run(self, frames, fps, filename_prefix, crf):
        from physmotion_core.video import write_mp4

        if frames.ndim != 4 or frames.shape[0] == 0:
            raise InputError(f"frames must be a non-empty IMAGE batch [T,H,W,3]; got shape {tuple(frames.shape)}. "
                             "Connect PhysMotion Blend's frames (or Render's rgb).")
        path, filename, subfolder = output_path(filename_prefix, "mp4")
        write_mp4(path, frames, fps=float(fps), crf=int(crf))
        preview = {"filename": filename, "subfolder": subfolder, "type": "output"}
        return {"ui": {"images": [preview], "animated": (True,)}, "result": (str(path), video_value(path))}


def video_value(path):
    """The saved file as a VIDEO: ComfyUI's own VideoFromFile where comfy_api has it (0.3.64 and
    newer), else the library's stand-in with the same methods (outside ComfyUI)."""
    try:
        from comfy_api.latest import InputImpl  # noqa: PLC0415 - only inside ComfyUI

        return InputImpl.VideoFromFile(str(path))
    except (ImportError, AttributeError):
        from physmotion_core.video_file import VideoFile

        return VideoFile(path)


NODE_CLASS_MAPPINGS = {
    "PhysMotionRender": PhysMotionRender,
    "PhysMotionBlend": PhysMotionBlend,
    "PhysMotionFillBackground": PhysMotionFillBackground,
    "PhysMotionSaveVideo": PhysMotionSaveVideo,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PhysMotionRender": "PhysMotion Render",
    "PhysMotionBlend": "PhysMotion Blend over Background",
    "PhysMotionFillBackground": "PhysMotion Fill Background",
    "PhysMotionSaveVideo": "PhysMotion Save Video (mp4)",
}
