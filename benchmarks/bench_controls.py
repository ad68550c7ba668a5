"""What the Wan controls cost next to the simulation they come from, for the shipped CPU templates.

Each CPU template of example_workflows/api/ (no learned weights, not a Wan template) runs in-process up
to its simulation (tests/comfy_harness.py: the node classes ComfyUI calls), at the template's own
settings. Then the three video-control nodes run on that simulation as the Wan templates use them:
832x480, 16 fps, the 4k+1 frame count the simulated duration fills (48 frames at 24 fps -> 33),
64 tracked points + 8 background anchors, an 8 px grown mask, forward flow, in that order (tracks,
controls, flow), as a workflow using all three runs them: the first renders the resampled clip once
(colour, depth and the forward flow's channels) and the other two reuse it. A plain render of the clip
(render_frames, what the coarse video costs) is timed too. Written to docs/benchmarks.md, section
"controls". Usage:
    .venv/bin/python -m benchmarks.bench_controls [name ...]   (names: a subset, said so in the section)
"""

from __future__ import annotations

import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

from physmotion_core import controls as C
from physmotion_core.errors import InputError
from physmotion_core.render.frames import render_frames
from physmotion_core.report import machine_description, update_section

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "scripts"))

from comfy_harness import node_classes, run_prompt  # noqa: E402
from make_wan_thumbnails import upstream  # noqa: E402

WIDTH, HEIGHT, FPS = 832, 480, 16.0


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def main(names: list[str]) -> int:
    # One torch thread, as the simulation's Warp CPU kernels: on a 2-core machine shared with other jobs,
    # two OpenMP threads spin against each other and the render's wall time balloons.
    torch.set_num_threads(1)
    classes = node_classes()
    loads = []  # 1-minute load averages while the nodes ran: how busy the shared machine was
    rows, totals = [], {"sim": 0.0, "render": 0.0, "tracks": 0.0, "controls": 0.0, "flow": 0.0}
    for path in sorted((ROOT / "example_workflows" / "api").glob("*.json")):
        if names and path.stem not in names:
            continue
        prompt = json.loads(path.read_text())
        if path.stem.startswith("wan_") or any("Loader" in n["class_type"] for n in prompt.values()):
            continue
        sim_id = next(nid for nid, n in prompt.items() if n["class_type"] == "PhysMotionMPMSimulate")
        cam_src = prompt[sim_id]["inputs"]["camera"]
        blend = next((n for n in prompt.values() if n["class_type"] == "PhysMotionBlend"), None)
        bg_src = blend["inputs"]["background"] if blend else None
        with tempfile.TemporaryDirectory() as tmp:
            os.environ["PHYSMOTION_OUTPUT_DIR"] = tmp
            part = upstream(prompt, sim_id)
            if bg_src:
                part.update(upstream(prompt, bg_src[0]))
            try:
                out = run_prompt(part)
            except InputError as exc:  # e.g. "your own splat" needs the user's .ply
                print(f"{path.stem}: skipped ({exc})", flush=True)
                continue
            sim = out["results"][sim_id][0]
            camera = out["results"][cam_src[0]][cam_src[1]]
            background = out["results"][bg_src[0]][bg_src[1]] if bg_src else None
            length = C.wan_length(sim.num_frames, C.sim_fps(sim), FPS)
            common = dict(simulation=sim, camera=camera, width=WIDTH, height=HEIGHT, fps=FPS, length=length)
            rs = C.resample_simulation(sim, FPS, length)
            loads.append(os.getloadavg()[0])
            _, t_render = _timed(lambda: render_frames(rs, C.fit_camera(camera, WIDTH, HEIGHT)))
            _, t_tracks = _timed(lambda: classes["PhysMotionPointTracks"]().run(
                **common, num_points=64, background_points=8, occlusion="end track", background=background))
            _, t_controls = _timed(lambda: classes["PhysMotionControlVideos"]().run(
                **common, grow_mask=8, background=background))
            _, t_flow = _timed(lambda: classes["PhysMotionExactFlow"]().run(
                **common, direction="forward", max_flow=0.0, filename_prefix="bench/flow"))
            loads.append(os.getloadavg()[0])
        t_sim = float(sim.stats["wall_time_s"])
        share = (t_tracks + t_controls + t_flow) / t_sim
        for k, v in zip(totals, (t_sim, t_render, t_tracks, t_controls, t_flow)):
            totals[k] += v
        rows.append(f"| {path.stem} | {len(sim.rest):,} | {sim.num_frames} -> {length} | {t_sim:.1f} | {t_render:.1f} | "
                    f"{t_tracks:.1f} | {t_controls:.1f} | {t_flow:.1f} | {100 * share:.0f} % |")
        print(rows[-1], flush=True)
    all_three = totals["tracks"] + totals["controls"] + totals["flow"]
    rows.append(f"| **all** | | | {totals['sim']:.1f} | {totals['render']:.1f} | {totals['tracks']:.1f} | "
                f"{totals['controls']:.1f} | {totals['flow']:.1f} | {100 * all_three / max(totals['sim'], 1e-9):.0f} % |")
    busy = (" (above the core count: shared with other jobs, so every time here is longer than on an idle machine)"
            if max(loads, default=0.0) > (os.cpu_count() or 1) else " (not above the core count)")
    md = f"""## Wan controls next to the simulation

The three video-control nodes (`PhysMotionPointTracks`, `PhysMotionControlVideos`, `PhysMotionExactFlow`)
on the simulation of each CPU template, as the Wan templates use them: {WIDTH}x{HEIGHT}, {FPS:g} fps, the
4k+1 frame count the simulated duration fills, 64 tracked points + 8 background anchors, forward flow.
The tracks node resamples the simulation and renders the clip once for all three nodes (colour, depth
and 9 flow channels per frame: `render_clip`), then samples, projects, tests visibility at the points,
writes the JSON and draws the preview; the controls node, run next on the same simulation, clock and size,
reuses that render and adds the depth/mask/blend/VACE videos; the flow node reuses it too and adds the
colour-wheel preview and the .npz. The "render" column is a plain render of the same clip (`render_frames`,
colour and depth only) for comparison. Posing the Gaussians each frame (`SimResult.gaussians_at`) and
rasterizing are most of it. Simulation: the template's own settings, Warp kernels already compiled. Templates: {"a representative subset (" + ", ".join(names) + ")"
                                                     if names else "every CPU template"}. Machine: {machine_description()}; 1-minute load
average while the nodes ran {min(loads, default=0):.1f}-{max(loads, default=0):.1f} on {os.cpu_count()} cores{busy}; torch ran with
{torch.get_num_threads()} thread(s). Measured
{datetime.date.today().isoformat()}. Re-run: `python -m benchmarks.bench_controls`.

| template | Gaussians | frames (sim -> Wan) | simulation s | render s | tracks node s | controls node s | flow node s | all three / simulation |
| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n"
    update_section("benchmarks.md", "controls", md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
