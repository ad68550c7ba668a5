"""`physmotion comfy-run` against a stand-in ComfyUI server (HTTP(S) + websocket, standard library).

The stand-in speaks the parts of ComfyUI's API the client uses: /upload/image (multipart),
/prompt, /history/<id>, /view and the /ws progress socket. (Against a real ComfyUI, see README:
"Headless runs".)
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import shutil
import ssl
import struct
import subprocess
import threading
import time
import urllib.parse
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import websocket

from physmotion_core.comfy import client as comfy_client
from physmotion_core.cli import main
from physmotion_core.comfy.client import ComfyError, apply_sets, run_workflow
from physmotion_core.errors import InputError

ROOT = Path(__file__).resolve().parent.parent
WORKFLOW = ROOT / "example_workflows" / "api" / "push_a_jelly.json"


class FakeComfy:
    def __init__(self, websocket=True, fail_node=None, reject=False, tls=None, interrupt_node=None,
                 ws_silent=False):
        """``tls``: (certfile, keyfile) to serve HTTPS and wss:// instead of HTTP and ws://.
        ``interrupt_node``: the run is cancelled there (as ComfyUI records a Cancel). ``ws_silent``: the
        socket opens but says nothing for 5 s (a loaded server whose /history is read first)."""
        self.interrupt_node = interrupt_node
        self.messages = []  # set when a prompt runs
        self.ws_silent = ws_silent
        self.websocket = websocket
        self.ws_requests = []  # (headers, over TLS?) of each /ws upgrade request
        self.fail_node = fail_node
        self.reject = reject
        self.uploads = {}
        self.prompts = {}
        self.done = {}
        self.events = threading.Event()
        fake = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):
                pass

            def _json(self, obj, code=200):
                body = json.dumps(obj).encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def do_POST(self):
                data = self.rfile.read(int(self.headers["Content-Length"]))
                if self.path == "/upload/image":
                    head, _, rest = data.partition(b'filename="')
                    name = rest.split(b'"', 1)[0].decode()
                    content = rest.split(b"\r\n\r\n", 1)[1].rsplit(b"\r\n--", 1)[0]
                    fake.uploads[name] = content
                    return self._json({"name": name, "subfolder": "", "type": "input"})
                if self.path == "/prompt":
                    body = json.loads(data)
                    if fake.reject:
                        return self._json({"error": {"message": "Prompt outputs failed validation"},
                                           "node_errors": {"6": {"errors": [{"message": "Value too big",
                                                                             "details": "force_x: 1e9 > 1e4"}]}}},
                                          400)
                    pid = f"p{len(fake.prompts)}"
                    fake.prompts[pid] = body["prompt"]
                    threading.Thread(target=fake.execute, args=(pid,), daemon=True).start()
                    return self._json({"prompt_id": pid, "number": 0})
                self._json({}, 404)

            def do_GET(self):
                url = urllib.parse.urlparse(self.path)
                if url.path.startswith("/history/"):
                    pid = url.path.rsplit("/", 1)[1]
                    return self._json({pid: fake.done[pid]} if pid in fake.done else {})
                if url.path == "/view":
                    q = urllib.parse.parse_qs(url.query)
                    body = f"{q['subfolder'][0]}/{q['filename'][0]}".encode()
                    self.send_response(200)
                    self.send_header("Content-Length", str(len(body)))
                    self.end_headers()
                    return self.wfile.write(body)
                if url.path == "/ws":
                    fake.ws_requests.append((dict(self.headers), isinstance(self.connection, ssl.SSLSocket)))
                if url.path == "/ws" and fake.websocket:
                    key = self.headers["Sec-WebSocket-Key"]
                    accept = base64.b64encode(hashlib.sha1((key + "258EAFA5-E914-47DA-95CA-C5AB0DC85B11")
                                                           .encode()).digest()).decode()
                    self.send_response(101)
                    self.send_header("Upgrade", "websocket")
                    self.send_header("Connection", "Upgrade")
                    self.send_header("Sec-WebSocket-Accept", accept)
                    self.end_headers()
                    fake.events.wait(10)
                    if fake.ws_silent:
                        time.sleep(5)
                    for msg in fake.messages:
                        payload = json.dumps(msg).encode()
                        self.wfile.write(bytes([0x81, 126]) + struct.pack(">H", len(payload)) + payload)
                    self.wfile.write(bytes([0x82, 3]) + b"bin")  # a binary preview frame: skipped
                    self.wfile.write(bytes([0x88, 0]))
                    return
                self._json({}, 404)

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        if tls is not None:
            ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            ctx.load_cert_chain(*tls)
            self.server.socket = ctx.wrap_socket(self.server.socket, server_side=True)
        scheme = "https" if tls is not None else "http"
        self.url = f"{scheme}://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def execute(self, pid):
        time.sleep(0.3)
        if self.interrupt_node:
            said = {"prompt_id": pid, "node_id": self.interrupt_node, "node_type": "PhysMotionMPMSimulate",
                    "executed": ["1", "2"], "timestamp": 1}
            self.messages = [{"type": "executing", "data": {"node": self.interrupt_node, "prompt_id": pid}},
                             {"type": "execution_interrupted", "data": said}]
            # ComfyUI 0.3.64 execution.py: an interrupt is recorded as status "error", not completed,
            # with the execution_interrupted message (no execution_error)
            self.done[pid] = {"status": {"status_str": "error", "completed": False, "messages": [
                ["execution_start", {"prompt_id": pid, "timestamp": 0}],
                ["execution_interrupted", said]]}, "outputs": {}}
        elif self.fail_node:
            self.messages = [{"type": "execution_error", "data": {"prompt_id": pid, "node_id": self.fail_node,
                                                                   "node_type": "PhysMotionMPMSimulate",
                                                                   "exception_message": "Simulation became invalid"}}]
            self.done[pid] = {"status": {"status_str": "error", "completed": False, "messages": [
                ["execution_error", {"exception_message": "Simulation became invalid"}]]}, "outputs": {}}
        else:
            self.messages = [{"type": "executing", "data": {"node": "7", "prompt_id": pid}},
                             {"type": "progress", "data": {"value": 3, "max": 47, "node": "7", "prompt_id": pid}},
                             {"type": "executing", "data": {"node": None, "prompt_id": pid}}]
            self.done[pid] = {"status": {"status_str": "success", "completed": True, "messages": []},
                              "outputs": {"12": {"images": [{"filename": "push_a_jelly_00001.mp4",
                                                             "subfolder": "PhysMotion", "type": "output"}],
                                                 "animated": [True]},
                                          "8": {"images": [{"filename": "PhysMotion_render_1a2b.mp4",
                                                            "subfolder": "", "type": "temp"}],
                                                "animated": [True]},
                                          "11": {"text": ["not a file"]}}}
        self.events.set()

    def close(self):
        self.server.shutdown()


@pytest.fixture
def photo(tmp_path):
    p = tmp_path / "photo.png"
    p.write_bytes(b"\x89PNG fake")
    return p


@pytest.mark.parametrize("websocket", [True, False])
def test_run_uploads_edits_queues_follows_and_downloads(tmp_path, photo, websocket):
    fake = FakeComfy(websocket=websocket)
    events = []
    try:
        saved = run_workflow(WORKFLOW, fake.url, tmp_path / "out", image=photo, sets=["SaveVideo.codec=h264"],
                             on_event=lambda k, d: events.append(k), timeout=20)
    finally:
        fake.close()
    assert fake.uploads == {"photo.png": b"\x89PNG fake"}
    prompt = fake.prompts["p0"]
    assert prompt["1"]["inputs"]["image"] == "photo.png"
    assert prompt["12"]["inputs"]["codec"] == "h264"
    assert [p.name for p in saved] == ["push_a_jelly_00001.mp4"]  # the Render preview (type temp) is skipped
    assert saved[0].read_bytes() == b"PhysMotion/push_a_jelly_00001.mp4"
    if websocket:
        assert events == ["executing", "progress", "executing"]
    else:
        assert events == []  # polled /history instead


def test_server_errors_are_reported_with_the_node_and_message(tmp_path, photo):
    fake = FakeComfy(reject=True)
    try:
        with pytest.raises(ComfyError, match="node 6: Value too big force_x"):
            run_workflow(WORKFLOW, fake.url, tmp_path, timeout=5)
    finally:
        fake.close()
    fake = FakeComfy(fail_node="7")
    try:
        with pytest.raises(ComfyError, match="Node 7 .*Simulation became invalid"):
            run_workflow(WORKFLOW, fake.url, tmp_path, timeout=5)
    finally:
        fake.close()


def test_unreachable_server_gives_a_clear_error(tmp_path, capsys):
    code = main(["comfy-run", str(WORKFLOW), "--server", "http://127.0.0.1:9", "-o", str(tmp_path), "-q"])
    assert code == 2
    assert "Cannot reach ComfyUI at http://127.0.0.1:9" in capsys.readouterr().err


def test_set_edits_are_checked():
    prompt = json.loads(WORKFLOW.read_text())
    apply_sets(prompt, ["12.codec=h264", "SaveVideo.filename_prefix=run/a", "10.fps=12.5"])
    assert prompt["12"]["inputs"]["codec"] == "h264" and prompt["10"]["inputs"]["fps"] == 12.5
    assert prompt["12"]["inputs"]["filename_prefix"] == "run/a"
    with pytest.raises(InputError, match="No node 'Nope'"):
        apply_sets(prompt, ["Nope.x=1"])
    with pytest.raises(InputError, match="has no input 'bogus'"):
        apply_sets(prompt, ["10.bogus=1"])
    with pytest.raises(InputError, match="is connected to node"):
        apply_sets(prompt, ["10.images=1"])
    with pytest.raises(InputError, match="NODE.INPUT=VALUE"):
        apply_sets(prompt, ["crf20"])


def test_cli_prints_the_saved_files(tmp_path, photo, capsys):
    fake = FakeComfy()
    try:
        code = main(["comfy-run", str(WORKFLOW), "--server", fake.url, "--image", str(photo), "-o",
                     str(tmp_path / "o"), "--set", "10.fps=30"])
    finally:
        fake.close()
    assert code == 0
    out = capsys.readouterr()
    assert out.out.strip().endswith("push_a_jelly_00001.mp4")
    assert "node 7: 3/47" in out.err


def test_progress_comes_through_websocket_client_on_ws(tmp_path, photo, monkeypatch):
    """The progress socket is websocket-client's: its handshake reaches the server and the messages
    the server sends arrive as events."""
    opened = []
    real = websocket.create_connection

    def recording(url, *a, **kw):
        ws = real(url, *a, **kw)
        opened.append((url, ws))
        return ws

    monkeypatch.setattr(comfy_client.websocket, "create_connection", recording)
    fake = FakeComfy()
    events = []
    try:
        run_workflow(WORKFLOW, fake.url, tmp_path / "out", on_event=lambda k, d: events.append((k, d)), timeout=20)
    finally:
        fake.close()
    assert len(opened) == 1
    url, ws = opened[0]
    assert url.startswith(fake.url.replace("http://", "ws://") + "/ws?clientId=")
    assert isinstance(ws, websocket.WebSocket) and not ws.connected  # closed after the run
    (headers, over_tls), = fake.ws_requests
    assert not over_tls and headers["Upgrade"].lower() == "websocket" and headers["Sec-WebSocket-Version"] == "13"
    assert [k for k, _ in events] == ["executing", "progress", "executing"]
    assert events[1][1] == {"value": 3, "max": 47, "node": "7", "prompt_id": "p0"}


@pytest.fixture
def self_signed(tmp_path):
    """A certificate for 127.0.0.1 (made with the openssl command line tool) and its key."""
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("the openssl command is not installed")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run([openssl, "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                    "-keyout", str(key), "-out", str(cert), "-days", "2", "-subj", "/CN=127.0.0.1",
                    "-addext", "subjectAltName=IP:127.0.0.1"], check=True, capture_output=True, timeout=60)
    return cert, key


def test_an_https_server_is_followed_over_wss_with_tls(tmp_path, photo, self_signed, monkeypatch):
    """An https:// server gets its progress socket as wss:// over TLS (verified against the trusted
    certificate), not plain TCP: the upgrade request arrives on a TLS connection and the progress
    messages come through (a plain-TCP attempt would fail the handshake and fall back to polling)."""
    cert, key = self_signed
    monkeypatch.setenv("SSL_CERT_FILE", str(cert))  # trust the test's certificate (and only it)
    monkeypatch.delenv("SSL_CERT_DIR", raising=False)
    fake = FakeComfy(tls=(cert, key))
    events = []
    try:
        assert fake.url.startswith("https://")
        saved = run_workflow(WORKFLOW, fake.url, tmp_path / "out", image=photo, on_event=lambda k, d: events.append(k),
                             timeout=20)
    finally:
        fake.close()
    assert [over_tls for _, over_tls in fake.ws_requests] == [True]
    assert events == ["executing", "progress", "executing"]
    assert saved[0].read_bytes() == b"PhysMotion/push_a_jelly_00001.mp4"  # HTTPS downloads too


def test_an_untrusted_certificate_is_refused_not_ignored(tmp_path, self_signed, monkeypatch):
    """TLS is verified: with the certificate not trusted, the wss:// socket is not opened (and says why
    in the log) and the HTTPS requests fail clearly."""
    cert, key = self_signed
    other = tmp_path / "other"
    other.mkdir()
    monkeypatch.setenv("SSL_CERT_FILE", str(other / "none.pem"))
    monkeypatch.setenv("SSL_CERT_DIR", str(other))
    fake = FakeComfy(tls=(cert, key))
    try:
        client = comfy_client.ComfyClient(fake.url)
        with pytest.raises(ComfyError, match="Cannot reach ComfyUI at https://127.0.0.1"):
            client.history("p0")
        assert client._open_socket() is None
    finally:
        fake.close()
    assert fake.ws_requests == []  # the TLS handshake failed before any upgrade request


def test_no_websocket_is_said_once_in_the_log_then_history_is_polled(tmp_path, caplog):
    fake = FakeComfy(websocket=False)
    events = []
    try:
        with caplog.at_level(logging.INFO, logger="physmotion"):
            saved = run_workflow(WORKFLOW, fake.url, tmp_path / "out", on_event=lambda k, d: events.append(k),
                                 timeout=20)
    finally:
        fake.close()
    assert [p.name for p in saved] == ["push_a_jelly_00001.mp4"]
    assert events == []
    said = [r for r in caplog.records if "progress socket" in r.getMessage()]
    assert len(said) == 1, [r.getMessage() for r in said]
    msg = said[0].getMessage()
    assert said[0].levelno == logging.WARNING
    assert fake.url.replace("http://", "ws://") + "/ws?clientId=" in msg and "404" in msg
    assert f"polling {fake.url}/history" in msg
    assert len(fake.ws_requests) == 1  # tried once, not again for the wait


@pytest.mark.parametrize("order", ["websocket_first", "history_first_polling", "history_first_socket_silent"])
def test_a_cancel_is_reported_as_cancelled_in_either_order(tmp_path, order):
    """ComfyUI records a Cancel in /history as status "error" plus an execution_interrupted message and
    says it on the websocket: whichever the client reads first, it reports a cancel, not a failure."""
    fake = FakeComfy(websocket=order != "history_first_polling", interrupt_node="7",
                     ws_silent=order == "history_first_socket_silent")
    try:
        with pytest.raises(comfy_client.ComfyCancelled) as err:
            run_workflow(WORKFLOW, fake.url, tmp_path / "out", timeout=30)
    finally:
        fake.close()
    msg = str(err.value)
    assert "cancelled" in msg and "node 7 (PhysMotionMPMSimulate)" in msg, msg
    assert "failed" not in msg.replace("nothing failed", "")
    assert isinstance(err.value, ComfyError)  # callers catching ComfyError still catch it
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_a_failure_is_still_a_failure_not_a_cancel(tmp_path):
    fake = FakeComfy(websocket=False, fail_node="7")
    try:
        with pytest.raises(ComfyError, match="failed on the server: Simulation became invalid") as err:
            run_workflow(WORKFLOW, fake.url, tmp_path / "out", timeout=30)
    finally:
        fake.close()
    assert not isinstance(err.value, comfy_client.ComfyCancelled)


def test_a_run_on_another_photo_warns_about_pixels_placed_on_the_workflows_own(tmp_path, photo, caplog):
    """push_a_jelly's Segment box and Force point are pixels of its coffee photo: run with --image on another
    photo, comfy-run says which inputs still hold them and how to give them; inputs given by --set, a Force
    on the whole object, or no --image at all, are not mentioned."""
    import logging

    from physmotion_core.comfy.client import placed_on_its_own_photo

    prompt = json.loads(WORKFLOW.read_text())
    stale = placed_on_its_own_photo(prompt, [])
    assert stale == ["PhysMotionSegment.box = '55, 6, 498, 395'", "PhysMotionForce.u = 200", "PhysMotionForce.v = 150"]
    assert placed_on_its_own_photo(prompt, ["PhysMotionSegment.box=", "6.u=10", "PhysMotionForce.v=20"]) == []
    prompt["6"]["inputs"]["region"] = "whole object"
    assert placed_on_its_own_photo(prompt, ["PhysMotionSegment.box=1,2,3,4"]) == []
    fake = FakeComfy()
    try:
        with caplog.at_level(logging.WARNING, logger="physmotion"):
            run_workflow(WORKFLOW, fake.url, tmp_path / "out", image=photo, timeout=20)
            (w,) = [r.getMessage() for r in caplog.records if "placed on its own photo" in r.getMessage()]
            caplog.clear()
            run_workflow(WORKFLOW, fake.url, tmp_path / "out2", timeout=20)
            assert not [r for r in caplog.records if "placed on its own photo" in r.getMessage()]
    finally:
        fake.close()
    assert "PhysMotionSegment.box" in w and "photo.png" in w and "--set" in w
