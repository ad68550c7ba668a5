"""The whole chain picks its stages from what the models folder holds (and what the scene needs).

Tiny random-weight SAM / ImageDream / LGM in the official layout (tests/tiny_models.py) stand in
for the real weights: the stage choice and the plumbing are what is checked, not the quality.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physmotion_core.errors import InputError
from physmotion_core.pipeline import available_models, generate
from physmotion_core.types import SimSettings

FAST = SimSettings(frames=2, grid_res=6, device="cpu", particles_per_cell=1)


def photo(h=64, w=64):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([0.3 + 0.2 * xx / w, 0.5 + 0.1 * yy / h, 0.35 * np.ones_like(xx)], -1)
    disc = (xx - w * 0.5) ** 2 + (yy - h * 0.5) ** 2 < (0.3 * h) ** 2
    img[disc] = (0.85, 0.15, 0.1)
    return img.astype(np.float32), torch.from_numpy(disc.astype(np.float32))


@pytest.fixture(scope="module")
def models_root(tmp_path_factory):
    from tiny_models import write_tiny_models_root

    return write_tiny_models_root(tmp_path_factory.mktemp("models"))


def test_learned_stages_are_used_when_their_weights_are_present(models_root, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_MODELS", str(models_root))
    found = available_models()
    assert found["sam"] and found["lgm"] and found["imagedream"]
    img, _ = photo()
    res = generate(img, settings=FAST, models="auto", multiview_steps=2, lgm_input_size=64, max_gaussians=500,
                   object_point=(32, 32))
    assert res.stages == {"segment": "sam", "lift": "lgm"}
    assert len(res.gaussians) == 500 and res.frames.shape == (2, 64, 64, 3)
    assert float(res.gaussians.means[:, 1].min()) == pytest.approx(0.0, abs=1e-5)  # on the ground


def test_stages_the_scene_does_not_need_are_skipped(models_root, monkeypatch):
    monkeypatch.setenv("PHYSMOTION_MODELS", str(models_root))
    img, disc = photo()
    rgba = np.dstack([img, disc.numpy()])
    # an alpha channel (or a given mask) is the segmentation: SAM is not loaded
    assert generate(rgba, settings=FAST, models="auto", multiview_steps=1, lgm_input_size=64,
                    max_gaussians=300).stages["segment"] == "alpha"
    assert generate(img, mask=disc, settings=FAST, models="none").stages == {"segment": "mask", "lift": "silhouette"}
    assert generate(img, settings=FAST, models="none").stages == {"segment": "grabcut", "lift": "silhouette"}


def test_half_of_the_learned_lift_falls_back_to_the_silhouette(tmp_path, monkeypatch, caplog):
    from tiny_models import write_tiny_models_root

    root = write_tiny_models_root(tmp_path / "m", sam=False, imagedream=False)
    monkeypatch.setenv("PHYSMOTION_MODELS", str(root))
    img, disc = photo()
    res = generate(img, mask=disc, settings=FAST, models="auto")
    assert res.stages == {"segment": "mask", "lift": "silhouette"}
    assert any("needs both LGM and ImageDream" in r.message for r in caplog.records)
    with pytest.raises(InputError, match="models must be one of"):
        generate(img, settings=FAST, models="sometimes")
