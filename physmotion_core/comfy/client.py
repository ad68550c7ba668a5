"""Run a workflow on a ComfyUI server over its HTTP API (headless): the standard library for HTTP(S),
websocket-client for the progress socket (ws://, or wss:// over TLS for an https:// server).

    physmotion comfy-run example_workflows/api/push_a_jelly.json --server http://127.0.0.1:8188 \\
        --image photo.png --set 5.force_x=40 -o out/

Steps: upload the image (POST /upload/image) and point the workflow's LoadImage node at it, apply
``--set NODE.INPUT=VALUE`` edits, queue the prompt (POST /prompt), follow its progress on the
server's websocket (/ws: "progress" and "executing" messages; if it cannot be opened the log says
why, once, and /history is polled instead), then download every file its output nodes list (GET /view) into the output folder.
"""

from __future__ import annotations

import json
import logging
import socket
import ssl
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from pathlib import Path
from typing import Callable, Optional

import websocket  # websocket-client

from ..errors import InputError, PhysMotionError
from ..fsutil import atomic_output

log = logging.getLogger("physmotion")


class ComfyError(PhysMotionError):
    """The server refused the prompt, or its execution failed."""


def _parse_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text  # a bare string such as a file name or a preset


def apply_sets(prompt: dict, sets: list[str]) -> dict:
    """Apply "NODE.INPUT=VALUE" edits; NODE is a node id, a node's title (``_meta.title``) or a
    class_type that occurs once. VALUE is JSON (numbers, true/false, lists) or a bare string."""
    for item in sets:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise InputError(f"--set expects NODE.INPUT=VALUE (e.g. 5.force_x=40); got '{item}'")
        target, value = item.split("=", 1)
        node_ref, name = target.rsplit(".", 1)
        node_id = find_node(prompt, node_ref)
        inputs = prompt[node_id].setdefault("inputs", {})
        if name not in inputs:
            raise InputError(f"Node {node_id} ({prompt[node_id].get('class_type')}) has no input '{name}'; "
                             f"its inputs: {', '.join(sorted(inputs))}")
        if isinstance(inputs[name], list) and len(inputs[name]) == 2 and isinstance(inputs[name][0], str):
            raise InputError(f"Input '{name}' of node {node_id} is connected to node {inputs[name][0]}; "
                             "set a widget value instead")
        inputs[name] = _parse_value(value)
    return prompt


def find_node(prompt: dict, ref: str) -> str:
    if ref in prompt:
        return ref
    titled = [k for k, n in prompt.items() if n.get("_meta", {}).get("title") == ref]
    typed = [k for k, n in prompt.items() if n.get("class_type") == ref]
    for hits in (titled, typed):
        if len(hits) == 1:
            return hits[0]
        if len(hits) > 1:
            raise InputError(f"'{ref}' names {len(hits)} nodes ({', '.join(hits)}); use the node id")
    listing = ", ".join(f"{k} ({n.get('class_type')})" for k, n in prompt.items())
    raise InputError(f"No node '{ref}' in the workflow; nodes: {listing}")


def _multipart(field: str, filename: str, data: bytes, extra: dict) -> tuple[bytes, str]:
    boundary = uuid.uuid4().hex
    parts = []
    for k, v in extra.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n{v}\r\n'.encode())
    parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{field}"; filename="{filename}"\r\n'
                 "Content-Type: application/octet-stream\r\n\r\n".encode() + data + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


def _recv_text(ws: websocket.WebSocket) -> Optional[str]:
    """The next text message on the progress socket; None once the server closes it. Binary frames
    (ComfyUI's preview images) are skipped; websocket-client answers pings itself."""
    while True:
        opcode, data = ws.recv_data()
        if opcode == websocket.ABNF.OPCODE_CLOSE:
            return None
        if opcode == websocket.ABNF.OPCODE_TEXT:
            return data.decode("utf-8", "replace") if isinstance(data, bytes) else data


def _close_socket(ws: websocket.WebSocket) -> None:
    try:
        ws.close(timeout=0.25)  # send the close frame; wait briefly for the server's reply
    except (OSError, websocket.WebSocketException):
        pass


class ComfyClient:
    def __init__(self, server: str = "http://127.0.0.1:8188", timeout: float = 30.0):
        if not server.startswith(("http://", "https://")):
            server = "http://" + server
        self.server = server.rstrip("/")
        self.timeout = timeout
        self.client_id = uuid.uuid4().hex
        # https:// servers: one TLS context (the system's CAs, or SSL_CERT_FILE / SSL_CERT_DIR) for the
        # HTTP requests and the wss:// progress socket alike.
        self._tls = ssl.create_default_context() if self.server.startswith("https://") else None
        self._ws: Optional[websocket.WebSocket] = None
        self._ws_failed = False

    @property
    def ws_url(self) -> str:
        """The progress socket: ws:// for an http:// server, wss:// (TLS) for an https:// one."""
        scheme, rest = self.server.split("://", 1)
        return f"{'wss' if scheme == 'https' else 'ws'}://{rest}/ws?clientId={self.client_id}"

    def _open_socket(self, poll: float = 0.5) -> Optional[websocket.WebSocket]:
        """The progress socket, or None (said once in the log) when it cannot be opened: then the run
        is followed by polling /history, without progress messages."""
        if self._ws_failed:
            return None
        url = self.ws_url
        try:
            ws = websocket.create_connection(url, timeout=5.0,
                                             sslopt={"context": self._tls} if self._tls is not None else {})
        except (OSError, websocket.WebSocketException) as exc:
            self._ws_failed = True
            log.warning("Cannot open ComfyUI's progress socket %s (%s: %s); following the run by polling "
                        "%s/history instead, without progress", url, type(exc).__name__, exc, self.server)
            return None
        ws.settimeout(poll)
        return ws

    def connect(self) -> None:
        """Open the progress socket before queueing, so that no message of the run is missed."""
        if self._ws is None:
            self._ws = self._open_socket()

    def _request(self, path: str, data: Optional[bytes] = None, content_type: str = "application/json") -> bytes:
        req = urllib.request.Request(self.server + path, data=data,
                                     headers={"Content-Type": content_type} if data is not None else {})
        try:
            with urllib.request.urlopen(req, timeout=self.timeout, context=self._tls) as resp:
                return resp.read()
        except urllib.error.HTTPError as exc:
            body = exc.read().decode("utf-8", "replace")
            try:
                err = json.loads(body)
                detail = err.get("error", {}).get("message", "") if isinstance(err.get("error"), dict) else err
                nodes = err.get("node_errors") or {}
                for nid, ne in nodes.items():
                    detail = f"{detail}; node {nid}: " + "; ".join(e.get("message", "") + " " + e.get("details", "")
                                                                for e in ne.get("errors", []))
            except (json.JSONDecodeError, AttributeError):
                detail = body[:500]
            raise ComfyError(f"ComfyUI refused {path} (HTTP {exc.code}): {detail}") from None
        except (urllib.error.URLError, OSError) as exc:
            raise ComfyError(f"Cannot reach ComfyUI at {self.server} ({exc}); start it (python main.py) or pass "
                             "--server") from None

    def upload_image(self, path: Path) -> str:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"Image not found: {path}")
        body, ctype = _multipart("image", path.name, path.read_bytes(), {"overwrite": "true", "type": "input"})
        info = json.loads(self._request("/upload/image", body, ctype))
        return f"{info['subfolder']}/{info['name']}" if info.get("subfolder") else info["name"]

    def queue(self, prompt: dict) -> str:
        data = json.dumps({"prompt": prompt, "client_id": self.client_id}).encode()
        return json.loads(self._request("/prompt", data))["prompt_id"]

    def history(self, prompt_id: str) -> Optional[dict]:
        return json.loads(self._request(f"/history/{prompt_id}")).get(prompt_id)

    def object_info(self) -> dict:
        return json.loads(self._request("/object_info"))

    def _finished(self, prompt_id: str) -> Optional[dict]:
        """The history entry once the prompt has run (raising if it failed), else None."""
        entry = self.history(prompt_id)
        if not entry:
            return None
        status = entry.get("status", {})
        if status.get("status_str") == "error":
            msgs = [m[1].get("exception_message", "").strip() for m in status.get("messages", [])
                    if m[0] == "execution_error"]
            raise ComfyError("The workflow failed on the server: " + ("; ".join(msgs) or "see the server log"))
        return entry if status.get("completed", True) else None

    def wait(self, prompt_id: str, on_event: Optional[Callable[[str, dict], None]] = None,
             timeout: float = 3600.0, poll: float = 0.5) -> dict:
        """Block until the prompt has run, passing websocket events (type, data) to ``on_event``;
        return its history entry. Without a websocket it polls /history."""
        deadline = time.monotonic() + timeout
        ws, self._ws = self._ws, None
        if ws is None:
            ws = self._open_socket(poll)
        last_check = time.monotonic()
        try:
            while time.monotonic() < deadline:
                if ws is None:
                    time.sleep(poll)
                    entry = self._finished(prompt_id)
                    if entry is not None:
                        return entry
                    continue
                try:
                    text = _recv_text(ws)
                except (websocket.WebSocketTimeoutException, socket.timeout):
                    # Messages sent before the socket opened are lost: look at /history now and then.
                    if time.monotonic() - last_check > 2.0:
                        last_check = time.monotonic()
                        entry = self._finished(prompt_id)
                        if entry is not None:
                            return entry
                    continue
                except (OSError, websocket.WebSocketException):
                    text = None
                if text is None:  # the server closed the socket: go on by polling
                    log.info("ComfyUI closed the progress socket; polling %s/history", self.server)
                    _close_socket(ws)
                    ws = None
                    continue
                msg = json.loads(text)
                kind, data = msg.get("type", ""), msg.get("data", {}) or {}
                if data.get("prompt_id", prompt_id) != prompt_id:
                    continue
                if on_event:
                    on_event(kind, data)
                if kind == "execution_interrupted":
                    raise ComfyError(f"The run was cancelled on the server (at node {data.get('node_id')}, "
                                     f"{data.get('node_type')})")
                if kind == "execution_error":
                    raise ComfyError(f"Node {data.get('node_id')} ({data.get('node_type')}) failed on the server: "
                                     f"{str(data.get('exception_message', '')).strip()}")
                if kind == "executing" and data.get("node") is None:
                    entry = self._finished(prompt_id)
                    if entry is not None:
                        return entry
            raise ComfyError(f"Timed out after {timeout:.0f}s waiting for prompt {prompt_id}")
        finally:
            if ws is not None:
                _close_socket(ws)

    def interrupt(self) -> None:
        """Cancel the running prompt (the server checks between substeps/frames/iterations)."""
        self._request("/interrupt", b"{}")

    def download_outputs(self, entry: dict, out_dir: Path, types: tuple[str, ...] = ("output",)) -> list[Path]:
        """Download the files the output nodes list. Only saved outputs by default: node previews
        (type "temp", e.g. Render's and Blend's preview clips) are skipped unless ``types`` names them."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        saved = []
        for node_out in entry.get("outputs", {}).values():
            for items in node_out.values():
                if not isinstance(items, list):
                    continue
                for it in items:
                    if not (isinstance(it, dict) and "filename" in it):
                        continue
                    if it.get("type", "output") not in types:
                        continue
                    q = urllib.parse.urlencode({"filename": it["filename"], "subfolder": it.get("subfolder", ""),
                                                "type": it.get("type", "output")})
                    data = self._request(f"/view?{q}")
                    name = Path(it["filename"]).name  # never a path from the server
                    with atomic_output(out_dir / name) as tmp:
                        Path(tmp).write_bytes(data)
                    saved.append(out_dir / name)
        return saved


def run_workflow(workflow: Path, server: str, out_dir: Path, *, image: Optional[Path] = None,
                 sets: Optional[list[str]] = None, on_event=None, timeout: float = 3600.0,
                 previews: bool = False) -> list[Path]:
    """Upload, edit, queue, follow and download: the whole headless run. Returns the saved files
    (with ``previews`` also the nodes' preview files from the server's temp folder)."""
    from .workflow import ui_to_api

    try:
        prompt = json.loads(Path(workflow).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"Cannot read the workflow {workflow}: {exc}") from None
    client = ComfyClient(server)
    if "nodes" in prompt and "links" in prompt:
        prompt = ui_to_api(prompt, client.object_info())  # a UI-format workflow: convert with the server's schemas
    if image is not None:
        loaders = [k for k, n in prompt.items() if n.get("class_type") == "LoadImage"]
        if len(loaders) != 1:
            raise InputError(f"--image needs exactly one LoadImage node; this workflow has {len(loaders)}. "
                             "Upload it and use --set NODE.image=NAME instead")
        prompt[loaders[0]]["inputs"]["image"] = client.upload_image(image)
    apply_sets(prompt, sets or [])
    client.connect()
    try:
        prompt_id = client.queue(prompt)
        entry = client.wait(prompt_id, on_event, timeout=timeout)
    finally:
        if client._ws is not None:
            _close_socket(client._ws)
            client._ws = None
    return client.download_outputs(entry, out_dir, ("output", "temp") if previews else ("output",))
