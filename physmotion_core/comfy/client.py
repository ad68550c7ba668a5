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

import http.client
import json
import logging
import os
import socket
import ssl
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
from pathlib import Path
from typing import Callable, Optional

import websocket  # websocket-client

from ..errors import InputError, PhysMotionError
from ..fsutil import atomic_output, check_free_space

log = logging.getLogger("physmotion")


class ComfyError(PhysMotionError):
    """The server refused the prompt, or its execution failed, or it answered in a way no ComfyUI
    does (not JSON where JSON belongs, an output file name that is not a file name, a redirect to
    another host), or it did not answer in time."""


class ComfyCancelled(ComfyError):
    """The run was cancelled on the server (Cancel in the UI, ``POST /interrupt``): not a failure. ComfyUI
    records an interrupt in /history as status ``error`` with an ``execution_interrupted`` message, and
    says it on the websocket; either may reach the client first, and both read as this."""


def _cancelled_message(data: dict) -> str:
    node, kind = data.get("node_id"), data.get("node_type")
    where = f" at node {node} ({kind})" if node is not None or kind else ""
    return f"The run was cancelled on the server{where}: Cancel was pressed or /interrupt was posted; nothing failed."


#: The longest an API answer (JSON) may be; downloads (/view) are streamed to disk instead.
MAX_JSON_BYTES = 64 << 20
#: A download must bring at least this many bytes in every ``read_timeout`` window: a server that
#: sends a byte every few seconds (each read within the socket timeout) is stalled, not slow.
MIN_DOWNLOAD_BYTES_PER_WINDOW = 64 << 10
#: Same-host redirects followed at most (ComfyUI itself never redirects its API).
MAX_REDIRECTS = 3


class _Guard:
    """Shut a socket down when a deadline passes. Socket timeouts bound each read, not a request:
    a server that answers one byte at a time, each within the timeout, would hold a blocking read
    (a header line, a websocket frame) forever. A timer shuts the socket down at the deadline, which
    ends any read in progress; ``fired`` tells the caller why the read failed."""

    def __init__(self, deadline: float, get_sock: Callable[[], Optional[socket.socket]]):
        self.fired = False
        self._get_sock = get_sock
        self._timer = threading.Timer(max(deadline - time.monotonic(), 0.0), self._fire)
        self._timer.daemon = True

    def _fire(self) -> None:
        self.fired = True
        try:
            sock = self._get_sock()
        except Exception:  # noqa: BLE001 - nothing to shut down
            sock = None
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except (OSError, ValueError):
                pass

    def __enter__(self) -> "_Guard":
        self._timer.start()
        return self

    def __exit__(self, *exc) -> bool:
        self._timer.cancel()
        return False


def _snippet(body: bytes, n: int = 120) -> str:
    text = body[:n].decode("utf-8", "replace")
    return " ".join(text.split())


def _json(body: bytes, what: str, server: str, content_type: str = ""):
    """Parse an API answer, or say plainly that the server did not answer as ComfyUI does."""
    try:
        return json.loads(body)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError):
        kind = (content_type or "").split(";")[0].strip() or "no content type"
        raise ComfyError(f"{server} answered {what} with something that is not JSON ({kind}: "
                         f"'{_snippet(body)}'). Is --server the address of ComfyUI itself (not a proxy's login "
                         "page or another web server)?") from None


def _safe_name(value, what: str) -> str:
    """An output file name from the server as a plain file name, or a ComfyError saying why not."""
    if not isinstance(value, str):
        raise ComfyError(f"the server listed an output whose {what} is {value!r} ({type(value).__name__}), not a "
                         "file name; this is not a ComfyUI answer (or a custom node writes a broken output list)")
    if "\x00" in value or any(ord(c) < 32 for c in value):
        raise ComfyError(f"the server listed an output {what} with a NUL or control character ({value!r:.80}); "
                         "refusing to use it as a file name")
    return value


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


#: Inputs that are pixels of the workflow's own photo: they mean nothing on another one.
PLACED_INPUTS = {"PhysMotionSegment": ("box", "object_points", "background_points"),
                 "PhysMotionSAMSegment": ("points", "boxes"),
                 "PhysMotionForce": ("u", "v"), "PhysMotionTorque": ("u", "v")}


def placed_on_its_own_photo(prompt: dict, sets: list[str]) -> list[str]:
    """For a workflow run on another photo (``--image``): the inputs still holding pixels placed on the
    workflow's own photo (a Segment node's box and points, a Force or Torque node's image point), that no
    ``--set`` gave. Each as "NODE.INPUT = value"."""
    given = set()
    for item in sets:
        target = item.split("=", 1)[0]
        if "." in target:
            node_ref, name = target.rsplit(".", 1)
            try:
                given.add((find_node(prompt, node_ref), name))
            except InputError:
                pass
    out = []
    for nid, node in prompt.items():
        if not isinstance(node, dict):
            continue
        cls, inputs = node.get("class_type"), node.get("inputs", {})
        names = PLACED_INPUTS.get(cls, ())
        if cls in ("PhysMotionForce", "PhysMotionTorque") and inputs.get("region") != "image point":
            continue
        for name in names:
            value = inputs.get(name)
            if value in (None, "") or (nid, name) in given or (isinstance(value, list) and len(value) == 2
                                                               and isinstance(value[0], str)):
                continue
            ref = cls if sum(1 for n in prompt.values() if isinstance(n, dict) and n.get("class_type") == cls) == 1 \
                else nid
            out.append(f"{ref}.{name} = {value!r}")
    return out


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
    """``timeout``: the longest a single read may wait for the server; ``request_timeout``: the longest
    one API request (upload, queue, history, ...) may take from connecting to its last byte;
    ``deadline`` (a time.monotonic() value, set by run_workflow): no request, wait or download goes
    past it. Downloads are not bound by ``request_timeout`` (a video may be large) but must keep
    moving: at least MIN_DOWNLOAD_BYTES_PER_WINDOW in every ``timeout`` seconds."""

    def __init__(self, server: str = "http://127.0.0.1:8188", timeout: float = 30.0,
                 request_timeout: float = 120.0, deadline: Optional[float] = None):
        if not server.startswith(("http://", "https://")):
            server = "http://" + server
        self.server = server.rstrip("/")
        parsed = urllib.parse.urlsplit(self.server)
        if not parsed.hostname:
            raise InputError(f"--server {server!r} has no host name; give e.g. http://127.0.0.1:8188")
        try:
            self._origin = (parsed.scheme, parsed.hostname.lower(), parsed.port or (443 if parsed.scheme == "https"
                                                                                   else 80))
        except ValueError as exc:
            raise InputError(f"--server {server!r}: {exc}; give e.g. http://127.0.0.1:8188") from None
        self._base_path = parsed.path.rstrip("/")
        self.timeout = timeout
        self.request_timeout = request_timeout
        self.deadline = deadline
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
        made: list = []

        class _Tracked(websocket.WebSocket):  # lets the guard reach the socket during the handshake
            def __init__(self, *a, **kw):
                super().__init__(*a, **kw)
                made.append(self)

        guard = _Guard(self._until(10.0), lambda: made[0].sock if made else None)  # a dripped handshake ends too
        try:
            with guard:
                ws = websocket.create_connection(url, timeout=min(5.0, self._left()), class_=_Tracked,
                                                 sslopt={"context": self._tls} if self._tls is not None else {})
        except (OSError, websocket.WebSocketException, ValueError) as exc:
            if guard.fired:
                exc = TimeoutError("the handshake did not complete in time")
            for w in made:
                _close_socket(w)
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

    # ------------------------------------------------------------------------------------------
    # deadlines and HTTP
    # ------------------------------------------------------------------------------------------

    def _left(self) -> float:
        """Seconds left before the run's deadline (the whole-run timeout); raises once it has passed."""
        if self.deadline is None:
            return float("inf")
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise ComfyError(f"the run on {self.server} did not finish within its time limit (--timeout); "
                             "nothing more was asked of the server. Raise --timeout for longer workflows.")
        return left

    def _until(self, seconds: float) -> float:
        """The monotonic time ``seconds`` from now, or the run's deadline if that comes first."""
        return time.monotonic() + min(seconds, self._left())

    def _connection(self, timeout: float) -> http.client.HTTPConnection:
        scheme, host, port = self._origin
        if scheme == "https":
            return http.client.HTTPSConnection(host, port, timeout=timeout, context=self._tls)
        return http.client.HTTPConnection(host, port, timeout=timeout)

    def _call(self, path: str, data: Optional[bytes], content_type: str, end: float, handle):
        """One request (following at most MAX_REDIRECTS redirects to the same host), answered by
        ``handle(response, end)``. Everything, from connecting to the last byte, ends by ``end``."""
        method = "POST" if data is not None else "GET"
        target = path
        for _ in range(MAX_REDIRECTS + 1):
            conn = self._connection(timeout=max(0.05, min(self.timeout, end - time.monotonic())))
            guard = _Guard(end, lambda c=conn: c.sock)
            connected = False
            try:
                with guard:
                    conn.connect()
                    connected = True
                    headers = {"Content-Type": content_type} if data is not None else {}
                    conn.request(method, self._base_path + target, body=data, headers=headers)
                    resp = conn.getresponse()
                    if resp.status in (301, 302, 303, 307, 308):
                        location = resp.getheader("Location") or ""
                        target = self._same_origin(path, location)
                        if resp.status == 303:
                            method, data = "GET", None
                        continue
                    if resp.status >= 400:
                        body = resp.read(64 << 10)
                        raise ComfyError(f"ComfyUI refused {path} (HTTP {resp.status}): {self._error_detail(body)}")
                    return handle(resp, end, guard)
            except PhysMotionError:  # ours (a refusal, a full disk): already says what happened
                raise
            except (OSError, http.client.HTTPException, ssl.SSLError, ValueError) as exc:
                if guard.fired or time.monotonic() >= end:
                    raise ComfyError(f"ComfyUI at {self.server} did not answer {path.split('?')[0]} in time "
                                     f"({self._limit_text(end)}); the server is stalled or sends too slowly. "
                                     "Check the server (its log, its load), or raise --timeout.") from None
                if not connected:  # refused, no such host, TLS verification failed, ...
                    raise ComfyError(f"Cannot reach ComfyUI at {self.server} ({exc}); start it (python main.py) or "
                                     "pass --server") from None
                raise ComfyError(f"ComfyUI at {self.server} broke off its answer to {path.split('?')[0]} "
                                 f"({type(exc).__name__}: {exc}); check the server's log") from None
            finally:
                conn.close()
        raise ComfyError(f"ComfyUI at {self.server} redirected {path.split('?')[0]} more than {MAX_REDIRECTS} times; "
                         "refusing to follow further")

    def _limit_text(self, end: float) -> str:
        if self.deadline is not None and end >= self.deadline - 1e-3:
            return "the run's --timeout was reached"
        return f"limit {self.request_timeout:g} s per request"

    def _same_origin(self, path: str, location: str) -> str:
        """The path a redirect points to, when it stays on this server; anything else is refused:
        a client of an untrusted server must not be sent to other hosts."""
        url = urllib.parse.urljoin(f"{self._origin[0]}://{self._origin[1]}:{self._origin[2]}{self._base_path}{path}",
                                   location)
        parts = urllib.parse.urlsplit(url)
        try:
            origin = (parts.scheme, (parts.hostname or "").lower(),
                      parts.port or (443 if parts.scheme == "https" else 80))
        except ValueError:
            origin = None
        if origin != self._origin:
            raise ComfyError(f"ComfyUI at {self.server} answered {path.split('?')[0]} with a redirect to "
                             f"'{location[:200]}', another host: refusing to follow it (ComfyUI never redirects "
                             "its API; a server that does may be pointing this client at other machines)")
        rel = parts.path
        if self._base_path and rel.startswith(self._base_path):
            rel = rel[len(self._base_path):]
        return rel + (f"?{parts.query}" if parts.query else "")

    @staticmethod
    def _error_detail(raw: bytes) -> str:
        body = raw.decode("utf-8", "replace")
        try:
            err = json.loads(body)
            if not isinstance(err, dict):
                return _snippet(raw, 500)
            detail = err.get("error", {}).get("message", "") if isinstance(err.get("error"), dict) else err
            nodes = err.get("node_errors") or {}
            for nid, ne in (nodes.items() if isinstance(nodes, dict) else ()):
                detail = f"{detail}; node {nid}: " + "; ".join(
                    str(e.get("message", "")) + " " + str(e.get("details", ""))
                    for e in (ne.get("errors", []) if isinstance(ne, dict) else []) if isinstance(e, dict))
            return str(detail)
        except (json.JSONDecodeError, AttributeError, TypeError):
            return _snippet(raw, 500)

    def _request(self, path: str, data: Optional[bytes] = None, content_type: str = "application/json") -> bytes:
        """An API request's whole answer (at most MAX_JSON_BYTES), within ``request_timeout`` and the run."""
        return self._request_typed(path, data, content_type)[0]

    def _request_typed(self, path: str, data: Optional[bytes] = None,
                       content_type: str = "application/json") -> tuple[bytes, str]:
        """(answer, its Content-Type): see ``_request``."""
        end = self._until(self.request_timeout)

        def read_all(resp, end, guard):
            chunks, total = [], 0
            while True:
                chunk = resp.read1(1 << 16)
                if not chunk:
                    if guard.fired:  # the deadline shut the socket: this end is not the answer's end
                        raise TimeoutError("deadline")
                    break
                total += len(chunk)
                if total > MAX_JSON_BYTES:
                    raise ComfyError(f"ComfyUI's answer to {path.split('?')[0]} is larger than "
                                     f"{MAX_JSON_BYTES >> 20} MiB; no API answer is that large")
                chunks.append(chunk)
            return b"".join(chunks), resp.getheader("Content-Type") or ""

        return self._call(path, data, content_type, end, read_all)

    def _request_json(self, path: str, data: Optional[bytes] = None, content_type: str = "application/json",
                      expect=dict):
        body, ctype = self._request_typed(path, data, content_type)
        value = _json(body, path.split("?")[0], self.server, ctype)
        if expect is not None and not isinstance(value, expect):
            raise ComfyError(f"{self.server} answered {path.split('?')[0]} with JSON of the wrong shape "
                             f"('{_snippet(body)}'); this is not a ComfyUI answer")
        return value

    def download(self, query: str, target: Path, label: str) -> Path:
        """Stream GET /view?``query`` into ``target`` (a temporary file beside it, renamed when complete):
        never held in memory; a Content-Length larger than the disk's free space is refused before
        the first byte."""
        path = f"/view?{query}"
        end = self._until(float("inf")) if self.deadline is not None else time.monotonic() + 24 * 3600.0

        def stream(resp, end, guard):
            length = resp.getheader("Content-Length")
            size = int(length) if length and length.isdigit() else None
            if size is not None:
                check_free_space(target.parent, size, f"The output {label}")
            with atomic_output(target, suffix=".part", need_bytes=size) as tmp:
                with open(tmp, "wb") as fh:
                    window_start, window_bytes = time.monotonic(), 0
                    while True:
                        chunk = resp.read1(1 << 20)
                        if not chunk:
                            if guard.fired:
                                raise TimeoutError("deadline")
                            break
                        fh.write(chunk)
                        window_bytes += len(chunk)
                        now = time.monotonic()
                        if now - window_start >= self.timeout:
                            if window_bytes < MIN_DOWNLOAD_BYTES_PER_WINDOW:
                                raise ComfyError(
                                    f"ComfyUI at {self.server} sent {label} at {window_bytes} bytes in "
                                    f"{now - window_start:.0f} s; the download is stalled (at least "
                                    f"{MIN_DOWNLOAD_BYTES_PER_WINDOW >> 10} KiB per {self.timeout:g} s is needed). "
                                    "Check the server and the network.")
                            window_start, window_bytes = now, 0
                if size is not None and os.path.getsize(tmp) != size:
                    raise ComfyError(f"ComfyUI at {self.server} sent {os.path.getsize(tmp)} bytes of {label} but "
                                     f"announced {size}; the download was cut short (nothing was saved)")
            return target

        return self._call(path, None, "", end, stream)

    def upload_image(self, path: Path) -> str:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"Image not found: {path}")
        body, ctype = _multipart("image", path.name, path.read_bytes(), {"overwrite": "true", "type": "input"})
        info = self._request_json("/upload/image", body, ctype)
        name, sub = info.get("name"), info.get("subfolder") or ""
        if not isinstance(name, str) or not name or not isinstance(sub, str):
            raise ComfyError(f"{self.server} answered /upload/image without the uploaded file's name ({info!r:.200}); "
                             "this is not a ComfyUI answer")
        return f"{sub}/{name}" if sub else name

    def queue(self, prompt: dict) -> str:
        data = json.dumps({"prompt": prompt, "client_id": self.client_id}).encode()
        answer = self._request_json("/prompt", data)
        pid = answer.get("prompt_id")
        if not isinstance(pid, str) or not pid or len(pid) > 200:
            raise ComfyError(f"{self.server} answered /prompt without a prompt id ({answer!r:.200}); this is not a "
                             "ComfyUI answer")
        return pid

    def history(self, prompt_id: str) -> Optional[dict]:
        entry = self._request_json(f"/history/{urllib.parse.quote(prompt_id, safe='')}").get(prompt_id)
        if entry is not None and not isinstance(entry, dict):
            raise ComfyError(f"{self.server}'s /history entry for {prompt_id} is not a JSON object; this is not a "
                             "ComfyUI answer")
        return entry

    def object_info(self) -> dict:
        return self._request_json("/object_info")

    def _finished(self, prompt_id: str) -> Optional[dict]:
        """The history entry once the prompt has run, else None. A failed run raises ComfyError, a cancelled
        one (status ``error`` with an ``execution_interrupted`` message) ComfyCancelled."""
        entry = self.history(prompt_id)
        if not entry:
            return None
        status = entry.get("status", {})
        if not isinstance(status, dict):
            status = {}
        if status.get("status_str") == "error":
            for m in status.get("messages", []) or []:
                if isinstance(m, (list, tuple)) and len(m) == 2 and m[0] == "execution_interrupted":
                    raise ComfyCancelled(_cancelled_message(m[1] if isinstance(m[1], dict) else {}))
            msgs = [str(m[1].get("exception_message", "")).strip() for m in status.get("messages", []) or []
                    if isinstance(m, (list, tuple)) and len(m) == 2 and m[0] == "execution_error"
                    and isinstance(m[1], dict)]
            raise ComfyError("The workflow failed on the server: " + ("; ".join(msgs) or "see the server log"))
        return entry if status.get("completed", True) else None

    def _recv_guarded(self, ws: websocket.WebSocket) -> Optional[str]:
        """The next text message, within ``request_timeout`` and the run: a frame dripped a byte at a
        time (each read within the socket's timeout) cannot hold the client."""
        end = self._until(self.request_timeout)
        with _Guard(end, lambda: ws.sock) as guard:
            try:
                return _recv_text(ws)
            except (websocket.WebSocketTimeoutException, socket.timeout):
                if guard.fired:
                    raise TimeoutError("a progress message took too long to arrive") from None
                raise
            except (OSError, websocket.WebSocketException):
                if guard.fired:
                    raise TimeoutError("a progress message took too long to arrive") from None
                raise

    def wait(self, prompt_id: str, on_event: Optional[Callable[[str, dict], None]] = None,
             timeout: float = 3600.0, poll: float = 0.5) -> dict:
        """Block until the prompt has run, passing websocket events (type, data) to ``on_event``;
        return its history entry. Without a websocket it polls /history. A progress socket that
        sends what no ComfyUI sends (not JSON, a message that is not an object) or stalls mid-message
        is closed, said once in the log, and the run is followed on /history instead."""
        deadline = time.monotonic() + timeout
        if self.deadline is not None:
            deadline = min(deadline, self.deadline)
        ws, self._ws = self._ws, None
        if ws is None:
            ws = self._open_socket(poll)
        last_check = time.monotonic()

        def drop_socket(why: str) -> None:
            nonlocal ws
            log.warning("ComfyUI's progress socket %s; following the run by polling %s/history instead",
                        why, self.server)
            _close_socket(ws)
            ws = None

        try:
            while time.monotonic() < deadline:
                if ws is None:
                    time.sleep(min(poll, max(deadline - time.monotonic(), 0)))
                    if time.monotonic() >= deadline:
                        break
                    entry = self._finished(prompt_id)
                    if entry is not None:
                        return entry
                    continue
                try:
                    text = self._recv_guarded(ws)
                except (websocket.WebSocketTimeoutException, socket.timeout):
                    # Messages sent before the socket opened are lost: look at /history now and then.
                    if time.monotonic() - last_check > 2.0:
                        last_check = time.monotonic()
                        entry = self._finished(prompt_id)
                        if entry is not None:
                            return entry
                    continue
                except TimeoutError:
                    drop_socket(f"stalled in the middle of a message (limit {self.request_timeout:g} s)")
                    continue
                except (OSError, websocket.WebSocketException):
                    text = None
                if text is None:  # the server closed the socket: go on by polling
                    log.info("ComfyUI closed the progress socket; polling %s/history", self.server)
                    _close_socket(ws)
                    ws = None
                    continue
                try:
                    msg = json.loads(text)
                except (json.JSONDecodeError, RecursionError):
                    drop_socket(f"sent a message that is not JSON ('{_snippet(text.encode())}'), which ComfyUI "
                                "never does")
                    continue
                data = msg.get("data", {}) if isinstance(msg, dict) else None
                data = {} if data is None else data
                if not isinstance(msg, dict) or not isinstance(data, dict):
                    drop_socket(f"sent a message that is not a ComfyUI event ('{_snippet(text.encode())}')")
                    continue
                kind = msg.get("type", "")
                if data.get("prompt_id", prompt_id) != prompt_id:
                    continue
                if on_event:
                    on_event(kind, data)
                if kind == "execution_interrupted":
                    raise ComfyCancelled(_cancelled_message(data))
                if kind == "execution_error":
                    raise ComfyError(f"Node {data.get('node_id')} ({data.get('node_type')}) failed on the server: "
                                     f"{str(data.get('exception_message', '')).strip()}")
                if kind == "executing" and data.get("node") is None:
                    entry = self._finished(prompt_id)
                    if entry is not None:
                        return entry
            raise ComfyError(f"Timed out waiting for prompt {prompt_id} to finish on {self.server} (the run's time "
                             "limit, --timeout, was reached); raise --timeout for longer workflows")
        finally:
            if ws is not None:
                _close_socket(ws)

    def interrupt(self) -> None:
        """Cancel the running prompt (the server checks between substeps/frames/iterations)."""
        self._request("/interrupt", b"{}")

    def _planned_outputs(self, entry: dict, types: tuple[str, ...]) -> list[tuple[dict, str]]:
        """(item, local file name) of every file the output nodes list, each once, with names that
        never collide: two outputs of one name in different subfolders (or types) are both kept, the
        later ones named after their subfolder (``sub_dir__name.mp4``)."""
        outputs = entry.get("outputs", {})
        if not isinstance(outputs, dict):
            raise ComfyError(f"{self.server}'s history lists the outputs as {type(outputs).__name__}, not a table; "
                             "this is not a ComfyUI answer")
        items, seen = [], set()
        for node_out in outputs.values():
            if not isinstance(node_out, dict):
                continue
            for listed in node_out.values():
                if not isinstance(listed, list):
                    continue
                for it in listed:
                    if not (isinstance(it, dict) and "filename" in it):
                        continue
                    kind = it.get("type", "output")
                    if kind not in types:
                        continue
                    filename = _safe_name(it["filename"], "file name")
                    sub = _safe_name(it.get("subfolder", "") or "", "subfolder")
                    _safe_name(kind, "type")
                    name = filename.replace("\\", "/").rsplit("/", 1)[-1]  # never a path from the server
                    if name in ("", ".", "..") or len(name.encode("utf-8", "surrogateescape")) > 200:
                        raise ComfyError(f"the server listed an output file name {filename!r:.80} that is not a "
                                         "usable file name (empty, '.', '..' or over 200 bytes)")
                    key = (filename, sub, kind)
                    if key in seen:
                        continue
                    seen.add(key)
                    items.append((dict(it, filename=filename, subfolder=sub, type=kind), name))
        planned, used = [], set()
        for it, name in items:
            local = name
            if local in used:
                prefix = "_".join(p for p in it["subfolder"].replace("\\", "/").split("/") if p not in ("", ".", ".."))
                stem = f"{prefix or it['type']}__{name}"
                local, n = stem, 2
                while local in used:
                    local, n = f"{n}_{stem}", n + 1
            used.add(local)
            planned.append((it, local))
        return planned

    def download_outputs(self, entry: dict, out_dir: Path, types: tuple[str, ...] = ("output",)) -> list[Path]:
        """Download the files the output nodes list, each streamed into the output folder (see
        ``download``). Only saved outputs by default: node previews (type "temp", e.g. Render's and
        Blend's preview clips) are skipped unless ``types`` names them."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        saved = []
        for it, local in self._planned_outputs(entry, types):
            q = urllib.parse.urlencode({"filename": it["filename"], "subfolder": it["subfolder"], "type": it["type"]})
            label = f"'{it['subfolder'] + '/' if it['subfolder'] else ''}{it['filename']}'"
            saved.append(self.download(q, out_dir / local, label))
        return saved


def run_workflow(workflow: Path, server: str, out_dir: Path, *, image: Optional[Path] = None,
                 sets: Optional[list[str]] = None, on_event=None, timeout: float = 3600.0,
                 previews: bool = False, request_timeout: float = 120.0, read_timeout: float = 30.0) -> list[Path]:
    """Upload, edit, queue, follow and download: the whole headless run, all of it within ``timeout``
    seconds (each API request also within ``request_timeout``, each read within ``read_timeout``).
    Returns the saved files (with ``previews`` also the nodes' preview files from the server's temp
    folder)."""
    from .workflow import ui_to_api

    if not (isinstance(timeout, (int, float)) and timeout > 0):
        raise InputError(f"--timeout must be a positive number of seconds; got {timeout!r}")
    deadline = time.monotonic() + float(timeout)
    try:
        prompt = json.loads(Path(workflow).read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"Cannot read the workflow {workflow}: {exc}") from None
    if not isinstance(prompt, dict):
        raise InputError(f"The workflow {workflow} is not a JSON object of nodes (API format) or a UI workflow")
    client = ComfyClient(server, timeout=read_timeout, request_timeout=request_timeout, deadline=deadline)
    if "nodes" in prompt and "links" in prompt:
        prompt = ui_to_api(prompt, client.object_info())  # a UI-format workflow: convert with the server's schemas
    if image is not None:
        loaders = [k for k, n in prompt.items() if isinstance(n, dict) and n.get("class_type") == "LoadImage"]
        if len(loaders) != 1:
            raise InputError(f"--image needs exactly one LoadImage node; this workflow has {len(loaders)}. "
                             "Upload it and use --set NODE.image=NAME instead")
        prompt[loaders[0]]["inputs"]["image"] = client.upload_image(image)
    apply_sets(prompt, sets or [])
    if image is not None:
        stale = placed_on_its_own_photo(prompt, sets or [])
        if stale:
            text = ("the workflow's " + "; ".join(stale) + f" were placed on its own photo, not on {Path(image).name}: "
                    "give them for your photo with --set NODE.INPUT=VALUE (a Segment node's box or points empty to "
                    "let it pick automatically; a Force's region 'whole object' to push all of it), or set them to "
                    "the same values to keep them")
            log.warning("%s", text)
    client.connect()
    try:
        prompt_id = client.queue(prompt)
        entry = client.wait(prompt_id, on_event, timeout=max(deadline - time.monotonic(), 0.0))
    finally:
        if client._ws is not None:
            _close_socket(client._ws)
            client._ws = None
    return client.download_outputs(entry, out_dir, ("output", "temp") if previews else ("output",))
