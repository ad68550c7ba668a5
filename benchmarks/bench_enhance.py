"""Enhancement benchmark: temporal consistency (coarse vs enhanced) and GPU throughput / memory.

1. Temporal consistency (default): the coarse video of the push_a_jelly template (run in-process,
   shortened) is inverted and re-sampled with keyframe-shared attention ("tokenflow") and without
   it ("per_frame"). The figure is the optical-flow warping error between consecutive frames:
   OpenCV Farneback flow is computed on the COARSE frames (the motion the physics produced), each
   video's frame t is warped onto frame t+1 with it, and the mean absolute difference over pixels
   whose forward/backward flows agree is reported (8-bit levels; lower = more consistent). By
   default the models are the tiny random-weight SD 2.1 / ControlNets (this shows the machinery,
   not image quality); with ``--model`` etc. the same script runs on real weights:

       python -m benchmarks.bench_enhance --models-root ~/ComfyUI/models --model stable-diffusion-2-1 \\
           --controlnet-depth control_v11p_sd21_depth.safetensors \\
           --controlnet-canny control_v11p_sd21_canny.safetensors --frames 24 --resolution 768 --steps 50

   ``--coarse clip.mp4 --depth depth.mp4`` use your own coarse video and depth video instead.

2. ``--gpu``: seconds per frame and peak memory of keyframe-shared sampling with FULL-SIZE
   random-initialised SD 2.1 UNet + two ControlNets (+ VAE, text encoder) built from the shipped
   configs (the compute does not depend on the weight values), fp16, at 512² and 768² for 16 and 48
   frames, with and without attention chunking, next to the up-front memory estimate. Needs CUDA.

Results go to docs/enhance.md (sections "consistency" and "gpu"). Usage:
    .venv/bin/python -m benchmarks.bench_enhance [--quick] [--gpu] [--no-write]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from physmotion_core.report import machine_description, update_section

ROOT = Path(__file__).resolve().parent.parent


# ----------------------------------------------------------------------------------------------
# Temporal consistency
# ----------------------------------------------------------------------------------------------

def _gray(frame: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.cvtColor((np.clip(frame, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def coarse_flows(frames: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per consecutive pair: (backward flow t+1 -> t, valid mask) from Farneback on the frames."""
    import cv2

    out = []
    g = [_gray(f) for f in frames]
    H, W = g[0].shape
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    for t in range(len(g) - 1):
        args = (None, 0.5, 3, 15, 3, 5, 1.2, 0)
        bwd = cv2.calcOpticalFlowFarneback(g[t + 1], g[t], *args)  # g[t+1](p) ~ g[t](p + bwd(p))
        fwd = cv2.calcOpticalFlowFarneback(g[t], g[t + 1], *args)
        mx, my = xs + bwd[..., 0], ys + bwd[..., 1]
        fwd_at = cv2.remap(fwd, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        cycle = np.linalg.norm(bwd + fwd_at, axis=-1)
        inside = (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
        out.append((bwd, inside & (cycle < 0.5 + 0.05 * np.linalg.norm(bwd, axis=-1))))
    return out


def warping_error(frames: np.ndarray, flows) -> float:
    """Mean |frame[t+1] - warp(frame[t])| over the valid pixels, in 8-bit levels."""
    import cv2

    H, W = frames.shape[1:3]
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    errs = []
    for t, (bwd, valid) in enumerate(flows):
        warped = cv2.remap(frames[t].astype(np.float32), xs + bwd[..., 0], ys + bwd[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
        d = np.abs(frames[t + 1].astype(np.float32) - warped).mean(-1)
        if valid.any():
            errs.append(float(d[valid].mean()) * 255)
    return float(np.mean(errs)) if errs else float("nan")


def latent_flows(flows, factor: int = 8):
    """The pixel flows at the latent grid (1/8 size, displacements /8)."""
    import cv2

    out = []
    for bwd, valid in flows:
        h, w = bwd.shape[0] // factor, bwd.shape[1] // factor
        f = cv2.resize(bwd, (w, h), interpolation=cv2.INTER_AREA) / factor
        v = cv2.resize(valid.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0.99
        out.append((f.astype(np.float32), v))
    return out


def latent_warping_error(latents: torch.Tensor, flows) -> float:
    """The same figure on the final latents (F,4,h,w): mean |z(t+1) - warp(z t)| over valid cells."""
    z = latents.permute(0, 2, 3, 1).numpy()
    return warping_error(z, flows) / 255


def coarse_clip(frames: int, quick: bool):
    """The push_a_jelly template's coarse video and rendered depth (shortened)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from comfy_harness import run_prompt

    prompt = json.loads((ROOT / "example_workflows" / "api" / "push_a_jelly.json").read_text())
    over = {"PhysMotionMPMSimulate.frames": frames, "PhysMotionMPMSimulate.grid_res": 10 if quick else 16,
            "PhysMotionSilhouetteLift.max_gaussians": 6000 if quick else 20000}
    with tempfile.TemporaryDirectory() as tmp:
        os.environ.setdefault("PHYSMOTION_OUTPUT_DIR", tmp)
        os.environ.setdefault("PHYSMOTION_TEMP_DIR", tmp)
        out = run_prompt(prompt, class_overrides=over)
    blend = next(n for n, v in prompt.items() if v["class_type"] == "PhysMotionBlend")
    render = next(n for n, v in prompt.items() if v["class_type"] == "PhysMotionRender")
    return out["results"][blend][0], out["results"][render][2]


def consistency(args) -> str:
    from physmotion_core.enhance import SampleSettings, invert_frames, keyframe_shared_sample, load_diffusion
    from physmotion_core.video import read_video

    if args.coarse:
        frames = torch.from_numpy(read_video(args.coarse)[0][: args.frames]).float() / 255
        depth = torch.from_numpy(read_video(args.depth)[0][: args.frames]).float() / 255
    else:
        frames, depth = coarse_clip(args.frames, args.quick)
    tmp = None
    if args.model is None:
        from tiny_sd21 import TINY_NAMES, build_tiny_models_root

        tmp = tempfile.TemporaryDirectory()
        build_tiny_models_root(tmp.name)
        root, model = tmp.name, TINY_NAMES["diffusers"]
        cn_d, cn_c = TINY_NAMES["controlnet_depth"], TINY_NAMES["controlnet_canny"]
        label = "tiny random-weight SD 2.1 + 2 ControlNets (machinery only, not quality)"
    else:
        root, model, cn_d, cn_c = args.models_root, args.model, args.controlnet_depth, args.controlnet_canny
        label = f"{model} + {cn_d} + {cn_c}" + (f" + LoRA {args.lora}" if args.lora else "")
    models = load_diffusion(model, controlnet_depth=cn_d, controlnet_canny=cn_c, lora=args.lora, root=root)
    t0 = time.perf_counter()
    inv = invert_frames(models, frames, depth, prompt=args.prompt, steps=args.steps, resolution=args.resolution,
                        refine_iterations=1, frame_batch=4)
    t_inv = time.perf_counter() - t0
    coarse = torch.nn.functional.interpolate(frames.permute(0, 3, 1, 2), size=tuple(inv.size), mode="area")
    coarse = coarse.permute(0, 2, 3, 1).numpy()
    flows = coarse_flows(coarse)
    lflows = latent_flows(flows)
    rows = [("coarse (input)", warping_error(coarse, flows), latent_warping_error(inv.clean, lflows), "-")]
    for mode in ("tokenflow", "per_frame"):
        st = SampleSettings(prompt=args.prompt, attention=mode, output_size="diffusion", memory="reduce")
        res = keyframe_shared_sample(models, inv, st)
        rows.append((f"enhanced, {mode}", warping_error(res.frames.numpy(), flows),
                     latent_warping_error(res.latents, lflows), f"{res.seconds:.1f}"))
        print(rows[-1], flush=True)
    recon = []
    sub = frames[:3]
    for refine in (0, 1, 2):
        iv = invert_frames(models, sub, depth[:3], prompt=args.prompt, steps=args.steps, resolution=args.resolution,
                           refine_iterations=refine, frame_batch=3)
        rr = keyframe_shared_sample(models, iv, SampleSettings(prompt=args.prompt, guidance=1.0, tau_features=0.0,
                                                               tau_attention=0.0, attention="per_frame",
                                                               output_size="diffusion"))
        d = rr.latents - iv.clean
        recon.append((refine, float(d.abs().max()), float(d.pow(2).mean().sqrt()), float(iv.clean.std())))
        print("reconstruction", recon[-1], flush=True)
    if tmp is not None:
        tmp.cleanup()
    H, W = inv.size
    rtable = "\n".join(f"| {r} | {mx:.2e} | {rms:.2e} | {sd:.2f} |" for r, mx, rms, sd in recon)
    table = "\n".join(f"| {name} | {err:.2f} | {lat:.3f} | {sec} |" for name, err, lat, sec in rows)
    return f"""## Temporal consistency: coarse vs enhanced

Models: {label}. Clip: {"your video" if args.coarse else "push_a_jelly's coarse video"}, {inv.frames} frames at
{W}×{H}, {args.steps} DDIM steps, prompt "{args.prompt}", guidance 7.5, τ_f 0.8, τ_A 0.5, keyframes every 5 frames.
Inversion took {t_inv:.1f} s. Machine: {machine_description()}. Measured {datetime.date.today().isoformat()}.
Re-run: `python -m benchmarks.bench_enhance{"".join(" " + a for a in sys.argv[1:])}`.

Warping error = mean |frame(t+1) − warp(frame t)| in 8-bit levels over the pixels where the coarse
video's Farneback forward/backward flows agree (the flow is the coarse video's, for every row). The
latent column is the same on the final latents (flow scaled to the 1/8 grid; latents have unit scale).

| video | warping error (8-bit levels, lower = steadier) | latent warping error | sampling s |
| --- | ---: | ---: | ---: |
{table}

Inversion round trip on the first 3 frames (invert, then sample with the same prompt and conditions,
guidance 1, no injection, per-frame attention): error of the final latents against the encoded frames.

| fixed-point refinements | max abs error | RMS error | latent std |
| ---: | ---: | ---: | ---: |
{rtable}
"""


# ----------------------------------------------------------------------------------------------
# GPU throughput and memory (full-size random SD 2.1 + 2 ControlNets)
# ----------------------------------------------------------------------------------------------

def full_size_models(device: torch.device):
    """DiffusionModels with random full-size SD 2.1 components built from the shipped configs."""
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    from physmotion_core.enhance.configs import SD21_CONFIG_DIR, read_config
    from physmotion_core.enhance.loader import DiffusionModels

    strip = lambda d: {k: v for k, v in d.items() if not k.startswith("_")}  # noqa: E731
    dt = torch.float16
    with torch.device(device):
        unet = UNet2DConditionModel(**strip(read_config("unet"))).to(dt).eval()
        cns = {k: ControlNetModel(**strip(read_config(f"controlnet_{k}"))).to(dt).eval() for k in ("depth", "canny")}
        vae = AutoencoderKL(**strip(read_config("vae"))).float().eval()
        te = read_config("text_encoder")
        text = CLIPTextModel(CLIPTextConfig(**{k: v for k, v in te.items() if k not in ("architectures",
                                                                                         "_name_or_path")})).to(dt)
    tok = CLIPTokenizer.from_pretrained(str(SD21_CONFIG_DIR / "tokenizer"), local_files_only=True)
    for m in (unet, vae, text, *cns.values()):
        m.requires_grad_(False)
    return DiffusionModels(unet=unet, vae=vae, text_encoder=text.eval(), tokenizer=tok, controlnets=cns,
                           scheduler_config=read_config("scheduler"), prediction_type="v_prediction", device=device,
                           dtype=dt, name="random SD 2.1 (full size)")


def throughput(models, resolutions, frame_counts, chunks, steps: int) -> list[tuple]:
    """(resolution, frames, chunk, s/frame scaled to 50 steps, measured peak GiB, estimated peak GiB)."""
    from physmotion_core.enhance import SampleSettings, keyframe_shared_sample
    from physmotion_core.enhance.invert import Inversion
    from physmotion_core.enhance.schedule import DDIMSchedule

    cuda = torch.device(models.device).type == "cuda"
    sched = DDIMSchedule.from_config(models.scheduler_config, steps)
    rows = []
    for res in resolutions:
        for frames in frame_counts:
            for chunk in chunks:
                g = torch.Generator().manual_seed(0)
                h = w = res // 8
                kinds = list(models.controlnets)
                inv = Inversion(latents=torch.randn(steps, frames, 4, h, w, generator=g),
                                clean=torch.randn(frames, 4, h, w, generator=g), timesteps=sched.timesteps,
                                prompt="a photo", controls={k: torch.rand(frames, 3, res, res, generator=g)
                                                            for k in kinds},
                                control_scales={k: 1.0 for k in kinds}, size=(res, res), input_size=(res, res),
                                prediction_type=models.prediction_type, model_fingerprint=models.fingerprint())
                st = SampleSettings(attention_chunk=chunk, output_size="diffusion", memory="refuse")
                if cuda:
                    torch.cuda.empty_cache()
                    torch.cuda.reset_peak_memory_stats()
                try:
                    if cuda:
                        torch.cuda.synchronize()
                    r = keyframe_shared_sample(models, inv, st)
                    if cuda:
                        torch.cuda.synchronize()
                    peak = f"{torch.cuda.max_memory_allocated() / 2**30:.1f}" if cuda else "-"
                    rows.append((res, frames, chunk or "off", f"{r.seconds / frames * 50 / steps:.2f}", peak,
                                 f"{r.memory.device_peak / 2**30:.1f}"))
                except Exception as exc:  # noqa: BLE001 - an OOM or a refusal is a result too
                    rows.append((res, frames, chunk or "off", f"failed: {type(exc).__name__}: {exc}"[:120], "-", "-"))
                print(rows[-1], flush=True)
    return rows


def gpu(args) -> str:
    if not torch.cuda.is_available():
        raise SystemExit("--gpu needs CUDA")
    models = full_size_models(torch.device("cuda"))
    steps = args.gpu_steps
    rows = throughput(models, (512, 768), (16, 48), (0, 4096), steps)
    table = "\n".join("| " + " | ".join(str(c) for c in r) + " |" for r in rows)
    return f"""## GPU: seconds per frame and peak memory

Full-size random-initialised SD 2.1 UNet + depth and canny ControlNets (fp16; VAE fp32), keyframe-shared
sampling with guidance 7.5 (3 branches), keyframes every 5 frames, frame_batch 4, keyframe_batch 8;
measured over {steps} steps and scaled to 50; includes VAE decoding. Machine: {machine_description()}.
Measured {datetime.date.today().isoformat()}. Re-run: `python -m benchmarks.bench_enhance --gpu`.

| resolution | frames | attention chunk | s/frame (50 steps) | peak GiB (measured) | peak GiB (estimated) |
| ---: | ---: | ---: | ---: | ---: | ---: |
{table}
"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller clip and fewer steps")
    ap.add_argument("--gpu", action="store_true", help="also run the full-size GPU timing/memory table")
    ap.add_argument("--gpu-steps", type=int, default=5, help="steps timed per GPU case (scaled to 50)")
    ap.add_argument("--no-write", action="store_true", help="print, do not update docs/enhance.md")
    ap.add_argument("--models-root", default=None, help="models folder (default $PHYSMOTION_MODELS)")
    ap.add_argument("--model", default=None, help="SD 2.1 folder in diffusers/ or file in checkpoints/")
    ap.add_argument("--controlnet-depth", default=None)
    ap.add_argument("--controlnet-canny", default=None)
    ap.add_argument("--lora", default=None)
    ap.add_argument("--coarse", default=None, help="a coarse video file instead of the template's")
    ap.add_argument("--depth", default=None, help="its depth video (near = bright)")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--resolution", type=int, default=None)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--prompt", default="a photo of an espresso cup on a saucer on a wooden table")
    args = ap.parse_args(argv)
    if args.coarse and not args.depth:
        ap.error("--coarse needs --depth")
    tiny = args.model is None
    args.frames = args.frames or (8 if args.quick else 16)
    args.resolution = args.resolution or (128 if tiny else 768)
    args.steps = args.steps or (5 if args.quick else (10 if tiny else 50))
    if tiny:
        torch.set_num_threads(1)  # tiny models: per-op overhead dominates
    sections = [("consistency", consistency(args))]
    if args.gpu:
        sections.append(("gpu", gpu(args)))
    for name, md in sections:
        print(md)
        if not args.no_write and not args.coarse and (tiny or args.model):
            update_section(ROOT / "docs" / "enhance.md", name, md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
