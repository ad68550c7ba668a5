"""Reliability and security: bad weights, path traversal, pickles, atomic output.

Every case asserts the library's own error type (InputError / MissingModelError), a message that
names the input and the fix, and that nothing outside the intended folders is touched.
"""

from __future__ import annotations

import os
import pickle

import pytest
import torch
from safetensors.torch import save_file

from physmotion_core.errors import InputError, MissingModelError
from physmotion_core.models import load_state_dict_file, resolve_model_dir, resolve_weight_file


class _Payload:
    """A pickle that runs code when unpickled (what a malicious .pth would carry)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture
def root(tmp_path, monkeypatch):
    r = tmp_path / "models"
    (r / "sams").mkdir(parents=True)
    (r / "physmotion" / "depth" / "dpt").mkdir(parents=True)
    (r / "physmotion" / "depth" / "dpt" / "config.json").write_text("{}")
    monkeypatch.setenv("PHYSMOTION_MODELS", str(r))
    monkeypatch.delenv("PHYSMOTION_ALLOW_PICKLE", raising=False)
    return r


def test_model_names_cannot_climb_out_of_the_model_folder(root, tmp_path):
    secret = tmp_path / "secret.safetensors"
    save_file({"w": torch.zeros(1)}, str(secret))
    for name in ("../../secret.safetensors", "../secret.safetensors", "sub/../../../secret.safetensors"):
        with pytest.raises(InputError, match="no absolute paths, no '..'"):
            resolve_weight_file("sams", name, expected="a SAM .pth")
    with pytest.raises(InputError, match="no absolute paths, no '..'"):
        resolve_model_dir("depth", "../../../", expected="a transformers folder")
    # Names inside the folder resolve; an absolute path is the library caller's own choice.
    save_file({"w": torch.zeros(1)}, str(root / "sams" / "ok.safetensors"))
    assert resolve_weight_file("sams", "ok.safetensors", expected="x") == root / "sams" / "ok.safetensors"
    assert resolve_weight_file("sams", str(secret), expected="x") == secret
    assert resolve_model_dir("depth", "dpt", expected="x", required=["config.json"]).name == "dpt"


def test_node_model_paths_refuse_traversal_and_absolute_names(root, tmp_path):
    from nodes._util import model_path

    (tmp_path / "elsewhere.pth").write_bytes(b"x")
    for name in ("../../elsewhere.pth", str(tmp_path / "elsewhere.pth")):
        with pytest.raises((InputError, MissingModelError)):
            model_path("sams", name, expected="a SAM .pth")


def test_pickles_outside_the_model_folders_need_an_opt_in(root, tmp_path, monkeypatch):
    outside = tmp_path / "download.pth"
    torch.save({"w": torch.ones(2)}, outside)
    with pytest.raises(InputError, match="pickled checkpoint outside the model folders.*allow_pickle"):
        load_state_dict_file(outside)
    assert torch.equal(load_state_dict_file(outside, allow_pickle=True)["w"], torch.ones(2))
    monkeypatch.setenv("PHYSMOTION_ALLOW_PICKLE", "1")
    assert torch.equal(load_state_dict_file(outside)["w"], torch.ones(2))
    monkeypatch.delenv("PHYSMOTION_ALLOW_PICKLE")
    inside = root / "sams" / "model.pth"
    torch.save({"w": torch.ones(3)}, inside)
    assert load_state_dict_file(inside)["w"].shape == (3,)  # a model folder: no opt-in needed


def test_a_malicious_pickle_is_refused_and_runs_nothing(root, tmp_path):
    marker = tmp_path / "pwned"
    evil = root / "sams" / "evil.pth"
    with open(evil, "wb") as f:
        pickle.dump({"w": _Payload(marker)}, f)
    with pytest.raises(InputError, match="Could not read weights"):
        load_state_dict_file(evil)
    # Even with the opt-in, weights_only=True refuses to call anything.
    with pytest.raises(InputError, match="Could not read weights"):
        load_state_dict_file(evil, allow_pickle=True)
    assert not marker.exists()


def test_truncated_corrupt_and_wrong_format_weights_give_clear_errors(root):
    good = root / "sams" / "good.safetensors"
    save_file({"w": torch.randn(64, 64)}, str(good))
    data = good.read_bytes()
    cases = {
        "truncated.safetensors": data[: len(data) // 2],
        "garbage.safetensors": os.urandom(4096),
        "text.safetensors": b"<html>404 Not Found</html>",
        "truncated.pth": None,
        "empty.pth": b"",
    }
    buf = root / "sams" / "full.pth"
    torch.save({"w": torch.randn(64, 64)}, buf)
    cases["truncated.pth"] = buf.read_bytes()[:300]
    for name, payload in cases.items():
        p = root / "sams" / name
        p.write_bytes(payload)
        with pytest.raises(InputError) as err:
            load_state_dict_file(p)
        msg = str(err.value)
        assert str(p) in msg and ("truncated" in msg or "not a checkpoint" in msg), msg
    # Not a state dict at all (a pickled list of tensors).
    odd = root / "sams" / "list.pth"
    torch.save([torch.zeros(1)], odd)
    with pytest.raises(InputError, match="does not hold a state dict"):
        load_state_dict_file(odd)
    with pytest.raises(MissingModelError, match="not found"):
        load_state_dict_file(root / "sams" / "absent.safetensors")


def test_an_interrupted_write_leaves_the_previous_file_and_no_debris(tmp_path, monkeypatch):
    """A Cancel (KeyboardInterrupt) or crash while a video is being encoded: the previous video
    stays byte-identical, and no temporary file is left beside it."""
    import av

    from physmotion_core.video import read_video, write_mp4

    target = tmp_path / "clip.mp4"
    frames = torch.rand(6, 32, 48, 3)
    write_mp4(target, frames, fps=12)
    before = target.read_bytes()
    real = av.VideoFrame.from_ndarray
    calls = {"n": 0}

    def dying(*a, **kw):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt  # Cancel mid-encode
        return real(*a, **kw)

    monkeypatch.setattr(av.VideoFrame, "from_ndarray", staticmethod(dying))
    with pytest.raises(KeyboardInterrupt):
        write_mp4(target, torch.rand(6, 32, 48, 3), fps=12)
    monkeypatch.undo()
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4"]
    video, fps = read_video(target)
    assert video.shape == (6, 32, 48, 3) and fps == pytest.approx(12)


def test_node_weights_must_fit_on_the_gpu_or_the_node_refuses(monkeypatch):
    """Before a model moves to the GPU: ComfyUI is asked for room, then weights that still do not fit
    are refused with the sizes (instead of an out-of-memory traceback mid-move)."""
    import nodes._util as util
    from physmotion_core import memory

    monkeypatch.setattr(memory, "device_available_bytes", lambda dev: 2 << 30)
    with pytest.raises(InputError, match=r"LGM Lift.*needs about 3.0 GiB of GPU memory; 2.0 GiB is available now and a run may use at most 95%"):
        util.free_memory_for(3 << 30, torch.device("cuda", 0), "LGM Lift")
    util.free_memory_for(1 << 30, torch.device("cuda", 0), "LGM Lift")  # fits: no error
    util.free_memory_for(64 << 30, torch.device("cpu"), "LGM Lift")  # on the CPU the weights are already in RAM


def test_out_of_memory_inside_a_stage_becomes_a_clear_error():
    from physmotion_core.memory import oom_as_input_error

    with pytest.raises(InputError, match="Multi-View Generate ran out of memory.*unload other models"):
        with oom_as_input_error("Multi-View Generate", "Free GPU memory (unload other models)."):
            raise torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB")
    with pytest.raises(ZeroDivisionError):  # anything else passes through unchanged
        with oom_as_input_error("x", "y"):
            raise ZeroDivisionError


def test_atomic_outputs_get_the_usual_file_mode(tmp_path):
    """Temporary files are private (0600); the finished file must be readable like any other
    (0666 minus the umask), or keep the mode of the file it replaces."""
    from physmotion_core.fsutil import atomic_output

    umask = os.umask(0o022)
    try:
        with atomic_output(tmp_path / "a.bin") as tmp:
            tmp.write_bytes(b"1")
        assert (tmp_path / "a.bin").stat().st_mode & 0o777 == 0o644
        os.chmod(tmp_path / "a.bin", 0o640)
        with atomic_output(tmp_path / "a.bin") as tmp:
            tmp.write_bytes(b"2")
        assert (tmp_path / "a.bin").stat().st_mode & 0o777 == 0o640 and (tmp_path / "a.bin").read_bytes() == b"2"
    finally:
        os.umask(umask)
