"""Run a workflow on a ComfyUI server over its HTTP API (headless), with the standard library only.

    physmotion comfy-run example_workflows/api/push_a_jelly.json --server http://127.0.0.1:8188 \\
        --image photo.png --set 5.force_x=40 -o out/

Steps: upload the image (POST /upload/image) and point the workflow's LoadImage node at it, apply
``--set NODE.INPUT=VALUE`` edits, queue the prompt (POST /prompt), follow its progress on the
server's websocket (/ws: "progress" and "executing" messages; polling /history if the websocket
cannot be opened), then download every file its output nodes list (GET /view) into the output folder.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from pathlib import Path
from typing import Callable, Optional

from .errors import InputError, PhysMotionError
from .fsutil import atomic_output


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


class _WebSocket:
    """The few parts of RFC 6455 a progress listener needs: handshake, unmasked server text frames,
    ping/pong and close. Binary frames (ComfyUI's preview images) are skipped."""

    def __init__(self, url: str, timeout: float = 5.0):
        u = urllib.parse.urlparse(url)
        self.sock = socket.create_connection((u.hostname, u.port or 80), timeout=timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        path = u.path + ("?" + u.query if u.query else "")
        self.sock.sendall((f"GET {path} HTTP/1.1\r\nHost: {u.hostname}:{u.port or 80}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n")
                          .encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1024)
            if not chunk:
                raise OSError("websocket handshake: connection closed")
            head += chunk
        status, _, rest = head.partition(b"\r\n\r\n")
        if b" 101 " not in status.split(b"\r\n")[0]:
            raise OSError(f"websocket handshake refused: {status.splitlines()[0]!r}")
        self.buf = rest

    def _read(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise OSError("websocket closed")
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def _send(self, opcode: int, payload: bytes) -> None:
        mask = os.urandom(4)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(bytes([0x80 | opcode, 0x80 | len(payload)]) + mask + masked)

    def recv_text(self) -> Optional[str]:
        """The next text message; None when the server closes."""
        while True:
            b0, b1 = self._read(2)
            opcode, n = b0 & 0x0F, b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            mask = self._read(4) if b1 & 0x80 else None
            payload = self._read(n)
            if mask:
                payload = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
            if opcode == 8:
                return None
            if opcode == 9:
                self._send(10, payload[:125])
            elif opcode == 1:
                return payload.decode("utf-8", "replace")

    def close(self) -> None:
        try:
            self._send(8, b"")
        except OSError:
            pass
        self.sock.close()


class ComfyClient:
    def __init__(self, server: str = "http://127.0.0.1:8188", timeout: float = 30.0):
        if not server.startswith(("http://", "https://")):
            server = "http://" + server
        self.server = server.rstrip("/")
        self.timeout = timeout
        self.client_id = uuid.uuid4().hex
        self._ws: Optional[_WebSocket] = None

    def _open_socket(self, poll: float = 0.5) -> Optional[_WebSocket]:
        try:
            ws = _WebSocket(self.server.replace("http", "ws", 1) + f"/ws?clientId={self.client_id}")
            ws.sock.settimeout(poll)
            return ws
        except OSError:
            return None  # no websocket: progress is not shown and /history is polled

    def connect(self) -> None:
        """Open the progress socket before queueing, so that no message of the run is missed."""
        if self._ws is None:
            self._ws = self._open_socket()

    def _request(self, path: str, data: Optional[bytes] = None, content_type: str = "application/json") -> bytes:
        req = urllib.request.Request(self.server + path, data=data,
                                     headers={"Content-Type": content_type} if data is not None else {})
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
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
                    text = ws.recv_text()
                except socket.timeout:
                    # Messages sent before the socket opened are lost: look at /history now and then.
                    if time.monotonic() - last_check > 2.0:
                        last_check = time.monotonic()
                        entry = self._finished(prompt_id)
                        if entry is not None:
                            return entry
                    continue
                except OSError:
                    text = None
                if text is None:  # the server closed the socket: go on by polling
                    ws.close()
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
                ws.close()

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
            client._ws.close()
            client._ws = None
    return client.download_outputs(entry, out_dir, ("output", "temp") if previews else ("output",))
