"""Registry metadata and requirements: what ComfyUI-Manager / the Comfy registry read."""

import re
import sys

import pytest

from comfy_harness import ROOT

tomllib = pytest.importorskip("tomllib") if sys.version_info >= (3, 11) else pytest.importorskip("tomli")


def _requirements():
    out = []
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            out.append(line)
    return out


def test_tool_comfy_fields():
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    comfy = meta["tool"]["comfy"]
    assert re.fullmatch(r"[a-z0-9][a-z0-9-]*", comfy["PublisherId"])
    assert comfy["DisplayName"].strip()
    assert isinstance(comfy["Icon"], str)
    assert (ROOT / "web" / "icon.png").is_file()
    for folder in comfy.get("includes", []):
        assert (ROOT / folder).is_dir(), folder
    assert re.fullmatch(r"\d+\.\d+\.\d+", meta["project"]["version"])


def test_requirements_never_pin_torch_gsplat_or_upper_bounds():
    reqs = _requirements()
    names = [re.split(r"[<>=!~\[ ;]", r, 1)[0].lower() for r in reqs]
    assert not {"torch", "torchvision", "torchaudio", "gsplat"} & set(names), names
    for r in reqs:
        assert "==" not in r and "<" not in r and "~=" not in r, f"pin or upper bound in requirements.txt: {r}"
        assert ">=" in r, f"give a lower bound: {r}"
    # Every third-party module the pack imports at load time is in the list (or comes with ComfyUI).
    with_comfyui = {"torch", "torchvision", "comfy", "comfy_api", "folder_paths", "server", "gsplat"}
    import_names = {"numpy": "numpy", "warp": "warp-lang", "cv2": "opencv-python-headless", "av": "av",
                    "safetensors": "safetensors", "diffusers": "diffusers", "transformers": "transformers",
                    "peft": "peft", "segment_anything": "segment-anything", "PIL": "pillow"}
    stdlib = set(sys.stdlib_module_names)
    found = set()
    for path in [ROOT / "__init__.py", *(ROOT / "nodes").glob("*.py"), *(ROOT / "physmotion_core").rglob("*.py")]:
        for m in re.finditer(r"^\s*(?:import\s+(\w+)|from\s+(\w+)[\w.]*\s+import\b)", path.read_text(), re.M):
            found.add(m.group(1) or m.group(2))
    third_party = found - stdlib - with_comfyui - {"physmotion_core", "nodes", "__future__"}
    unknown = sorted(third_party - set(import_names))
    assert not unknown, f"imported but not in requirements.txt: {unknown}"
    for mod in third_party:
        assert import_names[mod] in names, f"{mod} needs {import_names[mod]} in requirements.txt"


def test_only_example_workflows_can_be_taken_for_a_template_folder():
    """ComfyUI serves a pack's templates from the folders it takes for template folders, all under one
    route: 0.3.64 by the names example_workflows/example/examples/workflow/workflows, newer versions
    any top-level folder whose name contains "example" or "workflow". Two such folders shadow each
    other, so exactly one may exist; it lists only UI-format templates (the api/ twins sit below it)."""
    folders = sorted(p.name for p in ROOT.iterdir() if p.is_dir() and not p.name.startswith(".")
                     and ("example" in p.name.lower() or "workflow" in p.name.lower()))
    assert folders == ["example_workflows"], folders
    listed = sorted((ROOT / "example_workflows").glob("*.json"))
    assert listed
    import json
    for path in listed:
        ui = json.loads(path.read_text())
        assert "nodes" in ui and "links" in ui, f"{path.name} is not a UI-format workflow"
        assert (path.with_suffix(".jpg")).is_file(), f"no thumbnail for {path.name}"
        assert (ROOT / "example_workflows" / "api" / path.name).is_file(), f"no API twin for {path.name}"
