"""Denormals are flushed to zero inside the MPM solver's launches on the CPU, and only there
(physmotion_core/sim/fpmode.py): the caller's thread keeps its floating-point mode."""

import platform

import numpy as np
import pytest
import warp as wp

from physmotion_core.sim.fpmode import FlushedDenormals
from physmotion_core.sim.mpm import Domain, MPMSolver
from physmotion_core.types.material import material_preset
from physmotion_core.validate.harness import lattice

wp.config.quiet = True
wp.init()

X86 = platform.machine().lower() in ("x86_64", "amd64", "i386", "i686")
TINY = np.float32(1e-20)  # its square, 1e-40, is a denormal float32


@wp.kernel
def square(a: wp.array(dtype=float), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = a[i] * a[i]


def squared_in_warp() -> float:
    out = wp.zeros(1, dtype=float, device="cpu")
    wp.launch(square, 1, [wp.array([TINY], dtype=float, device="cpu"), out], device="cpu")
    return float(out.numpy()[0])


def denormal_numpy() -> float:
    return float(np.multiply(np.array([TINY]), np.array([TINY]))[0])


@pytest.mark.skipif(not X86, reason="MXCSR is x86's")
def test_flushed_inside_the_block_only():
    assert squared_in_warp() > 0.0 and denormal_numpy() > 0.0  # the default mode keeps denormals
    with FlushedDenormals("cpu"):
        assert squared_in_warp() == 0.0
    assert squared_in_warp() > 0.0 and denormal_numpy() > 0.0  # restored


@pytest.mark.parametrize("threads", [1, 2])
def test_a_substep_leaves_the_callers_mode(threads):
    x, vol = lattice((0.0, 0.3, 0.0), (0.1, 0.4, 0.1), 0.1 / 20)
    dom = Domain.around(x.min(0), x.max(0), 0.01, 1.0, None)
    s = MPMSolver(x, vol, np.zeros(len(x), np.int64), [material_preset("jelly")], dom, device="cpu", threads=threads)
    s.substep(1e-4)
    s.advance(2e-3)
    assert squared_in_warp() > 0.0 and denormal_numpy() > 0.0
    assert np.isfinite(s.positions()).all()
