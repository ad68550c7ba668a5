"""Bad input across the library, the CLI and the nodes: each case gets the library's own error
(InputError, a ValueError) whose message names the input and the fix, or a documented, logged
adaptation whose result is checked. No case may end in a traceback from inside torch, OpenCV or
Warp, or run for long: every case here either fails before simulating or runs 2 tiny frames.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
import torch

from physmotion_core.errors import InputError, PhysMotionError
from physmotion_core.image_io import load_image
from physmotion_core.pipeline import generate
from physmotion_core.types import Conditions, Force, Region, SimSettings

FAST = SimSettings(frames=2, grid_res=6, device="cpu", particles_per_cell=1)


def photo(h=72, w=96) -> np.ndarray:
    """A red disc on a grey-green gradient: GrabCut finds it, every format can encode it."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([0.3 + 0.2 * xx / w, 0.5 + 0.1 * yy / h, 0.35 * np.ones_like(xx)], -1)
    disc = (xx - w * 0.5) ** 2 + (yy - h * 0.55) ** 2 < (0.3 * h) ** 2
    img[disc] = (0.85, 0.15, 0.1)
    return img.astype(np.float32)


def disc_mask(h=72, w=96) -> torch.Tensor:
    yy, xx = np.mgrid[0:h, 0:w]
    return torch.from_numpy(((xx - w * 0.5) ** 2 + (yy - h * 0.55) ** 2 < (0.3 * h) ** 2).astype(np.float32))


IMG = photo()

# (case, call, message fragments that must all appear)
LIBRARY_CASES = [
    ("empty mask", lambda: generate(IMG, mask=torch.zeros(72, 96), settings=FAST), ["mask is empty"]),
    ("all-foreground mask", lambda: generate(IMG, mask=torch.ones(72, 96), settings=FAST),
     ["covers the whole image", "no background"]),
    ("NaN pixels", lambda: generate(np.where(IMG > 0.8, np.nan, IMG), settings=FAST), ["NaN or Inf"]),
    ("Inf pixels", lambda: generate(np.where(IMG > 0.8, np.inf, IMG), settings=FAST), ["NaN or Inf"]),
    ("float pixels above 1", lambda: generate(IMG * 255, settings=FAST), ["0..1", "255"]),
    ("negative pixels", lambda: generate(IMG - 1, settings=FAST), ["0..1"]),
    ("boolean image", lambda: generate(IMG > 0.5, settings=FAST), ["boolean", "mask"]),
    ("2-D array", lambda: generate(IMG[..., 0], settings=FAST), ["(H, W, 3)"]),
    ("zero frames", lambda: generate(IMG, mask=disc_mask(), settings=SimSettings(frames=0)), ["frames", "1"]),
    ("huge frame count", lambda: generate(IMG, mask=disc_mask(), settings=SimSettings(frames=100_000, fps=1000)),
     ["RAM", "frame count"]),
    ("negative fps", lambda: generate(IMG, settings=SimSettings(frames=2, fps=-1)), ["fps"]),
    ("zero object height", lambda: generate(IMG, mask=disc_mask(), object_height=0.0, settings=FAST),
     ["object_height", "metres"]),
    ("NaN object height", lambda: generate(IMG, mask=disc_mask(), object_height=float("nan"), settings=FAST),
     ["object_height"]),
    ("zero field of view", lambda: generate(IMG, mask=disc_mask(), fov_y_deg=0.0, settings=FAST), ["fov_y_deg"]),
    ("NaN force", lambda: Force((float("nan"), 0, 0)), ["finite", "NaN"]),
    ("reversed force window", lambda: Force((1, 0, 0), Region(), 0.5, 0.1), ["t_start < t_end"]),
    ("unknown material", lambda: generate(IMG, material="unobtainium", settings=FAST), ["Unknown material", "jelly"]),
    ("negative Young's modulus", lambda: generate(IMG, material_params={"E": -5.0}, settings=FAST),
     ["Young's modulus", "positive"]),
    ("Poisson ratio 0.5", lambda: generate(IMG, material_params={"nu": 0.5}, settings=FAST), ["Poisson"]),
    ("misspelt material parameter", lambda: generate(IMG, material_params={"youngs": 1e5}, settings=FAST),
     ["Unknown material parameter"]),
    ("force outside the object", lambda: generate(IMG, mask=disc_mask(), settings=FAST, conditions=Conditions(
        [Force((1, 0, 0), Region.at_pixel(2, 2, 1.0))])), ["does not touch the object", "x 27..70"]),
    ("two grounds", lambda: generate(IMG, mask=disc_mask(), settings=FAST, conditions=Conditions(
        [__import__("physmotion_core.types", fromlist=["Ground"]).Ground(0.0),
         __import__("physmotion_core.types", fromlist=["Ground"]).Ground(0.1)])), ["Only one Ground"]),
    ("too few Gaussians", lambda: generate(IMG, mask=disc_mask(), max_gaussians=0, settings=FAST),
     ["max_gaussians"]),
    ("bad max_side", lambda: generate(IMG, max_side=-3, settings=FAST), ["max_side"]),
]


@pytest.mark.parametrize("case,call,fragments", LIBRARY_CASES, ids=[c[0] for c in LIBRARY_CASES])
def test_library_refuses_bad_input_clearly(case, call, fragments):
    with pytest.raises(InputError) as err:
        call()
    msg = str(err.value)
    for frag in fragments:
        assert frag in msg, f"{case}: {frag!r} not in {msg!r}"


def test_tiny_images_make_a_tiny_video_or_a_clear_error(tmp_path):
    """12x12 is small but valid (a 12x12 mp4 that decodes); 3x3 leaves no background to inpaint."""
    import av

    small = cv2.resize(IMG, (12, 12), interpolation=cv2.INTER_AREA)
    # The object's mask at 12x12: the lift needs 16 pixels, and the inpainted hole (the mask grown by
    # 3 px) must leave some of the photo to fill from.
    small_mask = torch.zeros(12, 12)
    small_mask[4:8, 4:8] = 1.0
    res = generate(small, mask=small_mask, settings=FAST, output=tmp_path / "tiny.mp4")
    assert res.frames.shape == (2, 12, 12, 3)
    with av.open(str(res.video_path)) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(frames) == 2 and frames[0].shape == (12, 12, 3)
    with pytest.raises(InputError, match="nothing to fill from|at least 16"):
        generate(cv2.resize(IMG, (3, 3), interpolation=cv2.INTER_AREA), settings=FAST)


def test_integer_images_are_scaled_by_their_type_not_misread():
    """uint8 and uint16 arrays mean 0..255 and 0..65535: the same picture gives the same video."""
    m = disc_mask()
    ref = generate(IMG, mask=m, settings=FAST).frames
    u8 = generate((IMG * 255 + 0.5).astype(np.uint8), mask=m, settings=FAST).frames
    u16 = generate((IMG * 65535 + 0.5).astype(np.uint16), mask=m, settings=FAST).frames
    assert float((u8 - ref).abs().max()) < 3 / 255  # 8-bit quantisation of the input
    assert float((u16 - ref).abs().max()) < 1e-3


def test_oversized_photos_are_scaled_down_with_a_warning_and_regions_follow(caplog):
    big = cv2.resize(IMG, (96 * 4, 72 * 4), interpolation=cv2.INTER_NEAREST)
    big_mask = cv2.resize(disc_mask().numpy(), (96 * 4, 72 * 4), interpolation=cv2.INTER_NEAREST)
    push = Conditions([Force((2.0, 0, 0), Region.at_pixel(48 * 4, 40 * 4, 6.0 * 4), 0.0, 0.05)])
    with caplog.at_level(logging.WARNING, logger="physmotion"):
        res = generate(big, mask=torch.from_numpy(big_mask), settings=FAST, conditions=push, max_side=96)
    assert res.frames.shape[1:3] == (72, 96)
    assert any("scaled down to 96x72" in r.message and "max_side=0" in r.message for r in caplog.records)
    # The push given in the big photo's pixels lands on the object in the scaled one (else: "contains
    # no part of the object"), and with max_side=0 the full size is kept.
    kept = generate(big, mask=torch.from_numpy(big_mask), settings=SimSettings(frames=1, grid_res=6, device="cpu",
                                                                                particles_per_cell=1), max_side=0)
    assert kept.frames.shape[1:3] == (288, 384)


def _write(path, array, params=()):
    assert cv2.imwrite(str(path), array, list(params)), path


@pytest.fixture(scope="module")
def image_files(tmp_path_factory):
    from PIL import Image

    d = tmp_path_factory.mktemp("formats")
    rgb8 = (IMG * 255 + 0.5).astype(np.uint8)
    pil = Image.fromarray(rgb8)
    files = {}
    pil.save(d / "rgb.png"); files["rgb.png"] = "rgb"
    pil.convert("L").save(d / "gray.png"); files["gray.png"] = "gray"
    pil.convert("LA").save(d / "gray_alpha.png"); files["gray_alpha.png"] = "gray"
    pil.convert("CMYK").save(d / "cmyk.jpg", quality=95); files["cmyk.jpg"] = "rgb~"
    pil.convert("CMYK").save(d / "cmyk.tif"); files["cmyk.tif"] = "rgb"
    pil.convert("P").save(d / "palette.png"); files["palette.png"] = "rgb~"
    _write(d / "rgb16.png", (IMG[..., ::-1] * 65535 + 0.5).astype(np.uint16)); files["rgb16.png"] = "rgb16"
    pil.save(d / "rgb.webp", lossless=True); files["rgb.webp"] = "rgb"
    rgba = np.dstack([rgb8, (disc_mask().numpy() * 255).astype(np.uint8)])
    Image.fromarray(rgba, "RGBA").save(d / "cutout.png"); files["cutout.png"] = "alpha"
    Image.fromarray(np.dstack([rgb8, np.full(rgb8.shape[:2], 255, np.uint8)]), "RGBA").save(d / "opaque.png")
    files["opaque.png"] = "rgb"
    (d / "fake.png").write_bytes(b"<html>not an image</html>"); files["fake.png"] = "error"
    (d / "truncated.png").write_bytes((d / "rgb.png").read_bytes()[:200]); files["truncated.png"] = "error"
    (d / "empty.jpg").write_bytes(b""); files["empty.jpg"] = "error"
    (d / "folder.png").mkdir(); files["folder.png"] = "error"
    files["missing.png"] = "error"
    return d, files


def test_every_image_format_loads_as_rgb_in_0_1_or_fails_clearly(image_files):
    d, files = image_files
    ref = torch.from_numpy(IMG)
    gray = torch.from_numpy(IMG @ np.array([0.299, 0.587, 0.114], np.float32))
    for name, kind in files.items():
        path = d / name
        if kind == "error":
            with pytest.raises(InputError) as err:
                load_image(path)
            assert str(path.name) in str(err.value), name
            continue
        rgb, alpha = load_image(path)
        assert rgb.shape == (72, 96, 3) and rgb.dtype == torch.float32, name
        assert float(rgb.min()) >= 0 and float(rgb.max()) <= 1, name
        if kind == "gray":
            assert float((rgb[..., 0] - gray).abs().mean()) < 2 / 255, name
            assert torch.equal(rgb[..., 0], rgb[..., 2]), name
        elif kind == "rgb16":
            assert float((rgb - ref).abs().max()) < 1e-4, name  # 16 bits kept
        elif kind.endswith("~"):
            # Lossy encodings (CMYK JPEG, a 256-colour palette): compare with PIL's own RGB decoding.
            from PIL import Image

            pil_rgb = torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), np.float32) / 255)
            assert float((rgb - pil_rgb).abs().mean()) < 0.02, name
        else:
            assert float((rgb - ref).abs().mean()) < 1 / 255, name
        if kind == "alpha":
            assert alpha is not None and torch.equal(alpha > 0.5, disc_mask() > 0.5), name
        else:
            assert alpha is None, name  # opaque alpha carries no segmentation


def test_cli_reports_bad_input_without_a_traceback(tmp_path, capsys, image_files):
    from physmotion_core.cli import main

    d, _ = image_files
    good = str(d / "cutout.png")
    cases = [
        (["generate", str(tmp_path / "nope.png")], 2, "Image file not found"),
        (["generate", str(d / "fake.png")], 2, "Cannot decode"),
        (["generate", good, "--frames", "0"], 2, "frames"),
        (["generate", good, "--force", "1,2"], 2, "3 comma-separated numbers"),
        (["generate", good, "--at", "3,4"], 2, "matching --force"),
        (["generate", good, "--E", "-1", "-q"], 2, "Young's modulus"),
        (["generate", good, "--material", "kryptonite"], 2, "invalid choice"),
        (["generate", good, "--frames", "2", "--grid-res", "6", "-q", "-o", "/proc/forbidden/x.mp4"], 1,
         "writable"),
    ]
    for argv, code, fragment in cases:
        try:
            rc = main(argv)
        except SystemExit as exc:  # argparse errors exit with 2
            rc = exc.code
        err = capsys.readouterr().err
        assert rc == code, (argv, rc, err)
        assert fragment in err, (argv, err)
        assert "Traceback" not in err


def _nodes():
    from comfy_harness import load_pack

    return load_pack().NODE_CLASS_MAPPINGS


def test_nodes_refuse_bad_input_clearly():
    nodes = _nodes()
    img = torch.from_numpy(IMG)[None]
    seg = nodes["PhysMotionSegment"]()
    with pytest.raises(InputError, match="no mask is connected"):
        seg.run(img, "mask", "auto", 3)
    with pytest.raises(InputError, match="NaN or Inf"):
        seg.run(torch.full_like(img, float("nan")), "auto", "auto", 3)
    lift = nodes["PhysMotionSilhouetteLift"]()
    with pytest.raises(InputError, match="mask"):
        lift.run(img, torch.zeros(1, 72, 96), 0.3, 40.0, 1.0, 60000, True)
    mat = nodes["PhysMotionMaterial"]()
    with pytest.raises(InputError, match="Unknown material"):
        mat.run("unobtainium", 0.0, -1.0, 0.0)
    with pytest.raises(InputError):
        mat.run("jelly", 0.0, -1.0, 0.0, "yield_stress=abc")
    with pytest.raises(PhysMotionError):
        mat.run("jelly", 0.0, 0.7, 0.0)  # ν ≥ 0.5
