"""Cancel mid-loop, then run again: the next run must equal an uninterrupted one (nothing left
half-done in module state, models or files). And cache files are trusted only after their content
digest is verified: a damaged cache is recomputed and replaced, never used.

Cancel is what ComfyUI does through the progress callback (it raises); the latency bound is 1 s
(docs/reliability.md, "Interruption"; README.md: "stop within a second on Cancel"), measured from the
moment cancel is requested to the moment the exception reaches the caller.
"""

from __future__ import annotations

import logging
import threading
import time

import pytest
import torch

from physmotion_core.errors import Interrupted


class Canceller:
    """A progress callback that raises once ``cancel()`` was called (like ComfyUI's Cancel)."""

    def __init__(self, after_calls=None, after_seconds=None):
        self.calls = 0
        self.requested_at = None
        self.after_calls = after_calls
        if after_seconds is not None:
            threading.Timer(after_seconds, self.cancel).start()

    def cancel(self):
        if self.requested_at is None:
            self.requested_at = time.perf_counter()

    def __call__(self, done, total, *rest):
        self.calls += 1
        if self.after_calls is not None and self.calls >= self.after_calls:
            self.cancel()
        if self.requested_at is not None:
            raise Interrupted("cancelled")


def _block(n=6, size=0.1):
    from physmotion_core.types import Gaussians

    ax = torch.linspace(-size / 2, size / 2, n)
    g = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    g[:, 1] += size / 2 + 0.02
    return Gaussians.from_rgb(g, torch.full((len(g), 3), 0.5), torch.full((len(g), 3), size / n / 2),
                              torch.full((len(g),), 0.9))


def test_cancelled_simulation_stops_within_a_second_and_the_next_run_is_exact():
    from physmotion_core.sim import simulate
    from physmotion_core.types import Conditions, Force, Ground, Material, SimSettings

    conds = Conditions([Force((2.0, 0, 0), t_start=0.0, t_end=0.1), Ground(0.0)])
    # 3 frames: over a thousand substeps (7 s on the 2-core CI-class VM), far longer than the 0.3 s before
    # the cancel.
    st = SimSettings(frames=3, grid_res=10, device="cpu")
    reference = simulate(_block(), Material.preset("rubber"), conds, st)
    stopper = Canceller(after_seconds=0.3)
    t0 = time.perf_counter()
    with pytest.raises(Interrupted):
        simulate(_block(), Material.preset("rubber"), conds, st, progress=stopper)
    stopped = time.perf_counter()
    assert stopper.requested_at is not None and stopped - stopper.requested_at < 1.0
    assert stopped - t0 < reference.stats["wall_time_s"]  # it really stopped early
    again = simulate(_block(), Material.preset("rubber"), conds, st)
    assert torch.equal(again.x, reference.x) and again.stats["substeps"] == reference.stats["substeps"]


def test_cancelled_refinement_leaves_the_input_and_the_next_run_unchanged():
    from physmotion_core.refine import RefineSettings, RefineView, refine_gaussians
    from physmotion_core.render.rasterize import rasterize
    from physmotion_core.types import Camera

    g = _block(n=8)
    cam = Camera.look_at((0.0, 0.07, 0.5), (0.0, 0.07, 0.0), width=48, height=48, fov_y_deg=30)
    target = rasterize(g, cam)
    views = [RefineView(camera=cam, image=target.rgb.clamp(0, 1), mask=(target.alpha > 0.5).float(), colour=True)]
    start = g.detach()
    start.means = start.means + 0.003 * torch.randn(start.means.shape, generator=torch.Generator().manual_seed(0))
    before = start.means.clone()
    st = RefineSettings(iterations=30, max_render_side=48, seed=0)
    reference = refine_gaussians(start, views, st)
    with pytest.raises(Interrupted):
        refine_gaussians(start, views, st, progress=Canceller(after_calls=10))
    assert torch.equal(start.means, before)  # the caller's Gaussians are never modified
    again = refine_gaussians(start, views, st)
    assert torch.equal(again.gaussians.means, reference.gaussians.means)


@pytest.fixture(scope="module")
def tiny_sd(tmp_path_factory):
    from physmotion_core.enhance import load_diffusion
    from tiny_sd21 import TINY_NAMES, build_tiny_models_root

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("sd")
    build_tiny_models_root(root, seed=0)
    models = load_diffusion(TINY_NAMES["diffusers"], controlnet_depth=TINY_NAMES["controlnet_depth"],
                            controlnet_canny=TINY_NAMES["controlnet_canny"], root=root, device="cpu")
    yield models, root
    torch.set_num_threads(n)


def _clip(frames=3, size=64):
    g = torch.Generator().manual_seed(0)
    base = torch.rand(frames, 3, size // 8, size // 8, generator=g)
    img = torch.nn.functional.interpolate(base, size=(size, size), mode="bilinear", align_corners=False)
    depth = torch.linspace(0.2, 0.9, size)[None, :, None].expand(frames, size, size).contiguous()
    return img.permute(0, 2, 3, 1).contiguous(), depth


def test_cancelled_inversion_and_sampling_leave_the_next_run_exact(tiny_sd):
    from physmotion_core.enhance import SampleSettings, invert_frames, keyframe_shared_sample

    models, _ = tiny_sd
    frames, depth = _clip()
    processors = dict(models.unet.attn_processors)
    inv = invert_frames(models, frames, depth, prompt="a cube", steps=4, resolution=64)
    st = SampleSettings(prompt="a cube", keyframe_interval=2, output_size="diffusion")
    reference = keyframe_shared_sample(models, inv, st)
    with pytest.raises(Interrupted):
        invert_frames(models, frames, depth, prompt="a cube", steps=4, resolution=64, progress=Canceller(2))
    with pytest.raises(Interrupted):
        keyframe_shared_sample(models, inv, st, progress=Canceller(2))
    # The sampler's attention processors and hooks are gone again after the cancel.
    assert {k: type(v) for k, v in models.unet.attn_processors.items()} == {k: type(v) for k, v in processors.items()}
    inv2 = invert_frames(models, frames, depth, prompt="a cube", steps=4, resolution=64)
    assert torch.equal(inv2.latents, inv.latents)
    again = keyframe_shared_sample(models, inv2, st)
    assert torch.equal(again.latents, reference.latents)


def _flip_a_data_byte(path):
    """Damage a tensor byte but keep the safetensors header valid (the file still parses)."""
    import json
    import struct

    raw = bytearray(path.read_bytes())
    header_len = struct.unpack("<Q", raw[:8])[0]
    header = json.loads(raw[8:8 + header_len])
    name = next(k for k in header if k != "__metadata__")
    start = 8 + header_len + header[name]["data_offsets"][0]
    raw[start + 3] ^= 0x40
    path.write_bytes(bytes(raw))


def test_a_damaged_inversion_cache_is_recomputed_not_trusted(tiny_sd, tmp_path, caplog):
    from physmotion_core.enhance import invert_frames

    models, _ = tiny_sd
    frames, depth = _clip()
    first = invert_frames(models, frames, depth, prompt="a cube", steps=3, resolution=64, cache_dir=tmp_path)
    (cache,) = list(tmp_path.glob("inversion_*.safetensors"))
    hit = invert_frames(models, frames, depth, prompt="a cube", steps=3, resolution=64, cache_dir=tmp_path,
                        progress=Canceller(after_calls=2))  # a cache hit reports once: no cancel fires
    assert "loaded from the inversion cache" in hit.notes and torch.equal(hit.latents, first.latents)
    _flip_a_data_byte(cache)
    with caplog.at_level(logging.WARNING):
        redo = invert_frames(models, frames, depth, prompt="a cube", steps=3, resolution=64, cache_dir=tmp_path)
    assert any("ignoring unreadable cache file" in r.message and "damaged" in r.message for r in caplog.records)
    assert "loaded from the inversion cache" not in redo.notes
    assert torch.equal(redo.latents, first.latents)
    again = invert_frames(models, frames, depth, prompt="a cube", steps=3, resolution=64, cache_dir=tmp_path)
    assert "loaded from the inversion cache" in again.notes  # the replaced file verifies


def test_a_damaged_lora_cache_is_retrained_not_trusted(tiny_sd, tmp_path, caplog):
    from physmotion_core.enhance import LoraSettings, personalize
    from physmotion_core.fsutil import load_verified_safetensors

    models, _ = tiny_sd
    images, _ = _clip(frames=2)
    st = LoraSettings(steps=2, learning_rate=1e-3, resolution=64)
    first = personalize(models, list(images), settings=st, folder=tmp_path)
    assert first.trained
    assert not personalize(models, list(images), settings=st, folder=tmp_path).trained  # verified cache hit
    good, _ = load_verified_safetensors(first.path)
    _flip_a_data_byte(first.path)
    with pytest.raises(ValueError, match="damaged"):
        load_verified_safetensors(first.path)
    with caplog.at_level(logging.WARNING):
        redo = personalize(models, list(images), settings=st, folder=tmp_path)
    assert redo.trained and any("training again" in r.message for r in caplog.records)
    fixed, _ = load_verified_safetensors(redo.path)
    assert all(torch.equal(fixed[k], good[k]) for k in good)  # same seed: the same adapter again
