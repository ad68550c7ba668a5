"""Bad input, second round (issue 19): a user's files are never destroyed, every output location
is checked before any work, the output is what its name says, negative vectors parse, and the
remaining tracebacks (decompression bombs, malformed .ply, mis-shaped weights, empty node
batches, a NUL byte, Ctrl-C at start-up) are clear errors. SIGTERM and Cancel leave no debris.

Real files in tmp_path; CLI cases that end before any work run in-process, the signal cases in a
subprocess. Nothing here simulates more than 2 tiny frames.
"""

from __future__ import annotations

import json
import os
import re
import stat
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from physmotion_core.cli import _build_parser, _join_vector_values, main
from physmotion_core.errors import InputError, Interrupted
from physmotion_core.fsutil import (OutputLocationError, atomic_folder, atomic_output, check_output_path,
                                    check_outputs, protect_inputs)
from physmotion_core.image_io import load_image

ROOT = Path(__file__).resolve().parent.parent
FAST = ["--frames", "2", "--grid-res", "6", "-q"]


@pytest.fixture
def cutout(tmp_path) -> Path:
    """An 80x60 RGBA cut-out (a red disc): no segmentation model needed."""
    h, w = 60, 80
    img = np.full((h, w, 4), 128, np.uint8)
    yy, xx = np.mgrid[0:h, 0:w]
    disc = (xx - 40) ** 2 + (yy - 30) ** 2 <= 15 ** 2
    img[disc, :3] = (20, 20, 220)
    img[..., 3] = np.where(disc, 255, 0)
    path = tmp_path / "photo.png"
    assert cv2.imwrite(str(path), img)
    return path


def cli(argv, capsys) -> tuple[int, str]:
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse
        rc = exc.code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err


@pytest.fixture
def no_work(monkeypatch):
    """Any call into the pipeline fails the test: the CLI must refuse before the work starts."""
    import physmotion_core.pipeline as pipeline

    def started(*a, **kw):
        raise AssertionError("the pipeline started before the outputs were checked")

    monkeypatch.setattr(pipeline, "generate", started)


# ----------------------------------------------------------------------------------------------
# Data loss: outputs never replace an input, another output, or anything but a regular file
# ----------------------------------------------------------------------------------------------


def test_outputs_that_would_overwrite_an_input_are_refused_before_any_work(cutout, tmp_path, capsys, no_work):
    before = cutout.read_bytes()
    mask = tmp_path / "mask.png"
    cv2.imwrite(str(mask), np.full((60, 80), 255, np.uint8))
    (tmp_path / "link.png").symlink_to(cutout)
    os.link(cutout, tmp_path / "hard.png")
    cases = [
        (["-o", cutout], "-o/--output"),
        (["-o", tmp_path / "link.png"], "-o/--output"),          # a symbolic link to the photo
        (["-o", tmp_path / "hard.png"], "-o/--output"),          # a hard link: the same inode
        (["-o", tmp_path / "sub" / ".." / "photo.png"], "-o/--output"),
        (["--stats", cutout, "-o", tmp_path / "v.mp4"], "--stats"),
        (["--save-ply", cutout, "-o", tmp_path / "v.mp4"], "--save-ply"),
        (["--mask", mask, "--stats", mask, "-o", tmp_path / "v.mp4"], "--stats"),
    ]
    for extra, label in cases:
        rc, err = cli(["generate", cutout, *FAST, *extra], capsys)
        assert rc == 2, (extra, err)
        assert label in err and "input" in err and "destroy the input" in err, (extra, err)
    assert cutout.read_bytes() == before and mask.exists()
    # Two outputs of one run on the same path.
    rc, err = cli(["generate", cutout, *FAST, "-o", tmp_path / "a.mp4", "--stats", tmp_path / "a.mp4"], capsys)
    assert rc == 2 and "same file" in err


def test_outputs_that_are_not_regular_files_are_never_replaced(cutout, tmp_path, capsys, no_work):
    fifo = tmp_path / "pipe.mp4"
    os.mkfifo(fifo)
    folder = tmp_path / "folder.mp4"
    folder.mkdir()
    targets = [(fifo, "named pipe"), (folder, "a folder")]
    if os.geteuid() == 0:  # a device node of our own (as /dev/null is), inside tmp_path
        dev = tmp_path / "null.mp4"
        os.mknod(dev, stat.S_IFCHR | 0o666, os.makedev(1, 3))
        targets.append((dev, "a device"))
    for target, kind in targets:
        for opt in ("-o", "--stats", "--save-ply"):
            out = [] if opt == "-o" else ["-o", tmp_path / "v.mp4"]
            rc, err = cli(["generate", cutout, *FAST, *out, opt, target], capsys)
            assert rc == 2 and kind in err and "refusing to replace" in err, (opt, target, err)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and folder.is_dir()
    # The writers themselves check too (a caller that skipped the plan), before writing and
    # again right before the rename; /dev/null is only checked, never written.
    for target, kind in targets:
        with pytest.raises(InputError, match="not a regular file"):
            with atomic_output(target) as tmp:
                tmp.write_bytes(b"x")
    with pytest.raises(InputError, match="a device"):
        check_output_path("/dev/null", "-o")
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


def test_writers_refuse_to_replace_a_protected_input(tmp_path):
    from physmotion_core.pipeline import generate
    from physmotion_core.ply import write_ply
    from physmotion_core.types import Gaussians

    photo = tmp_path / "photo.ply"
    photo.write_bytes(b"precious")
    g = Gaussians(means=torch.zeros(2, 3), quats=torch.tensor([[1.0, 0, 0, 0]] * 2), scales=torch.full((2, 3), 0.01),
                  opacities=torch.full((2,), 0.5), sh=torch.zeros(2, 1, 3))
    with protect_inputs(photo):
        with pytest.raises(InputError, match="is the input"):
            write_ply(photo, g)
        (tmp_path / "alias.ply").symlink_to(photo)
        with pytest.raises(InputError, match="is the input"):
            write_ply(tmp_path / "alias.ply", g)  # replacing the link would be allowed; the photo behind it not
    assert photo.read_bytes() == b"precious"
    write_ply(photo, g)  # outside the run, replacing it is the caller's choice
    # The library's one-call pipeline refuses output == image before loading anything.
    img = tmp_path / "img.png"
    cv2.imwrite(str(img), np.zeros((16, 16, 3), np.uint8))
    with pytest.raises(InputError, match="destroy the input"):
        generate(img, output=img)
    assert cv2.imread(str(img)).shape == (16, 16, 3)


# ----------------------------------------------------------------------------------------------
# Fail late: every output location is checked before any work; long names work
# ----------------------------------------------------------------------------------------------


def test_unwritable_output_locations_are_found_before_any_work(cutout, tmp_path, capsys, no_work, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    for opt, path in [("-o", blocker / "out.mp4"), ("--stats", blocker / "s.json"), ("--save-ply", "/proc/nope/g.ply"),
                      ("-o", "/proc/forbidden/x.mp4")]:
        out = [] if opt == "-o" else ["-o", tmp_path / "v.mp4"]
        rc, err = cli(["generate", cutout, *FAST, *out, opt, path], capsys)
        assert rc == 1, (opt, path, err)
        assert opt in err and ("writable" in err or "not a folder" in err), err
    with pytest.raises(OutputLocationError):
        check_outputs({"--stats": blocker / "x" / "s.json"})
    # The other commands check theirs before their minutes of work too.
    import physmotion_core.validate.cases as cases
    import physmotion_core.validate.stress as stress

    def started(*a, **kw):
        raise AssertionError("work started before the outputs were checked")

    monkeypatch.setattr(stress, "run_matrix", started)
    monkeypatch.setattr(cases, "run_cases", started)
    assert cli(["stress", "--json", blocker / "s.json"], capsys)[0] == 1
    assert cli(["validate", "--markdown", tmp_path], capsys)[0] == 2  # a folder, not a page
    assert cli(["comfy-run", "wf.json", "-o", blocker / "out"], capsys)[0] == 1
    # A file name longer than the file system allows: refused before the run, naming the limit.
    rc, err = cli(["generate", cutout, *FAST, "-o", tmp_path / ("b" * 252 + ".mp4")], capsys)
    assert rc == 2 and "256 bytes" in err and "at most 255" in err


def test_a_244_character_name_and_a_gif_are_written_with_bounded_temporary_names(cutout, tmp_path, capsys):
    import av

    long_name = tmp_path / ("c" * 240 + ".mp4")
    assert len(long_name.name) == 244
    gif = tmp_path / ("g" * 251 + ".gif")  # 255 bytes: the longest name there is
    rc, err = cli(["generate", cutout, *FAST, "-o", long_name, "--stats", tmp_path / ("s" * 250 + ".json")], capsys)
    assert rc == 0, err
    with av.open(str(long_name)) as c:
        assert c.format.name.startswith("mov,mp4") and len(list(c.decode(video=0))) == 2
    with atomic_output(gif, suffix=".tmp.gif") as tmp:
        assert len(tmp.name.encode()) <= 64  # bounded, whatever the target's length
        tmp.write_bytes(b"GIF89a")
    assert gif.read_bytes() == b"GIF89a"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# ----------------------------------------------------------------------------------------------
# Silent wrong output: the container follows the name; EXIF orientation; empty force windows
# ----------------------------------------------------------------------------------------------


def test_every_video_extension_gets_its_own_container_and_codec(tmp_path, capsys, cutout, no_work):
    import av

    from physmotion_core.video import read_video, write_video

    yy, xx = np.mgrid[0:33, 0:47]
    frames = np.stack([np.stack([(xx * 5 + 20 * t) % 256, yy * 7, np.full_like(xx, 128)], -1)
                       for t in range(5)]).astype(np.uint8)
    expect = {".mp4": ("mp4", "h264"), ".mov": ("mov", "h264"), ".mkv": ("matroska", "h264"),
              ".webm": ("matroska", "vp9"), ".avi": ("avi", "mpeg4"), ".gif": ("gif", "gif")}
    for ext, (fmt, codec) in expect.items():
        path = write_video(tmp_path / f"clip{ext}", frames, fps=10)
        with av.open(str(path)) as c:
            assert fmt in c.format.name and c.streams.video[0].codec_context.name == codec, ext
        video, fps = read_video(path)
        assert video.shape[0] == 5 and fps == pytest.approx(10, rel=0.01), ext
        err = np.abs(video[:, :33, :47].astype(float) - frames).mean()
        assert err < 12, (ext, err)  # the picture survives each codec (chroma subsampling / palette)
    assert (tmp_path / "clip.gif").read_bytes()[:6] == b"GIF89a"
    # A fixed encoder thread count reaches x264 (it writes its settings into the stream).
    big = np.repeat(np.repeat(frames[:2], 10, axis=1), 10, axis=2)
    write_video(tmp_path / "threads.mp4", big, fps=10, threads=3)
    assert b"threads=3 " in (tmp_path / "threads.mp4").read_bytes()
    assert (tmp_path / "clip.avi").read_bytes()[:4] == b"RIFF"
    with pytest.raises(InputError, match=r"\.xyz.*\.mp4"):
        write_video(tmp_path / "clip.xyz", frames)
    for bad in ("clip.xyz", "clip"):
        rc, err = cli(["generate", cutout, *FAST, "-o", tmp_path / bad], capsys)
        assert rc == 2 and "not a video format" in err
    assert not (tmp_path / "clip.xyz").exists()


def _exif_jpeg(path: Path, upright: np.ndarray, orientation: int) -> None:
    """Store ``upright`` as a camera would: the pixels turned so that EXIF ``orientation`` turns
    them upright again (Pillow's inverse transpositions)."""
    from PIL import Image

    inverse = {1: None, 2: Image.Transpose.FLIP_LEFT_RIGHT, 3: Image.Transpose.ROTATE_180,
               4: Image.Transpose.FLIP_TOP_BOTTOM, 5: Image.Transpose.TRANSPOSE, 6: Image.Transpose.ROTATE_90,
               7: Image.Transpose.TRANSVERSE, 8: Image.Transpose.ROTATE_270}[orientation]
    im = Image.fromarray(upright)
    stored = im if inverse is None else im.transpose(inverse)
    exif = stored.getexif()
    exif[0x0112] = orientation
    stored.save(path, quality=95, exif=exif)


def test_exif_rotated_phone_photos_are_read_upright(tmp_path):
    from PIL import Image, ImageOps

    upright = np.zeros((40, 64, 3), np.uint8)
    upright[:12, :20] = (250, 10, 10)     # a red block top-left
    upright[30:, 50:] = (10, 250, 10)     # a green block bottom-right
    for o in range(1, 9):
        path = tmp_path / f"phone_{o}.jpg"
        _exif_jpeg(path, upright, o)
        rgb, _ = load_image(path)
        assert rgb.shape == (40, 64, 3), o
        assert float(np.abs(rgb.numpy() * 255 - upright).mean()) < 4, o  # upright again
        pil = np.asarray(ImageOps.exif_transpose(Image.open(path)).convert("RGB"), np.float32)
        assert float(np.abs(rgb.numpy() * 255 - pil).mean()) < 1.5, o   # as Pillow turns it
    # The pipeline reads the file the same way: a portrait phone photo gives a portrait video.
    from physmotion_core.pipeline import generate
    from physmotion_core.types import SimSettings

    portrait = cv2.cvtColor(cv2.resize(upright, (40, 64)), cv2.COLOR_BGR2RGB)
    _exif_jpeg(tmp_path / "portrait.jpg", portrait, 6)
    assert Image.open(tmp_path / "portrait.jpg").size == (64, 40)  # stored landscape
    mask = torch.zeros(64, 40)
    mask[20:44, 10:30] = 1
    res = generate(tmp_path / "portrait.jpg", mask=mask, settings=SimSettings(frames=1, grid_res=6, device="cpu",
                                                                             particles_per_cell=1))
    assert tuple(res.frames.shape[1:3]) == (64, 40)


def test_a_force_window_after_the_clip_or_without_a_force_is_refused(cutout, tmp_path, capsys, no_work):
    rc, err = cli(["generate", cutout, *FAST, "--force-time", "0,0.5", "-o", tmp_path / "a.mp4"], capsys)
    assert rc == 2 and "--force-time" in err and "no --force" in err
    from physmotion_core.pipeline import _check_condition_windows
    from physmotion_core.types import Conditions, Force, SimSettings, Torque

    s = SimSettings(frames=2, fps=24)  # the last frame is at t = 1/24 s
    _check_condition_windows(Conditions([Force((1, 0, 0), t_start=0.0, t_end=5.0)]), s)
    _check_condition_windows(Conditions([Force((1, 0, 0), t_start=0.04, t_end=5.0)]), s)
    for cond in (Force((1, 0, 0), t_start=1 / 24, t_end=2.0), Torque((0, 1, 0), t_start=3.0, t_end=4.0)):
        with pytest.raises(InputError, match="would change nothing"):
            _check_condition_windows(Conditions([cond]), s)


def test_a_force_window_after_the_clip_is_refused_by_the_cli(cutout, tmp_path, capsys):
    rc, err = cli(["generate", cutout, *FAST, "--force", "5,0,0", "--force-time", "3,4", "-o", tmp_path / "a.mp4"],
                  capsys)
    assert rc == 2 and "would change nothing" in err
    assert not (tmp_path / "a.mp4").exists()


# ----------------------------------------------------------------------------------------------
# CLI usability: negative vectors as written in the README's axes
# ----------------------------------------------------------------------------------------------


def test_negative_vectors_parse_as_values(cutout, tmp_path, capsys):
    argv = ["generate", "p.png", "--force", "-20,0,0", "--at", "-1,5", "--force", "-1e-3,-2,+3",
            "--force-time", "-0,0.1", "--object-point", "-4,-5", "--E", "-5", "--fps", "24"]
    args = _build_parser().parse_args(_join_vector_values(argv))
    assert args.force == ["-20,0,0", "-1e-3,-2,+3"] and args.at == ["-1,5"]
    assert args.force_time == "-0,0.1" and args.object_point == ["-4,-5"] and args.E == -5.0
    assert _join_vector_values(["--force=-1,0,0", "--force", "1,0,0"]) == ["--force=-1,0,0", "--force", "1,0,0"]
    # End to end: the push to the left reaches the pipeline (which then finds the pixel off the object).
    rc, err = cli(["generate", cutout, *FAST, "--force", "-20,0,0", "--at", "1,1", "--radius", "1",
                   "-o", tmp_path / "x.mp4"], capsys)
    assert rc == 2 and "does not touch the object" in err
    rc, err = cli(["generate", cutout, *FAST, "--force", "-20,0", "-o", tmp_path / "x.mp4"], capsys)
    assert rc == 2 and "3 comma-separated numbers" in err


# ----------------------------------------------------------------------------------------------
# Decompression bombs
# ----------------------------------------------------------------------------------------------


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _png(width: int, height: int, idat: bytes, color_type: int = 0) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


def real_black_png(side: int, rows_per_block: int = 500) -> bytes:
    """A valid grayscale PNG of side x side black pixels, built in a fraction of a second: a
    deflate block of zero rows is compressed once (a full flush makes it independent of what came
    before) and repeated; the zlib trailer is the Adler-32 of all-zero bytes (A = 1, B = length)."""
    row = b"\0" * (side + 1)  # filter byte + pixels
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = c.compress(row * rows_per_block) + c.flush(zlib.Z_FULL_FLUSH)
    full, rest = divmod(side, rows_per_block)
    t = zlib.compressobj(9, zlib.DEFLATED, -15)
    tail = t.compress(row * rest) + t.flush(zlib.Z_FINISH)
    adler = ((side * (side + 1)) % 65521) << 16 | 1
    return _png(side, side, b"\x78\xda" + block * full + tail + struct.pack(">I", adler))


def test_decompression_bombs_are_refused_from_the_header(tmp_path, capsys, monkeypatch):
    fake = tmp_path / "claims_100000.png"
    fake.write_bytes(_png(100_000, 100_000, zlib.compress(b"\0" * 1000)))
    real = tmp_path / "real_25000.png"
    real.write_bytes(real_black_png(25_000))
    assert real.stat().st_size < 2_000_000
    small = real_black_png(1234, 100)  # the same construction decodes to what it claims
    (tmp_path / "small.png").write_bytes(small)
    rgb, _ = load_image(tmp_path / "small.png")
    assert rgb.shape == (1234, 1234, 3) and float(rgb.max()) == 0.0
    for path, what in [(fake, "100000x100000"), (real, "25000x25000")]:
        t = time.perf_counter()
        with pytest.raises(InputError) as err:
            load_image(path)
        assert time.perf_counter() - t < 2.0  # nothing was decoded
        msg = str(err.value)
        assert path.name in msg and what in msg and "megapixels" in msg and "PHYSMOTION_MAX_IMAGE_PIXELS" in msg
        rc, err_text = cli(["generate", path, *FAST, "-o", tmp_path / "o.mp4"], capsys)
        assert rc == 2 and "megapixels" in err_text
    monkeypatch.setenv("PHYSMOTION_MAX_IMAGE_PIXELS", "1000000")
    with pytest.raises(InputError, match="1234x1234"):
        load_image(tmp_path / "small.png")
    # A format only OpenCV reads (no header facts from Pillow) is checked after decoding instead;
    # a file OpenCV refuses by its own limits is a clear error too.
    monkeypatch.setenv("PHYSMOTION_MAX_IMAGE_PIXELS", "100")
    hdr = tmp_path / "img.hdr"  # Radiance HDR: OpenCV reads it, Pillow does not
    assert cv2.imwrite(str(hdr), np.zeros((20, 20, 3), np.float32))
    with pytest.raises(InputError, match="20x20"):
        load_image(hdr)


# ----------------------------------------------------------------------------------------------
# Malformed .ply files
# ----------------------------------------------------------------------------------------------

_PROPS = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
          "rot_0", "rot_1", "rot_2", "rot_3"]


def _ply(header_lines, n=3, values=None) -> bytes:
    head = "ply\n" + "".join(line + "\n" for line in header_lines) + "end_header\n"
    data = np.zeros((n, len(_PROPS)), "<f4") if values is None else values
    return head.encode() + data.astype("<f4").tobytes()


def _good_header(count="3", fmt="format binary_little_endian 1.0"):
    return [fmt, f"element vertex {count}"] + [f"property float {p}" for p in _PROPS]


def test_malformed_ply_headers_and_nan_values_name_the_file(tmp_path):
    from physmotion_core.ply import read_ply

    vals = np.zeros((3, len(_PROPS)), "<f4")
    vals[:, _PROPS.index("rot_0")] = 1
    vals[:, _PROPS.index("scale_0"):_PROPS.index("scale_0") + 3] = -4
    ok = tmp_path / "ok.ply"
    ok.write_bytes(_ply(_good_header(), values=vals))
    assert len(read_ply(ok)) == 3
    nan_opacity = vals.copy()
    nan_opacity[1, _PROPS.index("opacity")] = np.nan
    inf_x = vals.copy()
    inf_x[0, 0] = np.inf
    cases = {
        "negative_count": (_ply(_good_header("-3")), "negative"),
        "missing_count": (_ply(["format binary_little_endian 1.0", "element vertex"] +
                               [f"property float {p}" for p in _PROPS]), "needs a name and a count"),
        "text_count": (_ply(_good_header("three")), "not a whole number"),
        "float_count": (_ply(_good_header("3.5")), "not a whole number"),
        "duplicate_property": (_ply(_good_header() + ["property float x"]), "'x' is given twice"),
        "format_without_value": (_ply(_good_header(fmt="format")), "format line has no value"),
        "no_format": (_ply(_good_header()[1:]), "no format line"),
        "property_without_name": (_ply(_good_header() + ["property float"]), "needs a type and a name"),
        "unknown_type": (_ply(_good_header() + ["property quaternion q"]), "unsupported property type"),
        "no_vertices": (_ply(["format binary_little_endian 1.0"]), "no vertex element"),
        "zero_vertices": (_ply(_good_header("0"), n=0), "holds no Gaussians"),
        "huge_count": (_ply(_good_header("999999999999")), "truncated"),
        "no_end_header": (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n", "no end_header"),
        "binary_garbage": (b"ply\n" + bytes(range(256)) * 50, "header"),
        "nan_opacity": (_ply(_good_header(), values=nan_opacity), "1 of 3 Gaussians have a NaN or infinite 'opacity'"),
        "inf_position": (_ply(_good_header(), values=inf_x), "'x'"),
    }
    for name, (data, fragment) in cases.items():
        path = tmp_path / f"{name}.ply"
        path.write_bytes(data)
        with pytest.raises(InputError) as err:
            read_ply(path)
        assert str(path) in str(err.value) and fragment in str(err.value), (name, str(err.value))
    # An element stored before the vertices (fixed-size) is skipped, not read as vertices.
    pre = ["format binary_little_endian 1.0", "element camera 2", "property float fx", "property float fy",
           "element vertex 3"] + [f"property float {p}" for p in _PROPS]
    path = tmp_path / "camera_first.ply"
    path.write_bytes(b"ply\n" + "".join(s + "\n" for s in pre).encode() + b"end_header\n" +
                     np.full(4, 7.0, "<f4").tobytes() + vals.tobytes())
    g = read_ply(path)
    assert torch.allclose(g.means, torch.zeros(3, 3)) and torch.allclose(g.opacities, torch.full((3,), 0.5))


# ----------------------------------------------------------------------------------------------
# Weights with wrong shapes or dtypes
# ----------------------------------------------------------------------------------------------


def test_sam_and_lgm_weights_with_wrong_shapes_or_dtypes_name_the_file_and_keys(tmp_path, monkeypatch):
    from safetensors.torch import load_file, save_file

    from physmotion_core.lift.lgm import load_lgm
    from physmotion_core.segment.sam import load_sam
    from tiny_models import write_tiny_lgm, write_tiny_sam

    monkeypatch.setenv("PHYSMOTION_MODELS", str(tmp_path))
    good = torch.load(write_tiny_sam(tmp_path), weights_only=True)
    k_dec, k_tok = "mask_decoder.output_upscaling.0.weight", "mask_decoder.iou_token.weight"
    sam_cases = {
        "shape": ({k_dec: torch.zeros(3, 3, 2, 2)}, ["with other shapes", k_dec, "(3, 3, 2, 2)"]),
        "dtype": ({k_tok: good[k_tok].to(torch.int32)}, ["not floating-point", k_tok, "int32"]),
        "layout_rank": ({"image_encoder.patch_embed.proj.weight": torch.zeros(5, 5)}, ["unexpected shape"]),
        "layout_scalar": ({"image_encoder.pos_embed": torch.zeros(1)}, ["unexpected shape"]),
    }
    for name, (change, fragments) in sam_cases.items():
        path = tmp_path / "sams" / f"bad_{name}.pth"
        torch.save({**good, **change}, path)
        with pytest.raises(InputError) as err:
            load_sam(path.name)
        for frag in [str(path), *fragments]:
            assert frag in str(err.value), (name, frag, str(err.value))
    lgm = load_file(str(write_tiny_lgm(tmp_path)))
    conv = "unet.mid_block.nets.0.conv1.weight" if "unet.mid_block.nets.0.conv1.weight" in lgm else next(
        k for k in lgm if k.endswith("conv2.weight"))
    lgm_cases = {
        "int": ({conv: lgm[conv].to(torch.int16)}, ["not floating-point", conv, "int16"]),
        "shape": ({conv: lgm[conv][:, :1].contiguous()}, ["with other shapes", conv]),
    }
    for name, (change, fragments) in lgm_cases.items():
        path = tmp_path / "physmotion" / "lgm" / f"{name}.safetensors"
        save_file({**lgm, **change}, str(path))
        with pytest.raises(InputError) as err:
            load_lgm(path.name, input_size=64)
        for frag in [path.name, *fragments]:
            assert frag in str(err.value), (name, frag, str(err.value))


# ----------------------------------------------------------------------------------------------
# Nodes: empty batches, a NUL byte in a file name prefix
# ----------------------------------------------------------------------------------------------


def test_nodes_refuse_empty_batches_and_nul_bytes_clearly():
    from comfy_harness import load_pack

    nodes = load_pack().NODE_CLASS_MAPPINGS
    img, mask = torch.rand(1, 32, 32, 3), torch.ones(1, 32, 32)
    empty_img, empty_mask = torch.zeros(0, 32, 32, 3), torch.zeros(0, 32, 32)
    calls = [
        lambda: nodes["PhysMotionSegment"]().run(empty_img, "auto", "auto", 1),
        lambda: nodes["PhysMotionSegment"]().run(img, "mask", "auto", 1, mask=empty_mask),
        lambda: nodes["PhysMotionSilhouetteLift"]().run(empty_img, mask, 0.3, 40.0, 1.0, 1000, True),
        lambda: nodes["PhysMotionSilhouetteLift"]().run(img, empty_mask, 0.3, 40.0, 1.0, 1000, True),
        lambda: nodes["PhysMotionSAMSegment"]().run(None, empty_img, "", "", "pixels", True),
        lambda: nodes["PhysMotionSaveVideo"]().run(empty_img, 24.0, "PhysMotion/x", 18),
        lambda: nodes["PhysMotionForce"]().run(1.0, 0.0, 0.0, "mask", 0, 0, 5.0, -1, 0.0, 0.2,
                                               region_mask=empty_mask),
        lambda: nodes["PhysMotionAnchor"]().run("mask", 0, 0, 5.0, -1, region_mask=torch.zeros(1, 0, 0)),
        # the batch is checked before the model is touched, so no model is needed here
        lambda: nodes["PhysMotionDepth"]().run(None, empty_img),
        lambda: nodes["PhysMotionDepth"]().run(None, img, mask=empty_mask),
        lambda: nodes["PhysMotionLoRAPersonalize"]().run(None, empty_img, "a sks cup", 10, 1e-4, 4, 64, 0, 1.0),
        lambda: nodes["PhysMotionDDIMInvert"]().run(None, empty_img, img, "a cup", 10, 64, 0, 100, 200, 1.0, 1.0, 4),
    ]
    for i, call in enumerate(calls):
        with pytest.raises(InputError, match="empty|0 pixels|pixels"):
            call()
    from physmotion_core.types import Gaussians

    g = Gaussians(means=torch.zeros(2, 3), quats=torch.tensor([[1.0, 0, 0, 0]] * 2), scales=torch.full((2, 3), 0.01),
                  opacities=torch.full((2,), 0.5), sh=torch.zeros(2, 1, 3))
    for prefix in ("PhysMotion/a\x00b", "bad\nname"):
        with pytest.raises(InputError, match="NUL byte or a control character"):
            nodes["PhysMotionSaveGaussians"]().run(g, prefix)
    with pytest.raises(InputError, match="255 bytes"):
        nodes["PhysMotionSaveGaussians"]().run(g, "PhysMotion/" + "n" * 250)


# ----------------------------------------------------------------------------------------------
# Signals and Cancel: clean messages and exit codes, no debris, no half-complete folders
# ----------------------------------------------------------------------------------------------


def _sigint_as_a_terminal_gives_it():
    # A shell without job control starts background commands with SIGINT ignored, and children
    # inherit that (Python then installs no KeyboardInterrupt handler): give the child the default
    # disposition a user's terminal gives, whatever started the test run.
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _child(code: str, tmp_path: Path, timeout: float = 180) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env,
                          timeout=timeout, preexec_fn=_sigint_as_a_terminal_gives_it)


def test_ctrl_c_during_start_up_exits_130_without_a_traceback(tmp_path):
    # A real SIGINT, delivered while the parser is being built (the heavy imports happen there).
    code = ("import os, signal, sys\n"
            "import physmotion_core.cli as cli\n"
            "real = cli._build_parser\n"
            "def build():\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    return real()\n"
            "cli._build_parser = build\n"
            "sys.exit(cli.main(['generate', 'photo.png']))\n")
    out = _child(code, tmp_path)
    assert out.returncode == 130, out.stderr
    assert "interrupted" in out.stderr and "Traceback" not in out.stderr


def test_sigterm_during_encoding_leaves_no_temporary_file(cutout, tmp_path):
    # A real SIGTERM, delivered while the second frame is being encoded.
    code = ("import os, signal, sys\n"
            "import av\n"
            "real = av.VideoFrame.from_ndarray\n"
            "n = [0]\n"
            "def frame(*a, **k):\n"
            "    n[0] += 1\n"
            "    if n[0] == 2:\n"
            "        os.kill(os.getpid(), signal.SIGTERM)\n"
            "    return real(*a, **k)\n"
            "av.VideoFrame.from_ndarray = staticmethod(frame)\n"
            "from physmotion_core.cli import main\n"
            f"sys.exit(main(['generate', {str(cutout)!r}, '--frames', '2', '--grid-res', '6', '-q', "
            "'-o', 'out/clip.mp4', '--stats', 'out/stats.json']))\n")
    out = _child(code, tmp_path)
    assert out.returncode == 143, out.stderr
    assert "terminated" in out.stderr and "Traceback" not in out.stderr
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == []  # no clip, no .tmp, no stats


def test_cancel_during_a_gaussian_sequence_leaves_no_folder_that_looks_complete(tmp_path):
    from physmotion_core.ply import read_ply, write_ply_sequence
    from physmotion_core.types import Gaussians

    class Trajectory:  # the two members write_ply_sequence reads from a SimResult
        num_frames = 6

        def gaussians_at(self, k):
            return Gaussians(means=torch.full((4, 3), float(k)), quats=torch.tensor([[1.0, 0, 0, 0]] * 4),
                             scales=torch.full((4, 3), 0.01), opacities=torch.full((4,), 0.5), sh=torch.zeros(4, 1, 3))

    def cancel_at_3(done, total):
        if done == 3:
            raise Interrupted("cancelled")

    target = tmp_path / "seq_00001_"
    with pytest.raises(Interrupted):
        write_ply_sequence(target, Trajectory(), progress=cancel_at_3)
    assert list(tmp_path.iterdir()) == []  # neither the folder nor a hidden partial one
    files = write_ply_sequence(target, Trajectory())
    assert [p.name for p in sorted(target.iterdir())] == [f"frame_{k:05d}.ply" for k in range(6)] == \
        [p.name for p in files]
    assert float(read_ply(files[-1]).means[0, 0]) == 5.0
    # Rewriting an existing sequence replaces it whole; a Cancel then keeps the old one intact.
    with pytest.raises(Interrupted):
        write_ply_sequence(target, Trajectory(), every=2, progress=lambda d, t: (_ for _ in ()).throw(Interrupted()))
    assert len(list(target.iterdir())) == 6 and sorted(p.name for p in tmp_path.iterdir()) == ["seq_00001_"]
    with atomic_folder(target) as tmp:
        (tmp / "only.txt").write_text("new")
    assert [p.name for p in target.iterdir()] == ["only.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["seq_00001_"]  # the old copy is gone too


# ----------------------------------------------------------------------------------------------
# Memory: the up-front estimate covers the measured peaks
# ----------------------------------------------------------------------------------------------


def test_the_memory_estimate_covers_the_documented_measurements():
    from physmotion_core.memory import pipeline_need_bytes

    text = (ROOT / "docs" / "reliability.md").read_text()
    section = re.search(r"<!-- BEGIN memory -->(.*?)<!-- END memory -->", text, re.S)
    assert section, "docs/reliability.md has no memory section (run benchmarks/bench_memory.py)"
    rows = json.loads(re.search(r"```json\n(.*?)\n```", section.group(1), re.S).group(1))
    assert len(rows) >= 4
    for r in rows:
        est = pipeline_need_bytes(r["width"], r["height"], r["frames"])
        assert r["need"] <= est <= 2.0 * r["need"], r  # covers the peak, with a margin, not wildly over


def test_the_memory_estimate_covers_a_measured_run(tmp_path):
    """A moderate run measured here, in a fresh process: peak RSS (VmHWM, reset after the imports)
    minus the RSS before the run must stay under the estimate."""
    code = ("import cv2, numpy as np, json\n"
            "from physmotion_core.pipeline import generate\n"
            "from physmotion_core.types import SimSettings\n"
            "import physmotion_core.lift, physmotion_core.render.frames, physmotion_core.segment, physmotion_core.sim\n"
            "h, w = 120, 160\n"
            "img = np.zeros((h, w, 4), np.uint8); img[..., :3] = 150\n"
            "yy, xx = np.mgrid[0:h, 0:w]; img[..., 3] = np.where((xx-80)**2 + (yy-60)**2 < 40**2, 255, 0)\n"
            "cv2.imwrite('c.png', img)\n"
            "def st(k):\n"
            "    return next(int(l.split()[1]) * 1024 for l in open('/proc/self/status') if l.startswith(k + ':'))\n"
            "open('/proc/self/clear_refs', 'w').write('5')\n"
            "before = st('VmRSS')\n"
            "generate('c.png', settings=SimSettings(frames=2, grid_res=8, device='cpu'), max_side=0, models='none',"
            " output='c.mp4')\n"
            "print(json.dumps({'need': st('VmHWM') - before}))\n")
    out = _child(code, tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    from physmotion_core.memory import pipeline_need_bytes

    need = json.loads(out.stdout.strip().splitlines()[-1])["need"]
    assert 0 < need <= pipeline_need_bytes(160, 120, 2)
