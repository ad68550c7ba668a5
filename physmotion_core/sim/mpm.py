"""The MPM driver: owns the Warp arrays and advances them with CFL-adaptive substeps."""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ..errors import InputError, SimulationError
from ..types import Ground, Material, Walls
from . import kernels as K
from .materials import IMPLEMENTED_MODELS, MODEL_IDS

log = logging.getLogger("physmotion.sim")

_CONTACT_IDS = {"sticky": 0, "slip": 1, "friction": 2}
PAD = 3  # cells of boundary padding at every face of the domain


def _warp():
    import warp as wp

    wp.config.quiet = True
    wp.init()
    return wp


def resolve_device(device: str = "auto") -> str:
    """'auto' → the first CUDA device when Warp sees one, else 'cpu'. PHYSMOTION_DEVICE overrides auto."""
    wp = _warp()
    if device == "auto":
        device = os.environ.get("PHYSMOTION_DEVICE", "auto")
    if device == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise InputError(f"device '{device}' was requested but Warp finds no CUDA device; use 'cpu' or 'auto'")
    return device


@dataclass
class Domain:
    """The simulation box: ``dims`` grid nodes of spacing ``dx`` from ``origin`` (metres)."""

    origin: np.ndarray
    dx: float
    dims: tuple[int, int, int]
    ground_node: int = -1  # grid index of the ground plane, -1 = no ground

    @property
    def lo(self) -> np.ndarray:
        return self.origin + PAD * self.dx

    @property
    def hi(self) -> np.ndarray:
        return self.origin + (np.asarray(self.dims) - PAD) * self.dx

    @classmethod
    def around(cls, lo: np.ndarray, hi: np.ndarray, dx: float, margin: float,
               ground: Optional[Ground]) -> "Domain":
        """A box around [lo, hi] with ``margin`` object-sizes of room on every side (floor: the ground)."""
        size = float(np.max(hi - lo))
        room = margin * size + 2 * dx
        box_lo = lo - room
        box_hi = hi + room
        ground_node = -1
        if ground is not None:
            if lo[1] < ground.height - 0.5 * dx:
                raise InputError(f"The object reaches below the ground (lowest point y={lo[1]:.4f} m, ground at "
                                 f"{ground.height:.4f} m). Raise the object or lower the ground.")
            box_lo[1] = ground.height
        # Snap so that the ground lies exactly on a grid node PAD cells above the origin.
        origin = box_lo - PAD * dx
        if ground is not None:
            origin[1] = ground.height - PAD * dx
            ground_node = PAD
        dims = tuple(int(math.ceil((box_hi[a] - origin[a]) / dx)) + PAD + 1 for a in range(3))
        return cls(origin=origin.astype(np.float64), dx=float(dx), dims=dims, ground_node=ground_node)


def estimate_bytes(num_particles: int, dims: Sequence[int], frames: int, recorded: int) -> dict:
    """Memory the run will need: device arrays, and the host copy of the recorded trajectory."""
    nodes = int(np.prod(dims))
    device = num_particles * (12 * 3 + 36 * 2 + 4 * 3) + nodes * 28
    host = (frames + 1) * recorded * (12 + 36)
    return {"device": device, "host": host, "nodes": nodes}


class MPMSolver:
    """MLS-MPM on a dense Warp grid, with grid work limited to the particles' active box."""

    def __init__(
        self,
        x: np.ndarray,
        volume: np.ndarray,
        mat_index: np.ndarray,
        materials: Sequence[Material],
        domain: Domain,
        *,
        gravity=(0.0, -9.81, 0.0),
        ground: Optional[Ground] = None,
        walls: Optional[Walls] = None,
        cfl: float = 0.4,
        device: str = "cpu",
        v0: Optional[np.ndarray] = None,
    ):
        for m in materials:
            m.validate()
            if m.model not in IMPLEMENTED_MODELS:
                raise InputError(f"Material '{m.name}' uses the '{m.model}' model, which this version of the "
                                 f"simulator does not implement yet; available: {', '.join(IMPLEMENTED_MODELS)}")
        self.wp = wp = _warp()
        self.device = device
        t0 = time.perf_counter()
        wp.load_module(K, device=device)  # JIT-compiles on first use, then comes from Warp's cache
        self.kernel_load_s = time.perf_counter() - t0
        self.domain = domain
        self.materials = list(materials)
        self.cfl = float(cfl)
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.ground = ground
        self.walls = walls or Walls()
        n = x.shape[0]
        self.n = n
        self.t = 0.0
        self.substeps = 0
        self.dt_min = math.inf
        self.dt_max = 0.0

        density = np.array([m.density for m in materials], dtype=np.float64)[mat_index]
        mass = (density * volume).astype(np.float32)
        self.mass_np = mass
        self.wave_speed = max(m.wave_speed() for m in materials)

        with wp.ScopedDevice(device):
            self.x = wp.array(x.astype(np.float32), dtype=wp.vec3)
            self.v = wp.array(np.zeros((n, 3), np.float32) if v0 is None else v0.astype(np.float32), dtype=wp.vec3)
            self.C = wp.zeros(n, dtype=wp.mat33)
            self.rot = wp.array(np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)), dtype=wp.quat)
            self.F = wp.array(np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)), dtype=wp.mat33)
            self.mass = wp.array(mass, dtype=float)
            self.vol = wp.array(volume.astype(np.float32), dtype=float)
            self.mat_id = wp.array(mat_index.astype(np.int32), dtype=int)
            self.f_ext = wp.zeros(n, dtype=wp.vec3)
            params = []
            for m in materials:
                p = K.MaterialParams()
                p.model = MODEL_IDS[m.model]
                p.mu = m.mu
                p.lam = m.lam
                p.density = m.density
                params.append(p)
            self.material_table = wp.array(params, dtype=K.MaterialParams)
            self.grid_m = wp.zeros(domain.dims, dtype=float)
            self.grid_mv = wp.zeros(domain.dims, dtype=wp.vec3)
            self.grid_v = wp.zeros(domain.dims, dtype=wp.vec3)
            self.stats = wp.zeros(8, dtype=float)

        g = K.GridInfo()
        g.origin = wp.vec3(*domain.origin.astype(np.float32))
        g.dx = domain.dx
        g.inv_dx = 1.0 / domain.dx
        g.nx, g.ny, g.nz = domain.dims
        self.grid = g
        bc = K.Boundary()
        bc.has_ground = int(ground is not None)
        bc.ground_node = domain.ground_node
        bc.ground_contact = _CONTACT_IDS[ground.contact] if ground else 0
        bc.ground_friction = ground.friction if ground else 0.0
        bc.wall_contact = _CONTACT_IDS[self.walls.contact]
        bc.wall_friction = self.walls.friction
        bc.pad = PAD
        self.bc = bc

        v_init = np.zeros(3) if v0 is None else np.abs(v0).max(axis=0)
        self._vmax = float(np.linalg.norm(v_init)) if v0 is None else float(np.linalg.norm(v0, axis=1).max())
        self._box = (x.min(axis=0), x.max(axis=0))
        self._check_box(frame=0)

    # -- host-side helpers ------------------------------------------------------------------
    def set_external_forces(self, f: np.ndarray) -> None:
        """Per-particle external forces (N) for the following substeps."""
        self.f_ext.assign(self.wp.array(f.astype(np.float32), dtype=self.wp.vec3, device=self.device))

    def stable_dt(self) -> float:
        """Largest stable step: CFL on the elastic wave speed plus the fastest particle."""
        return self.cfl * self.domain.dx / (self.wave_speed + self._vmax)

    def _check_box(self, frame: int) -> None:
        lo, hi = self._box
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise SimulationError(
                f"Simulation became invalid (NaN/Inf positions) at frame {frame}, t={self.t:.4f}s, material "
                f"'{self.materials[0].name}'. Likely cause: a force or stiffness too large for the grid; "
                "lower the force, E, or raise grid_res.", frame=frame, material=self.materials[0].name)
        d = self.domain
        node_lo = np.floor((lo - d.origin) / d.dx - 0.5).astype(int)
        node_hi = np.floor((hi - d.origin) / d.dx - 0.5).astype(int) + 2
        if np.any(node_lo < 0) or np.any(node_hi > np.asarray(d.dims) - 1):
            raise SimulationError(
                f"Particles left the simulation domain at frame {frame}, t={self.t:.4f}s (material "
                f"'{self.materials[0].name}', box {lo.round(3).tolist()}..{hi.round(3).tolist()} m, domain "
                f"{d.lo.round(3).tolist()}..{d.hi.round(3).tolist()} m). Likely cause: a force far too strong "
                "for the object's mass; lower it or enlarge domain_margin.",
                frame=frame, material=self.materials[0].name)
        self._node_lo = node_lo
        self._node_hi = node_hi

    # -- stepping ---------------------------------------------------------------------------
    def substep(self, dt: float, frame: int = 0) -> None:
        wp = self.wp
        lo = self._node_lo
        span = tuple(int(s) for s in (self._node_hi - lo + 1))
        with wp.ScopedDevice(self.device):
            wp.launch(K.p2g, dim=self.n, inputs=[self.x, self.v, self.C, self.F, self.rot, self.mass, self.vol, self.mat_id,
                                                 self.material_table, self.f_ext, self.grid, dt,
                                                 self.grid_m, self.grid_mv])
            gvec = wp.vec3(*self.gravity.astype(np.float32))
            wp.launch(K.grid_update, dim=span, inputs=[self.grid_m, self.grid_mv, self.grid_v,
                                                       wp.vec3i(int(lo[0]), int(lo[1]), int(lo[2])),
                                                       self.grid, self.bc, gvec, dt])
            wp.launch(K.reset_stats, dim=1, inputs=[self.stats])
            wp.launch(K.g2p, dim=self.n, inputs=[self.x, self.v, self.C, self.F, self.grid_v, self.grid, dt,
                                                 self.stats])
        s = self.stats.numpy()
        self.t += dt
        self.substeps += 1
        self.dt_min = min(self.dt_min, dt)
        self.dt_max = max(self.dt_max, dt)
        if s[7] != 0.0 or not np.isfinite(s[0]):
            self._box = (np.full(3, np.nan), np.full(3, np.nan))
        else:
            self._vmax = float(s[0])
            self._box = (s[1:4].astype(np.float64), s[4:7].astype(np.float64))
        self._check_box(frame)

    def positions(self) -> np.ndarray:
        return self.x.numpy().copy()

    def deformation(self) -> np.ndarray:
        return self.F.numpy().copy()

    def velocities(self) -> np.ndarray:
        return self.v.numpy().copy()

