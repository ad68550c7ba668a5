"""Generate the synthetic example inputs in examples/ (RGBA cut-outs with shading).

They are drawn here, procedurally and deterministically, so they carry no licence of anyone
else's: a metal bar, a bread loaf and a rubber ball. Run: .venv/bin/python scripts/make_examples.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
LIGHT = np.array([-0.45, -0.6, 0.66])  # towards the light, in image axes (x right, y down, z out)
LIGHT = LIGHT / np.linalg.norm(LIGHT)


def shade(normal: np.ndarray, base: np.ndarray, spec: float, shininess: float, ambient: float = 0.25) -> np.ndarray:
    diffuse = np.clip((normal * LIGHT).sum(-1), 0, 1)[..., None]
    half = LIGHT + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half)
    highlight = np.clip((normal * half).sum(-1), 0, 1)[..., None] ** shininess
    return np.clip(base * (ambient + (1 - ambient) * diffuse) + spec * highlight, 0, 1)


def backdrop(h: int, w: int) -> np.ndarray:
    """A plain studio backdrop (light grey wall over a slightly darker floor) for the RGB channels
    under the transparent pixels, so the cut-out also works as an ordinary photo."""
    yy = np.linspace(0, 1, h)[:, None, None]
    wall = 0.86 - 0.08 * yy
    floor = 0.7 + 0.1 * (yy - 0.72) / 0.28
    return np.broadcast_to(np.where(yy < 0.72, wall, floor), (h, w, 3)).copy()


def save_rgba(name: str, rgb: np.ndarray, alpha: np.ndarray) -> None:
    a = alpha[..., None]
    rgb = rgb * (a > 0) + backdrop(*alpha.shape) * (a <= 0)
    img = np.dstack([rgb[..., ::-1], alpha[..., None]])
    cv2.imwrite(str(ROOT / "examples" / name), (img * 255 + 0.5).astype(np.uint8))
    print("wrote", name)


def metal_bar(w=512, h=192) -> None:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    x0, x1, yc, r = 56.0, 456.0, h / 2, 22.0
    # A round bar along x with slightly rounded ends.
    dy = (yy - yc) / r
    end = np.clip(np.maximum(x0 + r * 0.3 - xx, xx - (x1 - r * 0.3)) / (r * 0.3), 0, None)
    inside = (dy**2 + end**2) <= 1.0
    nz = np.sqrt(np.clip(1 - dy**2 - end**2, 0, 1))
    nx = np.where(xx < (x0 + x1) / 2, -end, end)
    normal = np.dstack([nx, dy, nz])
    rng = np.random.default_rng(7)
    brushed = cv2.GaussianBlur(rng.normal(0, 1, (h, w)), (0, 0), sigmaX=25, sigmaY=0.6)
    base = np.array([0.55, 0.57, 0.6])[None, None, :] * (1 + 0.08 * brushed[..., None])
    rgb = shade(normal, base, spec=0.6, shininess=30)
    alpha = cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.7)
    save_rgba("metal_bar.png", rgb, alpha)


def bread(w=512, h=320) -> None:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    cx, cy, a, b = w / 2, h * 0.58, 200.0, 95.0
    u, v = (xx - cx) / a, (yy - cy) / b
    # A loaf: a superellipse, domed on top and flat underneath.
    v_top = np.where(v < 0, v, v * 1.6)
    d = np.abs(u) ** 3 + np.abs(v_top) ** 2.2
    inside = d <= 1.0
    nz = np.sqrt(np.clip(1 - d, 0, 1))
    normal = np.dstack([u * 0.8, v_top * 0.9, nz + 0.2])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    rng = np.random.default_rng(3)
    grain = cv2.GaussianBlur(rng.normal(0, 1, (h, w)), (0, 0), 2.0)
    crust = np.array([0.72, 0.45, 0.2]) + 0.12 * np.clip(-v_top, 0, 1)[..., None] * np.array([0.1, 0.05, -0.05])
    base = crust * (1 + 0.07 * grain[..., None])
    # Three diagonal scores across the top, paler where the crust opened.
    for k in (-0.5, 0.0, 0.5):
        score = np.abs((u - k) + 0.35 * v_top) < 0.035
        base = np.where((score & (v_top < -0.2))[..., None], np.array([0.93, 0.8, 0.58]), base)
    rgb = shade(normal, base, spec=0.12, shininess=8, ambient=0.35)
    alpha = cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.7)
    save_rgba("bread.png", rgb, alpha)


def ball(size=256) -> None:
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64) + 0.5
    c, r = size / 2, size * 0.4
    dx, dy = (xx - c) / r, (yy - c) / r
    d2 = dx**2 + dy**2
    inside = d2 <= 1
    normal = np.dstack([dx, dy, np.sqrt(np.clip(1 - d2, 0, 1))])
    base = np.array([0.85, 0.12, 0.1])[None, None, :] * np.ones((size, size, 1))
    rgb = shade(normal, base, spec=0.5, shininess=40)
    alpha = cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.7)
    save_rgba("ball.png", rgb, alpha)


def main() -> int:
    metal_bar()
    bread()
    ball()
    return 0


if __name__ == "__main__":
    sys.exit(main())
