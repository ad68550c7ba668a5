"""How to simulate: resolution, clock, step control and device (SimSettings)."""

from __future__ import annotations

import math
from dataclasses import dataclass


from ..errors import InputError

# Default resolution per device: a CPU is many times slower than a GPU even on all its cores, so the
# CPU default is sized for a demo that finishes in under a minute; the GPU is where resolution lives.
AUTO_GRID_RES = {"cpu": 24, "cuda": 48}
# Quality presets scale the automatic resolution (grid_res = 0) and set particles per cell.
QUALITY = {"draft": (0.67, 8), "standard": (1.0, 8), "high": (1.5, 8)}


MAX_CFL = 0.7  # the stress matrix (docs/stability.md) finds 0.9 unstable for rubber; 0.8 passes; keep a margin


@dataclass
class SimSettings:
    """How to simulate. Times in seconds; ``grid_res`` cells across the object's largest extent."""

    frames: int = 48
    fps: float = 24.0
    grid_res: int = 0  # cells across the object; 0 = auto (24 on CPU, 48 on CUDA: see AUTO_GRID_RES)
    particles_per_cell: int = 8
    cfl: float = 0.4
    domain_margin: float = 1.0  # free space around the object, in object sizes, for it to move into (the least:
    #                             given the camera, simulate() also holds its view: simulate.view_domain)
    max_particles: int = 200_000
    device: str = "auto"  # "cpu", "cuda", "cuda:N" or "auto"
    min_substeps: int = 8  # per frame, whatever the CFL allows: bounds the integrator's O(dt) drift
    quality: str = "standard"  # draft / standard / high: scales the automatic grid_res (see QUALITY)
    rest_speed: float = 2e-3  # m/s: a scene whose RMS particle speed (its kinetic energy per kg) stays
    #                         below this for 3 frames, with no force still to come, stops substepping and
    #                         repeats its state; 0 = off
    seed: int = 0
    transfer: str = "apic"  # particle↔grid velocity transfer: "apic" (affine, MLS-MPM) or "pic" (dissipative)
    fixed_dt: float = 0.0  # s; 0 = adaptive (CFL every substep). >0: this substep length, refused before the
    #                        run if above the stable step, shortened during the run wherever the CFL needs it
    max_substeps_per_frame: int = 100_000  # runs estimated to need more are refused before they start,
    #                                        and a frame that needs more stops the run with an explanation
    graph: str = "auto"  # capture each launch of substeps as a graph: "auto" (on CUDA with conditional graph
    #                      nodes, CUDA 12.4+), "on" (also on the CPU: Warp replays it there), "off"
    preload: bool = True  # start elastic solids (fixed_corotated, neo_hookean, fracture) that rest on the ground
    #                       in equilibrium under gravity: their photographed shape is the loaded one (see
    #                       MPMSolver.preload; skipped, at no cost, where it does not apply)
    ground_gap: float = 0.15  # cells: the ground acts on a column only where the material's underside lies within
    #                           this of the plane (MPMSolver's ground_gap; a stiff body otherwise rested or hovered
    #                           up to a cell above it); negative = off, the plain grid contact
    cpu_threads: int = 0  # threads for the CPU kernels; 0 = every core (PHYSMOTION_CPU_THREADS overrides 0).
    #                       The result does not depend on it (the work is split by particle count)

    def validate(self) -> None:
        if not (isinstance(self.cpu_threads, int) and 0 <= self.cpu_threads <= 1024):
            raise InputError(f"cpu_threads must be an integer in [0, 1024] (0 = every core); got {self.cpu_threads!r}")
        if self.graph not in ("auto", "on", "off"):
            raise InputError(f"graph must be 'auto', 'on' or 'off'; got {self.graph!r}")
        if not (isinstance(self.frames, int) and 1 <= self.frames <= 100_000):
            raise InputError(f"frames must be an integer between 1 and 100000; got {self.frames}")
        if not (math.isfinite(self.fps) and 0 < self.fps <= 1000):
            raise InputError(f"fps must be in (0, 1000]; got {self.fps}")
        if not (int(self.grid_res) == 0 or 4 <= int(self.grid_res) <= 1024):
            raise InputError(f"grid_res must be 0 (auto) or between 4 and 1024 cells; got {self.grid_res}")
        if self.particles_per_cell not in (1, 8, 27, 64):
            raise InputError(f"particles_per_cell must be 1, 8, 27 or 64 (n³ per cell); got {self.particles_per_cell}")
        if not (0.01 <= self.cfl <= MAX_CFL):
            raise InputError(f"cfl must be in [0.01, {MAX_CFL}]; 0.3-0.5 is typical, and above {MAX_CFL} stiff "
                             f"materials blow up (docs/stability.md); got {self.cfl}")
        if not (0.0 <= self.domain_margin <= 20.0):
            raise InputError(f"domain_margin must be in [0, 20] object sizes; got {self.domain_margin}")
        if self.max_particles < 1:
            raise InputError(f"max_particles must be positive; got {self.max_particles}")
        if not (isinstance(self.min_substeps, int) and 1 <= self.min_substeps <= 100_000):
            raise InputError(f"min_substeps must be an integer in [1, 100000]; got {self.min_substeps}")
        if self.quality not in QUALITY:
            raise InputError(f"quality must be one of {tuple(QUALITY)}; got '{self.quality}'")
        if not isinstance(self.preload, bool):
            raise InputError(f"preload must be True or False; got {self.preload!r}")
        if self.transfer not in ("apic", "pic"):
            raise InputError(f"transfer must be 'apic' or 'pic'; got '{self.transfer}'")
        if not (math.isfinite(self.fixed_dt) and 0.0 <= self.fixed_dt <= 0.1):
            raise InputError(f"fixed_dt must be 0 (adaptive) or a substep length in (0, 0.1] s; got {self.fixed_dt}")
        if not (isinstance(self.max_substeps_per_frame, int) and 1 <= self.max_substeps_per_frame <= 10_000_000):
            raise InputError(f"max_substeps_per_frame must be an integer in [1, 10000000]; got "
                             f"{self.max_substeps_per_frame}")
        if not (math.isfinite(self.ground_gap) and self.ground_gap <= 1.0):
            raise InputError(f"ground_gap must be at most 1 cell (negative turns the gap test off); got {self.ground_gap}")
        if not (math.isfinite(self.rest_speed) and self.rest_speed >= 0):
            raise InputError(f"rest_speed must be a non-negative speed in m/s (0 turns rest detection off); "
                             f"got {self.rest_speed}")

    def resolved_grid_res(self, device: str) -> int:
        if self.grid_res:
            return int(self.grid_res)
        scale, _ = QUALITY[self.quality]
        return max(4, int(round(AUTO_GRID_RES["cuda" if device.startswith("cuda") else "cpu"] * scale)))
