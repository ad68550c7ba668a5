"""One click without weights, and how much it depends on where the click lands (issue 33).

    python -m benchmarks.bench_segment_click                  # all eight photos, 5 clicks each
    python -m benchmarks.bench_segment_click --photos clock,rocket --draws 0

Prints, for each benchmark photo (``bench_segment``'s photos, references and prompts), the IoU of
the click-prompted GrabCut mask (``grabcut`` with one object point, then the clean-up and
``_keep_clicked`` exactly as ``segment`` does; no background inpainting, which is what makes
``bench_segment`` slow) for the given object point and for four clicks moved from it by up to 3 %
of the image in x and in y (uniform, seeded: the same offsets on every photo and in every run; an
offset that lands off the reference object is drawn again). The last lines count the photos at
IoU >= 0.75 per click (issue 33's target: 6 of 8). Numbers go to the terminal only: measured ones
are written into docs/quality.md's segment notes by hand, with the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np

from benchmarks.bench_segment import DATA, PHOTOS, iou, load_photo
from physmotion_core.segment.classic import _keep_clicked, clean_mask, grabcut

JITTER = 0.03  # of the image's width (x) and height (y)
DRAWS = 4
SEED = 33


def clicks(ref: np.ndarray, point, draws: int = DRAWS) -> list[tuple[float, float]]:
    """The given point, then ``draws`` points moved by up to ``JITTER`` of the image, on the object."""
    H, W = ref.shape
    p = np.asarray(point, float)
    out = [(float(p[0]), float(p[1]))]
    rng = np.random.default_rng(SEED)
    while len(out) < draws + 1:
        q = np.round(p + rng.uniform(-JITTER, JITTER, 2) * [W, H])
        if 0 <= q[0] < W and 0 <= q[1] < H and ref[int(q[1]), int(q[0])]:
            out.append((float(q[0]), float(q[1])))
    return out


def click_mask(image: np.ndarray, point) -> np.ndarray:
    """What ``segment(image, points=[point])`` keeps as the mask, without the inpainting."""
    raw = grabcut(image, points=[point])
    m = clean_mask(raw).numpy() > 0.5
    return _keep_clicked(m, raw, np.array([point], float))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--photos", default=",".join(PHOTOS))
    ap.add_argument("--draws", default=",".join(str(j) for j in range(DRAWS + 1)),
                    help="which clicks: 0 is the given point, 1-4 the moved ones")
    args = ap.parse_args()
    prompts = json.loads((DATA / "prompts.json").read_text())
    draws = [int(j) for j in args.draws.split(",")]
    names = args.photos.split(",")
    scores = {}
    for name in names:
        image = load_photo(name)
        ref = cv2.imread(str(DATA / f"{name}.png"), cv2.IMREAD_GRAYSCALE) > 127
        pts = clicks(ref, prompts[name]["object_point"])
        cells = []
        for j in draws:
            t0 = time.perf_counter()
            scores[name, j] = iou(click_mask(image, pts[j]), ref)
            cells.append(f"({pts[j][0]:.0f},{pts[j][1]:.0f}) {scores[name, j]:.3f} {time.perf_counter() - t0:.1f} s")
        print(f"{name:10s} " + " | ".join(cells), flush=True)
    for j in draws:
        n = sum(scores[name, j] >= 0.75 for name in names)
        print(f"click {j}: IoU >= 0.75 on {n} of {len(names)}")


if __name__ == "__main__":
    main()
