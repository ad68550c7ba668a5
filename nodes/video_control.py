"""Controls for ComfyUI's native Wan video nodes from the simulation: point tracks (WanTrackToVideo),
control videos (WanVaceToVideo, Wan22FunControlToVideo) and exact optical flow.

The library does the work (physmotion_core/controls.py, which names the ComfyUI commit the tracks
format is matched to); these nodes parse inputs, call it and report progress.
"""

from __future__ import annotations

from typing import Optional

from ._util import CATEGORY, output_path, preview_video, progress_callback, torch_device

_STAGE = f"{CATEGORY}/video_models"  # as ComfyUI files its Wan nodes: conditioning/video_models


def _clip_inputs() -> dict:
    return {
        "simulation": ("PM_SIM", {"tooltip": "The simulated trajectory (from MPM Simulate)."}),
        "camera": ("PM_CAMERA", {"tooltip": "The photo's camera (from the lift node)."}),
        "width": ("INT", {"default": 832, "min": 16, "max": 8192, "step": 16,
                          "tooltip": "Width of the video model's frames (a multiple of 16; Wan 2.1 480p: 832). The "
                                     "photo is centre-cropped to this aspect ratio as the Wan nodes crop their "
                                     "start/reference image, so the controls line up with it. Use the same value on "
                                     "the Wan node (or link this node's width output to it)."}),
        "height": ("INT", {"default": 480, "min": 16, "max": 8192, "step": 16,
                           "tooltip": "Height of the video model's frames (a multiple of 16; Wan 2.1 480p: 480)."}),
        "fps": ("FLOAT", {"default": 16.0, "min": 1.0, "max": 120.0, "step": 1.0,
                          "tooltip": "The video model's frame rate (Wan 2.1 and 2.2 14B: 16). The simulation is "
                                     "interpolated to it, so the motion keeps its real speed."}),
        "length": ("INT", {"default": 33, "min": 5, "max": 1025, "step": 4,
                           "tooltip": "Frames of the video model's clip, 4k+1 (33, 49, 81, ...). 48 simulated frames "
                                      "at 24 fps fill 33 frames at 16 fps; frames past the simulated time repeat its "
                                      "last state (with a warning in the log)."}),
    }


def _at_model_clock(simulation, camera, width, height, fps, length):
    """The simulation resampled to the model's clock and the camera fitted to its frame."""
    from physmotion_core import controls as C

    W, H = C.check_size(width, height)
    sim = C.resample_simulation(simulation, float(fps), C.check_length(length))
    return sim, C.fit_camera(camera, W, H)


#: The last clips rendered here (the newest last, at most ``_KEEP``): (weak reference to the simulation each came
#: from, settings, frames, flows by direction). Nodes on the same simulation at the same clock and size share a
#: render: the controls node and the flow node share one; the tracks node's "coarse video" preview keeps its own,
#: half the size.
_last_render: list = []
_KEEP = 2

_SETTINGS = ("width", "height", "fps", "length")

#: The tracks node's "coarse video" preview renders the clip at 1/PREVIEW_DIVISOR of the size, scaled up.
PREVIEW_DIVISOR = 2


def _flow_follows(prompt, unique_id) -> Optional[str]:
    """The direction of the exact flow a PhysMotion Exact Flow node of the running prompt will ask of the same
    clip as node ``unique_id`` (same simulation and camera links, same size, clock and length), so the render
    this node makes carries that flow's channels and the flow node costs nothing more; None when no such
    node is in the prompt. Without the prompt (the library's or an old caller's use): "forward", as before."""
    if not isinstance(prompt, dict) or unique_id is None or str(unique_id) not in prompt:
        return "forward"
    me = prompt[str(unique_id)].get("inputs", {})
    for node in prompt.values():
        if not isinstance(node, dict) or node.get("class_type") != "PhysMotionExactFlow":
            continue
        other = node.get("inputs", {})
        if other.get("simulation") != me.get("simulation") or other.get("camera") != me.get("camera"):
            continue
        # A linked setting may equal ours at run time: render the channels then too.
        if all(isinstance(other.get(k), list) or isinstance(me.get(k), list) or other.get(k) == me.get(k)
               for k in _SETTINGS):
            direction = other.get("direction", "forward")
            return direction if direction in ("forward", "backward") else "forward"
    return None


def _render(sim, cam, source=None, settings=(), flow=None, share=None):
    """The frames of the resampled clip and, when ``flow`` names a direction, its flow: from a kept clip when
    it is the same (simulation, clock, size), else rendered once (``render_clip``). A render for the controls
    carries the channels of the flow ``share`` names (a flow node that follows in the same prompt, see
    ``_flow_follows``: a fifth more than colour and depth alone), so that node then costs nothing more; with
    no flow node after it, none are rendered. The channels change no other output."""
    import weakref

    from physmotion_core import controls as C

    key = (tuple(settings), repr(cam.to_dict()))
    if source is not None:
        for i in range(len(_last_render) - 1, -1, -1):
            ref, k, frames, flows = _last_render[i]
            if ref() is source and k == key and (flow is None or flow in flows):
                _last_render.append(_last_render.pop(i))  # the most recently used is kept longest
                return frames, flows.get(flow)
    dev = torch_device()
    direction = flow or share
    frames, fl = C.render_clip(sim, cam, flow=direction if sim.num_frames > 1 else None,
                               device=dev if dev.type == "cuda" else "cpu", progress=progress_callback())
    _last_render[:] = [e for e in _last_render if e[0]() is not None and e[1] != key][-(_KEEP - 1):]
    if source is not None:
        _last_render.append((weakref.ref(source), key, frames, {direction: fl} if fl is not None else {}))
    return frames, (fl if flow else None)


def _fit_background(background, width, height, frames):
    from physmotion_core import controls as C
    from physmotion_core.errors import InputError

    if background is None:
        return None
    if background.ndim != 4 or background.shape[0] not in (1, frames):
        raise InputError(f"background must be one image or one per frame ({frames}); got shape "
                         f"{tuple(background.shape)}. Connect PhysMotion Segment's background.")
    bg = C.fit_images(background[..., :3], width, height)
    return bg[0] if bg.shape[0] == 1 else bg


class PhysMotionPointTracks:
    """Point tracks of the simulated object for WanTrackToVideo."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            **_clip_inputs(),
            "num_points": ("INT", {"default": 64, "min": 1, "max": 1024,
                                   "tooltip": "Object points to track, spread evenly over the object's visible "
                                              "silhouette in the first frame."}),
            "background_points": ("INT", {"default": 8, "min": 0, "max": 256,
                                          "tooltip": "Still anchor points on background pixels the object never "
                                                     "covers, so the model keeps the camera and background still. "
                                                     "0 = none."}),
            "occlusion": (["end track", "keep"], {
                "default": "end track",
                "tooltip": "WanTrackToVideo's format has no per-point visibility: a track shorter than the clip is "
                           "read as invisible after its end. 'end track' ends a point's track when it goes behind "
                           "the object or off-screen; 'keep' lists every position anyway."}),
            "preview": (["first frame", "coarse video"], {
                "default": "first frame",
                "tooltip": "What the tracks are drawn over. 'first frame': the first frame (what the video model "
                           "starts from), costing no more render. 'coarse video': the simulation rendered at half "
                           "the size and scaled up (costs about half a render of the clip)."}),
        }, "optional": {
            "background": ("IMAGE", {"tooltip": "The (inpainted) background, to draw the preview over the coarse "
                                                "render; without it the preview shows the render over black."}),
        }}

    DESCRIPTION = ("Tracks physics particles on the object's surface through the photo's camera, at the video model's "
                   "frame rate and 4k+1 frame count, as the tracks JSON WanTrackToVideo reads (pixel coordinates of "
                   "the width x height frame, 121 samples spanning the clip). The preview draws the tracks.")

    RETURN_TYPES = ("STRING", "IMAGE", "INT", "INT", "INT")
    RETURN_NAMES = ("tracks", "preview", "width", "height", "length")
    OUTPUT_TOOLTIPS = ("The tracks JSON for WanTrackToVideo's tracks input.",
                       "The tracks drawn (dot = visible, ring = hidden, with a trail) over the first frame or the "
                       "coarse video (the preview input).",
                       "Frame width: link to WanTrackToVideo's width.", "Frame height: link to its height.",
                       "Frame count: link to its length.")
    FUNCTION = "run"
    CATEGORY = _STAGE

    def run(self, simulation, camera, width, height, fps, length, num_points, background_points, occlusion,
            preview="first frame", background=None):
        from physmotion_core import controls as C
        from physmotion_core.errors import InputError

        if preview not in ("first frame", "coarse video"):
            raise InputError(f"preview must be 'first frame' or 'coarse video'; got {preview!r}")
        sim, cam = _at_model_clock(simulation, camera, width, height, fps, length)
        # The tracks are the particles projected through the camera; frame 0 is rendered to pick the points,
        # and in the other frames only the pixels around the points, for their visibility (C.probe_tracks).
        dev = torch_device()
        tracks, first = C.probe_tracks(sim, cam, int(num_points), background_points=int(background_points),
                                       device=dev if dev.type == "cuda" else "cpu", progress=progress_callback())
        text = C.wan_tracks_json(tracks, occlusion="end" if occlusion == "end track" else "keep")
        if preview == "coarse video":
            rcam = cam.resized(cam.width // PREVIEW_DIVISOR, cam.height // PREVIEW_DIVISOR)
            frames, _ = _render(sim, rcam, simulation, (fps, length))
            rgb = C.fit_images(frames.rgb, cam.width, cam.height)  # the same view: a plain bilinear upscale
            alpha = C.fit_images(frames.alpha, cam.width, cam.height)
        else:
            rgb, alpha = first.rgb, first.alpha
        bg = _fit_background(background, cam.width, cam.height, sim.num_frames)
        if bg is not None and rgb.shape[0] == 1 and bg.ndim == 4:
            bg = bg[:1]  # the first frame over the first background frame
        rgb = C.over_background(rgb, alpha, bg) if bg is not None else rgb.clamp(0, 1)
        drawn = C.draw_tracks(rgb.expand(sim.num_frames, -1, -1, -1), tracks)
        return {"ui": preview_video(drawn, float(fps), "PhysMotion_tracks"),
                "result": (text, drawn, cam.width, cam.height, sim.num_frames)}


class PhysMotionControlVideos:
    """Depth, render, mask and blended videos of the simulation for Wan's control models."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            **_clip_inputs(),
            "grow_mask": ("INT", {"default": 8, "min": 0, "max": 256,
                                  "tooltip": "Grow the object mask by this many pixels, so the model may also "
                                             "repaint the object's shadow and rim."}),
        }, "optional": {
            "background": ("IMAGE", {"tooltip": "The (inpainted) background from PhysMotion Segment, for the blended "
                                                "video and the VACE control. Without it they use black."}),
        }, "hidden": {"prompt": "PROMPT", "unique_id": "UNIQUE_ID"}}

    DESCRIPTION = ("Renders the simulation at the video model's frame rate, 4k+1 frame count and size (multiples of "
                   "16): depth (near = bright), the coarse render, the object mask, the blended coarse video, and "
                   "the VACE control (depth inside the mask, the coarse video outside) for WanVaceToVideo's "
                   "control_video with control_masks = mask.")

    RETURN_TYPES = ("IMAGE", "IMAGE", "MASK", "IMAGE", "IMAGE", "INT", "INT", "INT")
    RETURN_NAMES = ("depth", "render", "mask", "blended", "vace_control", "width", "height", "length")
    OUTPUT_TOOLTIPS = ("Inverse depth, near = bright, normalised over the clip, black where there is no object.",
                       "The object over black.", "The object (alpha > 0.5), grown by grow_mask.",
                       "The object over the background (the coarse video).",
                       "Depth inside the mask, the coarse video outside.",
                       "Frame width: link to the Wan node's width.", "Frame height: link to its height.",
                       "Frame count: link to its length.")
    FUNCTION = "run"
    CATEGORY = _STAGE

    def run(self, simulation, camera, width, height, fps, length, grow_mask, background=None, prompt=None,
            unique_id=None):
        from physmotion_core import controls as C

        sim, cam = _at_model_clock(simulation, camera, width, height, fps, length)
        frames, _ = _render(sim, cam, simulation, (fps, length), share=_flow_follows(prompt, unique_id))
        v = C.control_videos(frames, _fit_background(background, cam.width, cam.height, sim.num_frames),
                             grow_mask=int(grow_mask))
        return {"ui": preview_video(v.vace, float(fps), "PhysMotion_controls"),
                "result": (v.depth, v.render, v.mask, v.blended, v.vace, cam.width, cam.height, sim.num_frames)}


class PhysMotionExactFlow:
    """Exact optical flow of the rendered simulation, saved as .npz."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            **_clip_inputs(),
            "direction": (["forward", "backward"], {
                "default": "forward",
                "tooltip": "forward: from each frame to the next (frame t+1 at p + flow shows what frame t shows at "
                           "p, OpenCV's convention); backward: from each frame to the previous one."}),
            "max_flow": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 10000.0, "step": 0.5,
                                   "tooltip": "Flow (pixels) shown at full colour in the preview; 0 = the largest."}),
            "filename_prefix": ("STRING", {"default": "PhysMotion/flow",
                                           "tooltip": "The .npz goes to the output folder under this prefix."}),
        }}

    DESCRIPTION = ("Optical flow per frame pair from the simulation itself (the splats behind each visible pixel and "
                   "their exact motion), at the video model's clock and size: a PM_FLOW tensor, a colour-wheel "
                   "preview (hue = direction, saturation = speed) and an .npz in the output folder (flow in pixels, "
                   "valid mask, fps, camera).")

    RETURN_TYPES = ("PM_FLOW", "IMAGE", "STRING")
    RETURN_NAMES = ("flow", "preview", "npz_path")
    OUTPUT_TOOLTIPS = ("The flow (PhysMotion Flow object: flow [T-1,H,W,2] px, valid [T-1,H,W]).",
                       "Colour-wheel picture of the flow, one image per frame pair.",
                       "Absolute path of the saved .npz.")
    OUTPUT_NODE = True
    FUNCTION = "run"
    CATEGORY = _STAGE

    def run(self, simulation, camera, width, height, fps, length, direction, max_flow, filename_prefix):
        from physmotion_core import controls as C

        from concurrent.futures import ThreadPoolExecutor

        sim, cam = _at_model_clock(simulation, camera, width, height, fps, length)
        _, flow = _render(sim, cam, simulation, (fps, length), flow=direction)
        path, _, _ = output_path(filename_prefix, "npz")
        # The .npz is compressed (zlib, which releases the GIL) while the colour-wheel preview is made: on two
        # cores the two overlap. The file is complete (or, on an error, not written) before the node returns.
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="physmotion-npz") as pool:
            saved = pool.submit(C.save_flow_npz, path, flow, cam)
            try:
                preview = C.flow_to_color(flow.flow, float(max_flow))
                ui = preview_video(preview, float(fps), "PhysMotion_flow")
            finally:
                saved.result()
        return {"ui": ui, "result": (flow, preview, str(path))}


NODE_CLASS_MAPPINGS = {
    "PhysMotionPointTracks": PhysMotionPointTracks,
    "PhysMotionControlVideos": PhysMotionControlVideos,
    "PhysMotionExactFlow": PhysMotionExactFlow,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PhysMotionPointTracks": "PhysMotion Point Tracks (WanTrackToVideo)",
    "PhysMotionControlVideos": "PhysMotion Control Videos (Wan VACE / Fun Control)",
    "PhysMotionExactFlow": "PhysMotion Exact Optical Flow",
}
