"""Throughput of the PyTorch Gaussian-splat rasterizer (and gsplat where CUDA + gsplat are present).

    python -m benchmarks.bench_render            # full table, written to docs/benchmarks.md
    python -m benchmarks.bench_render --quick    # fewer repeats, same table

Scene: a ball of random Gaussians in front of the camera filling about half the image, with
anisotropic scales that make splats a few pixels across (sigma 1.25-3.75 px), random orientations,
opacities in [0.2, 1] and random colours: roughly what the lift stage produces for an object.
Times are medians over several runs after a warm-up; forward+backward backpropagates the sum of
the RGB, alpha and depth images to means, scales, quats, opacities and colours.
"""

from __future__ import annotations

import argparse
import datetime
import math
import statistics
import time

import torch

from physmotion_core.render import gsplat_available, rasterize
from physmotion_core.types.camera import Camera
from physmotion_core.types.gaussians import Gaussians, SH_C0


def make_scene(n: int, width: int, height: int, seed: int = 0, device: str = "cpu",
               sigma_px: float = 2.5) -> tuple[Gaussians, Camera]:
    gen = torch.Generator().manual_seed(seed)
    cam = Camera.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=width, height=height, fov_y_deg=49.1)
    # Ball radius r projects to f r / 3 px; pick r so the disc covers ~half the image.
    r_px = math.sqrt(0.5 * width * height / math.pi)
    radius = r_px * 3.0 / cam.fy
    d = torch.randn(n, 3, generator=gen)
    d = d / d.norm(dim=1, keepdim=True)
    means = d * radius * torch.rand(n, 1, generator=gen).pow(1.0 / 3.0)
    base = sigma_px * 3.0 / cam.fy
    scales = base * (0.5 + torch.rand(n, 3, generator=gen))
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1)
    opac = 0.2 + 0.8 * torch.rand(n, generator=gen)
    rgb = torch.rand(n, 3, generator=gen)
    g = Gaussians(means=means, quats=quats, scales=scales, opacities=opac,
                  sh=((rgb - 0.5) / SH_C0)[:, None, :])
    return g.to(device), cam


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_render(g: Gaussians, cam: Camera, *, backward: bool, backend: str, repeats: int,
                device: str) -> float:
    def once() -> float:
        if backward:
            gg = Gaussians(means=g.means.clone().requires_grad_(), quats=g.quats.clone().requires_grad_(),
                           scales=g.scales.clone().requires_grad_(),
                           opacities=g.opacities.clone().requires_grad_(), sh=g.sh.clone().requires_grad_())
            _sync(device)
            t0 = time.perf_counter()
            out = rasterize(gg, cam, backend=backend)
            (out.rgb.sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
        else:
            _sync(device)
            t0 = time.perf_counter()
            with torch.no_grad():
                rasterize(g, cam, backend=backend)
        _sync(device)
        return time.perf_counter() - t0

    once()  # warm-up
    return statistics.median(once() for _ in range(repeats))


def run(quick: bool = False) -> str:
    repeats = 3 if quick else 7
    configs = [(10_000, 256), (50_000, 256), (10_000, 512), (50_000, 512)]
    rows = []
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for device in devices:
        backends = ["torch"] + (["gsplat"] if device == "cuda" and gsplat_available() else [])
        for backend in backends:
            for n, res in configs + [(50_000, (600, 400))]:
                w, h = (res, res) if isinstance(res, int) else res
                g, cam = make_scene(n, w, h, device=device)
                fwd = time_render(g, cam, backward=False, backend=backend, repeats=repeats, device=device)
                bwd = time_render(g, cam, backward=True, backend=backend, repeats=max(3, repeats // 2),
                                  device=device)
                rows.append((device, backend, n, f"{w}x{h}", fwd, bwd))
                print(f"{device:5s} {backend:6s} N={n:6d} {w}x{h}: forward {fwd * 1e3:7.1f} ms "
                      f"({1 / fwd:6.1f} fps), forward+backward {bwd * 1e3:7.1f} ms ({1 / bwd:6.1f} fps)",
                      flush=True)
    lines = [
        "## Rasterizer throughput",
        "",
        f"Machine: {machine_line()}. Date: {datetime.date.today().isoformat()}.",
        "",
        "Scene: a ball of random Gaussians filling about half the image, anisotropic splats with "
        "sigma 1.25-3.75 px, opacities 0.2-1, random colours. Forward: `torch.no_grad()` render of "
        "RGB, alpha and depth; fwd+bwd: the same with gradients to means, quats, scales, opacities "
        "and SH. Median of several runs after a warm-up. Re-run: `python -m benchmarks.bench_render`.",
        "",
        "| device | backend | Gaussians | image | forward ms | forward fps | fwd+bwd ms | fwd+bwd fps |",
        "| --- | --- | ---: | --- | ---: | ---: | ---: | ---: |",
    ]
    for device, backend, n, size, fwd, bwd in rows:
        lines.append(f"| {device} | {backend} | {n:,} | {size} | {fwd * 1e3:.1f} | {1 / fwd:.1f} | "
                     f"{bwd * 1e3:.1f} | {1 / bwd:.1f} |")
    return "\n".join(lines) + "\n"


def machine_line() -> str:
    from physmotion_core.report import machine_description

    return machine_description()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    parser.add_argument("--no-write", action="store_true", help="print only; leave docs/ alone")
    args = parser.parse_args()
    markdown = run(quick=args.quick)
    print(markdown)
    if not args.no_write:
        from physmotion_core.report import update_section

        path = update_section("benchmarks.md", "render", markdown)
        print(f"written to {path}")


if __name__ == "__main__":
    main()
