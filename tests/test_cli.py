"""The `physmotion generate` command end to end, checked on the decoded mp4."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

from physmotion_core.cli import main
from physmotion_core.video import read_video


@pytest.fixture
def red_ball_png(tmp_path):
    """A red disk on a grey background, with an alpha channel marking the disk (RGBA PNG)."""
    h, w = 120, 160
    img = np.full((h, w, 4), 128, np.uint8)
    yy, xx = np.mgrid[0:h, 0:w]
    disk = (xx - 70) ** 2 + (yy - 55) ** 2 <= 22**2
    img[disk, :3] = (20, 20, 220)  # BGR red
    img[..., 3] = np.where(disk, 255, 0)
    path = tmp_path / "ball.png"
    cv2.imwrite(str(path), img)
    return path


def _red_centroids(video):
    red = (video[..., 0].astype(int) - video[..., 1].astype(int)) > 100
    ys, xs = np.mgrid[0:video.shape[1], 0:video.shape[2]]
    return np.array([[xs[r].mean(), ys[r].mean()] for r in red]), red.sum(axis=(1, 2))


def test_generate_writes_a_playable_mp4_whose_object_follows_force_and_gravity(red_ball_png, tmp_path):
    out = tmp_path / "out" / "ball.mp4"
    stats = tmp_path / "stats.json"
    code = main(["generate", str(red_ball_png), "--material", "rubber", "--force", "40,0,0",
                 "--ground", "none", "--frames", "10", "--fps", "60", "--grid-res", "10",
                 "-o", str(out), "--stats", str(stats), "-q"])
    assert code == 0
    video, fps = read_video(out)
    assert video.shape == (10, 120, 160, 3)
    assert fps == pytest.approx(60.0)
    c, area = _red_centroids(video)
    assert area.min() > 0.8 * area[0]  # the ball stays in view
    dx, dy = c[-1] - c[0]
    assert dx > 2.0, f"the +x force should move the ball right; moved {dx:.2f}px"
    assert dy > 2.0, f"gravity should move the ball down the image; moved {dy:.2f}px"
    # Both grow faster than linearly (constant accelerations from rest).
    assert c[-1, 0] - c[5, 0] > c[5, 0] - c[0, 0]
    assert c[-1, 1] - c[5, 1] > c[5, 1] - c[0, 1]
    info = json.loads(stats.read_text())
    assert info["frames"] == 10 and info["simulation"]["substeps"] > 10


def test_generate_reports_bad_input_without_a_traceback(red_ball_png, tmp_path, capsys):
    code = main(["generate", str(red_ball_png), "--force", "1,0,0", "--at", "5,5", "--frames", "3",
                 "--grid-res", "8", "-o", str(tmp_path / "x.mp4"), "-q"])
    assert code == 2
    err = capsys.readouterr().err
    assert "does not touch the object" in err and "its mask spans" in err and "Traceback" not in err
    assert not (tmp_path / "x.mp4").exists()
    assert main(["generate", str(tmp_path / "missing.png"), "-q", "-o", str(tmp_path / "y.mp4")]) == 2
    assert "missing.png" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["generate", str(red_ball_png), "--force", "1,2"])


def test_console_script_is_installed():
    out = subprocess.run([sys.executable, "-m", "physmotion_core.cli", "generate", "--help"],
                         capture_output=True, text=True, check=True)
    assert "--force" in out.stdout and "--material" in out.stdout


def test_same_inputs_give_bit_identical_frames_on_cpu(red_ball_png):
    # Determinism (issue 9): Warp's CPU kernels run on one thread, so the atomic scatter adds in a
    # fixed order; the fill, lift and rasterizer are deterministic on CPU. Two runs must agree to
    # the last bit, before encoding (the mp4 encoder is deterministic too, but lossy).
    from physmotion_core.pipeline import generate
    from physmotion_core.types import Conditions, Force, SimSettings

    def run():
        res = generate(str(red_ball_png), material="jelly", conditions=Conditions([Force((5.0, 0.0, 0.0))]),
                       settings=SimSettings(frames=4, fps=30, grid_res=8, device="cpu"), max_gaussians=4000)
        return res.frames, res.sim.x

    (f1, x1), (f2, x2) = run(), run()
    assert torch.equal(x1, x2)
    assert torch.equal(f1, f2)
    assert float((f1[-1] - f1[0]).abs().max()) > 0.05  # and the object did move


# -- issue 33: prompts, preview, parity with the nodes ----------------------------------------------


def _captured_generate(monkeypatch):
    import physmotion_core.pipeline as pipeline

    seen = {}

    def fake(image, **kw):
        seen.update(kw)
        seen["image"] = image
        raise SystemExit(0)  # stop before any work: only what reached generate() matters here

    monkeypatch.setattr(pipeline, "generate", fake)
    return seen


def test_generate_passes_every_prompt_and_condition_flag(red_ball_png, tmp_path, monkeypatch):
    from physmotion_core.types import Force, InitialVelocity, Torque

    seen = _captured_generate(monkeypatch)
    with pytest.raises(SystemExit):
        main(["generate", str(red_ball_png), "-o", str(tmp_path / "o.mp4"), "--object-point", "70,55",
              "--object-point", "75,60", "--background-point", "5,5", "--box", "40,30,100,90",
              "--quality", "draft", "--velocity", "-0.5,1,0", "--spin", "0,0,3",
              "--torque", "0,0.2,0", "--torque-at", "70,55", "--torque-time", "0.1,0.3",
              "--force", "-2,0,0", "--no-hold-edges", "--object-height", "1.5", "--texture", "splat"])
    assert seen["object_points"] == [(70.0, 55.0), (75.0, 60.0)]
    assert seen["background_points"] == [(5.0, 5.0)]
    assert seen["box"] == (40.0, 30.0, 100.0, 90.0)
    assert seen["settings"].quality == "draft"
    assert seen["hold_edges"] is False and seen["object_height"] == 1.5 and seen["preview"] is False
    assert seen["texture"] == "splat"
    conds = seen["conditions"]
    (tq,) = conds.of(Torque)
    assert tq.vector == (0.0, 0.2, 0.0) and (tq.t_start, tq.t_end) == (0.1, 0.3)
    assert tq.region.kind == "image" and tq.region.points == ((70.0, 55.0),)
    (iv,) = conds.of(InitialVelocity)
    assert iv.velocity == (-0.5, 1.0, 0.0) and iv.angular_velocity == (0.0, 0.0, 3.0)
    (f,) = conds.of(Force)
    assert f.vector == (-2.0, 0.0, 0.0)


@pytest.mark.parametrize("argv, words", [
    (["--box", "1,2,3"], "--box must be 4"),
    (["--object-point", "1"], "--object-point must be 2"),
    (["--torque-at", "3,4"], "--torque-at needs a matching --torque"),
    (["--torque-time", "0,1"], "no --torque is given"),
    (["--spin", "1,2"], "--spin must be 3"),
])
def test_bad_prompt_and_condition_flags_are_refused_clearly(red_ball_png, tmp_path, capsys, argv, words):
    with pytest.raises(SystemExit) as exc:
        code = main(["generate", str(red_ball_png), "-o", str(tmp_path / "o.mp4"), "-q", *argv])
        raise SystemExit(code)
    assert exc.value.code == 2
    assert words in capsys.readouterr().err


def test_a_closed_pipe_ends_the_listing_quietly(tmp_path):
    """`physmotion batch SPEC --list | head -1`: the reader leaves early; no disk-space error, exit 0."""
    spec = tmp_path / "spec.toml"
    ball = (__import__("pathlib").Path(__file__).resolve().parent.parent / "photos" / "ball.png")
    spec.write_text(f'[batch]\nimages = ["{ball}"]\n[defaults]\nframes = 2\n[axes]\n'
                    f'seed = {list(range(1, 3001))}\n')
    proc = subprocess.Popen([sys.executable, "-m", "physmotion_core.cli", "batch", str(spec), "--list"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    first = proc.stdout.readline()
    proc.stdout.close()  # like `head -1`
    err = proc.stderr.read().decode()
    rc = proc.wait(timeout=120)
    assert first.startswith(b"#")
    assert rc == 0, err
    assert "free space" not in err and "Traceback" not in err


def test_warps_no_driver_line_is_hidden_by_the_cli_and_other_lines_pass(capfd):
    """Warp's C library writes "Could not find or load the NVIDIA CUDA driver" to the process's stderr on every
    start without a GPU; the CLI hides that line (it is said at INFO) and lets anything else Warp writes
    through; outside the CLI (ComfyUI shares its stderr with other threads) nothing is caught."""
    import os
    from types import SimpleNamespace

    from physmotion_core import warp_build

    def fake_init():
        os.write(2, b"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution will not be "
                    b"available.\nWarp: something else worth seeing\n")

    wp = SimpleNamespace(config=SimpleNamespace(quiet=False), init=fake_init)
    warp_build.init_warp(wp)
    err = capfd.readouterr().err
    assert "NVIDIA CUDA driver" in err and "something else" in err
    warp_build.hide_no_driver_warning()
    try:
        warp_build.init_warp(wp)
    finally:
        warp_build.hide_no_driver_warning(False)
    err = capfd.readouterr().err
    assert "NVIDIA CUDA driver" not in err and "Warp: something else worth seeing" in err


def test_a_cli_run_on_a_cpu_machine_prints_no_warp_driver_warning(red_ball_png, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "physmotion_core.cli", "generate", str(red_ball_png), "--preview",
                           "--models", "none", "--grid-res", "8"], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "preview: stopped before simulating" in proc.stdout + proc.stderr
    assert "Could not find or load the NVIDIA CUDA driver" not in proc.stderr
    assert "lifted as a ball" in proc.stdout + proc.stderr  # a disk: the user is told how it was read
