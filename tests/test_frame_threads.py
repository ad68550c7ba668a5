"""Several frames rendered at once on the CPU (render.frames.run_frame_blocks): the same frames, flow and tracks
as one frame at a time, progress one step per frame, Cancel and a worker's error stop the render and leave
torch's thread count as it was."""

from __future__ import annotations

import threading
import time

import pytest
import torch

from physmotion_core import controls as C
from physmotion_core.render.frames import frame_threads, render_frames, run_frame_blocks
from test_controls import camera, cube_sim


@pytest.fixture
def two_threads(monkeypatch):
    before = torch.get_num_threads()
    monkeypatch.setenv("PHYSMOTION_RENDER_THREADS", "2")
    yield
    torch.set_num_threads(before)


def test_frame_threads_follow_the_setting(monkeypatch):
    monkeypatch.setenv("PHYSMOTION_RENDER_THREADS", "3")
    assert frame_threads(10, torch.device("cpu")) == 3
    assert frame_threads(2, torch.device("cpu")) == 2  # never more than the frames
    assert frame_threads(1, torch.device("cpu")) == 1
    assert frame_threads(10, torch.device("meta")) == 1  # off the CPU a frame fills the device
    monkeypatch.setenv("PHYSMOTION_RENDER_THREADS", "1")
    assert frame_threads(10, torch.device("cpu")) == 1


def test_frames_flow_and_tracks_match_one_frame_at_a_time(two_threads, monkeypatch):
    sim = C.resample_simulation(cube_sim(frames=24), 16.0, 13)
    cam = camera(96, 64)
    steps = []
    par = render_frames(sim, cam, progress=lambda d, n: steps.append((d, n)))
    assert steps == [(k, 13) for k in range(1, 14)]
    par_clip, par_flow = C.render_clip(sim, cam, flow="forward")
    par_tracks, _ = C.probe_tracks(sim, cam, 24, background_points=2)
    monkeypatch.setenv("PHYSMOTION_RENDER_THREADS", "1")
    seq = render_frames(sim, cam)
    seq_clip, seq_flow = C.render_clip(sim, cam, flow="forward")
    seq_tracks, _ = C.probe_tracks(sim, cam, 24, background_points=2)
    for a, b in ((par.rgb, seq.rgb), (par.alpha, seq.alpha), (par.depth, seq.depth), (par_clip.rgb, seq_clip.rgb),
                 (par_flow.flow, seq_flow.flow)):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=0)
    assert torch.equal(par_flow.valid, seq_flow.valid) and float(par.alpha.amax()) > 0.5
    assert torch.equal(par_tracks.visible, seq_tracks.visible) and torch.equal(par_tracks.uv, seq_tracks.uv)


def test_frames_render_at_once_under_inference_mode(two_threads):
    """ComfyUI runs nodes under torch.inference_mode(), which is per thread: the clip's tensors are then inference
    tensors, which the workers can fill only inside it too."""
    sim = C.resample_simulation(cube_sim(frames=12), 16.0, 9)
    cam = camera(64, 48)
    with torch.inference_mode():
        frames = render_frames(sim, cam)
        clip, flow = C.render_clip(sim, cam, flow="backward")
    torch.testing.assert_close(frames.rgb, clip.rgb, atol=2e-6, rtol=0)
    assert float(frames.alpha.amax()) > 0.5 and bool(flow.valid.any())


def test_cancel_stops_every_worker_and_restores_torch_threads():
    torch.set_num_threads(2)
    rendered, names = [], set()
    lock = threading.Lock()

    def work(a, b, done):
        for k in range(a, b):
            time.sleep(0.02)  # a frame's render
            with lock:
                rendered.append(k)
                names.add(threading.current_thread().name)
            done(k)

    class Cancelled(Exception):
        pass

    def progress(d, n):
        if d == 3:
            raise Cancelled

    with pytest.raises(Cancelled):
        run_frame_blocks(40, 2, work, progress)
    assert len(rendered) < 20 and len(names) == 2 and torch.get_num_threads() == 2
    assert not [t for t in threading.enumerate() if t.name.startswith("physmotion-render")]


def test_a_workers_error_reaches_the_caller():
    torch.set_num_threads(2)

    def work(a, b, done):
        for k in range(a, b):
            if k == 7:
                raise ValueError("frame 7 is broken")
            done(k)

    with pytest.raises(ValueError, match="frame 7"):
        run_frame_blocks(10, 2, work)
    assert torch.get_num_threads() == 2
