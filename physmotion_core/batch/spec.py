"""Batch specs: a TOML or YAML file that lists images and parameter axes, expanded into jobs.

    [batch]
    images = ["coffee.png", "shots/*.png"]   # paths or glob patterns, relative to the spec file
    combine = "grid"                          # grid (every combination) | zip (axes side by side) | list

    [defaults]                                # settings shared by every job
    frames = 48
    ground = "friction"

    [axes]                                    # one list of values per swept setting
    material = ["jelly", "rubber"]
    force = [[20, 0, 0], [0, 0, -20]]

    [[jobs]]                                  # combine = "list": one table per job (over the defaults)
    image = "coffee.png"
    material = "sand"

Each job's id is a content hash of what decides its video: the image's bytes (not its path), the
normalised settings (every default filled in, numbers as floats, so `E = 20000` and `E = 2e4` are
one job), the learned models the stages would load, and the physics version (the package version
plus a digest of the source of every stage that shapes the video). A changed photo, setting or
simulator gives new ids; a moved photo or a reordered spec does not.
"""

from __future__ import annotations

import glob
import hashlib
import itertools
import json
import math
import os
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Optional

from ..errors import InputError
from ..fsutil import file_sha256

SCHEMA = 1  # bump when the meaning of a normalised setting changes

# name -> default. None = not given. Every key a spec may set per job (besides image and the comfy
# NODE.INPUT overrides) is listed here, and every one of them is part of the job's hash.
DEFAULTS: dict[str, Any] = {
    "material": "jelly",
    "E": None, "nu": None, "density": None,
    "material_params": {},  # any other Material field: {yield_stress = 1e4, friction_angle = 35, ...}
    "force": None, "force_at": None, "force_radius": 25.0, "force_window": [0.0, 0.25],
    "forces": [],  # more pushes: [{vector = [..], at = [u, v], radius = 25, window = [t0, t1]}, ...]
    "torque": None, "torque_at": None, "torque_radius": 25.0, "torque_window": [0.0, 0.25],
    "velocity": None, "spin": None,  # initial linear (m/s) and angular (rad/s) velocity of the object
    "ground": "friction", "friction": 0.5,
    "frames": 48, "fps": 24.0, "grid_res": 0, "quality": "standard", "seed": 0,
    "object_height": 0.3, "max_side": 1024, "models": "auto", "device": "auto",
    "object_point": None, "mask": None,
    "crf": 18, "encode_threads": 1,  # encoder threads are fixed so the mp4 bytes do not depend on the machine
}
INT_KEYS = {"frames", "grid_res", "seed", "max_side", "crf", "encode_threads"}
FLOAT_KEYS = {"E", "nu", "density", "force_radius", "torque_radius", "friction", "fps", "object_height"}
VEC3_KEYS = {"force", "torque", "velocity", "spin"}
VEC2_KEYS = {"force_at", "torque_at", "object_point", "force_window", "torque_window"}
STR_CHOICES = {"ground": ("friction", "slip", "sticky", "none"), "quality": ("draft", "standard", "high"),
               "models": ("auto", "none")}
FORCE_KEYS = {"vector", "at", "radius", "window"}
# Outputs besides the mp4: they do not change the video, so they are not in the hash; a finished job
# that lacks one the spec now asks for runs again.
OUTPUT_DEFAULTS = {"ply": "none", "ply_every": 1, "tracks": False, "tracks_points": 64, "flow": False}
COMBINE = ("grid", "zip", "list")
#: A spec file larger than this is refused unread (specs are a few kB; a larger file is a mistake or an attack).
MAX_SPEC_BYTES = 4 << 20
#: The most values (scalars, lists and tables, counted as if every YAML alias were written out) a spec
#: document may hold once expanded: a few hundred bytes of nested aliases can otherwise stand for
#: billions of values, which hashing a job would walk one by one.
MAX_SPEC_VALUES = 100_000
#: The most jobs a spec may expand to unless the caller raises the limit (``--max-jobs``): a grid's
#: size is the product of its axes' lengths, so a short spec can name millions of videos.
MAX_JOBS = 10_000


class SpecError(InputError):
    """The spec itself is malformed (unknown key, axes of unequal length in zip, missing image): nothing runs."""


@dataclass
class Job:
    """One video to make. ``settings`` are normalised (every key of DEFAULTS present); ``error`` is set
    when a value is invalid: the job is then recorded as failed without running."""

    id: str
    name: str
    index: int
    image: Path
    image_sha256: str
    settings: dict
    sets: list = field(default_factory=list)  # comfy NODE.INPUT=VALUE overrides
    error: Optional[str] = None
    mask_sha256: Optional[str] = None


@dataclass
class BatchSpec:
    """A read and checked spec. ``count`` is the number of jobs it expands to (known before any job
    is built: at most that many, fewer when two spellings make one video); ``iter_jobs()`` builds
    them one at a time (``--list`` prints the first at once), ``jobs`` is the whole list, built on
    first use."""

    path: Path
    sha256: str
    outputs: dict
    comfy: Optional[dict] = None  # {"workflow": Path, "map": {setting: NODE.INPUT or [..]}}
    count: int = 0
    _make_jobs: Any = field(default=None, repr=False)
    _jobs: Optional[list] = field(default=None, repr=False)

    def iter_jobs(self):
        if self._jobs is not None:
            yield from self._jobs
            return
        yield from self._make_jobs()

    @property
    def jobs(self) -> list:
        if self._jobs is None:
            self._jobs = list(self._make_jobs())
        return self._jobs


# ----------------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------------


def _expanded_values(node, path: Path, limit: int) -> int:
    """How many values a composed YAML node stands for with every alias written out (shared nodes
    counted once per use), stopping as soon as the count passes ``limit``. Composed nodes share an
    aliased node rather than copying it, so this walks each node once (memoised): a billion-value
    alias bomb is counted in microseconds. A node that contains itself (a recursive alias) is
    refused."""
    import yaml

    sizes: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[Any, bool]] = [(node, False)]
    while stack:
        n, children_done = stack.pop()
        key = id(n)
        if children_done:
            on_path.discard(key)
            if isinstance(n, yaml.SequenceNode):
                kids = n.value
            elif isinstance(n, yaml.MappingNode):
                kids = [x for pair in n.value for x in pair]
            else:
                kids = []
            total = 1 + sum(sizes[id(k)] for k in kids)
            sizes[key] = total
            if total > limit:
                return total
            continue
        if key in sizes:
            continue
        if key in on_path:
            raise SpecError(f"{path}: a YAML alias refers to a list or table that contains it (a recursive "
                            "alias); a spec must be finite. Write the values out.")
        on_path.add(key)
        stack.append((n, True))
        if isinstance(n, yaml.SequenceNode):
            kids = n.value
        elif isinstance(n, yaml.MappingNode):
            kids = [x for pair in n.value for x in pair]
        else:
            kids = []
        for k in kids:
            if id(k) in on_path:
                raise SpecError(f"{path}: a YAML alias refers to a list or table that contains it (a recursive "
                                "alias); a spec must be finite. Write the values out.")
            if id(k) not in sizes:
                stack.append((k, False))
    return sizes[id(node)]


def _load_yaml(text: str, path: Path):
    """The YAML document, refused before it is built when its aliases expand past MAX_SPEC_VALUES."""
    import yaml

    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        n = _expanded_values(node, path, MAX_SPEC_VALUES)
        if n > MAX_SPEC_VALUES:
            raise SpecError(f"{path}: the YAML document stands for more than {MAX_SPEC_VALUES:,} values once its "
                            f"aliases (*name) are expanded (at least {n:,}); a batch spec needs a few hundred. Remove "
                            "the nested aliases (repeat a value by writing it out, or use an axis), or split the spec.")
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _read_document(path: Path) -> dict:
    size = path.stat().st_size
    if size > MAX_SPEC_BYTES:
        raise SpecError(f"{path} is {size:,} bytes; a batch spec may be at most {MAX_SPEC_BYTES:,} bytes (specs list "
                        "axes of values, not the values of every job). Use axes, or split it into several specs.")
    text = path.read_bytes()
    suffix = path.suffix.lower()
    if suffix == ".toml":
        try:
            import tomllib  # Python 3.11+
        except ModuleNotFoundError:
            try:
                import tomli as tomllib  # type: ignore[no-redef]
            except ModuleNotFoundError:
                raise SpecError(f"Reading {path} needs a TOML parser: Python 3.11+ has one built in; on Python "
                                "3.10 install 'tomli' (pip install tomli), or write the spec as YAML") from None
        try:
            return tomllib.loads(text.decode("utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise SpecError(f"{path} is not valid TOML: {exc}") from None
    if suffix in (".yaml", ".yml"):
        try:
            import yaml
        except ModuleNotFoundError:
            raise SpecError(f"Reading {path} needs PyYAML (pip install pyyaml, or pip install "
                            "'physmotion[batch]'), or write the spec as TOML") from None
        try:
            doc = _load_yaml(text.decode("utf-8"), path)
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise SpecError(f"{path} is not valid YAML: {exc}") from None
        except RecursionError:
            raise SpecError(f"{path}: the YAML document is nested too deeply to be a batch spec") from None
        if not isinstance(doc, dict):
            raise SpecError(f"{path}: the YAML document must be a mapping with batch/defaults/axes/jobs keys")
        return doc
    raise SpecError(f"Batch spec {path} must be a .toml, .yaml or .yml file")




def _resolve_images(patterns, base: Path) -> list[Path]:
    if isinstance(patterns, (str, os.PathLike)):
        patterns = [patterns]
    if not isinstance(patterns, list) or not patterns:
        raise SpecError("batch.images must be a non-empty list of image paths or glob patterns")
    out: list[Path] = []
    for pat in patterns:
        if not isinstance(pat, str):
            raise SpecError(f"batch.images: {pat!r} is not a path")
        full = Path(pat).expanduser()
        full = full if full.is_absolute() else base / full
        if any(ch in pat for ch in "*?["):
            hits = sorted(Path(p) for p in glob.glob(str(full), recursive=True) if Path(p).is_file())
            if not hits:
                raise SpecError(f"batch.images: the pattern {pat!r} matches no file (looked in {full.parent})")
            out.extend(hits)
        else:
            if not full.is_file():
                raise SpecError(f"batch.images: no image at {full} (paths are relative to the spec's folder)")
            out.append(full)
    return out


# ----------------------------------------------------------------------------------------------
# normalisation (a value error belongs to one job; the others go on)
# ----------------------------------------------------------------------------------------------


def _num(value, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{key} must be a number; got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"{key} must be finite; got {value!r}")
    return v + 0.0  # -0.0 -> 0.0: one hash for one value


def _int(value, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or float(value) != int(value):
        raise InputError(f"{key} must be a whole number; got {value!r}")
    return int(value)


def _vec(value, n: int, key: str) -> list:
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise InputError(f"{key} must be a list of {n} numbers; got {value!r}")
    return [_num(v, key) for v in value]


def _force_entry(d, key: str) -> dict:
    if not isinstance(d, dict):
        raise InputError(f"{key}: each entry must be a table {{vector = [fx, fy, fz], at = [u, v], ...}}; got {d!r}")
    unknown = set(d) - FORCE_KEYS
    if unknown:
        raise InputError(f"{key}: unknown key(s) {sorted(unknown)}; use {sorted(FORCE_KEYS)}")
    if "vector" not in d:
        raise InputError(f"{key}: each entry needs vector = [x, y, z]")
    return {"vector": _vec(d["vector"], 3, f"{key}.vector"),
            "at": None if d.get("at") is None else _vec(d["at"], 2, f"{key}.at"),
            "radius": _num(d.get("radius", 25.0), f"{key}.radius"),
            "window": _vec(d.get("window", [0.0, 0.25]), 2, f"{key}.window")}


def normalise(raw: dict) -> dict:
    """Every DEFAULTS key, with values of one canonical type. Raises InputError naming a bad value."""
    s = json.loads(json.dumps(DEFAULTS))
    for key, value in raw.items():
        if value is None:
            continue
        if key in INT_KEYS:
            s[key] = _int(value, key)
        elif key in FLOAT_KEYS:
            s[key] = _num(value, key)
        elif key in VEC3_KEYS:
            s[key] = _vec(value, 3, key)
        elif key in VEC2_KEYS:
            s[key] = _vec(value, 2, key)
        elif key in STR_CHOICES:
            if value not in STR_CHOICES[key]:
                raise InputError(f"{key} must be one of {STR_CHOICES[key]}; got {value!r}")
            s[key] = value
        elif key == "material":
            from ..types.material import material_names

            if not isinstance(value, str) or value.strip().lower() not in material_names():
                raise InputError(f"material must be one of {', '.join(material_names())}; got {value!r}")
            s[key] = value.strip().lower()
        elif key == "material_params":
            if not isinstance(value, dict):
                raise InputError(f"material_params must be a table of Material fields; got {value!r}")
            s[key] = {k: _num(v, f"material_params.{k}") for k, v in sorted(value.items())}
        elif key == "forces":
            if not isinstance(value, list):
                raise InputError(f"forces must be a list of tables; got {value!r}")
            s[key] = [_force_entry(f, "forces") for f in value]
        elif key == "device":
            if not isinstance(value, str) or not (value in ("auto", "cpu") or value.startswith("cuda")):
                raise InputError(f"device must be auto, cpu, cuda or cuda:N; got {value!r}")
            s[key] = value
        elif key == "mask":
            s[key] = str(value)
        else:  # pragma: no cover - keys are checked before
            raise SpecError(f"unknown setting {key!r}")
    return s


def canonical_json(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


# Modules whose source does not shape a job's video: the rest of the package is the "physics" the id
# names (a new module counts until it is listed here).
_NOT_PHYSICS = ("cli.py", "comfy/", "report.py", "progress.py", "batch/", "validate/",
                "interop_gaussian.py")


@lru_cache(maxsize=1)
def physics_version() -> str:
    """``<package version>+<digest>``: the digest covers the source of every module that shapes a video."""
    from .. import __version__

    root = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        rel = p.relative_to(root).as_posix()
        if rel.startswith(_NOT_PHYSICS) or "__pycache__" in rel:
            continue
        h.update(rel.encode() + b"\0" + p.read_bytes() + b"\0")
    return f"{__version__}+{h.hexdigest()[:12]}"


def models_identity(models: str) -> dict:
    """The learned models a job's stages would load (names in $PHYSMOTION_MODELS), for the hash."""
    if models != "auto":
        return {}
    from ..pipeline import available_models

    return {k: v for k, v in available_models().items() if v}


def job_id(image_sha: str, settings: dict, extra: Optional[dict] = None) -> str:
    payload = {"schema": SCHEMA, "physics": physics_version(), "image": image_sha, "settings": settings,
               **(extra or {})}
    return hashlib.sha256(canonical_json(payload).encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------------------------
# expansion
# ----------------------------------------------------------------------------------------------


def _check_keys(d: dict, where: str, allow_sets: bool) -> None:
    for key in d:
        if key in DEFAULTS or key in ("image", "images"):
            continue
        if "." in key and allow_sets:
            continue
        hint = " (NODE.INPUT overrides need comfy.workflow in the spec and --comfy URL)" if "." in key else ""
        raise SpecError(f"{where}: unknown setting {key!r}{hint}. Settings: {', '.join(DEFAULTS)}")


def _combinations(doc: dict, combine: str) -> tuple[int, Any]:
    """(how many combinations, a function giving an iterator over them): nothing is expanded here,
    so a grid of a million combinations costs no memory until its jobs are built one by one."""
    defaults = doc.get("defaults", {}) or {}
    axes = doc.get("axes", {}) or {}
    if not isinstance(defaults, dict) or not isinstance(axes, dict):
        raise SpecError("defaults and axes must be tables")
    if combine == "list":
        jobs = doc.get("jobs")
        if not isinstance(jobs, list) or not jobs:
            raise SpecError("combine = 'list' needs a non-empty list of [[jobs]] tables")
        if axes:
            raise SpecError("combine = 'list' takes [[jobs]], not [axes]; use grid or zip for axes")
        for j in jobs:
            if not isinstance(j, dict):
                raise SpecError(f"each [[jobs]] entry must be a table of settings; got {j!r:.80}")
        return len(jobs), lambda: ({**defaults, **j} for j in jobs)
    if doc.get("jobs"):
        raise SpecError(f"[[jobs]] tables need combine = 'list' (this spec says {combine!r})")
    for k, v in axes.items():
        if not isinstance(v, list) or not v:
            raise SpecError(f"axes.{k} must be a non-empty list of values (one per job along that axis)")
    names = list(axes)
    if combine == "grid":
        return (math.prod(len(axes[n]) for n in names),
                lambda: ({**defaults, **dict(zip(names, combo))}
                         for combo in itertools.product(*(axes[n] for n in names))))
    lengths = {n: len(axes[n]) for n in names if len(axes[n]) != 1}
    if len(set(lengths.values())) > 1:
        raise SpecError(f"combine = 'zip' needs axes of one length (or length 1); got {lengths}")
    n = next(iter(lengths.values()), 1)
    return n, lambda: ({**defaults, **{k: (axes[k][i] if len(axes[k]) > 1 else axes[k][0]) for k in names}}
                       for i in range(n))


def _own_image(c: dict):
    return c.get("image") or c.get("images")


def load_spec(path, *, comfy: bool = False, max_jobs: Optional[int] = MAX_JOBS) -> BatchSpec:
    """Read and check a spec; its jobs are built lazily (``BatchSpec.iter_jobs`` / ``.jobs``). Malformed
    specs, and specs of more than ``max_jobs`` jobs (None or 0: no limit), raise SpecError before any
    job is built; a bad value makes that job fail only."""
    path = Path(path)
    if not path.is_file():
        raise SpecError(f"No batch spec at {path}")
    doc = _read_document(path)
    unknown = set(doc) - {"batch", "defaults", "axes", "jobs", "outputs", "comfy"}
    if unknown:
        raise SpecError(f"{path}: unknown section(s) {sorted(unknown)}; use batch, defaults, axes, jobs, outputs, comfy")
    base = path.parent
    batch = doc.get("batch", {}) or {}
    unknown = set(batch) - {"images", "combine", "name"}
    if unknown:
        raise SpecError(f"[batch]: unknown key(s) {sorted(unknown)}; use images, combine, name")
    combine = batch.get("combine", "grid")
    if combine not in COMBINE:
        raise SpecError(f"batch.combine must be one of {COMBINE}; got {combine!r}")
    comfy_doc = doc.get("comfy")
    comfy_cfg = None
    if comfy_doc is not None:
        if not isinstance(comfy_doc, dict) or "workflow" not in comfy_doc:
            raise SpecError("[comfy] needs workflow = 'path/to/api_workflow.json'")
        wf = Path(comfy_doc["workflow"]).expanduser()
        wf = wf if wf.is_absolute() else base / wf
        if not wf.is_file():
            raise SpecError(f"comfy.workflow: no workflow at {wf}")
        mapping = comfy_doc.get("map", {}) or {}
        bad = [k for k in mapping if k not in DEFAULTS]
        if bad:
            raise SpecError(f"comfy.map: unknown setting(s) {bad}; map settings of: {', '.join(DEFAULTS)}")
        unknown = set(comfy_doc) - {"workflow", "map", "timeout"}
        if unknown:
            raise SpecError(f"[comfy]: unknown key(s) {sorted(unknown)}; use workflow, map, timeout")
        limit = comfy_doc.get("timeout", 3600.0)
        if isinstance(limit, bool) or not isinstance(limit, (int, float)) or not (0 < limit <= 7 * 86400):
            raise SpecError(f"comfy.timeout must be the seconds one job may take on the server, in (0, 604800]; "
                            f"got {limit!r}")
        comfy_cfg = {"workflow": wf, "map": mapping, "workflow_sha256": file_sha256(wf), "timeout": float(limit)}
    if comfy and comfy_cfg is None:
        raise SpecError(f"--comfy needs a [comfy] section in {path} naming the workflow (workflow = '...json')")
    outputs = {**OUTPUT_DEFAULTS, **(doc.get("outputs", {}) or {})}
    unknown = set(outputs) - set(OUTPUT_DEFAULTS)
    if unknown:
        raise SpecError(f"[outputs]: unknown key(s) {sorted(unknown)}; use {sorted(OUTPUT_DEFAULTS)}")
    if outputs["ply"] not in ("none", "rest", "sequence"):
        raise SpecError(f"outputs.ply must be none, rest (the lifted Gaussians) or sequence (one per frame); "
                        f"got {outputs['ply']!r}")
    outputs["ply_every"] = _int(outputs["ply_every"], "outputs.ply_every")
    outputs["tracks_points"] = _int(outputs["tracks_points"], "outputs.tracks_points")
    for key in ("tracks", "flow"):
        if not isinstance(outputs[key], bool):
            raise SpecError(f"outputs.{key} must be true or false; got {outputs[key]!r}")

    images_axis = batch.get("images")
    n_combos, combos = _combinations(doc, combine)
    for key in ("defaults", "axes"):
        _check_keys(doc.get(key, {}) or {}, f"[{key}]", comfy_cfg is not None)
    if combine == "list":
        for j in doc["jobs"]:
            _check_keys(j, "[[jobs]]", comfy_cfg is not None)
    # Images are one more grid axis (or zip column): each combination is taken for each image, except
    # where a job names its own image (list mode) or images is itself an axis. Each distinct pattern is
    # resolved (globbed) once.
    resolved: dict[str, list[Path]] = {}

    def images_of(value) -> list[Path]:
        key = json.dumps(value, sort_keys=True, default=str)
        if key not in resolved:
            resolved[key] = _resolve_images(value, base)
        return resolved[key]

    defaults = doc.get("defaults", {}) or {}
    axes = doc.get("axes", {}) or {}
    image_keys = [k for k in ("image", "images") if k in axes]
    if combine == "list" or (combine == "zip" and image_keys):
        count = 0
        for c in combos():  # a list or a zip: as many combinations as the document holds values
            own = _own_image(c)
            if own is None and images_axis is None:
                raise SpecError("no images: give batch.images = [...] (or image = ... in each [[jobs]] table)")
            count += len(images_of(own if own is not None else images_axis))
    elif image_keys:  # grid with the images as an axis
        rest = math.prod(len(v) for k, v in axes.items() if k not in image_keys)
        count = sum(len(images_of(v)) for k in image_keys for v in axes[k]) * rest
    else:
        own = _own_image(defaults)
        if own is None and images_axis is None:
            raise SpecError("no images: give batch.images = [...] (or image = ... in each [[jobs]] table)")
        imgs = images_of(own if own is not None else images_axis)
        if combine == "zip" and own is None and len(imgs) > 1 and n_combos > 1:
            if len(imgs) != n_combos:
                raise SpecError(f"combine = 'zip': {len(imgs)} images but {n_combos} values per axis")
            count = n_combos
        else:
            count = n_combos * len(imgs)
    if max_jobs is not None and max_jobs > 0 and count > max_jobs:
        shape = " x ".join(f"{k} ({len(v)})" for k, v in axes.items()) if combine != "list" else \
            f"{n_combos} [[jobs]] tables"
        raise SpecError(f"{path} expands to {count:,} jobs ({shape or 'one combination'}, over the images), more than "
                        f"the limit of {max_jobs:,} jobs per batch. Narrow the axes or split the spec into several, "
                        f"or confirm this many videos with --max-jobs {count} (max_jobs={count} in Python).")

    def expanded():
        for ci, c in enumerate(combos()):
            c = dict(c)
            own = c.pop("image", None) or c.pop("images", None)
            if own is not None:
                imgs = images_of(own)
            elif images_axis is not None:
                imgs = images_of(images_axis)
            else:
                raise SpecError("no images: give batch.images = [...] (or image = ... in each [[jobs]] table)")
            if combine == "zip" and own is None and len(imgs) > 1 and n_combos > 1:
                imgs = [imgs[ci % len(imgs)]]  # zipped: the ci-th image with the ci-th values
            for im in imgs:
                yield im, dict(c)

    def make_jobs():
        image_sha: dict[Path, str] = {}
        models_cache: dict[str, dict] = {}
        seen: set[str] = set()
        index = 0
        for img, raw in expanded():
            job = _make_job(img, raw, base, comfy_cfg, image_sha, models_cache, index)
            if job.id in seen:
                continue  # the same video twice (e.g. two spellings of one value): made once
            seen.add(job.id)
            index += 1
            yield job

    return BatchSpec(path=path, sha256=file_sha256(path), outputs=outputs, comfy=comfy_cfg, count=count,
                     _make_jobs=make_jobs)


def _make_job(img: Path, raw: dict, base: Path, comfy_cfg, image_sha: dict, models_cache: dict, index: int) -> Job:
    sha = image_sha.get(img) or image_sha.setdefault(img, file_sha256(img))
    sets = [f"{k}={json.dumps(v)}" for k, v in sorted(raw.items()) if "." in k]
    plain = {k: v for k, v in raw.items() if "." not in k}
    error, mask_sha = None, None
    try:
        settings = normalise(plain)
        if settings["mask"] is not None:
            mpath = Path(settings["mask"]).expanduser()
            mpath = mpath if mpath.is_absolute() else base / mpath
            if not mpath.is_file():
                raise InputError(f"mask: no file at {mpath}")
            settings["mask"] = str(mpath)
            mask_sha = file_sha256(mpath)
    except InputError as exc:
        settings, error = {k: plain.get(k) for k in plain}, str(exc)
    extra: dict = {}
    if mask_sha:
        extra["mask"] = mask_sha
    if comfy_cfg is not None:
        extra["comfy"] = {"workflow": comfy_cfg["workflow_sha256"], "sets": sets, "map": comfy_cfg["map"]}
    elif error is None:
        m = settings["models"]
        extra["models"] = models_cache.get(m) or models_cache.setdefault(m, models_identity(m))
    hashed = {k: v for k, v in settings.items() if k != "mask"}
    try:
        jid = job_id(sha, hashed, extra)
    except (TypeError, ValueError):  # an unnormalisable value (NaN, an object): hash its repr
        jid = job_id(sha, {"invalid": repr(sorted(settings.items()))[:10000]}, extra)
    return Job(id=jid, name=f"{img.stem}-{index:04d}", index=index, image=img, image_sha256=sha, settings=settings,
               sets=sets, error=error, mask_sha256=mask_sha)
