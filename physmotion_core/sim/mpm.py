"""The MPM driver: owns the Warp arrays and advances them with CFL-adaptive substeps."""

from __future__ import annotations

import functools
import logging
import math
import os
import time
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from ..errors import InputError, SimulationError
from ..types.conditions import Ground, ObjectContact, Walls
from ..types.material import CONSTITUTIVE_MODELS, Material
from . import fpmode
from . import kernels as K
from .materials import kernel_params

log = logging.getLogger("physmotion.sim")

_CONTACT_IDS = {"sticky": 0, "slip": 1, "friction": 2}
PAD = 3  # cells of boundary padding at every face of the domain
MAX_TORQUES = 30  # torque regions are a per-particle bit mask
# Models whose particles transfer without the affine velocity next to Coulomb-friction ground (kernels.p2g):
# the elastic solids, which otherwise crept on a slope at 0.9 μ; flowing materials keep APIC there.
CONTACT_PIC_MODELS = ("fixed_corotated", "neo_hookean", "fracture")
# ... but with their body's spin as the affine part (kernels.spin_solve): a stiff disc pushed along the ground
# otherwise lost its spin there every substep and rocked to a stop instead of rolling (False: C = 0 there).
CONTACT_SPIN = True
SPIN_SAMPLES = 4096  # particles at most that each substep's spin estimate sums (kernels.spin_reduce)
# How long the ground's Coulomb friction keeps the budget a column left unused (kernels.static_friction), in
# periods of the bodies' slowest vertical ringing, 4 H / c (H: the active box's height above the ground,
# c: the stiffest wave speed); 0 = none, Coulomb's law on each substep's impulses alone (issue 37).
FRICTION_MEMORY = 1.0
# The ground acts on a column of nodes only where the material's underside lies within this many cells of
# the plane (kernels.ground_column; None = wherever the nodes at the plane have mass, the plain grid
# contact, which held a stiff body that the nodes' B-splines reached, up to 1.5 cells above the plane).
GROUND_GAP = 0.15
# ... for bodies that keep their shape. Flows settle onto the plane under the plain contact anyway (a sand
# block dropped 45 mm: its lowest particle at -0.1 mm, honey -0.8 mm), and the gap test shortened the sand
# column's run-out, which the plain contact matches to experiments (docs/accuracy.md, "Landing on the ground").
FLOW_MODELS = ("drucker_prager", "viscoplastic", "fluid")
# Gravity preload (MPMSolver.preload): the elastic solid models a photographed body's loaded shape is
# restored for, the most periods of its slowest vertical ringing it may relax for, and the RMS speed
# (a fraction of g / ω, the release ringing's speed) at which it counts as settled.
PRELOAD_MODELS = ("fixed_corotated", "neo_hookean", "fracture")
PRELOAD_PERIODS = 8.0
PRELOAD_TOL = 0.01
PRELOAD_MAX_SAG = 0.1  # a relaxation that moves a particle by more than this fraction of the height is given up
PRELOAD_MAX_STRAIN = 0.15  # ... and one whose 99th percentile of the largest principal strain exceeds this
#   (0.15: the soft preset's 0.3 x 0.15 x 0.15 m block, 11 %, holds preloaded at 0.9 μ, 3.7 mm in 1 s against
#   51.2 mm stress-free; the coffee-cup jelly, 19 %, toppled from its preloaded state and is given up)
TRANSFERS = ("apic", "pic")  # particle-grid velocity transfer: affine (APIC / MLS-MPM) or plain PIC
SPAN_QUANTUM = 4  # grid spans are rounded out to multiples of this many nodes (fewer graph captures)
MAX_SPAN_MARGIN = 32  # nodes of room around the particles' stencils a span may add per side (graphs)
EAGER_SPAN_MARGIN = 8  # the same without graphs (CPU), where a new span costs nothing to set up
MAX_GRAPHS = 8  # captured launch graphs kept per solver (one per grid span and torque state)
# CPU parallelism. Warp runs a CPU kernel on one thread, and its atomics there are plain adds, so the
# CPU splits the particles into contiguous chunks: each chunk's p2g scatters into its own layer of
# grid accumulators (summed by grid_update in layer order) and each chunk's g2p reduces into its own
# row of statistics (folded by merge_stats). Chunks run concurrently on a thread pool (Warp releases
# the GIL while a kernel runs). How many chunks depends only on the particle count, never on the
# number of threads, so a run gives the same bits on any machine. The layers cover the launch's grid
# span (plus LAYER_SLACK), not the whole domain, and are reallocated when the span outgrows them; a
# span too large for CHUNK_GRID_BUDGET with a layer per chunk gets 2, 4, 8, ... layers (layer_count),
# each filled by a contiguous run of chunks one after another in chunk order (layer_of_chunk), so p2g
# still runs on two or more threads, and the sums still depend only on the scene; with no room for
# two layers, one layer, filled by all chunks in turn (what one unsplit pass computes).
MIN_CHUNK_PARTICLES = 4096
MAX_CPU_CHUNKS = 16
LAYER_BYTES = 32  # per grid node and chunk: mass (4) + momentum (12) + anchored mass (4) + anchored momentum (12)
FIELD_BYTES = 28  # per grid node, chunk and object past the first with one velocity field per object:
#                  mass (4) + momentum (12) + mass gradient (12); the mass gradient of the first too
CHUNK_GRID_BUDGET = 256 * 2 ** 20  # bytes all chunks' accumulator layers may take together
LAYER_SLACK = 8  # nodes of room the layers get around a span, so a growing scene reallocates rarely
ROW_PAD = 32  # 4-byte values per row of chunk-private reductions: no false sharing between threads
MIN_SLAB_NODES = 65536  # grid spans smaller than this are updated by one thread (handing work to another
#                        thread costs tens of microseconds, what ~5000 nodes take)


def _warp():
    import warp as wp

    from ..warp_build import init_warp

    init_warp(wp)
    return wp


def _graphs_supported(wp, device: str) -> bool:
    """Capture each launch of substeps as a graph on CUDA when the driver has conditional nodes
    (CUDA 12.4+). On the CPU the same kernels are launched one by one: Warp's CPU graphs replay
    the same launches, and a CPU substep costs milliseconds against microseconds of launch overhead."""
    if not str(device).startswith("cuda"):
        return False
    try:
        return bool(wp.is_conditional_graph_supported())
    except Exception:  # noqa: BLE001 - older Warp: no conditional graphs
        return False


def resolve_device(device: str = "auto") -> str:
    """'auto' → the first CUDA device when Warp sees one, else 'cpu'. PHYSMOTION_DEVICE overrides auto."""
    wp = _warp()
    if device == "auto":
        device = os.environ.get("PHYSMOTION_DEVICE", "auto")
    if device == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise InputError(f"device '{device}' was requested but Warp finds no CUDA device; use 'cpu' or 'auto'")
    if device != "cpu" and not device.startswith("cuda"):
        raise InputError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N'; got '{device}'")
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


def _bspline(d: np.ndarray) -> np.ndarray:
    """The quadratic B-spline of MPM's transfers at distance d (cells)."""
    d = np.abs(d)
    return np.where(d < 0.5, 0.75 - d * d, np.where(d < 1.5, 0.5 * (1.5 - d) ** 2, 0.0))


@functools.lru_cache(maxsize=None)
def ground_touch_ratio(gap: Optional[float]) -> float:
    """The ground's contact test (kernels.ground_column, ``MPMSolver.field_touch``): for material filling
    the space above a height s (cells) over the ground plane's node row, the mass that the rows at and
    below the plane hold over the mass of the row above, as a function of s, is this ratio at s = ``gap``.
    A column whose ratio is at least that has its underside within ``gap`` cells of the plane. The ratio
    falls as the gap opens (0.53 at s = 0, 0.45 at 0.1, 0.20 at half a cell, 0 from 1.5) and depends on
    the particles' spacing only through the sampling (particles of spacing dx/2 at s = 0: 0.52).
    ``gap`` None: 0, a contact wherever the plane's nodes have mass."""
    if gap is None:
        return 0.0
    y = np.linspace(gap, gap + 3.0, 30001)
    low = np.trapezoid(_bspline(y) + _bspline(y + 1.0), y)
    up = np.trapezoid(_bspline(y - 1.0), y)
    return float(low / up)


def ground_impact_speed(g: float, dx: float) -> float:
    """The approach speed (m/s) above which a ground column within the nodes' reach but not touching
    meets the ground anyway (kernels.ground_column): the speed of a fall through that reach, √(2 g 1.5 dx).
    A body that settles or hops within the reach falls to the plane; one that comes in faster is met
    where the nodes first reach it, as plain grid contact does, which keeps its bounce."""
    return math.sqrt(2.0 * g * 1.5 * dx)


def _launch_all(cmds: list) -> None:
    for c in cmds:
        c.launch()


@functools.lru_cache(maxsize=64)
def _groups(n: int, k: int) -> tuple:
    """n parts in k contiguous groups of near-equal size, as (start, end) pairs."""
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return tuple((int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]))


def cpu_chunks(num_particles: int, device: str) -> int:
    """How many particle chunks p2g and g2p are split into: 1 on CUDA; on the CPU one per
    MIN_CHUNK_PARTICLES particles, at most MAX_CPU_CHUNKS."""
    if str(device) != "cpu":
        return 1
    return int(max(1, min(MAX_CPU_CHUNKS, num_particles // MIN_CHUNK_PARTICLES)))


def layer_bytes(fields: int = 1) -> int:
    """Accumulator bytes per grid node and layer with ``fields`` velocity fields."""
    return LAYER_BYTES if fields <= 1 else LAYER_BYTES + (fields - 1) * FIELD_BYTES + 12


def layer_count(chunks: int, span_nodes: int, fields: int = 1) -> int:
    """Accumulator layers for a span of ``span_nodes`` nodes: one per chunk within the budget, else the
    most of 2, 4, 8, ... (fewer than the chunks) that fit it, else one."""
    per_layer = span_nodes * layer_bytes(fields)
    if chunks <= 1:
        return 1
    if chunks * per_layer <= CHUNK_GRID_BUDGET:
        return chunks
    layers = 1
    while 2 * layers < chunks and 2 * layers * per_layer <= CHUNK_GRID_BUDGET:
        layers *= 2
    return layers


def layer_of_chunk(chunk: int, chunks: int, layers: int) -> int:
    """The accumulator layer chunk ``chunk`` scatters into: contiguous runs of chunks share a layer (their
    particles lie near each other, so the layer's box stays small), and take turns on it in chunk order."""
    return chunk * layers // chunks


class _InOrder:
    """Launches that must run one after another (the chunks sharing one accumulator layer), as one part
    of a step that runs concurrently with the step's other parts."""

    def __init__(self, cmds: list):
        self.cmds = cmds

    def launch(self) -> None:
        for c in self.cmds:
            c.launch()


def cpu_threads(requested: int = 0) -> int:
    """Worker threads for the CPU kernels: ``requested``, or with 0 every core this process may
    use (PHYSMOTION_CPU_THREADS overrides 0)."""
    if requested <= 0:
        env = os.environ.get("PHYSMOTION_CPU_THREADS", "").strip()
        if env:
            if not env.isdigit() or int(env) < 1:
                raise InputError(f"PHYSMOTION_CPU_THREADS must be a positive integer; got {env!r}")
            return int(env)
        try:
            return max(len(os.sched_getaffinity(0)), 1)
        except AttributeError:  # macOS, Windows
            return max(os.cpu_count() or 1, 1)
    return int(requested)


def estimate_bytes(num_particles: int, dims: Sequence[int], frames: int, recorded: int, chunks: int = 1,
                   fields: int = 1) -> dict:
    """Memory the run will need: device arrays, and the host copy of the recorded trajectory.
    ``chunks`` (``cpu_chunks``) > 1: the accumulator layers take at most CHUNK_GRID_BUDGET, or one
    layer over the whole domain, whichever is more. ``fields``: velocity fields (one per object
    when objects meet on fields of their own)."""
    nodes = int(np.prod(dims))
    accumulators = nodes * (layer_bytes(fields) + 12 * (fields - 1))  # + the extra fields' velocities
    if chunks > 1:
        accumulators = max(min(chunks * accumulators, CHUNK_GRID_BUDGET), accumulators)
    # x v f_ext (vec3) + C F tau (mat33) + rot (quat) + mass vol plastic mat flags body torque (scalars)
    device = num_particles * (12 * 3 + 36 * 3 + 16 + 4 * 7) + nodes * 12 + accumulators
    host = (frames + 1) * recorded * (12 + 36)
    return {"device": device, "host": host, "nodes": nodes}


def _check_materials(materials: Sequence[Material], transfer: str) -> None:
    for m in materials:
        m.validate()
        if m.model not in CONSTITUTIVE_MODELS:
            raise InputError(f"Material '{m.name}' uses the '{m.model}' model, which this simulator does "
                             f"not implement; available: {', '.join(CONSTITUTIVE_MODELS)}")
    if transfer not in TRANSFERS:
        raise InputError(f"transfer must be one of {TRANSFERS}; got '{transfer}'")


class MPMSolver:
    """MLS-MPM on a dense Warp grid, with grid work limited to the particles' active box.

    Per particle: a material index, flags (anchored, rigid), an optional rigid body index, and a
    bit mask of the torque regions it belongs to.
    """

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
        C0: Optional[np.ndarray] = None,
        anchored: Optional[np.ndarray] = None,
        body: Optional[np.ndarray] = None,
        torque_mask: Optional[np.ndarray] = None,
        transfer: str = "apic",
        graph: Optional[bool] = None,
        threads: int = 0,
        objects: Optional[np.ndarray] = None,
        object_contact: Optional[ObjectContact] = None,
        friction_memory: float = FRICTION_MEMORY,
        ground_gap: Optional[float] = GROUND_GAP,
    ):
        _check_materials(materials, transfer)
        if ground_gap is not None and not (math.isfinite(ground_gap) and 0.0 <= ground_gap <= 1.0):
            raise InputError(f"ground_gap must be None or a number of cells in [0, 1]; got {ground_gap}")
        self.ground_gap = ground_gap
        if not (math.isfinite(friction_memory) and friction_memory >= 0.0):
            raise InputError(f"friction_memory must be a finite number >= 0; got {friction_memory}")
        self.friction_memory = float(friction_memory)
        self.apic = 1.0 if transfer == "apic" else 0.0
        self.wp = wp = _warp()
        self.device = device
        t0 = time.perf_counter()
        wp.load_module(K, device=device)  # JIT-compiles on first use, then comes from Warp's cache
        self.kernel_load_s = time.perf_counter() - t0
        self.domain = domain
        self.materials = list(materials)
        self.cfl = float(cfl)
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self._gravity_w = wp.vec3(*self.gravity.astype(np.float32))
        self.ground = ground
        self.walls = walls or Walls()
        self.object_contact = object_contact or ObjectContact()
        self.n = x.shape[0]
        self._init_launch_state(graph, threads)
        mat_index = np.asarray(mat_index, dtype=np.int64)
        mass = self._init_mass_and_limits(mat_index, volume)
        flags, tmask = self._particle_flags(mat_index, anchored, body, torque_mask)
        self._init_fields(mat_index if objects is None else np.asarray(objects, np.int64), flags)
        self._anchors_on = bool((flags & K.FLAG_ANCHORED).any())
        self._held = np.flatnonzero(flags & K.FLAG_ANCHORED)
        with wp.ScopedDevice(device):
            self._alloc_particles(x, v0, C0, volume, mass, mat_index, flags)
            self._alloc_grid()
            self._alloc_step_control()
            self._alloc_torques(tmask)
            self.particles = self._particle_struct()
            if self.n_bodies:
                self._init_bodies(x, mass, volume, v0)
        self.grid = self._grid_info()
        self.bc = self._boundary()
        self._init_host_mirrors(x, v0, mass, flags)
        self._check_box(frame=0)

    # -- setup steps (in the order __init__ takes them) ----------------------------------------
    def _init_launch_state(self, graph: Optional[bool], threads: int) -> None:
        """Counters, caches of recorded programs and graphs, and the CPU's particle chunks and threads."""
        self.kernel_times: Optional[dict] = None  # set to {} to time every kernel (benchmarks; no graphs)
        self.use_graph = _graphs_supported(self.wp, self.device) if graph is None else bool(graph)
        self.graph_captures = 0  # how many launch graphs were captured (benchmarks / tests)
        self.launches = 0
        self.span_changes = 0  # how often the particles outgrew the grid span of a launch
        self._graphs: dict = {}
        self._programs: dict = {}  # recorded substep launch commands, per grid span and torque state
        self._span: Optional[tuple] = None
        self._aspan: Optional[tuple] = None  # the anchor passes' span (inside _span), see _anchor_span
        self._chunk = 8
        # Particle chunks (see MIN_CHUNK_PARTICLES) and the threads that run them.
        self.chunks = cpu_chunks(self.n, self.device)
        edges = np.linspace(0, self.n, self.chunks + 1).astype(np.int64)
        self._chunk_ranges = [(int(a), int(b - a)) for a, b in zip(edges[:-1], edges[1:])]
        self.threads = cpu_threads(threads) if self.device == "cpu" else 1
        self._pool: Optional[ThreadPoolExecutor] = None
        self._capturing = False
        # The substeps compute with denormals flushed to zero on the CPU (fpmode: a scene at rest made them
        # ~3x slower per particle).
        self._flushed = fpmode.FlushedDenormals(self.device)

    def _init_fields(self, objects: np.ndarray, flags: np.ndarray) -> None:
        """One grid velocity field per object where objects meet on fields of their own (multi-field
        contact, kernels.update_node_fields); one shared field for a single object, for
        ObjectContact('shared'), and with anchors (whose passes work on one field). ``field_np``:
        each particle's field."""
        ids = np.unique(objects) if len(objects) else np.zeros(0, np.int64)
        self.fields = 1
        self.field_np = np.zeros(self.n, np.int32)
        if len(ids) > 1 and self.object_contact.contact != "shared":
            if (flags & K.FLAG_ANCHORED).any():
                log.warning("Anchors hold their object on one velocity field shared by all objects: the objects "
                            "of this scene stick where they touch instead of bouncing off each other")
                return
            self.fields = len(ids)
            self.field_np = np.searchsorted(ids, objects).astype(np.int32)

    def _init_mass_and_limits(self, mat_index: np.ndarray, volume: np.ndarray) -> np.ndarray:
        """Particle masses (float32), and what bounds the step besides them: the stiffest
        material's wave speed, the viscous limit and gravity."""
        materials = self.materials
        density = np.array([m.density for m in materials], dtype=np.float64)[mat_index]
        mass = (density * volume).astype(np.float32)
        self.mass_np = mass
        self.mat_index = mat_index
        self._c0 = max(m.wave_speed() for m in materials)
        # Explicit viscosity is stable for dt <= ρ dx² / (6 η) (diffusion in 3-D); keep half of it.
        visc = [m.density / m.viscosity for m in materials if m.model == "fluid" and m.viscosity > 0]
        self._dt_viscous = 0.5 * min(visc) * self.domain.dx**2 / 6.0 if visc else math.inf
        self._accel_static = float(np.linalg.norm(self.gravity))
        self._accel_extra = 0.0
        self._accel_torque = 0.0
        self._anchor_speed = 0.0
        return mass

    def _particle_flags(self, mat_index: np.ndarray, anchored: Optional[np.ndarray], body: Optional[np.ndarray],
                        torque_mask: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Each particle's flags (anchored, rigid), its rigid body (``body_np``) and torque bits."""
        n = self.n
        flags = np.zeros(n, np.int32)
        if anchored is not None:
            flags[np.asarray(anchored, bool)] |= K.FLAG_ANCHORED
        rigid_model = np.array([m.model == "rigid" for m in self.materials])[mat_index]
        body_np = np.full(n, -1, np.int32) if body is None else np.asarray(body, np.int32).copy()
        if rigid_model.any() and (body_np[rigid_model] < 0).any():
            raise InputError("rigid particles need a body index (one per rigid object)")
        body_np[~rigid_model] = -1
        flags[rigid_model] |= K.FLAG_RIGID
        # Elastic solids next to Coulomb ground transfer with their body's spin as the affine part, not their own
        # (kernels.p2g, spin_solve).
        elastic = np.array([m.model in CONTACT_PIC_MODELS for m in self.materials])[mat_index]
        flags[elastic] |= K.FLAG_CONTACT_PIC
        self._contact_spin = bool(elastic.any()) and CONTACT_SPIN
        self.body_np = body_np
        self.n_bodies = int(body_np.max()) + 1 if (body_np >= 0).any() else 0
        tmask = np.zeros(n, np.int32) if torque_mask is None else np.asarray(torque_mask, np.int32)
        self.n_torques = int(np.max(np.floor(np.log2(np.maximum(tmask, 1)))) + 1) if tmask.any() else 0
        return flags, tmask

    def _alloc_particles(self, x: np.ndarray, v0: Optional[np.ndarray], C0: Optional[np.ndarray],
                         volume: np.ndarray, mass: np.ndarray, mat_index: np.ndarray, flags: np.ndarray) -> None:
        """The particle arrays (the ``Particles`` struct's fields), the force arrays and the material table."""
        wp, n, materials = self.wp, self.n, self.materials
        self.x = wp.array(x.astype(np.float32), dtype=wp.vec3)
        self.v = wp.array(np.zeros((n, 3), np.float32) if v0 is None else v0.astype(np.float32), dtype=wp.vec3)
        self.C = (wp.zeros(n, dtype=wp.mat33) if C0 is None
                  else wp.array(np.asarray(C0, np.float32).reshape(n, 3, 3), dtype=wp.mat33))
        self.F = wp.array(np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)), dtype=wp.mat33)
        self.F_err = wp.zeros(n, dtype=wp.mat33)
        self.tau = wp.zeros(n, dtype=wp.mat33)
        self.rot = wp.array(np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)), dtype=wp.quat)
        snow = np.array([m.model == "snow" for m in materials])[mat_index]
        self.plastic = wp.array(np.where(snow, 1.0, 0.0).astype(np.float32), dtype=float)  # snow: Jp = 1
        self.mass = wp.array(mass, dtype=float)
        self.vol = wp.array(volume.astype(np.float32), dtype=float)
        self.mat_id = wp.array(mat_index.astype(np.int32), dtype=int)
        self.flags = wp.array(flags, dtype=int)
        self.anchor_v = wp.zeros(n, dtype=wp.vec3)
        self.field = wp.array(self.field_np, dtype=int)
        # Each field's rest density (its material's mass over volume), inverted: update_node_fields'
        # fill check turns a field's nodal mass into the volume of material it stands for.
        vol = np.asarray(volume, np.float64)
        fmass = np.bincount(self.field_np, weights=mass.astype(np.float64), minlength=self.fields)
        fvol = np.bincount(self.field_np, weights=vol, minlength=self.fields)
        self.field_inv_rho = wp.array((fvol / np.maximum(fmass, 1e-30)).astype(np.float32), dtype=float)
        # Each field's ground test (kernels.ground_column): the gap test where every particle of the field is
        # of a body that keeps its shape; flows (FLOW_MODELS) keep the plain grid contact.
        flows = np.array([m.model in FLOW_MODELS for m in self.materials], bool)
        has_flow = np.bincount(self.field_np, weights=flows[mat_index].astype(np.float64), minlength=self.fields) > 0
        self.field_touch = wp.array(np.where(has_flow, 0.0, ground_touch_ratio(self.ground_gap)).astype(np.float32),
                                    dtype=float)
        self.f_static = wp.zeros(n, dtype=wp.vec3)
        self.f_total = wp.zeros(n, dtype=wp.vec3)
        self.material_table = wp.array([kernel_params(m) for m in materials], dtype=K.MaterialParams)

    def _alloc_grid(self) -> None:
        """Node velocities over the domain, and the accumulators: one layer over the whole domain
        with one chunk (CUDA, small scenes); with several, layers over the grid span, allocated by
        _fit_layers at the first launch."""
        wp, dims = self.wp, self.domain.dims
        self.grid_v = wp.zeros((self.fields,) + tuple(dims), dtype=wp.vec3)  # one velocity field per object
        # The masses of the nodes at and below the ground plane and of the row above it
        # (kernels.ground_contact), per field.
        self.ground_m = wp.zeros((self.fields, dims[0], max(self.domain.ground_node + 2, 1), dims[2]), dtype=float)
        # Per ground column and field, the friction budget (an impulse) its substeps left unused
        # (kernels.static_friction).
        self.ground_credit = wp.zeros((self.fields, dims[0], dims[2]), dtype=float)
        self.layers = 1
        self._layer_lo = (0, 0, 0)
        self._layer_hi = tuple(int(d) - 1 for d in dims)
        if self.chunks == 1:
            self._alloc_layers(1, self._layer_lo, self._layer_hi)
        else:
            self.grid_m = self.grid_mv = self.grid_fix = self.grid_fix_v = self.grid_g = None  # at the first launch
            self._layer_hi = (-1, -1, -1)
            self.layer_reallocations = -1
        # Each layer's box of stencil bases (p2g). Rows of chunk-private data are padded to
        # ROW_PAD values (128 bytes), so threads never share a cache line.
        self.layer_box = wp.zeros((self.chunks, ROW_PAD), dtype=int)

    def _alloc_step_control(self) -> None:
        """The device's step control: reductions (one row per chunk when chunked), clock, checks."""
        wp = self.wp
        self.stats = wp.zeros(K.N_STATS, dtype=float)
        self.stats_rows = None  # per-chunk reductions of a chunked g2p
        self._stats_of = [self.stats]
        if self.chunks > 1:
            self.stats_rows = wp.zeros((self.chunks, max(K.N_STATS, ROW_PAD)), dtype=float)
            wp.launch(K.init_chunk_stats, dim=self.chunks, inputs=[self.stats_rows])
            self._stats_of = [self.stats_rows[k] for k in range(self.chunks)]
        self.ctl = wp.zeros(K.N_CTL, dtype=wp.float64)
        self.status = wp.zeros(K.N_STATUS, dtype=int)
        self.cond = wp.zeros(1, dtype=int)
        self.dt_arr = wp.zeros(1, dtype=float)

    def _alloc_torques(self, tmask: np.ndarray) -> None:
        wp = self.wp
        self.torque_mask = wp.array(tmask, dtype=int)
        self.torque_sums = wp.zeros((max(self.n_torques, 1), K.N_TORQUE_SUMS), dtype=float)
        # Each field's spin for the ground's contact layer (kernels.spin_reduce, spin_solve, p2g)
        self.spin_sums = wp.zeros((self.fields, K.N_SPIN_SUMS), dtype=float)
        self.spin = wp.zeros(self.fields, dtype=wp.mat33)
        self.torque_taus = wp.zeros(max(self.n_torques, 1), dtype=wp.vec3)
        self._torques_on = False

    def _particle_struct(self):
        """The kernels' view of the particle arrays (the struct holds references: it stays valid
        while the arrays are only written in place)."""
        ps = K.Particles()
        for name in ("x", "v", "C", "F", "F_err", "tau", "rot", "plastic", "mass", "vol", "mat_id", "flags",
                     "anchor_v", "field"):
            setattr(ps, name, getattr(self, name))
        return ps

    def _grid_info(self):
        d = self.domain
        g = K.GridInfo()
        g.origin = self.wp.vec3(*d.origin.astype(np.float32))
        g.dx = d.dx
        g.inv_dx = 1.0 / d.dx
        g.nx, g.ny, g.nz = d.dims
        return g

    def _boundary(self):
        ground = self.ground
        bc = K.Boundary()
        bc.has_ground = int(ground is not None)
        bc.ground_node = self.domain.ground_node
        bc.ground_contact = _CONTACT_IDS[ground.contact] if ground else 0
        bc.ground_friction = ground.friction if ground else 0.0
        bc.wall_contact = _CONTACT_IDS[self.walls.contact]
        bc.wall_friction = self.walls.friction
        bc.pad = PAD
        oc = self.object_contact
        bc.object_contact = _CONTACT_IDS.get(oc.contact, K.CONTACT_STICKY)
        bc.object_friction = float(oc.friction)
        # What a fall through the nodes' reach (1.5 cells) gives: a column approaching faster is an impact,
        # met by the plain grid contact (a gap test there cost a stiff ball 0.07 of its bounce).
        bc.ground_impact = ground_impact_speed(float(np.linalg.norm(self.gravity)), self.domain.dx)
        return bc

    def _init_host_mirrors(self, x: np.ndarray, v0: Optional[np.ndarray], mass: np.ndarray, flags: np.ndarray) -> None:
        """Host mirrors of the device's step control (uploaded before, read back after each launch)."""
        vmax0 = 0.0 if v0 is None or self.n == 0 else float(np.linalg.norm(v0, axis=1).max())
        st = np.zeros(K.N_STATS, np.float32)
        st[K.S_VMAX] = vmax0
        st[K.S_C2] = self._c0 ** 2
        st[K.S_BOX_MIN:K.S_BOX_MIN + 3], st[K.S_BOX_MAX:K.S_BOX_MAX + 3] = x.min(axis=0), x.max(axis=0)
        self._stats = st
        self._ctl = np.zeros(K.N_CTL, np.float64)
        self._ctl[K.C_DT_CAP] = math.inf
        self._ctl[K.C_CFL_DX] = self.cfl * self.domain.dx
        self._ctl[K.C_ACCEL] = self._accel_static
        self._ctl[K.C_DT_VISC] = self._dt_viscous
        self._ctl[K.C_DT_MIN] = math.inf
        self._ctl[K.C_FRAME_VMAX] = vmax0
        deformable = (flags & (K.FLAG_ANCHORED | K.FLAG_RIGID)) == 0
        self._ctl[K.C_DEF_MASS] = float(mass[deformable].astype(np.float64).sum())
        self._ctl[K.C_GROUND_Y] = float(self.domain.origin[1] + self.domain.ground_node * self.domain.dx)
        self._ctl[K.C_GROUND_MEMORY] = self.friction_memory
        self._status = np.zeros(K.N_STATUS, np.int32)
        self._status[K.I_MAX_FRAME_SUBSTEPS] = 2 ** 31 - 1
        self.stats.assign(st)
        self._box = (x.min(axis=0).astype(np.float64), x.max(axis=0).astype(np.float64))

    # -- accumulator layers -------------------------------------------------------------------
    def _alloc_layers(self, layers: int, lo: tuple, hi: tuple) -> None:
        wp = self.wp
        shape = (layers,) + tuple(int(h - l + 1) for l, h in zip(lo, hi))
        # With several velocity fields a layer holds one slot per field (slot = layer · fields + field).
        fshape = (layers * self.fields,) + shape[1:]
        with wp.ScopedDevice(self.device):
            self.grid_m = wp.zeros(fshape, dtype=float)
            self.grid_mv = wp.zeros(fshape, dtype=wp.vec3)
            self.grid_g = wp.zeros(fshape if self.fields > 1 else (1, 1, 1, 1), dtype=wp.vec3)
            self.grid_fix = wp.zeros(shape, dtype=float)
            self.grid_fix_v = wp.zeros(shape, dtype=wp.vec3)
        self.layers, self._layer_lo, self._layer_hi = layers, tuple(lo), tuple(hi)
        self._layer_lo_w = wp.vec3i(*self._layer_lo)
        self.layer_reallocations = getattr(self, "layer_reallocations", -1) + 1

    def _fit_layers(self, span: tuple) -> None:
        """Make the accumulator layers cover ``span`` (chunked runs only). Every p2g writes inside
        the span (each particle checks that its next stencil does), so the layers need no more.
        Captured graphs hold the old arrays' addresses and are dropped."""
        if self.chunks == 1:
            return
        lo, hi = span
        if all(a <= l and h <= b for a, l, h, b in zip(self._layer_lo, lo, hi, self._layer_hi)):
            return
        dims = self.domain.dims
        new_lo = tuple(max(int(l) - LAYER_SLACK, 0) for l in lo)
        new_hi = tuple(min(int(h) + LAYER_SLACK, int(d) - 1) for h, d in zip(hi, dims))
        nodes = int(np.prod([h - l + 1 for l, h in zip(new_lo, new_hi)]))
        self._alloc_layers(layer_count(self.chunks, nodes, self.fields), new_lo, new_hi)
        self._graphs.clear()
        self._programs.clear()

    # -- rigid bodies -------------------------------------------------------------------------
    def _init_bodies(self, x: np.ndarray, mass: np.ndarray, volume: np.ndarray,
                     v0: Optional[np.ndarray] = None) -> None:
        """Each rigid body's centre, inertia (with its principal axes) and initial momenta.

        The body starts with the linear and angular momentum of its particles' initial velocities
        (float64), and its particles start on the rigid motion that carries them: v = V + ω × r and
        the affine velocity C = [ω]× (so the first transfer to the grid is exact, as every later
        one is)."""
        wp = self.wp
        nb = self.n_bodies
        centres = np.zeros((nb, 3))
        inertia = np.zeros((nb, 3, 3))
        axes = np.zeros((nb, 3, 3))
        moments = np.zeros((nb, 3))
        lin = np.zeros((nb, 3))
        ang = np.zeros((nb, 3))
        omega = np.zeros((nb, 3))
        v_all = None if v0 is None else np.asarray(v0, np.float64)
        masses = np.zeros(nb)
        offsets = np.zeros_like(x, dtype=np.float64)
        starts, ends = np.zeros(nb, np.int32), np.zeros(nb, np.int32)
        for b in range(nb):
            sel = self.body_np == b
            idx = np.nonzero(sel)[0]
            if idx[-1] - idx[0] + 1 != len(idx):
                raise InputError("a rigid body's particles must be contiguous (fill objects one after another)")
            starts[b], ends[b] = idx[0], idx[-1] + 1
            m = mass[sel].astype(np.float64)
            c = (x[sel] * m[:, None]).sum(0) / m.sum()
            r = x[sel] - c
            # Point-mass inertia: the angular momentum the particles show, Σ r × m v, is exactly
            # I_points ω for a rigid motion, so the body's L and what a viewer measures agree.
            # (It differs from the solid's by ~(s/L)², s the particle spacing and L the body's size.)
            inertia[b] = np.eye(3) * (m * (r * r).sum(1)).sum() - (r.T * m) @ r
            centres[b], masses[b] = c, m.sum()
            offsets[sel] = r
            # Principal axes (columns, right-handed) and moments I1 <= I2 <= I3; a degenerate
            # direction (particles on a line) gets a tiny moment instead of a division by zero.
            evals, evecs = np.linalg.eigh(inertia[b])
            if np.linalg.det(evecs) < 0:
                evecs[:, 2] *= -1
            axes[b] = evecs
            moments[b] = np.maximum(evals, 1e-9 * max(float(evals[-1]), 1e-30))
            if v_all is not None:
                mv = m[:, None] * v_all[sel]
                lin[b] = mv.sum(0) / m.sum()
                ang[b] = np.cross(r, mv).sum(0)
                omega[b] = evecs @ ((evecs.T @ ang[b]) / moments[b])
        if v_all is not None:
            v_rigid = v_all.copy()
            C = self.C.numpy()
            for b in range(nb):
                sel = self.body_np == b
                v_rigid[sel] = lin[b] + np.cross(omega[b], offsets[sel])
                C[sel] = np.array([[0.0, -omega[b][2], omega[b][1]], [omega[b][2], 0.0, -omega[b][0]],
                                   [-omega[b][1], omega[b][0], 0.0]])
            self.v.assign(wp.array(v_rigid.astype(np.float32), dtype=wp.vec3))
            self.C.assign(wp.array(C.astype(np.float32), dtype=wp.mat33))
        self.body_centre0 = centres
        self.body_radius = np.array([np.linalg.norm(offsets[self.body_np == b], axis=1).max() for b in range(nb)])
        self.body_radius_w = wp.array(self.body_radius.astype(np.float32), dtype=float)
        self.body_inertia = inertia
        self.body_mass_np = masses
        self.body = wp.array(self.body_np, dtype=int)
        self.body_offset = wp.array(offsets.astype(np.float32), dtype=wp.vec3)
        self.body_centre = wp.array(centres.astype(np.float32), dtype=wp.vec3)
        self.body_orient = wp.array(np.tile(np.array([0, 0, 0, 1], np.float32), (nb, 1)), dtype=wp.quat)
        self.body_axes_np, self.body_moments_np = axes, moments
        self.body_axes = wp.array(axes.astype(np.float32), dtype=wp.mat33)
        self.body_moments = wp.array(moments.astype(np.float32), dtype=wp.vec3)
        self.body_mass = wp.array(masses.astype(np.float32), dtype=float)
        self.body_start = wp.array(starts, dtype=int)
        self.body_end = wp.array(ends, dtype=int)
        self.body_dp = wp.zeros(nb, dtype=wp.vec3)  # the substep's change of momentum (rigid_reduce)
        self.body_dl = wp.zeros(nb, dtype=wp.vec3)  # ... of angular momentum
        self.body_ext_p = wp.zeros(nb, dtype=wp.vec3)  # ... of which the external forces' impulse
        self.body_ext_l = wp.zeros(nb, dtype=wp.vec3)
        self.body_l = wp.array(ang.astype(np.float32), dtype=wp.vec3)  # angular momentum, world frame
        self.body_v = wp.array(lin.astype(np.float32), dtype=wp.vec3)
        self.body_w = wp.array(omega.astype(np.float32), dtype=wp.vec3)
        self.body_contact = wp.zeros(nb, dtype=int)

    # -- host-side controls -------------------------------------------------------------------
    def set_external_forces(self, f: np.ndarray) -> None:
        """Per-particle external forces (N) for the following substeps (not counting torques)."""
        self.f_static.assign(self.wp.array(f.astype(np.float32), dtype=self.wp.vec3, device=self.device))
        m = self.mass_np.astype(np.float64)
        self._accel_extra = float((np.linalg.norm(f, axis=1) / m).max()) if len(m) else 0.0
        self._ctl[K.C_ACCEL] = self._accel_static + self._accel_extra + self._accel_torque

    def set_anchors(self, anchored: np.ndarray, velocity: np.ndarray) -> None:
        """Which particles are held now, and their prescribed velocities (P,3) m/s."""
        flags = self.flags.numpy()
        flags = (flags & ~K.FLAG_ANCHORED) | np.where(np.asarray(anchored, bool), K.FLAG_ANCHORED, 0).astype(np.int32)
        self.flags.assign(self.wp.array(flags.astype(np.int32), dtype=int, device=self.device))
        self.anchor_v.assign(self.wp.array(np.asarray(velocity, np.float32), dtype=self.wp.vec3, device=self.device))
        held = np.asarray(anchored, bool)
        if self.fields > 1 and held.any():
            raise InputError("Anchors need the objects on one shared velocity field: give the solver the anchors "
                             "at the start (it then shares one field) or use ObjectContact('shared')")
        idx = np.flatnonzero(held)
        if not np.array_equal(idx, self._held):
            self._aspan = None  # other particles are held: the anchor's span is found again
        self._held = idx
        self._anchors_on = bool(held.any())
        self._anchor_speed = float(np.linalg.norm(velocity[held], axis=1).max()) if held.any() else 0.0
        self._ctl[K.C_SPEED_FLOOR] = self._anchor_speed

    def set_torques(self, taus: np.ndarray, accel_bound: float = 0.0) -> None:
        """Torque vectors (n_torques, 3) N·m, zero for inactive ones; ``accel_bound`` bounds |α × r|."""
        taus = np.asarray(taus, np.float64).reshape(-1, 3)
        self._torques_on = bool(np.any(taus != 0))
        if self.n_torques:
            self.torque_taus.assign(self.wp.array(taus.astype(np.float32), dtype=self.wp.vec3, device=self.device))
        self._accel_torque = accel_bound if self._torques_on else 0.0
        self._ctl[K.C_ACCEL] = self._accel_static + self._accel_extra + self._accel_torque

    def set_limits(self, max_dt: float = math.inf, max_frame_substeps: int = 2 ** 31 - 1) -> None:
        """Caps on the adaptive step (s) and on the substeps of one frame (see ``advance``)."""
        self._ctl[K.C_DT_CAP] = float(max_dt)
        self._status[K.I_MAX_FRAME_SUBSTEPS] = int(min(max_frame_substeps, 2 ** 31 - 1))

    def begin_frame(self) -> None:
        """Reset the per-frame reductions (fastest particle, RMS speed, substep count)."""
        self._ctl[K.C_FRAME_VMAX] = 0.0
        self._ctl[K.C_FRAME_RMS] = 0.0
        self._status[K.I_FRAME_SUBSTEPS] = 0

    # -- the state the device keeps, as the host last read it ---------------------------------
    @property
    def t(self) -> float:
        return float(self._ctl[K.C_T])

    @property
    def substeps(self) -> int:
        return int(self._status[K.I_SUBSTEPS])

    @property
    def work(self) -> float:
        """J done by the external forces and torques so far."""
        return float(self._ctl[K.C_WORK])

    @property
    def dt_min(self) -> float:
        return float(self._ctl[K.C_DT_MIN])

    @property
    def dt_max(self) -> float:
        return float(self._ctl[K.C_DT_MAX])

    @property
    def frame_vmax(self) -> float:
        return float(self._ctl[K.C_FRAME_VMAX])

    @property
    def frame_rms(self) -> float:
        return float(self._ctl[K.C_FRAME_RMS])

    @property
    def frame_substeps(self) -> int:
        return int(self._status[K.I_FRAME_SUBSTEPS])

    def stable_dt(self) -> float:
        """Largest stable step: CFL on the current sound speed plus the fastest particle, an
        acceleration bound (a particle starting from rest must not cross a cell in one step),
        and the explicit-viscosity limit. (``plan_step`` computes the same on the device.)"""
        accel = self._accel_static + self._accel_extra + self._accel_torque
        vmax = float(self._stats[K.S_VMAX])
        return self._dt_limit(self.wave_speed(), max(vmax, self._anchor_speed), accel)

    def wave_speed(self) -> float:
        """The fastest elastic wave speed among the particles now (m/s)."""
        return math.sqrt(max(float(self._stats[K.S_C2]), 0.0))

    def _dt_limit(self, c: float, speed: float, accel: float) -> float:
        dx = self.domain.dx
        dt = self.cfl * dx / max(c + speed, 1e-12)
        if accel > 0:
            dt = min(dt, math.sqrt(self.cfl * dx / accel))
        return min(dt, self._dt_viscous)

    def estimate_dt(self, peak_accel: float, peak_speed: float = 0.0) -> tuple[float, str]:
        """The step the run will start with when external accelerations reach ``peak_accel`` (m/s²,
        besides gravity) and driven particles ``peak_speed``; and which limit sets it."""
        c, speed = self._c0, max(float(self._stats[K.S_VMAX]), peak_speed)
        accel = self._accel_static + peak_accel
        dx = self.domain.dx
        limits = {"wave speed": self.cfl * dx / max(c + speed, 1e-12),
                  "acceleration": math.sqrt(self.cfl * dx / accel) if accel > 0 else math.inf,
                  "viscosity": self._dt_viscous}
        why = min(limits, key=limits.get)
        return limits[why], why

    def _check_box(self, frame: int) -> None:
        lo, hi = self._box
        name = self.materials[0].name if len(self.materials) == 1 else "/".join(m.name for m in self.materials)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise SimulationError(
                f"Simulation became invalid (NaN/Inf values) at frame {frame}, t={self.t:.4f}s, material "
                f"'{name}'. Likely cause: a force or stiffness too large for the grid; lower the force or E, "
                "or raise grid_res.", frame=frame, material=name)
        d = self.domain
        node_lo = np.floor((lo - d.origin) / d.dx - 0.5).astype(int)
        node_hi = np.floor((hi - d.origin) / d.dx - 0.5).astype(int) + 2
        if np.any(node_lo < 0) or np.any(node_hi > np.asarray(d.dims) - 1):
            raise SimulationError(
                f"Particles left the simulation domain at frame {frame}, t={self.t:.4f}s (material "
                f"'{name}', box {lo.round(3).tolist()}..{hi.round(3).tolist()} m, domain "
                f"{d.lo.round(3).tolist()}..{d.hi.round(3).tolist()} m). Likely cause: a force far too strong "
                "for the object's mass; lower it or enlarge domain_margin.", frame=frame, material=name)
        self._node_lo = node_lo
        self._node_hi = node_hi

    # -- stepping -----------------------------------------------------------------------------
    # A substep is a fixed program of kernel launches. It is recorded once per grid span (and
    # torque state) as Warp launch commands, with every argument packed, and replayed each substep:
    # replaying a command costs a couple of microseconds of Python where wp.launch costs ten to
    # forty, which is most of a small scene's substep on the CPU.
    def _contact_row(self) -> int:
        """The node row at and below which p2g transfers without the affine velocity (kernels.p2g):
        on Coulomb-friction ground the row above the ground plane's (the particles whose stencil
        reaches the ground row or the first free row above it, between which the friction makes its
        velocity jump: within 2.5 cells of the ground), else −1 (none). Only the ground row (1.5
        cells) left some blocks creeping (a 0.11 m jelly cube at 0.9 μ: 45 mm/s)."""
        g = self.ground
        return int(self.domain.ground_node) + 1 if g is not None and g.contact == "friction" else -1

    def _cmd(self, kernel, dim, inputs):
        return self.wp.launch(kernel, dim=dim, inputs=inputs, device=self.device, record_cmd=True)

    def _parallel(self) -> bool:
        """Run chunks on the thread pool: on the CPU with more than one thread, outside a capture
        (a captured graph replays its launches one after another)."""
        if self.threads <= 1 or self._capturing:
            return False
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="physmotion-mpm",
                                            initializer=fpmode.flush_denormals_in_this_thread,
                                            initargs=(self.device,))
            weakref.finalize(self, self._pool.shutdown, wait=False)
        return True

    def _run_step(self, kernel, cmds: list, concurrent: bool) -> None:
        """Launch one step's commands: concurrently on the CPU's threads when they write disjoint
        memory (chunks have their own layers and rows), else in order. With ``kernel_times`` set
        to a dict, also time the step (synchronising)."""
        t0 = time.perf_counter() if self.kernel_times is not None else 0.0
        if len(cmds) > 1 and concurrent and self._parallel():
            # One contiguous group of parts per thread, the calling thread taking the first: a
            # hand-over to another thread costs tens of microseconds, so make as few as possible.
            groups = _groups(len(cmds), min(self.threads, len(cmds)))
            futures = [self._pool.submit(_launch_all, cmds[a:b]) for a, b in groups[1:]]
            _launch_all(cmds[groups[0][0]:groups[0][1]])
            for f in futures:
                f.result()
        else:
            for c in cmds:
                c.launch()
        if self.kernel_times is not None:
            self.wp.synchronize_device(self.device)
            self.kernel_times[kernel.key] = self.kernel_times.get(kernel.key, 0.0) + time.perf_counter() - t0

    def _grid_slabs(self, span_lo: tuple, dims: tuple) -> list:
        """grid_update's launches as (launch dims, slab origin, run): on the CPU a thread per
        z-column of the span, the span cut into slabs along x for the threads (nodes are
        independent, so the cut cannot change a result); on CUDA a thread per node."""
        if self.device != "cpu":
            return [(dims, self.wp.vec3i(*span_lo), 1)]
        slabs = min(self.threads, dims[0]) if self.threads > 1 and int(np.prod(dims)) >= MIN_SLAB_NODES else 1
        edges = np.linspace(0, dims[0], slabs + 1).astype(np.int64)
        return [((int(b - a), dims[1], 1), self.wp.vec3i(span_lo[0] + int(a), span_lo[1], span_lo[2]), dims[2])
                for a, b in zip(edges[:-1], edges[1:]) if b > a]

    def _record_substep(self, span_lo: tuple, span_hi: tuple, torques: bool, anchors: bool, aspan: tuple) -> list:
        """The substep program: [(kernel, commands, concurrent)], in order plan → [torques] → p2g
        → grid → [anchors] → g2p → [merge] → [rigid] → end. The anchor passes work over ``aspan``, the
        anchored particles' part of the span (``_anchor_span``). Every step reads dt and writes its checks on the
        device, so the program can also be captured as a graph."""
        wp = self.wp
        lo = wp.vec3i(*span_lo)
        hi = wp.vec3i(*span_hi)
        dims = tuple(int(h - l + 1) for l, h in zip(span_lo, span_hi))
        alo, ahi = wp.vec3i(*aspan[0]), wp.vec3i(*aspan[1])
        prog = []

        def step(kernel, dim, inputs):
            prog.append((kernel, [self._cmd(kernel, dim, inputs)], False))

        step(K.plan_step, 1, [self.stats, self.ctl, self.dt_arr, self.layer_box])
        forces = self.f_static
        if torques:
            step(K.zero_sums, self.torque_sums.shape, [self.torque_sums])
            step(K.torque_reduce, self.n, [self.particles, self.torque_mask, self.n_torques, self.torque_sums])
            step(K.apply_torques, self.n, [self.particles, self.torque_mask, self.n_torques, self.torque_sums,
                                           self.torque_taus, self.f_static, self.f_total])
            forces = self.f_total
        if self._contact_row() >= 0 and self._contact_spin:
            stride = max(1, -(-self.n // SPIN_SAMPLES))
            step(K.spin_reduce, -(-self.n // stride), [self.particles, self.spin_sums, stride, self.n])
            step(K.spin_solve, self.fields, [self.spin_sums, self.spin])
        chunks = list(enumerate(self._chunk_ranges))
        # Each layer's chunks scatter into it one after another, in chunk order; the layers fill concurrently.
        layer_of = [layer_of_chunk(c, self.chunks, self.layers) for c in range(self.chunks)]
        scatter = [self._cmd(K.p2g, count, [
            self.particles, forces, self.grid, self.dt_arr, self.grid_m, self.grid_mv, self.grid_fix,
            self.grid_fix_v, self.apic, start, layer_of[c], self.layer_box, self._layer_lo_w, self.fields,
            self.grid_g, self._contact_row(), self.spin])
            for c, (start, count) in chunks]
        prog.append((K.p2g, [_InOrder([cmd for c, cmd in enumerate(scatter) if layer_of[c] == layer])
                             for layer in range(self.layers)], self.layers > 1))
        slabs = self._grid_slabs(span_lo, dims)
        k_end = int(span_hi[2]) + 1
        prog.append((K.grid_update, [self._cmd(K.grid_update, slab_dims, [
            self.grid_m, self.grid_mv, self.grid_v, self.grid_fix, self.grid_fix_v, self.ground_m, slab_lo, self.grid,
            self.bc, self._gravity_w, self.dt_arr, self.layer_box, self._layer_lo_w, run, k_end, int(anchors), alo, ahi,
            self.fields, self.grid_g, self.field_inv_rho])
            for slab_dims, slab_lo, run in slabs], True))
        if self.ground is not None and span_lo[1] <= self.domain.ground_node:
            step(K.ground_contact, (dims[0], dims[2]), [self.grid_v, self.ground_m, self.grid_mv, lo, self.bc,
                                                        self._layer_lo_w, int(anchors), alo, ahi,
                                                        self.ground_credit, self.dt_arr, self.ctl, self.field_touch])
        if anchors:
            # The anchored nodes, from the sums grid_update left in layer 0 (kernels.anchor_update), over the
            # anchor's span only: elsewhere no node is held or next to a held one, and these passes change nothing.
            adims = tuple(int(h - l + 1) for l, h in zip(aspan[0], aspan[1]))
            aslabs = self._grid_slabs(aspan[0], adims)
            ak_end = int(aspan[1][2]) + 1
            step(K.anchor_pin, self.n, [self.particles, self.grid, self.grid_m, self.grid_fix, alo, ahi,
                                        self._layer_lo_w])
            prog.append((K.anchor_update, [self._cmd(K.anchor_update, slab_dims, [
                self.grid_m, self.grid_mv, self.grid_v, self.grid_fix, self.grid_fix_v, slab_lo, alo, ahi,
                self._layer_lo_w, run, ak_end]) for slab_dims, slab_lo, run in aslabs], True))
            prog.append((K.anchor_clear, [self._cmd(K.anchor_clear, slab_dims, [
                self.grid_m, self.grid_mv, self.grid_fix, self.grid_fix_v, slab_lo, self._layer_lo_w, run, ak_end])
                for slab_dims, slab_lo, run in aslabs], True))
        prog.append((K.g2p, [self._cmd(K.g2p, count, [
            self.particles, self.material_table, forces, self.grid_v, self.grid, self.dt_arr, self._stats_of[c],
            lo, hi, self.status, start, alo, ahi]) for c, (start, count) in chunks], True))
        if self.stats_rows is not None:
            step(K.merge_stats, 1, [self.stats_rows, self.stats])
        if self.n_bodies:
            step(K.rigid_reduce, self.n, [self.particles, forces, self.body, self.body_centre,
                                          self.body_v, self.body_w, self.dt_arr, self.body_dp, self.body_dl,
                                          self.body_ext_p, self.body_ext_l])
            step(K.rigid_velocity, self.n_bodies, [self.body_orient, self.body_axes, self.body_moments,
                                                   self.body_mass, self.body_dp, self.body_dl, self.body_l,
                                                   self.body_v, self.body_w])
            step(K.rigid_contacts, self.n_bodies, [self.particles, self.body_start, self.body_end,
                                                   self.body_centre, self.body_orient, self.body_axes,
                                                   self.body_moments, self.body_mass, self.body_v, self.body_w,
                                                   self.body_l, self.body_contact, self.grid, self.bc, 8])
            step(K.rigid_integrate, self.n_bodies, [self.body_centre, self.body_orient, self.body_axes,
                                                    self.body_moments, self.body_mass, self.body_v, self.body_w,
                                                    self.body_l, self.body_ext_p, self.body_ext_l,
                                                    self.body_contact, self._gravity_w, self.dt_arr])
            step(K.rigid_apply, self.n, [self.particles, self.body, self.body_offset,
                                         self.body_centre, self.body_orient, self.body_v, self.body_w, self.grid,
                                         self.stats, lo, hi, self.status])
            step(K.body_speed, self.n_bodies, [self.body_v, self.body_w, self.body_radius_w, self.stats])
        step(K.end_step, 1, [self.stats, self.ctl, self.status, self.cond])
        return prog

    def _substep_kernels(self, span_lo: tuple, span_hi: tuple, torques: bool) -> None:
        """Run one substep: the recorded program for this span, torque and anchor state."""
        aspan = self._aspan if self._anchors_on and self._aspan is not None else (span_lo, span_hi)
        key = (span_lo, span_hi, torques, self._anchors_on, aspan)
        prog = self._programs.get(key)
        if prog is None:
            if len(self._programs) >= MAX_GRAPHS:
                self._programs.pop(next(iter(self._programs)))
            prog = self._programs[key] = self._record_substep(span_lo, span_hi, torques, self._anchors_on, aspan)
        for kernel, cmds, concurrent in prog:
            self._run_step(kernel, cmds, concurrent)

    def _grid_span(self, horizon: float) -> tuple[tuple, tuple]:
        """Grid nodes the next launch works on: the particles' stencils now, plus room for what they
        can travel in ``horizon`` seconds, rounded outwards to multiples of SPAN_QUANTUM nodes so
        that a slowly moving scene keeps replaying the same captured graph.

        With graphs, the room also covers the acceleration bound (a new span means a new capture).
        Without, it covers the present speed only, at most EAGER_SPAN_MARGIN nodes: outgrowing a
        span only ends the launch early, and every grid node spared is work saved each substep."""
        return self._span_around(*self._box, horizon)

    def _anchor_span(self, horizon: float) -> tuple[tuple, tuple]:
        """The nodes the anchor passes work on: the held particles' stencils and one node around them
        (anchor_update's links), with the same room for travel as ``_grid_span``, inside the launch's span.
        Every other node has no held mass and no held neighbour, so the passes would leave it as it is; a
        held particle whose stencil would leave this span ends the launch (kernels.track_anchored)."""
        xa = self.x.numpy()[self._held].astype(np.float64)
        (alo, ahi) = self._span_around(xa.min(0), xa.max(0), horizon, extra=1, quantum=1)
        (slo, shi) = self._span
        lo = tuple(max(a, s) for a, s in zip(alo, slo))
        hi = tuple(max(min(a, s), l) for a, s, l in zip(ahi, shi, lo))
        return lo, hi

    def _span_around(self, lo: np.ndarray, hi: np.ndarray, horizon: float, extra: int = 0,
                     quantum: int = SPAN_QUANTUM) -> tuple[tuple, tuple]:
        """The span of ``_grid_span`` for particles in the box lo .. hi, ``extra`` nodes wider per side,
        rounded out to multiples of ``quantum`` nodes."""
        d = self.domain
        node_lo = np.floor((lo - d.origin) / d.dx - 0.5).astype(np.int64) - extra
        node_hi = np.floor((hi - d.origin) / d.dx - 0.5).astype(np.int64) + 2 + extra
        speed = max(float(self._stats[K.S_VMAX]), self._anchor_speed)
        travel = speed * horizon
        cap = EAGER_SPAN_MARGIN
        if self.use_graph:
            travel += 0.5 * float(self._ctl[K.C_ACCEL]) * horizon * horizon
            cap = MAX_SPAN_MARGIN
        margin = int(min(max(math.ceil(travel / d.dx) + 1, 2), cap))
        q = int(quantum)
        span_lo = np.maximum((node_lo - margin) // q * q, 0)
        span_hi = np.minimum(-((-(node_hi + margin + 1)) // q) * q - 1, np.asarray(d.dims) - 1)
        return tuple(int(v) for v in span_lo), tuple(int(v) for v in span_hi)

    def _push(self) -> None:
        self.ctl.assign(self._ctl)
        self.status.assign(self._status)

    def _pull(self) -> None:
        self._ctl = self.ctl.numpy().copy()
        self._status = self.status.numpy().copy()
        self._stats = self.stats.numpy().copy()
        st = self._stats
        if self._status[K.I_NAN] == 0:
            self._box = (st[K.S_BOX_MIN:K.S_BOX_MIN + 3].astype(np.float64),
                         st[K.S_BOX_MAX:K.S_BOX_MAX + 3].astype(np.float64))
        else:
            self._box = (np.full(3, np.nan), np.full(3, np.nan))

    def _run_launch(self, span: tuple, eager: bool) -> None:
        """Substeps until end_step clears the condition: a replay of the captured graph for this
        span, or the same kernels launched one by one."""
        wp = self.wp
        self.cond.fill_(1)
        self.launches += 1
        with wp.ScopedDevice(self.device), self._flushed:
            if eager or not self.use_graph or self.kernel_times is not None:
                wp.capture_while(self.cond, self._substep_kernels, span_lo=span[0], span_hi=span[1],
                                 torques=self._torques_on)
                return
            key = (span, self._torques_on, self._anchors_on, self._aspan)
            graph = self._graphs.get(key)
            if graph is None:
                if len(self._graphs) >= MAX_GRAPHS:
                    self._graphs.pop(next(iter(self._graphs)))
                self._capturing = True
                try:
                    with wp.ScopedCapture(device=self.device) as cap:
                        wp.capture_while(self.cond, self._substep_kernels, span_lo=span[0], span_hi=span[1],
                                         torques=self._torques_on)
                finally:
                    self._capturing = False
                graph = self._graphs[key] = cap.graph
                self.graph_captures += 1
                # A capture on CUDA records without running; on the CPU, APIC recording does not run
                # either. Reset the condition the capture may have left and replay.
                self.cond.fill_(1)
            wp.capture_launch(graph)

    def _raise_invalid(self, frame: int) -> None:
        name = self.materials[0].name if len(self.materials) == 1 else "/".join(m.name for m in self.materials)
        if self._status[K.I_NAN]:
            raise SimulationError(
                f"Simulation became invalid (NaN/Inf values) at frame {frame}, t={self.t:.4f}s, material "
                f"'{name}'. Likely cause: a force or stiffness too large for the grid; lower the force or E, "
                "or raise grid_res.", frame=frame, material=name)
        if self._status[K.I_ESCAPE]:
            lo, hi = self._box
            d = self.domain
            raise SimulationError(
                f"Particles left the simulation domain at frame {frame}, t={self.t:.4f}s (material "
                f"'{name}', box {lo.round(3).tolist()}..{hi.round(3).tolist()} m, domain "
                f"{d.lo.round(3).tolist()}..{d.hi.round(3).tolist()} m). Likely cause: a force far too strong "
                "for the object's mass; lower it or enlarge domain_margin.", frame=frame, material=name)
        if self._status[K.I_TOO_MANY]:
            raise SimulationError(
                f"Frame {frame} needed more than max_substeps_per_frame={int(self._status[K.I_MAX_FRAME_SUBSTEPS])} "
                f"substeps (step now {float(self._ctl[K.C_DT]):.3g} s: fastest particle {self.frame_vmax:.3g} m/s, "
                f"wave speed {self.wave_speed():.3g} m/s). Likely cause: the material was compressed far stiffer "
                "than at rest, or a force accelerates it without bound; lower the force or E, or raise "
                "max_substeps_per_frame.", frame=frame, material=name)

    def advance(self, t_end: float, frame: int = 0, progress: Optional[callable] = None,
                launch_seconds: float = 0.2) -> None:
        """Advance to time ``t_end`` with CFL-adaptive substeps chosen on the device.

        Substeps run in launches of up to a few hundred milliseconds each (``progress()`` is called
        between launches, so it may raise to cancel); on CUDA each launch replays a captured graph
        (no host synchronisation inside it). Between launches the host reads back the clock and the
        checks: NaN/Inf, particles leaving the domain and a frame that needs more than its substep
        limit raise ``SimulationError`` naming the frame, material and likely cause.
        """
        while self.t < t_end - 1e-9:
            if self._status[K.I_FRAME_SUBSTEPS] >= self._status[K.I_MAX_FRAME_SUBSTEPS]:
                self._status[K.I_TOO_MANY] = 1
                self._raise_invalid(frame)
            if self._span is None:
                self._span = self._grid_span(t_end - self.t)
                self._fit_layers(self._span)
                self._aspan = None
            if self._anchors_on and self._aspan is None:
                self._aspan = self._anchor_span(t_end - self.t)
            self._ctl[K.C_T_END] = t_end
            self._status[K.I_LAUNCH_SUBSTEPS] = 0
            self._status[K.I_CHUNK] = self._chunk
            self._push()
            t0 = time.perf_counter()
            self._run_launch(self._span, eager=False)
            self._pull()
            done = int(self._status[K.I_LAUNCH_SUBSTEPS])
            if done:
                per = (time.perf_counter() - t0) / done
                self._chunk = int(min(max(launch_seconds / max(per, 1e-9), 1), 1_000_000))
            if self._status[K.I_NAN] or self._status[K.I_ESCAPE] or self._status[K.I_TOO_MANY]:
                self._raise_invalid(frame)
            if self._status[K.I_OVERFLOW]:
                self._status[K.I_OVERFLOW] = 0
                self._span = None  # the particles outgrew a span: the next launch gets wider ones
                self.span_changes += 1
            if progress is not None:
                progress()

    def substep(self, dt: float, frame: int = 0) -> None:
        """Exactly one substep of length ``dt`` (no CFL limit; for tests and reference runs)."""
        if self._span is None:
            self._span = self._grid_span(float(dt))
            self._fit_layers(self._span)
            self._aspan = None
        if self._anchors_on and self._aspan is None:
            self._aspan = self._anchor_span(float(dt))
        self._ctl[K.C_FORCE_DT] = float(dt)
        self._ctl[K.C_T_END] = self.t + float(dt)
        self._status[K.I_LAUNCH_SUBSTEPS] = 0
        self._status[K.I_CHUNK] = 1
        self._push()
        with self.wp.ScopedDevice(self.device), self._flushed:
            self._substep_kernels(self._span[0], self._span[1], self._torques_on)
        self._pull()
        self._ctl[K.C_FORCE_DT] = 0.0
        if self._status[K.I_NAN] or self._status[K.I_ESCAPE]:
            self._raise_invalid(frame)
        if self._status[K.I_OVERFLOW]:
            self._status[K.I_OVERFLOW] = 0
            self._span = None

    def preload(self, height: float, wave_speed: float, max_periods: float = PRELOAD_PERIODS,
                tol: float = PRELOAD_TOL, max_sag: float = PRELOAD_MAX_SAG,
                max_strain: float = PRELOAD_MAX_STRAIN, on_step: Optional[Callable[[], None]] = None) -> dict:
        """Start the bodies in equilibrium under gravity (dynamic relaxation).

        A photographed body already carries its weight: the photo shows its loaded shape. Released
        stress-free instead, an elastic body sags and rings (its base unloading once a period, which
        lets it creep on a slope at friction below the limit). Here, before the first frame, the scene
        relaxes under gravity alone with its velocities damped at the critical rate of its slowest
        mode (a quarter-wave column of ``height`` m and wave speed ``wave_speed`` m/s, simulate() passes
        the slowest shear wave speed: ω = π c / 2 H, damping exp(-2 ω dt) per substep), until its
        mass-weighted RMS speed falls below
        ``tol`` · g / ω (after at least one period) or ``max_periods`` periods of 4 H / c have passed.
        Then the deformation gradients (the internal stress) are KEPT while the positions return to
        the photo's, the velocities, affine velocities, float32 carry of F, plastic / damage state and
        the ground friction's credit return to their start, and the clock, work and substep counters
        restart at 0. For small strains that state is in equilibrium to first order.

        A scene with no equilibrium near the photo (a soft tall body that tips or slides away under its
        own weight: some particle moves by more than ``max_sag`` · ``height``) or that has not settled
        after ``max_periods`` is given up as soon as that shows; so is one whose strains are not small (the
        99th percentile over the particles of the largest principal Green strain above ``max_strain``),
        where the photo's positions with the relaxed stress are far from equilibrium (a soft cup with thin
        parts, strained 20-35 %, toppled from that state). Given up, F returns to the identity too, and
        the run starts stress-free as without the preload (``applied`` False).

        Returns what it did: ``applied``, ``substeps``, ``seconds`` (wall), ``sim_time`` (s relaxed),
        ``periods``, ``rms`` (m/s at the end), ``settled``, ``sag`` (the largest particle displacement,
        m, the relaxation showed before the positions were restored) and ``strain`` (the percentile above). The F it kept is ``self.F_preload``
        (None when given up). ``on_step``, if given, is called every 16 substeps (progress, and a host's cancel
        check, which may raise)."""
        g = float(np.linalg.norm(self.gravity))
        if not (height > 0 and wave_speed > 0 and g > 0 and self.n):
            raise InputError("preload needs a body of positive height and wave speed under gravity")
        if self.n_bodies:
            raise InputError("preload is for deformable bodies; this scene has rigid ones")
        t0 = time.perf_counter()
        period = 4.0 * height / wave_speed
        omega = 2.0 * math.pi / period
        target = tol * g / omega
        x0 = self.x.numpy().copy()
        plastic0 = self.plastic.numpy().copy()
        m = self.mass_np.astype(np.float64)
        m_sum = max(float(m.sum()), 1e-30)
        wp = self.wp
        t, steps, rms, settled, sag = 0.0, 0, math.inf, False, 0.0
        dt_cap = float(self._ctl[K.C_DT_CAP])
        while t < max_periods * period:
            dt = min(self.stable_dt(), dt_cap, max_periods * period - t + 1e-12)
            self.substep(dt)
            t += dt
            steps += 1
            keep = math.exp(-2.0 * omega * dt)
            v = self.v.numpy() * np.float32(keep)
            self.v.assign(wp.array(v, dtype=wp.vec3, device=self.device))
            self.C.assign(wp.array(self.C.numpy() * np.float32(keep), dtype=wp.mat33, device=self.device))
            rms = math.sqrt(float((m * (v.astype(np.float64) ** 2).sum(1)).sum()) / m_sum)
            sag = max(sag, float(np.sqrt(((self.x.numpy() - x0) ** 2).sum(1).max())))
            if sag > max_sag * height:
                break
            if steps % 16 == 0:
                if on_step is not None:
                    on_step()  # progress and the host's cancel check (a node's Cancel interrupts here)
                if self._strain99() > 1.25 * max_strain:  # the ringing overshoots ~10 % at most
                    break
            if t >= period and rms < target:
                settled = True
                break
        strain = self._strain99()
        applied = settled and sag <= max_sag * height and strain <= max_strain
        self.F_preload = self.F.numpy().copy() if applied else None
        with wp.ScopedDevice(self.device):
            if not applied:
                self.F.assign(wp.array(np.tile(np.eye(3, dtype=np.float32), (self.n, 1, 1)), dtype=wp.mat33))
                self.tau.zero_()
                self.rot.assign(wp.array(np.tile(np.array([0, 0, 0, 1], np.float32), (self.n, 1)), dtype=wp.quat))
            self.x.assign(wp.array(x0, dtype=wp.vec3))
            self.v.zero_()
            self.C.zero_()
            self.F_err.zero_()
            self.plastic.assign(wp.array(plastic0, dtype=float))
            self.ground_credit.zero_()
        for i in (K.C_T, K.C_WORK, K.C_FRAME_VMAX, K.C_FRAME_RMS, K.C_DT_MAX):
            self._ctl[i] = 0.0
        self._ctl[K.C_DT_MIN] = math.inf
        self._status[K.I_SUBSTEPS] = 0
        self._status[K.I_FRAME_SUBSTEPS] = 0
        st = self._stats
        st[K.S_VMAX] = 0.0
        if not applied:
            st[K.S_C2] = self._c0 ** 2
        st[K.S_BOX_MIN:K.S_BOX_MIN + 3], st[K.S_BOX_MAX:K.S_BOX_MAX + 3] = x0.min(axis=0), x0.max(axis=0)
        self.stats.assign(st)
        self._box = (x0.min(axis=0).astype(np.float64), x0.max(axis=0).astype(np.float64))
        self._span = None
        self._aspan = None
        self._push()
        self.preload_info = {"applied": applied, "substeps": steps, "seconds": time.perf_counter() - t0, "sim_time": t,
                             "periods": t / period, "rms": rms, "settled": settled, "sag": sag, "strain": strain}
        return self.preload_info

    def _strain99(self) -> float:
        """The 99th percentile over the particles of the largest principal Green strain |½ (FᵀF − 1)|."""
        F = self.F.numpy().astype(np.float64)
        green = 0.5 * (np.einsum("pji,pjk->pik", F, F) - np.eye(3))
        return float(np.percentile(np.abs(np.linalg.eigvalsh(green)).max(1), 99)) if len(F) else 0.0

    # -- read-back ------------------------------------------------------------------------------
    def positions(self) -> np.ndarray:
        return self.x.numpy().copy()

    def deformation(self) -> np.ndarray:
        return self.F.numpy().copy()

    def velocities(self) -> np.ndarray:
        return self.v.numpy().copy()

    def energy(self) -> tuple[float, float]:
        """Kinetic and gravitational potential energy (J; potential relative to the origin)."""
        m = self.mass_np.astype(np.float64)
        v = self.v.numpy().astype(np.float64)
        x = self.x.numpy().astype(np.float64)
        return 0.5 * float((m * (v * v).sum(1)).sum()), -float((m * (x @ self.gravity)).sum())

    def plastic_state(self) -> np.ndarray:
        return self.plastic.numpy().copy()

    def body_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Rigid bodies' centres, orientations (xyzw), linear and angular velocities."""
        if not self.n_bodies:
            z = np.zeros((0, 3))
            return z, np.zeros((0, 4)), z, z
        return (self.body_centre.numpy().copy(), self.body_orient.numpy().copy(), self.body_v.numpy().copy(),
                self.body_w.numpy().copy())

    def body_angular_momentum(self) -> np.ndarray:
        """Rigid bodies' angular momenta about their centres, world frame (N·m·s), as the solver keeps them."""
        if not self.n_bodies:
            return np.zeros((0, 3))
        return self.body_l.numpy().astype(np.float64)
