import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# Tests run on the CPU; keep torch to the cores CI gives us and make runs reproducible.
os.environ.setdefault("PHYSMOTION_DEVICE", "cpu")


@pytest.fixture(scope="session", autouse=True)
def _outputs_outside_the_repository(tmp_path_factory):
    """Nodes called outside ComfyUI write to $PHYSMOTION_OUTPUT_DIR (default ./output): keep every
    test's videos, .ply files and previews in a temporary folder, never in the checkout."""
    out = tmp_path_factory.mktemp("physmotion_output")
    old = {k: os.environ.get(k) for k in ("PHYSMOTION_OUTPUT_DIR",)}
    os.environ["PHYSMOTION_OUTPUT_DIR"] = str(out)  # previews follow it (<output>/.previews)
    yield out
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(autouse=True)
def _seed():
    import numpy as np
    import torch

    torch.manual_seed(0)
    np.random.seed(0)
    yield


@pytest.fixture(scope="session")
def example_image_path():
    return ROOT / "photos" / "coffee.png"
