"""Generate the synthetic example inputs in photos/ (RGBA cut-outs with shading).

They are drawn here, procedurally and deterministically, so they carry no licence of anyone
else's: a metal bar, a bread loaf, a rubber ball, a snow block, a drop of water, a dollop of honey, a
lump of clay, a small ball in a wide frame (to throw) and a wooden block in a wide frame (to slide).
Run: .venv/bin/python scripts/make_examples.py [name ...]
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
    cv2.imwrite(str(ROOT / "photos" / name), (img * 255 + 0.5).astype(np.uint8))
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


def _blob(w: int, h: int, cx: float, cy: float, a: float, b: float, p_top: float = 2.0, p_bottom: float = 2.0,
          p_side: float = 2.0):
    """A superellipse blob: (inside mask, surface normal, u, v) with separate exponents above and below."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    u, v = (xx - cx) / a, (yy - cy) / b
    pv = np.where(v < 0, p_top, p_bottom)
    d = np.abs(u) ** p_side + np.abs(v) ** pv
    inside = d <= 1.0
    nz = np.sqrt(np.clip(1 - d, 0, 1))
    normal = np.dstack([u * 0.9, v * 0.9, nz + 0.15])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return inside, normal, u, v


def _noise(h: int, w: int, seed: int, sigma: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = cv2.GaussianBlur(rng.normal(0, 1, (h, w)), (0, 0), sigma)
    return n / (n.std() + 1e-9)


def snow_block(w=512, h=320) -> None:
    inside, normal, u, v = _blob(w, h, w / 2, h * 0.6, 150.0, 80.0, p_top=4.0, p_bottom=8.0, p_side=4.0)
    sparkle = (np.random.default_rng(11).random((h, w)) > 0.996)[..., None] * 0.25
    base = np.array([0.9, 0.93, 0.98]) * (1 + 0.03 * _noise(h, w, 5, 1.5)[..., None])
    rgb = np.clip(shade(normal, base, spec=0.15, shininess=6, ambient=0.55) + sparkle, 0, 1)
    save_rgba("snow_block.png", rgb, cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.7))


def water_drop(size=384) -> None:
    # A falling drop: round below, drawn to a point above.
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64) + 0.5
    cx, cy, r = size / 2, size * 0.46, size * 0.2
    dy = (yy - cy) / r
    half_width = np.where(dy >= 0, np.sqrt(np.clip(1 - dy**2, 0, 1)),
                          np.clip(1 + dy / 1.6, 0, 1) ** 1.5)  # tapers over 1.6 r above the centre
    dx = (xx - cx) / r
    inside = (np.abs(dx) <= half_width) & (dy >= -1.6) & (dy <= 1)
    nx = np.where(half_width > 0, dx / np.maximum(half_width, 1e-3), 0) * 0.9
    normal = np.dstack([nx, np.clip(dy, -1, 1) * 0.6, np.sqrt(np.clip(1 - nx**2, 0.05, 1))])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    base = np.array([0.25, 0.5, 0.85]) * np.ones((size, size, 1))
    rgb = shade(normal, base, spec=0.9, shininess=60, ambient=0.35)
    save_rgba("water_drop.png", rgb, cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.7))


def honey(w=448, h=320) -> None:
    # A tall dollop: narrower than tall, domed, on a flat base.
    inside, normal, u, v = _blob(w, h, w / 2, h * 0.55, 80.0, 110.0, p_top=1.8, p_bottom=6.0, p_side=2.2)
    swirl = 0.06 * np.sin(10 * v + 4 * u)[..., None]
    base = np.array([0.85, 0.55, 0.1]) * (1 + swirl)
    rgb = shade(normal, base, spec=0.7, shininess=35, ambient=0.4)
    save_rgba("honey.png", rgb, cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.7))


def clay(w=448, h=320) -> None:
    inside, normal, u, v = _blob(w, h, w / 2, h * 0.56, 95.0, 95.0, p_top=2.4, p_bottom=6.0, p_side=2.4)
    base = np.array([0.75, 0.38, 0.22]) * (1 + 0.05 * _noise(h, w, 9, 3.0)[..., None])
    rgb = shade(normal, base, spec=0.1, shininess=6, ambient=0.35)
    save_rgba("clay.png", rgb, cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.7))


def throw_ball(w=640, h=360) -> None:
    """A small ball low at the left of a wide frame: room to fly to the right."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    c, r = (110.0, 270.0), 32.0
    dx, dy = (xx - c[0]) / r, (yy - c[1]) / r
    d2 = dx**2 + dy**2
    inside = d2 <= 1
    normal = np.dstack([dx, dy, np.sqrt(np.clip(1 - d2, 0, 1))])
    stripe = (np.abs(dy + 0.25 * dx) < 0.18)[..., None]
    base = np.where(stripe, np.array([0.95, 0.85, 0.2]), np.array([0.15, 0.35, 0.85]))
    rgb = shade(normal, base, spec=0.5, shininess=40)
    save_rgba("throw_ball.png", rgb, cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.7))


def block(w=640, h=320) -> None:
    """A wooden block at the left of a wide frame: room to slide to the right."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    x0, x1, y0, y1 = 50.0, 170.0, 200.0, 260.0
    inside = (xx >= x0) & (xx <= x1) & (yy >= y0) & (yy <= y1)
    grain = 0.5 + 0.5 * np.sin(0.35 * yy + 2.0 * _noise(h, w, 4, 6.0))
    base = np.array([0.62, 0.42, 0.22])[None, None, :] * (0.85 + 0.2 * grain[..., None])
    edge = np.minimum.reduce([xx - x0, x1 - xx, yy - y0, y1 - yy])
    rgb = base * np.where(edge < 3, 0.8, 1.0)[..., None]
    save_rgba("block.png", np.clip(rgb, 0, 1), cv2.GaussianBlur(inside.astype(np.float64), (0, 0), 0.7))


EXAMPLES = {"metal_bar": metal_bar, "bread": bread, "ball": ball, "snow_block": snow_block,
            "water_drop": water_drop, "honey": honey, "clay": clay, "throw_ball": throw_ball, "block": block}


def main(names: list[str]) -> int:
    for name in names or EXAMPLES:
        EXAMPLES[name]()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
