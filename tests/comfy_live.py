"""A real ComfyUI server with only this pack, for the live tests (tests/test_comfyui_live.py,
tests/test_browser.py). Skipped unless ``COMFYUI_DIR`` points at a ComfyUI checkout.

The server runs from ComfyUI's own Python (``COMFYUI_PYTHON``; default: the Python running the tests)
with ``--cpu --listen 127.0.0.1 --port <free port>``, a fresh ``--base-directory`` whose
``custom_nodes/`` holds only a link to this repository, and ``--disable-all-custom-nodes
--whitelist-custom-nodes ComfyUI-PhysMotion`` so nothing else the checkout has installed loads.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from comfy_harness import ROOT

PACK_NAME = "ComfyUI-PhysMotion"
COMFYUI_DIR = os.environ.get("COMFYUI_DIR", "")
STARTUP_TIMEOUT_S = float(os.environ.get("COMFYUI_STARTUP_TIMEOUT", "240"))

requires_comfyui = pytest.mark.skipif(
    not (COMFYUI_DIR and (Path(COMFYUI_DIR) / "main.py").is_file()),
    reason="set COMFYUI_DIR to a ComfyUI checkout (and COMFYUI_PYTHON to its Python) to run the live tests")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ComfyServer:
    def __init__(self, base: Path):
        self.base = base
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        (base / "custom_nodes").mkdir(parents=True, exist_ok=True)
        link = base / "custom_nodes" / PACK_NAME
        if not link.exists():
            link.symlink_to(ROOT, target_is_directory=True)
        for sub in ("input", "output", "temp", "user"):
            (base / sub).mkdir(exist_ok=True)
        python = os.environ.get("COMFYUI_PYTHON") or sys.executable
        self.log_path = base / "comfyui.log"
        cmd = [python, "main.py", "--cpu", "--listen", "127.0.0.1", "--port", str(self.port),
               "--base-directory", str(base), "--disable-all-custom-nodes",
               "--whitelist-custom-nodes", PACK_NAME, "--database-url", "sqlite:///:memory:",
               "--disable-auto-launch"]
        # COMFYUI_FRONTEND_ROOT: serve another frontend build (e.g. the static/ folder of the newest
        # comfyui-frontend-package wheel) instead of the one pinned by this ComfyUI.
        if os.environ.get("COMFYUI_FRONTEND_ROOT"):
            cmd += ["--front-end-root", os.environ["COMFYUI_FRONTEND_ROOT"]]
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        env.pop("PHYSMOTION_OUTPUT_DIR", None)
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(cmd, cwd=COMFYUI_DIR, stdout=self.log, stderr=subprocess.STDOUT, env=env)
        self._wait_ready()

    def _wait_ready(self) -> None:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"ComfyUI exited with {self.proc.returncode}:\n{self.log_tail()}")
            try:
                with urllib.request.urlopen(self.url + "/system_stats", timeout=2) as r:
                    if r.status == 200:
                        return
            except OSError:
                time.sleep(0.5)
        self.close()
        raise RuntimeError(f"ComfyUI did not answer within {STARTUP_TIMEOUT_S:.0f}s:\n{self.log_tail()}")

    def get_json(self, path: str):
        with urllib.request.urlopen(self.url + path, timeout=60) as r:
            return json.loads(r.read())

    def get_bytes(self, path: str) -> bytes:
        with urllib.request.urlopen(self.url + path, timeout=60) as r:
            return r.read()

    def log_tail(self, n: int = 4000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-n:]
        except OSError:
            return ""

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self.log.close()


@pytest.fixture(scope="module")
def comfy_server(tmp_path_factory):
    server = ComfyServer(tmp_path_factory.mktemp("comfyui_base"))
    try:
        yield server
    finally:
        server.close()


# Every workflow whose nodes need no weights runs on a CPU. Shrunk so the live suite stays quick.
TINY_SETS = {"PhysMotionSilhouetteLift": {"max_gaussians": 4000},
             "PhysMotionMPMSimulate": {"frames": 6, "grid_res": 8},
             "PhysMotionFitGaussiansToPhoto": {"max_render_side": 96}}


def cpu_capable(prompt: dict) -> bool:
    """No loader of learned weights in the graph."""
    return not any("Loader" in n["class_type"] for n in prompt.values())


def shrink(prompt: dict, prefix: str) -> dict:
    prompt = json.loads(json.dumps(prompt))
    for node in prompt.values():
        for name, value in TINY_SETS.get(node["class_type"], {}).items():
            node["inputs"][name] = value
        if "filename_prefix" in node["inputs"]:
            node["inputs"]["filename_prefix"] = f"live/{prefix}"
    return prompt
