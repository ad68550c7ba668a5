import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# Tests run on the CPU; keep torch to the cores CI gives us and make runs reproducible.
os.environ.setdefault("PHYSMOTION_DEVICE", "cpu")


@pytest.fixture(autouse=True)
def _seed():
    import numpy as np
    import torch

    torch.manual_seed(0)
    np.random.seed(0)
    yield


@pytest.fixture(scope="session")
def example_image_path():
    return ROOT / "examples" / "coffee.png"
