"""Reliability, third round (issue 36): small inputs that would cause unbounded work, a hostile or
stalled ComfyUI server, documented forms that crashed, a full disk, lenient entries and messages.

The client cases run against a stand-in server on 127.0.0.1 (never another address) that misbehaves
on purpose: it drips its answers a byte at a time, answers HTML, redirects elsewhere, lists odd file
names. Every case is bounded in time: a test that took the client's word for "forever" would hang.
"""

from __future__ import annotations

import base64
import errno
import hashlib
import io
import json
import logging
import os
import struct
import subprocess
import sys
import threading
import time
import tracemalloc
import types
import urllib.parse
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
import torch

from physmotion_core.comfy.client import ComfyClient, ComfyError, run_workflow
from physmotion_core.errors import InputError

ROOT = Path(__file__).resolve().parent.parent
WORKFLOW = ROOT / "example_workflows" / "api" / "push_a_jelly.json"


# ----------------------------------------------------------------------------------------------
# a hostile stand-in for ComfyUI
# ----------------------------------------------------------------------------------------------


class Hostile:
    """A ComfyUI stand-in on 127.0.0.1 whose answers the test replaces: ``routes`` maps a path prefix
    ("/prompt", "/history/", "/view", "/ws", "/upload/image") to ``fn(handler, body)``; the rest
    answer as a well-behaved server (upload, queue, a finished history entry with ``outputs``)."""

    def __init__(self, routes=None, outputs=None):
        self.routes = dict(routes or {})
        self.outputs = outputs if outputs is not None else {
            "12": {"images": [{"filename": "clip.mp4", "subfolder": "PhysMotion", "type": "output"}]}}
        self.hits: list[str] = []
        self.stop = threading.Event()
        fake = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *a):
                pass

            def _body(self) -> bytes:
                n = int(self.headers.get("Content-Length") or 0)
                return self.rfile.read(n) if n else b""

            def _dispatch(self):
                body = self._body()
                fake.hits.append(self.path)
                for prefix, fn in fake.routes.items():
                    if self.path.startswith(prefix):
                        try:
                            return fn(self, body)
                        except (BrokenPipeError, ConnectionResetError, OSError):
                            return None
                return fake.default(self, body)

            do_GET = do_POST = _dispatch

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.server.daemon_threads = True
        self.port = self.server.server_address[1]
        self.url = f"http://127.0.0.1:{self.port}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def default(self, h, body):
        path = urllib.parse.urlparse(h.path).path
        if path == "/upload/image":
            return answer(h, {"name": "photo.png", "subfolder": "", "type": "input"})
        if path == "/prompt":
            return answer(h, {"prompt_id": "p1", "number": 0})
        if path.startswith("/history/"):
            return answer(h, {"p1": {"status": {"status_str": "success", "completed": True}, "outputs": self.outputs}})
        if path == "/view":
            q = urllib.parse.parse_qs(urllib.parse.urlparse(h.path).query)
            return raw(h, 200, f"{q.get('subfolder', [''])[0]}|{q['filename'][0]}".encode())
        return raw(h, 404, b"not here")

    def close(self):
        self.stop.set()
        self.server.shutdown()
        self.server.server_close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def raw(h, code: int, body: bytes, ctype: str = "application/octet-stream", headers=()):
    h.send_response(code)
    h.send_header("Content-Type", ctype)
    h.send_header("Content-Length", str(len(body)))
    for k, v in headers:
        h.send_header(k, v)
    h.end_headers()
    h.wfile.write(body)


def answer(h, obj, code: int = 200):
    raw(h, code, json.dumps(obj).encode(), "application/json")


def dripping(data: bytes, every: float, stop: threading.Event, headers: bool = False):
    """A route that sends ``data`` (a whole HTTP answer when ``headers``, else a body announced in full)
    one byte every ``every`` seconds: each read of the client gets a byte well within any read timeout."""
    def fn(h, body):
        payload = data
        if not headers:
            h.wfile.write(b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\n"
                          + f"Content-Length: {len(data)}\r\n\r\n".encode())
        for i in range(len(payload)):
            if stop.is_set():
                return
            h.wfile.write(payload[i:i + 1])
            h.wfile.flush()
            time.sleep(every)
    return fn


@pytest.fixture
def photo(tmp_path):
    p = tmp_path / "photo.png"
    p.write_bytes(b"\x89PNG fake")
    return p


# ----------------------------------------------------------------------------------------------
# a stalled or hostile ComfyUI server
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("where", ["body", "status line"])
def test_a_server_that_drips_its_answer_is_cut_off_by_the_request_deadline(where):
    """One byte every 0.2 s passes every per-read timeout; the request's own deadline (1.5 s here)
    ends it, in the body as in the status line."""
    stop = threading.Event()
    if where == "body":
        route = dripping(b'{"prompt_id": "p1"}' * 20, 0.2, stop)
    else:
        route = dripping(b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\n{}", 0.2, stop, headers=True)
    with Hostile({"/prompt": route}) as fake:
        client = ComfyClient(fake.url, timeout=1.0, request_timeout=1.5)
        t0 = time.monotonic()
        with pytest.raises(ComfyError, match=r"did not answer /prompt in time \(limit 1.5 s per request\)"):
            client.queue({"1": {"class_type": "X", "inputs": {}}})
        assert time.monotonic() - t0 < 4.0
        stop.set()


def test_the_whole_run_has_a_deadline_even_when_every_request_is_answered(tmp_path):
    """A server that answers every /history poll promptly but never finishes: the run's --timeout
    ends it (not only the wait: upload, queue, wait and downloads share one deadline)."""
    with Hostile({"/history/": lambda h, b: answer(h, {}), "/ws": lambda h, b: raw(h, 404, b"")}) as fake:
        t0 = time.monotonic()
        with pytest.raises(ComfyError, match=r"--timeout"):
            run_workflow(WORKFLOW, fake.url, tmp_path / "out", timeout=2.0)
        assert time.monotonic() - t0 < 6.0
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_the_cli_ends_a_stalled_run_with_a_message_not_a_traceback(tmp_path, capsys):
    from physmotion_core.cli import main

    stop = threading.Event()
    with Hostile({"/prompt": dripping(b"x" * 1000, 0.3, stop), "/ws": lambda h, b: raw(h, 404, b"")}) as fake:
        t0 = time.monotonic()
        code = main(["comfy-run", str(WORKFLOW), "--server", fake.url, "-o", str(tmp_path / "out"), "-q",
                     "--timeout", "2"])
        stop.set()
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and "did not answer /prompt in time" in err, err
    assert time.monotonic() - t0 < 6.0


def test_downloads_are_streamed_to_a_temporary_file_not_held_in_memory(tmp_path):
    """A 24 MiB /view answer: the Python heap grows by a few MiB at most (the file is written as it
    arrives), the file is complete and no temporary file is left."""
    blob = np.random.default_rng(0).integers(0, 256, 24 << 20, dtype=np.uint8).tobytes()

    def view(h, body):
        h.send_response(200)
        h.send_header("Content-Length", str(len(blob)))
        h.end_headers()
        for i in range(0, len(blob), 1 << 20):
            h.wfile.write(blob[i:i + (1 << 20)])

    with Hostile({"/view": view}) as fake:
        client = ComfyClient(fake.url)
        tracemalloc.start()
        try:
            saved = client.download_outputs({"outputs": {"1": {"v": [{"filename": "big.mp4", "subfolder": ""}]}}},
                                            tmp_path)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    assert [p.name for p in saved] == ["big.mp4"]
    assert hashlib.sha256(saved[0].read_bytes()).digest() == hashlib.sha256(blob).digest()
    assert peak < 6 << 20, f"the download held {peak / 2**20:.1f} MiB in Python memory"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.mp4"]


def test_a_download_larger_than_the_free_space_is_refused_before_the_first_byte(tmp_path, monkeypatch):
    from physmotion_core import fsutil

    monkeypatch.setattr(fsutil, "free_bytes", lambda folder: 1000)
    with Hostile({"/view": lambda h, b: raw(h, 200, b"v" * 5000)}) as fake:
        client = ComfyClient(fake.url)
        with pytest.raises(fsutil.DiskFullError, match=r"needs about 4.9 KiB of disk space .* only 1000.0 B is free"):
            client.download_outputs({"outputs": {"1": {"v": [{"filename": "big.mp4", "subfolder": ""}]}}}, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_a_download_that_stalls_is_given_up_and_leaves_nothing(tmp_path):
    stop = threading.Event()

    def view(h, body):
        h.wfile.write(b"HTTP/1.1 200 OK\r\nContent-Length: 1000000\r\n\r\n")
        while not stop.is_set():
            h.wfile.write(b"0123456789")
            h.wfile.flush()
            time.sleep(0.05)

    with Hostile({"/view": view}) as fake:
        client = ComfyClient(fake.url, timeout=0.5)
        t0 = time.monotonic()
        with pytest.raises(ComfyError, match=r"download is stalled"):
            client.download_outputs({"outputs": {"1": {"v": [{"filename": "slow.mp4", "subfolder": ""}]}}}, tmp_path)
        stop.set()
        assert time.monotonic() - t0 < 4.0
    assert list(tmp_path.iterdir()) == []  # neither the file nor its temporary twin


def test_outputs_of_one_name_in_different_subfolders_are_all_kept(tmp_path):
    outputs = {"12": {"images": [{"filename": "clip.mp4", "subfolder": "a", "type": "output"},
                                 {"filename": "clip.mp4", "subfolder": "b/c", "type": "output"},
                                 {"filename": "clip.mp4", "subfolder": "a", "type": "output"}]},  # listed twice
               "13": {"images": [{"filename": "clip.mp4", "subfolder": "", "type": "output"}]}}
    with Hostile() as fake:
        saved = ComfyClient(fake.url).download_outputs({"outputs": outputs}, tmp_path)
    assert [p.name for p in saved] == ["clip.mp4", "b_c__clip.mp4", "output__clip.mp4"]
    assert [p.read_bytes() for p in saved] == [b"a|clip.mp4", b"b/c|clip.mp4", b"|clip.mp4"]


def test_an_html_answer_to_prompt_is_a_clear_error(tmp_path, capsys):
    from physmotion_core.cli import main

    login = b"<!doctype html><html><body>Please log in</body></html>"
    with Hostile({"/prompt": lambda h, b: raw(h, 200, login, "text/html; charset=utf-8"),
                  "/ws": lambda h, b: raw(h, 404, b"")}) as fake:
        with pytest.raises(ComfyError, match=r"answered /prompt with something that is not JSON \(text/html: "
                                             r"'<!doctype html><html><body>Please log in"):
            ComfyClient(fake.url).queue({})
        code = main(["comfy-run", str(WORKFLOW), "--server", fake.url, "-o", str(tmp_path / "o"), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "not JSON" in err and "Traceback" not in err
    # JSON of the wrong shape (a list, no prompt id) is refused as clearly.
    with Hostile({"/prompt": lambda h, b: answer(h, [1, 2])}) as fake:
        with pytest.raises(ComfyError, match="JSON of the wrong shape"):
            ComfyClient(fake.url).queue({})
    with Hostile({"/prompt": lambda h, b: answer(h, {"prompt_id": 7})}) as fake:
        with pytest.raises(ComfyError, match="without a prompt id"):
            ComfyClient(fake.url).queue({})


def _ws_route(frames: list[bytes], stop: threading.Event):
    """A websocket upgrade that sends ``frames`` (raw text payloads) and then stays open."""
    def fn(h, body):
        key = h.headers["Sec-WebSocket-Key"]
        accept = base64.b64encode(hashlib.sha1((key + "258EAFA5-E914-47DA-95CA-C5AB0DC85B11").encode())
                                  .digest()).decode()
        h.send_response(101)
        h.send_header("Upgrade", "websocket")
        h.send_header("Connection", "Upgrade")
        h.send_header("Sec-WebSocket-Accept", accept)
        h.end_headers()
        for payload in frames:
            h.wfile.write(bytes([0x81, 126]) + struct.pack(">H", len(payload)) + payload)
        h.wfile.flush()
        stop.wait(10)
    return fn


def test_a_non_json_websocket_frame_is_said_and_the_run_goes_on_by_polling(tmp_path, photo, caplog):
    stop = threading.Event()
    history = {"n": 0}

    def hist(h, body):  # finished from the third poll on
        history["n"] += 1
        done = history["n"] >= 3
        answer(h, {"p1": {"status": {"status_str": "success", "completed": True},
                          "outputs": {"12": {"images": [{"filename": "clip.mp4", "subfolder": ""}]}}}} if done else {})

    with Hostile({"/ws": _ws_route([b"this is not JSON", b'{"type": "progress"}'], stop), "/history/": hist}) as fake:
        t0 = time.monotonic()
        with caplog.at_level(logging.INFO, logger="physmotion"):
            saved = run_workflow(WORKFLOW, fake.url, tmp_path / "out", image=photo, timeout=15)
        stop.set()
    assert [p.name for p in saved] == ["clip.mp4"]
    assert time.monotonic() - t0 < 10
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("not JSON ('this is not JSON')" in w and "polling" in w for w in warnings), warnings
    # A message that is JSON but not an event object is handled the same way.
    stop2 = threading.Event()
    history["n"] = 0
    with Hostile({"/ws": _ws_route([b"[1, 2, 3]"], stop2), "/history/": hist}) as fake:
        with caplog.at_level(logging.INFO, logger="physmotion"):
            assert run_workflow(WORKFLOW, fake.url, tmp_path / "out2", timeout=15)
        stop2.set()
    assert any("not a ComfyUI event" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("name, match", [(12345, r"file name is 12345 \(int\), not a file name"),
                                         ("clip\x00.mp4", r"NUL or control character"),
                                         ("..", r"not a usable file name"),
                                         (None, r"not a file name")])
def test_output_file_names_that_are_not_file_names_are_refused(tmp_path, name, match):
    with Hostile() as fake:
        client = ComfyClient(fake.url)
        with pytest.raises(ComfyError, match=match):
            client.download_outputs({"outputs": {"1": {"v": [{"filename": name, "subfolder": ""}]}}}, tmp_path)
        assert not any(h.startswith("/view") for h in fake.hits)  # refused before asking for anything
    assert list(tmp_path.iterdir()) == []
    # A path in the name is cut to its last part (never written outside the folder).
    with Hostile() as fake:
        saved = ComfyClient(fake.url).download_outputs(
            {"outputs": {"1": {"v": [{"filename": "../../etc/x.mp4", "subfolder": ""}]}}}, tmp_path)
    assert saved == [tmp_path / "x.mp4"]


def test_a_redirect_on_view_to_another_host_is_not_followed(tmp_path):
    with Hostile() as other:
        to_other = lambda h, b: raw(h, 302, b"", headers=[("Location", f"{other.url}/steal?x=1")])  # noqa: E731
        with Hostile({"/view": to_other}) as fake:
            with pytest.raises(ComfyError, match=r"redirect to 'http://127.0.0.1:\d+/steal\?x=1', another host"):
                ComfyClient(fake.url).download_outputs(
                    {"outputs": {"1": {"v": [{"filename": "clip.mp4", "subfolder": ""}]}}}, tmp_path)
        assert other.hits == []  # never contacted
    assert list(tmp_path.iterdir()) == []
    # A redirect that stays on the server is followed.
    with Hostile() as fake:
        fake.routes["/view?"] = lambda h, b: raw(h, 307, b"", headers=[("Location", "/moved")])
        fake.routes["/moved"] = lambda h, b: raw(h, 200, b"moved bytes")
        saved = ComfyClient(fake.url).download_outputs(
            {"outputs": {"1": {"v": [{"filename": "clip.mp4", "subfolder": ""}]}}}, tmp_path)
    assert saved[0].read_bytes() == b"moved bytes"


def test_batch_comfy_jobs_have_a_deadline(tmp_path):
    """`batch --comfy` against a server that never finishes: the job fails within [comfy] timeout
    with the reason, the batch ends."""
    from physmotion_core.batch.runner import run_batch

    (tmp_path / "photo.png").write_bytes(b"\x89PNG fake")
    (tmp_path / "s.toml").write_text(f'[batch]\nimages = ["photo.png"]\n[comfy]\nworkflow = "{WORKFLOW}"\n'
                                     "timeout = 2\n")
    with Hostile({"/history/": lambda h, b: answer(h, {}), "/ws": lambda h, b: raw(h, 404, b"")}) as fake:
        t0 = time.monotonic()
        s = run_batch(tmp_path / "s.toml", tmp_path / "out", comfy=fake.url, progress=False, retries=0)
        assert time.monotonic() - t0 < 15
    assert (s.total, s.failed) == (1, 1)
    assert "--timeout" in s.failures[0][3] or "time limit" in s.failures[0][3]


# ----------------------------------------------------------------------------------------------
# small inputs, unbounded work
# ----------------------------------------------------------------------------------------------


def _png(path: Path) -> Path:
    import cv2

    cv2.imwrite(str(path), np.full((8, 8, 3), 120, np.uint8))
    return path


def test_a_yaml_alias_bomb_is_refused_before_it_is_expanded(tmp_path):
    from physmotion_core.batch.spec import SpecError, load_spec

    _png(tmp_path / "a.png")
    levels = ["a: &a [x, x, x, x, x, x, x, x, x, x]"]
    for i, name in enumerate("bcdefghi"):
        prev = "abcdefghi"[i]
        levels.append(f"{name}: &{name} [" + ", ".join([f"*{prev}"] * 10) + "]")
    # About 1 kB of text standing for 10^9 values once the aliases are written out.
    bomb = "defaults:\n  material_params:\n    " + "\n    ".join(levels) + "\nbatch: {images: [a.png]}\n"
    (tmp_path / "bomb.yaml").write_text(bomb)
    assert len(bomb) < 1500
    t0 = time.monotonic()
    with pytest.raises(SpecError, match=r"more than 100,000 values once its aliases .* are expanded"):
        load_spec(tmp_path / "bomb.yaml")
    assert time.monotonic() - t0 < 5.0  # refused without writing out its 10^9 values
    (tmp_path / "rec.yaml").write_text("batch: {images: [a.png]}\ndefaults: &d {forces: [*d]}\n")
    with pytest.raises(SpecError, match="recursive alias"):
        load_spec(tmp_path / "rec.yaml")
    # Aliases that expand to a few values are fine (and mean what they say).
    (tmp_path / "ok.yaml").write_text("batch: {images: [a.png]}\naxes: {E: &e [20000, 50000], density: *e}\n"
                                      "defaults: {models: none}\n")
    jobs = load_spec(tmp_path / "ok.yaml").jobs
    assert sorted((j.settings["E"], j.settings["density"]) for j in jobs) == [
        (2e4, 2e4), (2e4, 5e4), (5e4, 2e4), (5e4, 5e4)]
    big = tmp_path / "big.toml"
    with open(big, "wb") as fh:
        fh.truncate(5 << 20)
    with pytest.raises(SpecError, match="may be at most"):
        load_spec(big)


def _million(tmp_path) -> Path:
    _png(tmp_path / "a.png")
    spec = tmp_path / "grid.toml"
    spec.write_text('[batch]\nimages = ["a.png"]\n[defaults]\nmodels = "none"\n[axes]\n'
                    f"E = {[1e4 + i for i in range(100)]}\nnu = {[0.1 + 0.001 * i for i in range(100)]}\n"
                    f"seed = {list(range(100))}\n")
    return spec


def test_a_million_job_grid_is_refused_at_once_unless_confirmed(tmp_path, capsys):
    from physmotion_core.batch.spec import SpecError, load_spec
    from physmotion_core.cli import main

    spec = _million(tmp_path)
    t0 = time.monotonic()
    with pytest.raises(SpecError, match=r"expands to 1,000,000 jobs \(E \(100\) x nu \(100\) x seed \(100\).*"
                                        r"limit of 10,000 .* --max-jobs 1000000"):
        load_spec(spec)
    assert time.monotonic() - t0 < 5.0  # refused before expanding (a million jobs take far longer)
    code = main(["batch", str(spec), "-o", str(tmp_path / "out"), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "--max-jobs 1000000" in err and "Traceback" not in err
    assert not (tmp_path / "out" / "manifest.jsonl").exists()
    # Confirmed, it is counted without being expanded, and its jobs come one at a time.
    tracemalloc.start()
    try:
        t0 = time.monotonic()
        s = load_spec(spec, max_jobs=1_000_000)
        it = s.iter_jobs()
        first = [next(it) for _ in range(3)]
        took = time.monotonic() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert s.count == 1_000_000 and len({j.id for j in first}) == 3
    assert took < 1.0 and peak < 20 << 20, (took, peak)


def test_batch_list_streams_its_first_line_within_a_second(tmp_path):
    """`batch --list --max-jobs 0` on a million jobs: lines come as the jobs are built (here the
    reader stops after five, as `| head -5` would)."""
    from physmotion_core.batch import cli as batch_cli

    spec = _million(tmp_path)

    class Head(io.StringIO):
        def __init__(self):
            super().__init__()
            self.lines, self.t_first = 0, None

        def write(self, text):
            if self.t_first is None:
                self.t_first = time.monotonic()
            self.lines += text.count("\n")
            if self.lines > 5:
                raise BrokenPipeError(errno.EPIPE, "reader gone")
            return super().write(text)

    args = types.SimpleNamespace(spec=spec, list=True, comfy=None, max_jobs=0, output=None)
    head, old = Head(), sys.stdout
    t0 = time.monotonic()
    sys.stdout = head
    try:
        with pytest.raises(BrokenPipeError):
            batch_cli.run(args)
    finally:
        sys.stdout = old
    assert head.t_first - t0 < 1.0 and time.monotonic() - t0 < 3.0
    lines = head.getvalue().splitlines()
    assert lines[0].startswith("# 1000000 jobs") and len(lines[1].split()[0]) == 16


def _ply_header(count: int, extra: str = "") -> bytes:
    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
             "rot_0", "rot_1", "rot_2", "rot_3"]
    return ("ply\nformat binary_little_endian 1.0\n" + extra + f"element vertex {count}\n"
            + "".join(f"property float {p}\n" for p in props) + "end_header\n").encode()


def test_a_ply_declaring_64m_vertices_is_refused_before_reading(tmp_path, monkeypatch):
    from physmotion_core import memory
    from physmotion_core.ply import read_ply

    p = tmp_path / "huge.ply"
    head = _ply_header(64_000_000)
    with open(p, "wb") as fh:
        fh.write(head)
        fh.truncate(len(head) + 64_000_000 * 14 * 4)  # sparse: the size a real file would have
    monkeypatch.setattr(memory, "host_available_bytes", lambda: 4 << 30)
    t0 = time.monotonic()
    with pytest.raises(InputError, match=r"reading its 64,000,000 Gaussians needs about .* GiB of RAM; 4.0 GiB is "
                                         r"available now and a run may use at most 80%"):
        read_ply(p)
    assert time.monotonic() - t0 < 1.0


def _small_gaussians(n: int = 20):
    from physmotion_core.types.gaussians import Gaussians

    g = torch.Generator().manual_seed(0)
    return Gaussians(means=torch.randn(n, 3, generator=g), quats=torch.nn.functional.normalize(
        torch.randn(n, 4, generator=g), dim=-1), scales=torch.rand(n, 3, generator=g) * 0.01 + 1e-3,
        opacities=torch.rand(n, generator=g), sh=torch.randn(n, 1, 3, generator=g))


def test_a_ply_with_a_long_header_comment_is_read(tmp_path):
    from physmotion_core.ply import read_ply, write_ply

    g = _small_gaussians()
    p = write_ply(tmp_path / "a.ply", g)
    data = p.read_bytes()
    comment = b"comment " + b"settings=" + b"x" * 10_000 + b"\n"
    q = tmp_path / "b.ply"
    q.write_bytes(data.replace(b"element vertex", comment + b"element vertex", 1))
    h = read_ply(q)
    assert torch.equal(h.means, read_ply(p).means) and len(h) == len(g)
    # A long line that is not a comment is refused, naming the line.
    r = tmp_path / "c.ply"
    r.write_bytes(data.replace(b"element vertex", b"property " + b"y" * 5000 + b"\nelement vertex", 1))
    with pytest.raises(InputError, match=r"header line 4: longer than 4096 bytes and not a comment"):
        read_ply(r)


# ----------------------------------------------------------------------------------------------
# documented forms that crashed
# ----------------------------------------------------------------------------------------------


def test_wan_length_refuses_a_zero_frame_rate_clearly():
    from physmotion_core.controls import wan_length

    assert wan_length(48, 24.0, 16.0) == 33
    for fps_in, fps_out in [(0, 16.0), (24.0, 0), (float("nan"), 16.0), (-24.0, 16.0)]:
        with pytest.raises(InputError, match=r"fps_(in|out) must be a frame rate in \(0, 1000\]"):
            wan_length(48, fps_in, fps_out)
    with pytest.raises(InputError, match="num_frames must be a whole number"):
        wan_length(0, 24.0)


def test_ray_client_without_its_packages_says_what_to_install(tmp_path, monkeypatch):
    from physmotion_core.batch.executors import RayExecutor

    fake = types.ModuleType("ray")
    fake.is_initialized = lambda: False

    def init(address=None, **kw):  # what Ray 2.x raises for ray:// without ray[client]
        raise ValueError("Ray Client requires pip package `ray[client]`. If you installed the minimal Ray (e.g. "
                         "`pip install ray`), please reinstall by executing `pip install ray[client]`.")

    fake.init = init
    monkeypatch.setitem(sys.modules, "ray", fake)
    ex = RayExecutor(tmp_path, "ray://10.0.0.1:10001", cpus=1, threads=1)
    with pytest.raises(InputError, match=r"--ray ray://10.0.0.1:10001 needs Ray Client.*pip install 'ray\[client\]'"):
        ex.start()

    def init_missing(address=None, **kw):
        raise ModuleNotFoundError("No module named 'grpc'")

    fake.init = init_missing
    with pytest.raises(InputError, match=r"needs Ray Client.*No module named 'grpc'"):
        RayExecutor(tmp_path, "ray://h:10001", cpus=1, threads=1).start()


# ----------------------------------------------------------------------------------------------
# a full disk
# ----------------------------------------------------------------------------------------------


@pytest.fixture
def tiny_disk(tmp_path):
    """A 256 KiB tmpfs (root only; skipped where mounting is not allowed)."""
    d = tmp_path / "tiny"
    d.mkdir()
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(d)], capture_output=True,
                           timeout=10)
    except (OSError, subprocess.SubprocessError):
        pytest.skip("cannot mount a tmpfs here")
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.decode(errors='replace').strip()})")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True, timeout=10)


def test_writers_on_a_full_disk_fail_clearly_and_leave_nothing(tiny_disk):
    from physmotion_core.batch import manifest as M
    from physmotion_core.fsutil import DiskFullError
    from physmotion_core.ply import write_ply
    from physmotion_core.video import write_video

    noise = np.random.default_rng(0).integers(0, 256, (8, 256, 256, 3), dtype=np.uint8)  # ~300 kB as H.264
    for ext in ("mp4", "mkv"):
        with pytest.raises(DiskFullError, match=r"could not be written: its disk is full .*Nothing was written"):
            write_video(tiny_disk / f"o.{ext}", noise, threads=1)
        assert list(tiny_disk.iterdir()) == []
    # .ply: the size is known, so it is refused before a byte is written.
    big = _small_gaussians(20_000)  # 20000 x 68 bytes = 1.3 MiB
    with pytest.raises(DiskFullError, match=r"'g.ply' needs about 1.3 MiB of disk space .* Free at least"):
        write_ply(tiny_disk / "g.ply", big)
    assert list(tiny_disk.iterdir()) == []
    # A manifest record (JSON) and an .npz through the same writer.
    with open(tiny_disk / "filler", "wb") as fh:
        try:
            fh.write(b"\0" * (1 << 20))
        except OSError:
            pass
    with pytest.raises(DiskFullError):
        M.write_record(tiny_disk, {"id": "abc", "status": "done", "blob": "x" * 100_000})
    assert sorted(p.name for p in tiny_disk.rglob("*") if p.is_file()) == ["filler"]  # no record, no temp file


def test_an_encoder_that_drops_writes_silently_is_not_taken_for_success(tmp_path, monkeypatch):
    """FFmpeg's muxers do not report every failed write. Simulated here by a container that drops
    every packet after the first: the clip is checked before the rename and refused."""
    import av

    from physmotion_core.video import write_video

    real = av.open

    class Dropping:
        def __init__(self, c):
            self._c, self._n = c, 0

        def __getattr__(self, name):
            return getattr(self._c, name)

        def mux(self, packet):
            self._n += 1
            if self._n == 1:
                self._c.mux(packet)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._c.close()
            return False

    monkeypatch.setattr(av, "open", lambda f, mode="r", **kw: Dropping(real(f, mode=mode, **kw)) if mode == "w"
                        else real(f, mode=mode, **kw))
    frames = np.random.default_rng(1).integers(0, 256, (6, 64, 80, 3), dtype=np.uint8)
    with pytest.raises(InputError, match=r"came out incomplete .* \d of 6 frames readable back"):
        write_video(tmp_path / "o.mp4", frames, threads=1)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(av, "open", real)
    write_video(tmp_path / "o.mp4", frames, threads=1)  # the real encoder passes the same check
    assert (tmp_path / "o.mp4").stat().st_size > 0


def test_a_write_that_hits_enospc_names_the_space(tmp_path, monkeypatch):
    """Without a small disk to fill: a write failing with ENOSPC becomes a DiskFullError naming the
    file and the free space, and the temporary file is removed."""
    from physmotion_core.fsutil import DiskFullError, atomic_write_text

    real_write = Path.write_text

    def full(self, *a, **kw):
        real_write(self, "partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))

    monkeypatch.setattr(Path, "write_text", full)
    with pytest.raises(DiskFullError, match=r"'.*manifest.json' could not be written: its disk is full .* free in"):
        atomic_write_text(tmp_path / "manifest.json", "{}")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------------------------
# the memory estimate and its message
# ----------------------------------------------------------------------------------------------

#: Measured peaks of `generate` on a 2048x2048 RGBA cut-out at max_side 0 (benchmarks/bench_memory.py's
#: child, square instead of 4:3; docs/reliability.md): frames -> bytes the run added.
MEASURED_2048 = {2: 1_206_022_144, 4: 1_684_115_456, 8: 2_551_095_296}


def test_the_memory_estimate_covers_large_cut_outs_with_a_margin():
    from physmotion_core.memory import pipeline_need_bytes

    for frames, need in MEASURED_2048.items():
        assert pipeline_need_bytes(2048, 2048, frames) >= 1.25 * need, frames
    per_frame = pipeline_need_bytes(2048, 2048, 9) - pipeline_need_bytes(2048, 2048, 8)
    measured = (MEASURED_2048[8] - MEASURED_2048[2]) / 6
    assert per_frame >= 1.25 * measured and per_frame >= 1.25 * (197 << 20)  # the 197 MiB per frame


def test_a_memory_refusal_says_what_the_limit_is(monkeypatch):
    from physmotion_core import memory

    need = memory.pipeline_need_bytes(1000, 1000, 48)
    monkeypatch.setattr(memory, "host_available_bytes", lambda: int(need / 0.9))  # more than needed, over 80 %
    with pytest.raises(InputError) as exc:
        memory.check_pipeline_fits(1000, 1000, 48)
    msg = str(exc.value)
    assert "but only" not in msg
    assert "is available now and a run may use at most 80% of it" in msg and "Lower the frame count" in msg


# ----------------------------------------------------------------------------------------------
# lenient entries
# ----------------------------------------------------------------------------------------------


def _native(pos, scl=None, rot=None, opa=None, sh=None):
    n = pos.shape[1]
    return types.SimpleNamespace(
        positions=pos, scales=scl if scl is not None else torch.full((1, n, 3), 0.01),
        rotations=rot if rot is not None else torch.tensor([1.0, 0, 0, 0]).expand(1, n, 4).clone(),
        opacities=opa if opa is not None else torch.full((1, n, 1), 0.5),
        sh=sh if sh is not None else torch.zeros(1, n, 1, 3), counts=None)


def test_a_native_gaussian_is_checked_as_a_ply_is():
    from physmotion_core.interop_gaussian import from_native, from_native_scene, to_native_tensors
    from physmotion_core.types.gaussians import Gaussians

    pos = torch.zeros(1, 5, 3)
    assert len(from_native(_native(pos))[0]) == 5
    bad = pos.clone()
    bad[0, 2, 1] = float("nan")
    with pytest.raises(InputError, match=r"the GAUSSIAN: 1 of 5 splats have a NaN or infinite positions value"):
        from_native_scene(_native(bad))
    with pytest.raises(InputError, match=r"scale <= 0"):
        from_native(_native(pos, scl=torch.zeros(1, 5, 3)))
    with pytest.raises(InputError, match=r"opacity outside \[0, 1\]"):
        from_native(_native(pos, opa=torch.full((1, 5, 1), 3.0)))
    with pytest.raises(InputError, match=r"all-zero rotation"):
        from_native(_native(pos, rot=torch.zeros(1, 5, 4)))
    # Ours -> native: the same checks, and nothing to convert is an error, not an empty item.
    empty = Gaussians(means=torch.zeros(0, 3), quats=torch.zeros(0, 4), scales=torch.zeros(0, 3),
                      opacities=torch.zeros(0), sh=torch.zeros(0, 1, 3))
    with pytest.raises(InputError, match=r"hold no splats \(0 Gaussians\)"):
        to_native_tensors(empty)
    g = _small_gaussians(4)
    g.sh[1, 0, 0] = float("inf")
    with pytest.raises(InputError, match=r"1 of 4 splats have a NaN or infinite sh value"):
        to_native_tensors(g)
