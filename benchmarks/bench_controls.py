"""What the Wan controls cost next to the simulation they come from, for the shipped CPU templates.

Each CPU template of example_workflows/api/ (no learned weights, not a Wan template) runs in-process up
to its simulation (tests/comfy_harness.py: the node classes ComfyUI calls), at the template's own
settings. Then the three video-control nodes run on that simulation at 832x480, 16 fps and the 4k+1
frame count the simulated duration fills (48 frames at 24 fps -> 33), in three scenarios as prompts
hold them: the tracks node alone (as the Wan tracks template), the controls node alone (as the VACE
template) and all three (tracks, controls, forward flow; one render shared, see nodes/video_control.py).
A plain render of the clip
(render_frames, what the coarse video costs) is timed too. Written to docs/benchmarks.md, section
"controls" ("controls-gpu" on a CUDA machine, where the simulations and renders run on the GPU;
scripts/gpu_checks.sh runs it). Usage:
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


_NODES = {"tracks": "PhysMotionPointTracks", "controls": "PhysMotionControlVideos", "flow": "PhysMotionExactFlow"}


def _scenario(classes, common, background, which) -> float:
    """Seconds the nodes ``which`` take on one simulation, run in that order as ComfyUI runs a prompt that
    holds just them (the controls node gets the hidden PROMPT and UNIQUE_ID, so its render carries the flow's
    channels only when a flow node follows). Nothing is shared with an earlier scenario."""
    import sys as _sys

    vc = _sys.modules[classes["PhysMotionPointTracks"].__module__]
    vc._last_render.clear()
    clip = {k: common[k] for k in ("width", "height", "fps", "length")}
    links = {"simulation": ["7", 0], "camera": ["3", 1]}
    extra = {"tracks": dict(num_points=64, background_points=8, occlusion="end track", preview="first frame",
                            background=background),
             "controls": dict(grow_mask=8, background=background),
             "flow": dict(direction="forward", max_flow=0.0, filename_prefix="bench/flow")}
    prompt = {str(20 + i): {"class_type": _NODES[w], "inputs": {**links, **clip,
                                                                **{k: v for k, v in extra[w].items() if k != "background"}}}
              for i, w in enumerate(which)}
    t0 = time.perf_counter()
    for i, w in enumerate(which):
        hidden = {"prompt": prompt, "unique_id": str(20 + i)} if w == "controls" else {}
        classes[_NODES[w]]().run(**common, **extra[w], **hidden)
    return time.perf_counter() - t0


def _gpu_renderer() -> str:
    from physmotion_core.render.rasterize import gsplat_available

    return "with gsplat" if gsplat_available() else "with the PyTorch rasterizer on CUDA (gsplat not installed)"


def main(names: list[str]) -> int:
    # Torch renders with as many threads as the simulation ran with (PHYSMOTION_CPU_THREADS, else every
    # core), as in ComfyUI, where both use the machine.
    env = os.environ.get("PHYSMOTION_CPU_THREADS", "").strip()
    torch.set_num_threads(int(env) if env.isdigit() and int(env) > 0 else (os.cpu_count() or 1))
    classes = node_classes()
    # On a CUDA machine the simulations, renders and nodes run there (the nodes follow ComfyUI's device, else
    # CUDA when available); the numbers go to their own section. Warp's kernels are compiled first, so no
    # simulation pays for it, and each clip's plain render is timed after a warm-up render (gsplat's JIT).
    gpu = torch.cuda.is_available()
    dev = torch.device("cuda:0" if gpu else "cpu")
    if gpu:
        import warp as wp

        from physmotion_core.sim import kernels, pose

        for module in (kernels, pose):
            wp.load_module(module, device="cuda:0")
    loads = []  # 1-minute load averages while the nodes ran: how busy the shared machine was
    rows, totals = [], {"sim": 0.0, "render": 0.0, "tracks": 0.0, "controls": 0.0, "all": 0.0}
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
            fitted = C.fit_camera(camera, WIDTH, HEIGHT)
            if not rows:
                # Once per process, untimed: the first render and the first run of each node pay one-time costs
                # (PyTorch's lazy set-up, the allocator's first pages: 0.3-0.4 s on the blocks, measured), which
                # a ComfyUI server pays once, not per clip.
                render_frames(rs, fitted, device=dev)
                _scenario(classes, common, background, ("tracks", "controls", "flow"))
            loads.append(os.getloadavg()[0])
            if gpu:
                render_frames(rs, fitted, device=dev)  # warm-up
            _, t_render = _timed(lambda: render_frames(rs, fitted, device=dev))
            t_tracks = _scenario(classes, common, background, ("tracks",))
            t_controls = _scenario(classes, common, background, ("controls",))
            t_all = _scenario(classes, common, background, ("tracks", "controls", "flow"))
            loads.append(os.getloadavg()[0])
        t_sim = float(sim.stats["wall_time_s"])
        threads = int(sim.stats.get("threads", 0))
        for k, v in zip(totals, (t_sim, t_render, t_tracks, t_controls, t_all)):
            totals[k] += v
        rows.append(f"| {path.stem} | {len(sim.rest):,} | {sim.num_frames} -> {length} | {t_sim:.1f} ({threads}) | "
                    f"{t_render:.1f} | {t_tracks:.1f} ({100 * t_tracks / t_sim:.0f} %) | "
                    f"{t_controls:.1f} ({100 * t_controls / t_sim:.0f} %) | {t_all:.1f} ({100 * t_all / t_sim:.0f} %) |")
        print(rows[-1], flush=True)
    ts = max(totals["sim"], 1e-9)
    rows.append(f"| **all** | | | {totals['sim']:.1f} | {totals['render']:.1f} | {totals['tracks']:.1f} "
                f"({100 * totals['tracks'] / ts:.0f} %) | {totals['controls']:.1f} ({100 * totals['controls'] / ts:.0f} %) | "
                f"{totals['all']:.1f} ({100 * totals['all'] / ts:.0f} %) |")
    busy = (" (above the core count: shared with other jobs, so every time here is longer than on an idle machine)"
            if max(loads, default=0.0) > (os.cpu_count() or 1) else " (not above the core count)")
    where = "" if not gpu else f" (GPU: simulations with Warp on cuda:0, renders {_gpu_renderer()})"
    md = f"""## Wan controls next to the simulation{where}

The three video-control nodes (`PhysMotionPointTracks`, `PhysMotionControlVideos`, `PhysMotionExactFlow`)
on the simulation of each CPU template, at {WIDTH}x{HEIGHT}, {FPS:g} fps and the 4k+1 frame count the
simulated duration fills, as the Wan templates use them: the tracks node alone (64 points + 8 background
anchors; the `wan_tracks_*` template), the controls node alone (8 px grown mask; the `wan_vace_*` template),
and all three in one prompt (tracks, controls, forward flow). Each scenario starts from nothing (no kept
clip); an untimed run of the first template's render and nodes first takes the process's one-time costs. The
tracks node renders no clip (`probe_tracks`: frame 0 whole, to pick the points, then in every other frame
only the 3x3 pixels around each point, for its visibility; preview over the first frame, the template's
setting); the controls node renders the full-size clip once
(`render_clip`: colour and depth, plus the flow's 9 channels only when a flow node of the same prompt asks
for that clip), and the flow node reuses it. The "render" column is a plain render of the same clip (`render_frames`), what any coarse video of
it costs. Percentages are of the simulation's time. Simulation: the template's own settings, Warp kernels
already compiled, its thread count in brackets; torch ran with {torch.get_num_threads()} thread(s).
Templates: {"a representative subset (" + ", ".join(names) + ")" if names else "every CPU template"}. Machine:
{machine_description()}; 1-minute load average while the nodes ran {min(loads, default=0):.1f}-{max(loads, default=0):.1f}
on {os.cpu_count()} cores{busy}. Measured {datetime.date.today().isoformat()}. Re-run:
`python -m benchmarks.bench_controls`.

| template | Gaussians | frames (sim -> Wan) | simulation s (threads) | render s | tracks node s | controls node s | all three s |
| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |
""" + "\n".join(rows) + "\n"
    update_section("benchmarks.md", "controls-gpu" if gpu else "controls", md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
