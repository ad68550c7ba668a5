"""Load the pack the way ComfyUI does and execute API-format workflows in-process (no ComfyUI).

Only what the tests need of ComfyUI's behaviour is reproduced: the package import of the pack's
``__init__.py``, widget/link input resolution in topological order, OUTPUT_NODE results, and the
core ``LoadImage`` node (IMAGE plus MASK = 1 - alpha, or a 64x64 zero mask without alpha), and the
native video pair ``CreateVideo`` (IMAGE + fps -> VIDEO) -> ``SaveVideo`` (an H.264 mp4 in the output
folder with the prompt as metadata), as comfy_extras/nodes_video.py does in 0.3.64.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
PRIMITIVES = ("INT", "FLOAT", "STRING", "BOOLEAN")


def load_pack(name: str = "physmotion_pack"):
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / "__init__.py",
                                                  submodule_search_locations=[str(ROOT)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


class LoadImage:
    """Stand-in for ComfyUI's core LoadImage (same outputs)."""

    input_dir = ROOT / "photos"

    @classmethod
    def INPUT_TYPES(cls):
        files = sorted(p.name for p in cls.input_dir.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        files += ["physmotion_" + p.name for p in (ROOT / "photos").glob("*.png")]
        return {"required": {"image": (files, {"image_upload": True})}}

    RETURN_TYPES = ("IMAGE", "MASK")
    FUNCTION = "load_image"
    CATEGORY = "image"

    def load_image(self, image):
        from physmotion_core.image_io import load_image

        path = self.input_dir / image
        if not path.exists() and image.startswith("physmotion_"):  # the pack copies these into input/
            path = ROOT / "photos" / image[len("physmotion_"):]
        rgb, alpha = load_image(path)
        if alpha is None:
            mask = torch.zeros(64, 64)
        else:
            mask = 1.0 - alpha
        return (rgb[None], mask[None])


class _FramesVideo:
    """Stand-in for comfy_api's VideoFromComponents (what 0.3.64's CreateVideo returns)."""

    def __init__(self, images: torch.Tensor, frame_rate: Fraction, audio=None):
        self.images, self.frame_rate, self.audio = images, frame_rate, audio

    def get_components(self):
        from physmotion_core.video_file import VideoComponents

        return VideoComponents(images=self.images, frame_rate=self.frame_rate, audio=self.audio)

    def get_dimensions(self) -> tuple[int, int]:
        return int(self.images.shape[2]), int(self.images.shape[1])

    def save_to(self, path, format="auto", codec="auto", metadata=None):
        """As VideoFromComponents.save_to in 0.3.64: H.264 yuv420p mp4, the metadata as JSON tags."""
        import av

        if format not in ("auto", "mp4") or codec not in ("auto", "h264"):
            raise ValueError("Only MP4 format and H264 codec are supported")
        with av.open(str(path), mode="w", options={"movflags": "use_metadata_tags"}) as out:
            for key, value in (metadata or {}).items():
                out.metadata[key] = json.dumps(value)
            stream = out.add_stream("h264", rate=Fraction(round(self.frame_rate * 1000), 1000))
            stream.width, stream.height = self.get_dimensions()
            stream.pix_fmt = "yuv420p"
            for frame in self.images:
                img = (frame * 255).clamp(0, 255).byte().cpu().numpy()
                out.mux(stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24").reformat(format="yuv420p")))
            out.mux(stream.encode(None))


class CreateVideo:
    """Stand-in for ComfyUI's CreateVideo (comfy_extras/nodes_video.py, 0.3.64): IMAGE + fps -> VIDEO."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {"images": ("IMAGE", {}), "fps": ("FLOAT", {"default": 30.0, "min": 1.0, "max": 120.0,
                                                                          "step": 1.0})},
                "optional": {"audio": ("AUDIO", {})}}

    RETURN_TYPES = ("VIDEO",)
    FUNCTION = "run"
    CATEGORY = "image/video"

    def run(self, images, fps, audio=None):
        return (_FramesVideo(images, Fraction(fps), audio),)


class SaveVideo:
    """Stand-in for ComfyUI's SaveVideo (0.3.64): ``video.save_to(<output>/<prefix>_NNNNN_.mp4, format, codec,
    metadata={"prompt": ...})`` and the PreviewVideo ui ({"images": [...], "animated": (True,)})."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {"video": ("VIDEO", {}), "filename_prefix": ("STRING", {"default": "video/ComfyUI"}),
                             "format": (["auto", "mp4"], {"default": "auto"}),
                             "codec": (["auto", "h264"], {"default": "auto"})},
                "hidden": {"prompt": "PROMPT"}}

    RETURN_TYPES = ()
    OUTPUT_NODE = True
    FUNCTION = "run"
    CATEGORY = "image/video"

    def run(self, video, filename_prefix, format, codec, prompt=None):
        output_path = sys.modules[load_pack().__name__ + ".nodes._util"].output_path
        path, name, subfolder = output_path(filename_prefix, "mp4")
        video.save_to(str(path), format=format, codec=codec, metadata={"prompt": prompt} if prompt else None)
        return {"ui": {"images": [{"filename": name, "subfolder": subfolder, "type": "output"}], "animated": (True,)},
                "result": ()}


CORE_NODES = {"LoadImage": LoadImage, "CreateVideo": CreateVideo, "SaveVideo": SaveVideo}


def node_classes() -> dict:
    return {**CORE_NODES, **load_pack().NODE_CLASS_MAPPINGS}


def input_spec(cls) -> dict:
    types = cls.INPUT_TYPES()
    return {**types.get("required", {}), **types.get("optional", {})}


def is_widget(spec) -> bool:
    kind = spec[0]
    return isinstance(kind, list) or kind in PRIMITIVES


def topological_order(prompt: dict) -> list[str]:
    order, seen, visiting = [], set(), set()

    def visit(nid):
        if nid in seen:
            return
        if nid in visiting:
            raise ValueError(f"cycle at node {nid}")
        visiting.add(nid)
        for value in prompt[nid]["inputs"].values():
            if isinstance(value, list) and len(value) == 2 and isinstance(value[0], str):
                visit(value[0])
        visiting.discard(nid)
        seen.add(nid)
        order.append(nid)

    for nid in prompt:
        visit(nid)
    return order


def run_prompt(prompt: dict, overrides: dict | None = None, class_overrides: dict | None = None) -> dict:
    """Execute an API prompt and return outputs per node, each node under ``torch.inference_mode()``
    as ComfyUI runs them (so a node that needs gradients must turn them on itself).

    ``overrides`` maps "node_id.input" to a value; ``class_overrides`` maps "ClassName.input" to a
    value for every node of that class (e.g. shrink every simulation for a quick test).
    """
    classes = node_classes()
    prompt = json.loads(json.dumps(prompt))
    for key, value in (class_overrides or {}).items():
        cls_name, name = key.split(".", 1)
        for node in prompt.values():
            if node["class_type"] == cls_name:
                node["inputs"][name] = value
    for key, value in (overrides or {}).items():
        nid, name = key.split(".", 1)
        prompt[nid]["inputs"][name] = value
    results: dict[str, tuple] = {}
    ui: dict[str, dict] = {}
    for nid in topological_order(prompt):
        node = prompt[nid]
        cls = classes[node["class_type"]]
        kwargs = {}
        if "prompt" in cls.INPUT_TYPES().get("hidden", {}):  # ComfyUI's hidden PROMPT: the prompt being run
            kwargs["prompt"] = prompt
        if "unique_id" in cls.INPUT_TYPES().get("hidden", {}):  # and UNIQUE_ID: the node's own id, a string
            kwargs["unique_id"] = str(nid)
        for name, value in node["inputs"].items():
            if isinstance(value, list) and len(value) == 2 and isinstance(value[0], str):
                kwargs[name] = results[value[0]][value[1]]
            else:
                kwargs[name] = value
        with torch.inference_mode():  # as ComfyUI 0.3.64 runs every node (execution.py)
            out = getattr(cls(), cls.FUNCTION)(**kwargs)
        if isinstance(out, dict):
            ui[nid] = out.get("ui", {})
            out = out.get("result", ())
        results[nid] = tuple(out)
    return {"results": results, "ui": ui}


def load_workflow(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def to_numpy_frames(images: torch.Tensor) -> np.ndarray:
    return (images.clamp(0, 1).numpy() * 255).astype(np.uint8)


def standin_splat(photo: str = "coffee.png", max_gaussians: int = 20000):
    """The Gaussians of the stand-in .ply (see write_standin_splat), the silhouette lift they were
    made from (its camera, with the principal point on the object's base line, reproduces the
    photo) and the similarity applied, ``(R, scale, offset)``: x_standin = scale · R x_lift + offset."""
    import math

    from physmotion_core.image_io import load_image
    from physmotion_core.lift import silhouette_lift
    from physmotion_core.segment import segment
    from physmotion_core.types import Gaussians, quat_to_rotmat, rotmat_to_quat

    rgb, alpha = load_image(ROOT / "photos" / photo)
    seg = segment(rgb, alpha=alpha)
    lift = silhouette_lift(rgb, seg.mask, max_gaussians=max_gaussians)
    g = lift.gaussians.with_covariance_as_rotscale()
    if g.sh.shape[1] != 1:
        raise ValueError("the stand-in turns only SH degree 0 colours")
    c, s = math.cos(math.pi / 2), math.sin(math.pi / 2)
    rx = torch.tensor([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    rz = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    R, scale, offset = rz @ rx, 100.0, torch.tensor([12.0, -40.0, 7.5])
    turned = Gaussians(means=scale * g.means @ R.T + offset, quats=rotmat_to_quat(R @ quat_to_rotmat(g.quats)),
                       scales=scale * g.scales, opacities=g.opacities, sh=g.sh)
    return turned, lift, (R, scale, offset)


#: Where a template's PhysMotion Load Gaussians node may point at a .ply that the test, thumbnail and
#: benchmark runs write first (see write_standin_splat).
def write_standin_splat(path: Path, photo: str = "coffee.png", max_gaussians: int = 20000) -> Path:
    """A .ply as another 3DGS tool might write one for the photo's object: the pack's silhouette
    lift of ``photos/<photo>``, turned into a z-up frame whose input view looks along +x (rotations
    of 90° about x, then 90° about z), in centimetres, off-centre. Lining it up again is the Fit's job
    (``tests/test_fit.py`` checks that it does, against the transform ``standin_splat`` returns)."""
    from physmotion_core.ply import write_ply

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_ply(path, standin_splat(photo, max_gaussians)[0])


def prepare_template_inputs(prompt: dict, output_dir: Path, max_gaussians: int = 20000) -> list[Path]:
    """Write the stand-in .ply for every PhysMotion Load Gaussians node whose file (relative to the
    output folder) is not there yet, so templates that start from "your own splat" run as shipped."""
    written = []
    for node in prompt.values():
        if node["class_type"] == "PhysMotionLoadGaussians":
            target = Path(output_dir) / node["inputs"]["ply_path"]
            if not Path(node["inputs"]["ply_path"]).is_absolute() and not target.exists():
                written.append(write_standin_splat(target, max_gaussians=max_gaussians))
    return written


#: Templates the harness has every node of but that cannot run here yet, with why (skipped by the
#: in-process and the live runs).
TEMPLATES_NOT_YET: dict[str, str] = {}
