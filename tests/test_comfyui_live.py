"""The pack inside a REAL ComfyUI (skipped unless COMFYUI_DIR is set; see docs/comfyui.md).

Starts ComfyUI on the CPU with only this pack, checks /object_info against the node classes, runs
every CPU-capable API workflow through /prompt -> websocket/history -> /view with the pack's own
headless client, decodes the videos and checks that they move; also the CLI with an uploaded
image, the node previews in /history and Cancel (POST /interrupt) latency.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from comfy_harness import ROOT, TEMPLATES_NOT_YET, load_pack, prepare_template_inputs
from comfy_live import comfy_server, cpu_capable, requires_comfyui, shrink  # noqa: F401 - fixture

from physmotion_core.comfy.client import ComfyClient, ComfyError, run_workflow
from physmotion_core.video import read_video

pytestmark = requires_comfyui
API = sorted((ROOT / "example_workflows" / "api").glob("*.json"))


def _names(section: dict) -> set:
    return set(section or {})


def test_object_info_lists_every_node_with_its_inputs_outputs_and_category(comfy_server):
    info = comfy_server.get_json("/object_info")
    ours = load_pack().NODE_CLASS_MAPPINGS
    missing = sorted(set(ours) - set(info))
    assert not missing, f"not registered in ComfyUI: {missing}\n{comfy_server.log_tail()}"
    for name, cls in ours.items():
        entry = info[name]
        types = cls.INPUT_TYPES()
        for section in ("required", "optional"):
            assert _names(entry["input"].get(section)) == _names(types.get(section)), (name, section)
            for inp, spec in (types.get(section) or {}).items():
                served = entry["input"][section][inp]
                kind = spec[0]
                if isinstance(kind, list):
                    assert isinstance(served[0], list), (name, inp)
                else:
                    assert served[0] == kind, (name, inp, served[0], kind)
                assert served[1].get("tooltip") == spec[1]["tooltip"], (name, inp)
        assert entry["output"] == list(cls.RETURN_TYPES), name
        assert entry["category"] == cls.CATEGORY, name
        assert entry["output_node"] == bool(getattr(cls, "OUTPUT_NODE", False)), name
    # The frontend extension and the templates are served too.
    assert any(e.endswith("/ComfyUI-PhysMotion/force_picker.js") for e in comfy_server.get_json("/extensions"))
    listed = comfy_server.get_json("/workflow_templates").get("ComfyUI-PhysMotion", [])
    assert sorted(listed) == sorted(p.stem for p in (ROOT / "example_workflows").glob("*.json")), listed
    # ... and served from the template route: each UI file and its thumbnail (the api/ twins are not
    # listed as templates).
    import urllib.error

    for name in listed:
        for ext in ("json", "jpg"):
            try:
                data = comfy_server.get_bytes(f"/api/workflow_templates/ComfyUI-PhysMotion/{name}.{ext}")
            except urllib.error.HTTPError as exc:
                raise AssertionError(f"the template route answers {exc.code} for {name}.{ext}") from exc
            if ext == "json":
                assert json.loads(data) == json.loads((ROOT / "example_workflows" / f"{name}.json").read_text()), name
            else:
                assert data[:3] == b"\xff\xd8\xff", f"{name}.jpg is not a JPEG"


def _video_moves(path, frames: int) -> None:
    video, fps = read_video(path)
    assert video.shape[0] == frames, (path, video.shape)
    diff = np.abs(video[-1].astype(np.float32) - video[0].astype(np.float32)).mean()
    assert diff > 0.5, f"{path.name}: first and last frames differ by only {diff:.3f} grey levels"


@pytest.mark.parametrize("path", [p for p in API if cpu_capable(json.loads(p.read_text()))
                                  and p.stem not in TEMPLATES_NOT_YET], ids=lambda p: p.stem)
def test_api_workflow_runs_on_comfyui_and_its_video_moves(comfy_server, path, tmp_path):
    prompt = shrink(json.loads(path.read_text()), path.stem)
    prepare_template_inputs(prompt, comfy_server.base / "output", max_gaussians=4000)  # "your own splat"
    wf = tmp_path / path.name
    wf.write_text(json.dumps(prompt))
    events = []
    saved = run_workflow(wf, comfy_server.url, tmp_path / "out", on_event=lambda k, d: events.append((k, d)),
                         timeout=600)
    videos = [p for p in saved if p.suffix == ".mp4"]
    assert videos, f"no video downloaded: {saved}\n{comfy_server.log_tail()}"
    for v in videos:
        _video_moves(v, 6)
    # The websocket reported the simulation's progress.
    sim = [nid for nid, n in prompt.items() if n["class_type"] == "PhysMotionMPMSimulate"]
    progress = [d for k, d in events if k == "progress" and d.get("node") in sim]
    # (by the simulated time: 100 steps a frame, physmotion_core.sim.simulate.PROGRESS_PER_FRAME)
    assert progress and all(d["max"] == 500 and 0 <= d["value"] <= 500 for d in progress), progress[-3:]


def test_previews_are_in_the_history_and_served(comfy_server, tmp_path):
    prompt = shrink(json.loads((ROOT / "example_workflows/api/push_a_jelly.json").read_text()), "previews")
    client = ComfyClient(comfy_server.url)
    client.connect()
    entry = client.wait(client.queue(prompt), timeout=600)
    outputs = entry["outputs"]
    by_class = {prompt[nid]["class_type"]: out for nid, out in outputs.items()}
    for cls in ("PhysMotionRender", "PhysMotionBlend", "SaveVideo"):
        ui = by_class[cls]
        assert ui["animated"] == [True], (cls, ui)
        item = ui["images"][0]
        assert item["filename"].endswith(".mp4")
        assert item["type"] == ("output" if cls == "SaveVideo" else "temp")
        data = comfy_server.get_bytes(f"/view?filename={item['filename']}&subfolder={item['subfolder']}"
                                      f"&type={item['type']}")
        clip = tmp_path / f"{cls}.mp4"
        clip.write_bytes(data)
        _video_moves(clip, 6)
    assert by_class["PhysMotionSegment"]["images"][0]["filename"].endswith(".png")
    # The .ply the template saves is in the output folder, where Preview3D / Load3D read it.
    ply = by_class["PhysMotionSaveGaussians"]["text"][0]
    assert (comfy_server.base / "output" / ply).stat().st_size > 1000


def test_cli_uploads_the_image_applies_sets_and_downloads(comfy_server, tmp_path):
    prompt = shrink(json.loads((ROOT / "example_workflows/api/push_a_jelly.json").read_text()), "cli")
    wf = tmp_path / "wf.json"
    wf.write_text(json.dumps(prompt))
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "physmotion_core.cli", "comfy-run", str(wf), "--server",
                           comfy_server.url, "--image", str(ROOT / "photos" / "ball.png"),
                           "--set", "PhysMotionForce.region=whole object", "--set", "PhysMotionMPMSimulate.frames=5",
                           "-o", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:] + comfy_server.log_tail()
    saved = [Path(s) for s in proc.stdout.split() if s.endswith(".mp4")]
    assert len(saved) == 1 and saved[0].parent == out
    _video_moves(saved[0], 5)
    assert (comfy_server.base / "input" / "ball.png").exists()  # uploaded
    assert "node " in proc.stderr  # progress lines from the websocket


def test_cancel_stops_a_running_simulation_within_a_second(comfy_server):
    prompt = json.loads((ROOT / "example_workflows/api/push_a_jelly.json").read_text())
    for node in prompt.values():  # long enough that it is certainly still simulating when cancelled
        if node["class_type"] == "PhysMotionMPMSimulate":
            node["inputs"].update(frames=400, grid_res=20)
        if node["class_type"] == "PhysMotionSilhouetteLift":
            node["inputs"]["max_gaussians"] = 4000
    client = ComfyClient(comfy_server.url)
    client.connect()
    pid = client.queue(prompt)
    sim = next(n for n, v in prompt.items() if v["class_type"] == "PhysMotionMPMSimulate")
    sent = {}

    def on_event(kind, data):
        if kind == "progress" and data.get("node") == sim and "t" not in sent and data["value"] >= 2:
            sent["t"] = time.monotonic()
            threading.Thread(target=client.interrupt, daemon=True).start()

    with pytest.raises(ComfyError, match="cancelled"):
        client.wait(pid, on_event, timeout=600)
    latency = time.monotonic() - sent["t"]
    assert latency < 1.0, f"Cancel took {latency:.2f}s"


def test_wan_control_nodes_get_the_prompt_and_run_alone_and_together(comfy_server, tmp_path):
    """The controls node reads ComfyUI's hidden PROMPT and UNIQUE_ID (to render the flow's channels only for a
    flow node that follows); the tracks node renders no clip (its preview over the first frame, or over a
    half-size clip). In a real ComfyUI the tracks node with either preview, the controls node alone and the
    controls node with Exact Flow after it run and give full-size images."""
    from PIL import Image

    sys.path.insert(0, str(ROOT / "scripts"))
    from make_wan_thumbnails import upstream

    full = shrink(json.loads((ROOT / "example_workflows/api/push_a_jelly.json").read_text()), "wanctl")
    sim_id = next(nid for nid, n in full.items() if n["class_type"] == "PhysMotionMPMSimulate")
    base = upstream(full, sim_id)
    clip = {"simulation": [sim_id, 0], "camera": full[sim_id]["inputs"]["camera"], "width": 160, "height": 96,
            "fps": 16.0, "length": 5}
    tracks = {"class_type": "PhysMotionPointTracks",
              "inputs": {**clip, "num_points": 8, "background_points": 2, "occlusion": "end track",
                         "preview": "first frame"}}
    coarse = {**tracks, "inputs": {**tracks["inputs"], "preview": "coarse video"}}
    controls = {"class_type": "PhysMotionControlVideos", "inputs": {**clip, "grow_mask": 4}}
    flow = {"class_type": "PhysMotionExactFlow",
            "inputs": {**clip, "direction": "forward", "max_flow": 0.0, "filename_prefix": "live/wanflow"}}
    client = ComfyClient(comfy_server.url)
    client.connect()
    for nodes in ({"90": tracks, "91": {"class_type": "PreviewImage", "inputs": {"images": ["90", 1]}}},
                  {"90": coarse, "91": {"class_type": "PreviewImage", "inputs": {"images": ["90", 1]}}},
                  {"90": controls, "91": {"class_type": "PreviewImage", "inputs": {"images": ["90", 0]}}},
                  {"90": controls, "91": {"class_type": "PreviewImage", "inputs": {"images": ["90", 4]}}, "92": flow}):
        outputs = client.wait(client.queue({**base, **nodes}), timeout=600)["outputs"]
        item = outputs["91"]["images"][0]
        data = comfy_server.get_bytes(f"/view?filename={item['filename']}&subfolder={item['subfolder']}"
                                      f"&type={item['type']}")
        (tmp_path / "p.png").write_bytes(data)
        assert Image.open(tmp_path / "p.png").size == (160, 96)
        if "92" in nodes:
            assert outputs["92"]["animated"] == [True]


def test_the_segment_nodes_click_shows_progress_and_cancel_stops_it(comfy_server):
    """A click on a 1024 px photo cuts for seconds: the Segment node's progress reaches the websocket, and
    Cancel (POST /interrupt) stops the cut at GrabCut's next iteration on both of its threads."""
    import cv2

    img = cv2.imread(str(ROOT / "photos" / "coffee.png"))
    big = cv2.resize(img, (1024, round(img.shape[0] * 1024 / img.shape[1])), interpolation=cv2.INTER_CUBIC)
    cv2.imwrite(str(comfy_server.base / "input" / "coffee_1024.png"), big)
    s = 1024 / img.shape[1]

    def prompt(iterations):
        return {"1": {"class_type": "LoadImage", "inputs": {"image": "coffee_1024.png"}},
                "2": {"class_type": "PhysMotionSegment",
                      "inputs": {"image": ["1", 0], "method": "grabcut", "mask_polarity": "auto",
                                 "grabcut_iterations": iterations, "object_points": f"{300 * s:.0f}, {235 * s:.0f}",
                                 "background_points": "", "box": "", "mask": ["1", 1]}},
                "3": {"class_type": "PreviewImage", "inputs": {"images": ["2", 3]}}}

    client = ComfyClient(comfy_server.url)
    client.connect()
    events = []
    client.wait(client.queue(prompt(5)), lambda k, d: events.append((k, d)), timeout=600)
    values = [d["value"] for k, d in events if k == "progress" and d.get("node") == "2"]
    assert len(values) >= 10 and values == sorted(values) and values[-1] == 100, values
    # again (6 iterations: not cached), cancelled once its progress shows the cut is under way
    sent = {}

    def on_event(kind, data):
        if kind == "progress" and data.get("node") == "2" and "t" not in sent and data["value"] >= 5:
            sent["t"] = time.monotonic()
            threading.Thread(target=client.interrupt, daemon=True).start()

    with pytest.raises(ComfyError, match="cancelled"):
        client.wait(client.queue(prompt(6)), on_event, timeout=600)
    latency = time.monotonic() - sent["t"]
    print(f"Segment node: Cancel took {latency:.2f} s")
    assert latency < 3.0, f"Cancel took {latency:.2f}s"


def test_the_simulate_nodes_forecast_reaches_the_node_as_text(comfy_server):
    """MPM Simulate sends its forecast (mass, what the push does) as the node's text (the websocket's binary
    TEXT event, which the frontend draws under the node) before the frames, and again after the run."""
    import struct
    import urllib.request
    import uuid

    import websocket

    prompt = shrink(json.loads((ROOT / "example_workflows/api/push_a_jelly.json").read_text()), "text")
    prepare_template_inputs(prompt, comfy_server.base / "output", max_gaussians=4000)
    sim = next(n for n, v in prompt.items() if v["class_type"] == "PhysMotionMPMSimulate")
    cid = uuid.uuid4().hex
    ws = websocket.create_connection(comfy_server.url.replace("http", "ws", 1) + f"/ws?clientId={cid}", timeout=600)
    try:
        req = urllib.request.Request(comfy_server.url + "/prompt", headers={"Content-Type": "application/json"},
                                     data=json.dumps({"prompt": prompt, "client_id": cid}).encode())
        pid = json.loads(urllib.request.urlopen(req, timeout=60).read())["prompt_id"]
        texts, progress_before = [], []
        seen_progress = 0
        while True:
            m = ws.recv()
            if isinstance(m, bytes):
                if struct.unpack(">I", m[:4])[0] == 3:  # BinaryEventTypes.TEXT: node id length, node id, text
                    n = struct.unpack(">I", m[4:8])[0]
                    texts.append((m[8:8 + n].decode(), m[8 + n:].decode()))
                    progress_before.append(seen_progress)
                continue
            d = json.loads(m)
            if d["type"] == "progress" and d["data"].get("node") == sim:
                seen_progress += 1
            if d["type"] == "executing" and d["data"].get("node") is None and d["data"].get("prompt_id") == pid:
                break
    finally:
        ws.close()
    mine = [t for node, t in texts if node == sim]
    assert len(mine) == 2, texts
    assert "object: jelly" in mine[0] and "force 1:" in mine[0] and progress_before[0] <= 1
    assert mine[1].startswith(mine[0])
