"""Registry metadata and requirements: what ComfyUI-Manager / the Comfy registry read."""

import re
import sys
from pathlib import Path

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
                    "peft": "peft", "segment_anything": "segment-anything", "PIL": "pillow",
                    "websocket": "websocket-client", "scipy": "scipy"}
    # Optional packages: imported lazily (inside a function, never at module level) by the parts that use
    # them, and listed in the pyproject extra named here (None: used when present, never required).
    optional = {"ray": "batch", "yaml": "batch", "pyarrow": "batch", "tomli": "batch", "tqdm": None}
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    stdlib = set(sys.stdlib_module_names)
    found = set()
    for path in [ROOT / "__init__.py", *(ROOT / "nodes").glob("*.py"), *(ROOT / "physmotion_core").rglob("*.py")]:
        for m in re.finditer(r"^(\s*)(?:import\s+(\w+)|from\s+(\w+)[\w.]*\s+import\b)", path.read_text(), re.M):
            mod = m.group(2) or m.group(3)
            if mod in optional:
                assert m.group(1), f"{path.name} imports the optional {mod} at module level: import it where it is used"
                extra = optional[mod]
                if extra is not None:
                    listed = [re.split(r"[<>=!~\[ ;]", r, 1)[0].lower() for r in extras[extra]]
                    assert {"yaml": "pyyaml"}.get(mod, mod) in listed, f"{mod} is not in the '{extra}' extra"
                continue
            found.add(mod)
    third_party = found - stdlib - with_comfyui - {"physmotion_core", "nodes", "__future__"}
    unknown = sorted(third_party - set(import_names))
    assert not unknown, f"imported but not in requirements.txt: {unknown}"
    for mod in third_party:
        assert import_names[mod] in names, f"{mod} needs {import_names[mod]} in requirements.txt"


def _file_requirements(name):
    return [line.split("#", 1)[0].strip() for line in (ROOT / name).read_text().splitlines()
            if line.split("#", 1)[0].strip()]


def test_one_dependency_list_read_by_pyproject_with_torch_for_pip_installs():
    """pyproject.toml lists no dependencies of its own: setuptools reads requirements.txt (ComfyUI-Manager's
    list, no torch) and requirements-torch.txt, so a pip install gets exactly those, torch included."""
    from setuptools.config.pyprojecttoml import read_configuration

    raw = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "dependencies" not in raw["project"] and "dependencies" in raw["project"]["dynamic"]
    assert raw["tool"]["setuptools"]["dynamic"]["dependencies"]["file"] == ["requirements.txt",
                                                                            "requirements-torch.txt"]
    expanded = read_configuration(ROOT / "pyproject.toml")["project"]["dependencies"]
    torch_reqs = _file_requirements("requirements-torch.txt")
    assert expanded == _requirements() + torch_reqs
    names = {re.split(r"[<>=!~\[ ;]", r, 1)[0].lower() for r in torch_reqs}
    assert names == {"torch", "torchvision"}, names
    # torchvision is there for segment-anything, whose package imports it (the pack itself does not).
    sam = __import__("importlib.util").util.find_spec("segment_anything")
    if sam is not None:
        src = " ".join(p.read_text() for p in Path(sam.origin).parent.rglob("*.py"))
        assert "from torchvision" in src


def test_registry_urls_and_classifiers():
    """[project.urls] has the registry's Homepage/Repository/Issues (valid URLs: setuptools refuses empty
    ones); the OS and accelerator classifiers are among the ones the Comfy registry accepts (it drops all
    of a kind when one is not)."""
    from urllib.parse import urlparse

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    for key in ("Homepage", "Repository", "Issues"):
        u = urlparse(project["urls"][key])
        assert u.scheme == "https" and u.netloc, (key, project["urls"][key])
    classifiers = project["classifiers"]
    os_values = [c.split(" :: ", 1)[1] for c in classifiers if c.startswith("Operating System :: ")]
    env_values = [c.split(" :: ", 1)[1] for c in classifiers if c.startswith("Environment :: ")]
    assert os_values and all(v.startswith(("Microsoft", "POSIX", "MacOS", "OS Independent")) for v in os_values)
    assert env_values and set(env_values) <= {"GPU :: NVIDIA CUDA", "GPU :: AMD ROCm", "GPU :: Intel Arc",
                                              "NPU :: Huawei Ascend", "GPU :: Apple Metal"}


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


def test_registry_metadata_is_complete():
    """The Registry fields issue 35 asked for: the minimum ComfyUI, and a .comfyignore that leaves the
    development files out but nothing the pack needs at run time."""
    import fnmatch

    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    comfy = meta["tool"]["comfy"]
    assert re.fullmatch(r">=\d+\.\d+\.\d+", comfy["requires-comfyui"]), comfy.get("requires-comfyui")
    assert meta["project"]["urls"]["Repository"] and meta["project"]["license"]
    ignored = [ln.strip() for ln in (ROOT / ".comfyignore").read_text().splitlines()
               if ln.strip() and not ln.startswith("#")]
    assert {"tests/", "benchmarks/"} <= set(ignored)

    def left_out(path: str) -> bool:
        return any(path.startswith(p) if p.endswith("/") else fnmatch.fnmatch(path, p) for p in ignored)

    for needed in ["__init__.py", "nodes/physics.py", "physmotion_core/pipeline.py", "web/force_picker.js",
                   "example_workflows/push_a_jelly.json", "requirements.txt", "pyproject.toml", "LICENSE"]:
        assert (ROOT / needed).exists() and not left_out(needed), needed
    for folder in comfy["includes"]:
        assert not left_out(folder + "/"), folder


def test_the_license_is_a_pep639_expression_so_future_setuptools_still_build_the_install():
    """setuptools deprecated the ``license = {text = ...}`` table (and license classifiers) and announced
    that builds using it stop working after 2027-02-18: the install the README's two commands run would
    fail then. An SPDX string plus license-files is PEP 639's form; comfy-cli 1.23 writes and reads it
    too (``license = "MIT"``)."""
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    project = meta["project"]
    assert project["license"] == "MIT" and project["license-files"] == ["LICENSE"]
    assert (ROOT / "LICENSE").is_file() and "MIT" in (ROOT / "LICENSE").read_text()
    assert not [c for c in project["classifiers"] if c.startswith("License ::")]
    (req,) = [r for r in meta["build-system"]["requires"] if r.startswith("setuptools")]
    assert int(re.search(r">=\s*(\d+)", req).group(1)) >= 77  # the first setuptools with PEP 639
