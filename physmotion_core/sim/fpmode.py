"""Flush denormal floats to zero in the CPU threads that run the MPM kernels.

A scene at rest or in free fall has a velocity field uniform to round-off, so its particles' velocity
gradients C are ~1e-15 1/s and the products the substep forms from them (the rotation's torque, its
square, the stress of F − R ~ 1e-19, the affine momentum) fall below float32's smallest normal number,
1.2e-38. x86 cores compute with such denormal numbers through a microcode assist of ~100 cycles per
operation: the material update of a 2.1 M-particle jelly released at rest took 982 ns per particle,
218 with the flushing (55 k particles, whose C happened to be larger: 233 and 104; docs/benchmarks.md,
"Large scenes: what changed").
With MXCSR's flush-to-zero and denormals-are-zero bits set, such values are zero: no change a
simulation could resolve (they are 1e-38 of any quantity that matters), at full speed.

MXCSR belongs to a thread. Warp runs a CPU kernel in the thread that launches it, so the solver sets
the bits in its worker threads once (they run nothing else) and in the calling thread around its
launches only, restoring the caller's mode afterwards (numpy or torch in the same thread keep theirs).
Every kernel of a run then executes in the same mode, whichever thread runs it: results stay
independent of the thread count. CUDA flushes nothing here (GPUs handle denormals at full speed), and
non-x86 CPUs compile the snippet to nothing.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

_SNIPPET = """
#if !defined(__CUDA_ARCH__) && (defined(__x86_64__) || defined(_M_X64) || defined(__i386__))
    if (flush == 1) {
        unsigned int csr = __builtin_ia32_stmxcsr();
        saved[0] = (int)csr;
        __builtin_ia32_ldmxcsr(csr | 0x8040u);  // FTZ (bit 15) | DAZ (bit 6)
    } else {
        __builtin_ia32_ldmxcsr((unsigned int)saved[0]);
    }
#endif
"""


@wp.func_native(_SNIPPET)
def _set_mxcsr(saved: wp.array(dtype=int), flush: int):
    ...


@wp.kernel
def set_flush_denormals(saved: wp.array(dtype=int), flush: int):
    """flush = 1: save this thread's MXCSR into saved[0] and set FTZ | DAZ; flush = 0: restore saved[0]."""
    _set_mxcsr(saved, flush)


def flush_denormals_in_this_thread(device: str = "cpu") -> None:
    """Set FTZ | DAZ for the rest of the calling thread's life (the solver's worker threads)."""
    wp.launch(set_flush_denormals, dim=1, inputs=[wp.zeros(1, dtype=int, device=device), 1], device=device)


class FlushedDenormals:
    """``with`` block: the calling thread computes with FTZ | DAZ inside it, in its own mode after."""

    def __init__(self, device: str):
        self.device = str(device)
        self.on = self.device == "cpu"
        self.saved = wp.zeros(1, dtype=int, device=self.device) if self.on else None

    def __enter__(self):
        if self.on:
            wp.launch(set_flush_denormals, dim=1, inputs=[self.saved, 1], device=self.device)
        return self

    def __exit__(self, *exc):
        if self.on:
            wp.launch(set_flush_denormals, dim=1, inputs=[self.saved, 0], device=self.device)
        return False
