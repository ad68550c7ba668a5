"""Warp kernels of the MLS-MPM solver (quadratic B-splines, APIC affine transfer).

The same kernels run on ``cpu`` and ``cuda``. One substep is:

  p2g          particles -> grid: mass, momentum, the stored stress's impulse, external forces
  grid_update  grid velocities, gravity, ground and wall contact (sticky / slip / Coulomb)
  anchor_*     with anchored particles: the nodes at and past the anchor's edge (anchor_update)
  g2p          grid -> particles: velocity, affine C, position, F = (I + dt C) F, then the
               material's return mapping (plasticity) and the Kirchhoff stress for the next p2g
  rigid_*      for rigid objects: the body's momenta take the grid's exchange, the forces and the
               contacts; the body moves (exact free rotation, gravity at the half step) and places
               its particles on its rigid motion

Computing the stress at the end of g2p, right after the return mapping, means a plastic model does
one SVD per substep (the mapping's) instead of two, and elastic models skip the mapping entirely.

Grid kernels are launched over a span of nodes around the particles' active box (``lo`` offset +
launch dims), and ``grid_update`` zeroes the accumulators it consumed, so the next ``p2g`` starts
from a clean grid without a separate clearing pass over the whole domain. Every moved particle
checks that its next stencil stays inside that span (else the host widens it) and inside the
domain (else the run stops with an error): no kernel ever writes outside the grid.

The step itself is controlled on the device: ``plan_step`` picks dt from the CFL limits using
the previous substep's reductions, ``end_step`` advances the clock and sets the condition of the
substep loop, so a launch of many substeps needs no host round trip and can be captured once as
a (CUDA or CPU) graph with ``wp.capture_while`` and replayed every frame.

On the CPU, where Warp runs a kernel on one thread and its atomics are plain adds, the solver
splits the particles into contiguous chunks and launches p2g and g2p once per chunk on a thread
pool: each chunk scatters into its own layer of the grid accumulators (``grid_update`` sums the
layers in order, over the box of nodes each layer's particles reach) and reduces into its own row
of statistics (``merge_stats``). The layers cover the launch's span from node ``layer_lo``. On CUDA
there is one chunk and one layer over the whole domain.

Materials are a table of structs indexed by each particle's material id; ``model`` selects the
constitutive rule, one named function each in ``constitutive.py``, which ``update_material`` only
dispatches to: adding a model adds a function there and a line to the dispatch.
"""

from __future__ import annotations

import warp as wp

from .constitutive import MaterialParams, update_material  # noqa: F401 - the material table and its rules
from .constitutive import MODEL_FIXED_COROTATED, barrier_corotated

# The simulation is never differentiated: no adjoint code (halves the CUDA build; the forward code
# and its results are unchanged).
wp.set_module_options({"enable_backward": False})

# Contact ids.
CONTACT_STICKY = wp.constant(0)
CONTACT_SLIP = wp.constant(1)
CONTACT_FRICTION = wp.constant(2)

# Particle flags.
FLAG_ANCHORED = wp.constant(1)
FLAG_RIGID = wp.constant(2)
FLAG_CONTACT_PIC = wp.constant(4)  # an elastic solid's particle: PIC next to Coulomb ground (p2g)

# An anchor holds the grid nodes where its particles carry at least this fraction of the mass, and
# on the grid links that cross its edge (where the fraction passes ½) it puts the clamp on the edge
# itself (anchor_update). Before, a node was held from 15 % up, so the clamp sat on a node and
# jumped by most of a cell as the grid slid past the edge: a hanging bar at 10 cells rang −3.2 …
# +4.5 % off 4 L / c over ten offsets of the grid across a cell, now −1.9 … +0.6 % (L from the held
# particles' face; tests/test_sim_anchor.py).
ANCHOR_LEVEL = wp.constant(0.5)


@wp.struct
class GridInfo:
    origin: wp.vec3
    dx: float
    inv_dx: float
    nx: int
    ny: int
    nz: int


@wp.struct
class Boundary:
    has_ground: int
    ground_node: int  # nodes with index <= ground_node are in contact with the ground
    ground_contact: int
    ground_friction: float
    wall_contact: int
    wall_friction: float
    pad: int  # cells of padding at each wall: nodes closer than this to a face are wall nodes
    object_contact: int  # between objects' velocity fields (multi-field): CONTACT_* (see field_contact)
    object_friction: float
    ground_impact: float  # m/s: a ground column with a gap meets the ground when it approaches faster (ground_column)


@wp.struct
class Particles:
    """The particles' state: what every substep's kernels read and write (MPMSolver owns the arrays)."""

    x: wp.array(dtype=wp.vec3)  # positions (m)
    v: wp.array(dtype=wp.vec3)  # velocities (m/s)
    C: wp.array(dtype=wp.mat33)  # affine velocity (APIC / MLS-MPM), the velocity gradient
    F: wp.array(dtype=wp.mat33)  # elastic deformation gradient
    F_err: wp.array(dtype=wp.mat33)  # what float32 rounded off F's last update (see g2p)
    tau: wp.array(dtype=wp.mat33)  # Kirchhoff stress for the next p2g
    rot: wp.array(dtype=wp.quat)  # the tracked rotation of F (corotated models)
    plastic: wp.array(dtype=float)  # the model's state: plastic strain, snow's J_p, fracture damage
    mass: wp.array(dtype=float)  # kg
    vol: wp.array(dtype=float)  # rest volume (m³)
    mat_id: wp.array(dtype=int)  # row of the material table
    flags: wp.array(dtype=int)  # FLAG_ANCHORED | FLAG_RIGID
    anchor_v: wp.array(dtype=wp.vec3)  # prescribed velocity of an anchored particle (m/s)
    field: wp.array(dtype=int)  # the grid velocity field the particle moves on (its object; 0 with one field)


# ----------------------------------------------------------------------------------------------
# Transfers
# ----------------------------------------------------------------------------------------------


@wp.func
def bspline_weights(fx: wp.vec3, axis: int):
    f = fx[axis]
    return wp.vec3(0.5 * (1.5 - f) * (1.5 - f), 0.75 - (f - 1.0) * (f - 1.0), 0.5 * (f - 0.5) * (f - 0.5))


@wp.func
def bspline_slopes(fx: wp.vec3, axis: int):
    """d/df of bspline_weights (f in cells)."""
    f = fx[axis]
    return wp.vec3(f - 1.5, -2.0 * (f - 1.0), f - 0.5)


@wp.func
def stencil_base(x: wp.vec3, grid: GridInfo) -> wp.vec3i:
    xp = (x - grid.origin) * grid.inv_dx
    return wp.vec3i(int(xp[0] - 0.5), int(xp[1] - 0.5), int(xp[2] - 0.5))


# ----------------------------------------------------------------------------------------------
# Step control on the device: the time step, the clock and the checks live in small arrays, so a
# frame's substeps need no host round trip and can be replayed from a captured graph.
# ----------------------------------------------------------------------------------------------

# stats (float32, reset by plan_step, filled during the substep)
S_VMAX = wp.constant(0)  # fastest particle (m/s)
S_BOX_MIN = wp.constant(1)  # 1..3 the active box's lower corner (m)
S_BOX_MAX = wp.constant(4)  # 4..6 its upper corner (m)
S_NAN = wp.constant(7)  # 1 when a NaN/Inf speed or stiffness appeared
S_C2 = wp.constant(8)  # largest wave speed² (m²/s²) at the current deformation
S_MV2 = wp.constant(9)  # Σ m v² of the deformable particles
S_WORK = wp.constant(10)  # work of the external forces in this substep (J)
S_BODY_SPEED = wp.constant(11)  # fastest rigid-body point |V| + |ω| r
N_STATS = 12

# ctl (float64): the clock, the step limits the host sets, and per-frame / per-run accumulators
C_T = wp.constant(0)
C_T_END = wp.constant(1)  # the current launch runs substeps until t reaches this
C_DT_CAP = wp.constant(2)  # upper bound on dt (frame_dt / min_substeps, fixed_dt)
C_CFL_DX = wp.constant(3)  # cfl · dx
C_ACCEL = wp.constant(4)  # bound on the particles' acceleration (gravity + forces + torques)
C_SPEED_FLOOR = wp.constant(5)  # prescribed speeds (moving anchors) the CFL must also respect
C_DT_VISC = wp.constant(6)  # explicit-viscosity limit
C_FORCE_DT = wp.constant(7)  # > 0: take exactly this step (MPMSolver.substep)
C_DT = wp.constant(8)  # the step taken by the current substep
C_DT_MIN = wp.constant(9)
C_DT_MAX = wp.constant(10)
C_WORK = wp.constant(11)  # cumulative work of the external forces (J)
C_FRAME_VMAX = wp.constant(12)
C_FRAME_RMS = wp.constant(13)  # largest RMS speed of the deformable particles (or body speed) this frame
C_DEF_MASS = wp.constant(14)  # mass of the deformable particles (kg)
C_GROUND_Y = wp.constant(15)  # height of the ground plane (m)
C_GROUND_TAU = wp.constant(16)  # how long the ground's friction remembers unused budget (s; ground_contact)
C_GROUND_MEMORY = wp.constant(17)  # that time in periods of the bodies' slowest vertical ringing, 4 H / c
N_CTL = 18

# status (int32)
I_COND = wp.constant(0)  # capture_while condition: 1 = take another substep
I_SUBSTEPS = wp.constant(1)
I_FRAME_SUBSTEPS = wp.constant(2)
I_LAUNCH_SUBSTEPS = wp.constant(3)
I_CHUNK = wp.constant(4)  # at most this many substeps per launch (keeps Cancel responsive)
I_MAX_FRAME_SUBSTEPS = wp.constant(5)
I_NAN = wp.constant(6)
I_ESCAPE = wp.constant(7)  # a particle's stencil left the domain
I_OVERFLOW = wp.constant(8)  # a particle's stencil left the grid span of this launch (the host widens it)
I_TOO_MANY = wp.constant(9)  # the frame needed more than I_MAX_FRAME_SUBSTEPS substeps
N_STATUS = 10


@wp.func
def node_in_span(n: wp.vec3i, span_lo: wp.vec3i, span_hi: wp.vec3i) -> bool:
    return n[0] >= span_lo[0] and n[1] >= span_lo[1] and n[2] >= span_lo[2] and n[0] <= span_hi[0] and \
        n[1] <= span_hi[1] and n[2] <= span_hi[2]


@wp.func
def track_position(x: wp.vec3, grid: GridInfo, span_lo: wp.vec3i, span_hi: wp.vec3i,
                   stats: wp.array(dtype=float), status: wp.array(dtype=int)):
    """Grow the active box by x and check that x's next stencil lies inside the launch's grid span
    (else the next p2g would write outside the cleared region, or outside the domain)."""
    if not (x[0] == x[0] and x[1] == x[1] and x[2] == x[2]) or wp.abs(x[0]) > 1.0e18 or \
            wp.abs(x[1]) > 1.0e18 or wp.abs(x[2]) > 1.0e18:
        stats[S_NAN] = 1.0
        return
    wp.atomic_min(stats, S_BOX_MIN, x[0])
    wp.atomic_min(stats, S_BOX_MIN + 1, x[1])
    wp.atomic_min(stats, S_BOX_MIN + 2, x[2])
    wp.atomic_max(stats, S_BOX_MAX, x[0])
    wp.atomic_max(stats, S_BOX_MAX + 1, x[1])
    wp.atomic_max(stats, S_BOX_MAX + 2, x[2])
    b = stencil_base(x, grid)
    if b[0] < span_lo[0] or b[1] < span_lo[1] or b[2] < span_lo[2] or b[0] + 2 > span_hi[0] or \
            b[1] + 2 > span_hi[1] or b[2] + 2 > span_hi[2]:
        status[I_OVERFLOW] = 1
        if b[0] < 0 or b[1] < 0 or b[2] < 0 or b[0] + 2 > grid.nx - 1 or b[1] + 2 > grid.ny - 1 or \
                b[2] + 2 > grid.nz - 1:
            status[I_ESCAPE] = 1


@wp.func
def track_anchored(x: wp.vec3, grid: GridInfo, anchor_lo: wp.vec3i, anchor_hi: wp.vec3i, status: wp.array(dtype=int)):
    """Check that an anchored particle's next stencil, and a node around it, lie inside the anchor's span
    (anchor_update's links reach one node past the held nodes; past the grid's edge there is no node to
    reach); else end the launch so the host widens it."""
    b = stencil_base(x, grid)
    lo = wp.vec3i(wp.max(b[0] - 1, 0), wp.max(b[1] - 1, 0), wp.max(b[2] - 1, 0))
    hi = wp.vec3i(wp.min(b[0] + 3, grid.nx - 1), wp.min(b[1] + 3, grid.ny - 1), wp.min(b[2] + 3, grid.nz - 1))
    if lo[0] < anchor_lo[0] or lo[1] < anchor_lo[1] or lo[2] < anchor_lo[2] or hi[0] > anchor_hi[0] or \
            hi[1] > anchor_hi[1] or hi[2] > anchor_hi[2]:
        status[I_OVERFLOW] = 1


@wp.kernel
def plan_step(stats: wp.array(dtype=float), ctl: wp.array(dtype=wp.float64), dt_arr: wp.array(dtype=float),
              layer_box: wp.array2d(dtype=int)):
    """The CFL step from the previous substep's fastest particle and stiffest material point, the
    acceleration and viscosity bounds and the host's caps; then reset the reductions (and the
    node boxes the chunks of p2g will scatter into)."""
    c = wp.sqrt(wp.max(wp.float64(stats[S_C2]), wp.float64(0.0)))
    speed = wp.max(wp.float64(stats[S_VMAX]), ctl[C_SPEED_FLOOR])
    dt = ctl[C_CFL_DX] / wp.max(c + speed, wp.float64(1.0e-12))
    if ctl[C_ACCEL] > wp.float64(0.0):
        dt = wp.min(dt, wp.sqrt(ctl[C_CFL_DX] / ctl[C_ACCEL]))
    dt = wp.min(wp.min(dt, ctl[C_DT_VISC]), ctl[C_DT_CAP])
    if ctl[C_FORCE_DT] > wp.float64(0.0):
        dt = ctl[C_FORCE_DT]
    dt = wp.min(dt, ctl[C_T_END] - ctl[C_T])
    dt32 = float(dt)
    dt_arr[0] = dt32
    ctl[C_DT] = wp.float64(dt32)
    # The ground friction's memory (static_friction): C_GROUND_MEMORY periods of the bodies' slowest
    # vertical ringing, 4 H / c (a quarter-wave column: a compression wave crosses the height H above the
    # ground four times), from the active box and the stiffest wave speed of the previous substep.
    tau = wp.float64(0.0)
    if c > wp.float64(0.0):
        height = wp.max(wp.float64(stats[S_BOX_MAX + 1]) - ctl[C_GROUND_Y], wp.float64(0.0))
        tau = ctl[C_GROUND_MEMORY] * wp.float64(4.0) * height / c
    ctl[C_GROUND_TAU] = tau
    stats[S_VMAX] = 0.0
    for a in range(3):
        stats[S_BOX_MIN + a] = 1.0e30
        stats[S_BOX_MAX + a] = -1.0e30
    stats[S_NAN] = 0.0
    stats[S_C2] = 0.0
    stats[S_MV2] = 0.0
    stats[S_WORK] = 0.0
    stats[S_BODY_SPEED] = 0.0
    for l in range(layer_box.shape[0]):
        for a in range(3):
            layer_box[l, a] = 2147483647
            layer_box[l, 3 + a] = -2147483647


@wp.kernel
def end_step(stats: wp.array(dtype=float), ctl: wp.array(dtype=wp.float64), status: wp.array(dtype=int),
             cond: wp.array(dtype=int)):
    """Advance the clock, fold this substep into the frame's and run's accumulators, and decide
    whether the launch takes another substep."""
    dt = ctl[C_DT]
    t = ctl[C_T] + dt
    if wp.abs(ctl[C_T_END] - t) < wp.float64(1.0e-6) * dt:
        t = ctl[C_T_END]  # dt went through float32: land exactly on the end instead of a sliver short
    ctl[C_T] = t
    status[I_SUBSTEPS] = status[I_SUBSTEPS] + 1
    status[I_FRAME_SUBSTEPS] = status[I_FRAME_SUBSTEPS] + 1
    status[I_LAUNCH_SUBSTEPS] = status[I_LAUNCH_SUBSTEPS] + 1
    ctl[C_DT_MIN] = wp.min(ctl[C_DT_MIN], dt)
    ctl[C_DT_MAX] = wp.max(ctl[C_DT_MAX], dt)
    vmax = stats[S_VMAX]
    if stats[S_NAN] != 0.0 or not (vmax == vmax) or vmax > 1.0e30:
        status[I_NAN] = 1
    else:
        ctl[C_WORK] = ctl[C_WORK] + wp.float64(stats[S_WORK])
        ctl[C_FRAME_VMAX] = wp.max(ctl[C_FRAME_VMAX], wp.float64(vmax))
        rms = wp.float64(0.0)
        if ctl[C_DEF_MASS] > wp.float64(0.0):
            rms = wp.sqrt(wp.max(wp.float64(stats[S_MV2]), wp.float64(0.0)) / ctl[C_DEF_MASS])
        rms = wp.max(rms, wp.float64(stats[S_BODY_SPEED]))
        ctl[C_FRAME_RMS] = wp.max(ctl[C_FRAME_RMS], rms)
    go = 1
    if status[I_NAN] != 0 or status[I_ESCAPE] != 0 or status[I_OVERFLOW] != 0:
        go = 0
    if t >= ctl[C_T_END] - wp.float64(1.0e-9):
        go = 0
    elif status[I_FRAME_SUBSTEPS] >= status[I_MAX_FRAME_SUBSTEPS]:
        status[I_TOO_MANY] = 1
        go = 0
    if status[I_LAUNCH_SUBSTEPS] >= status[I_CHUNK]:
        go = 0
    cond[0] = go


@wp.kernel
def body_speed(lin_vel: wp.array(dtype=wp.vec3), ang_vel: wp.array(dtype=wp.vec3),
               radius: wp.array(dtype=float), stats: wp.array(dtype=float)):
    """A rigid body's fastest point moves at |V| + |ω| r: a body spinning in place is not at rest."""
    b = wp.tid()
    wp.atomic_max(stats, S_BODY_SPEED, wp.length(lin_vel[b]) + wp.length(ang_vel[b]) * radius[b])


@wp.kernel
def p2g(
    ps: Particles,
    f_ext: wp.array(dtype=wp.vec3),
    grid: GridInfo,
    dt_arr: wp.array(dtype=float),
    grid_m: wp.array4d(dtype=float),
    grid_mv: wp.array4d(dtype=wp.vec3),
    grid_fix: wp.array4d(dtype=float),
    grid_fix_v: wp.array4d(dtype=wp.vec3),
    apic: float,
    offset: int,
    layer: int,
    layer_box: wp.array2d(dtype=int),
    layer_lo: wp.vec3i,
    fields: int,
    grid_g: wp.array4d(dtype=wp.vec3),
    contact_row: int,
    spin: wp.array(dtype=wp.mat33),
):
    """Scatter particles offset .. offset + launch dim into accumulator layer ``layer`` (see
    ``grid_update``: the layers of one substep are summed there). The layers start at node
    ``layer_lo``. With several layers, also grow the layer's box of stencil bases, so grid_update
    reads only the nodes a layer can hold.

    With several velocity fields (one per object, ``fields`` > 1) a layer holds one slot per field
    (slot = layer · fields + field) and each particle also scatters its mass gradient, Σ m ∇w, into
    ``grid_g``: at a node it points from the field's material towards the node, the field's outward
    normal there (field_contact).

    A particle whose stencil reaches a node row at or below ``contact_row`` (on Coulomb-friction
    ground the row above the ground plane's, MPMSolver._contact_row; −1 otherwise) transfers with its
    body's spin ``spin[field]`` as its affine velocity (spin_solve) instead of its own C: on such
    ground a stiff jelly block on a μ = 0.5 slope at 0.9 μ crept downhill at ~60 mm/s, hopping at
    ~11 Hz with most contact columns alternately slipping and lifting, an oscillation the bottom
    particles' C (which holds the velocity jump the friction makes between the stuck ground nodes and
    the free row above) carried from substep to substep. Without it there the block settles and
    holds (issue 37; docs/accuracy.md, "Friction on a slope"). Dropping C for the whole particle
    keeps its momentum exactly (the affine part sums to zero over the stencil); what the particle's
    own C holds beyond its body's turn (the shear, and its share of spin differing from the body's) is
    not carried (a PIC-like dissipation, in the contact layer only). Only
    elastic solids' particles (FLAG_CONTACT_PIC): a granular front a cell or two thick flowing over
    the ground would be all contact layer, and PIC there cut the sand column's run-out by a third.
    Plain PIC there (C = 0) also took the particles' share of a rolling body's spin every substep: a
    rubber disc pushed along the ground rocked to a stop instead of rolling (docs/accuracy.md,
    "Rolling"). The body's spin, a rigid turn, carries no shear: the slope tests hold as with PIC."""
    p = wp.tid() + offset
    dt = dt_arr[0]
    base = stencil_base(ps.x[p], grid)
    if grid_m.shape[0] > 1:
        for a in range(3):
            wp.atomic_min(layer_box, layer, a, base[a])
            wp.atomic_max(layer_box, layer, 3 + a, base[a])
    xp = (ps.x[p] - grid.origin) * grid.inv_dx
    fx = xp - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    wx = bspline_weights(fx, 0)
    wy = bspline_weights(fx, 1)
    wz = bspline_weights(fx, 2)
    slot = layer
    dwx = wp.vec3(0.0, 0.0, 0.0)
    dwy = wp.vec3(0.0, 0.0, 0.0)
    dwz = wp.vec3(0.0, 0.0, 0.0)
    if fields > 1:
        slot = layer * fields + ps.field[p]
        dwx = bspline_slopes(fx, 0)
        dwy = bspline_slopes(fx, 1)
        dwz = bspline_slopes(fx, 2)
    m = ps.mass[p]
    # MLS-MPM: the stress enters as an affine momentum term -dt * V * (4/dx^2) * tau. The particle's
    # affine velocity m C is transferred with APIC (apic = 1) and dropped with PIC (apic = 0).
    fl = ps.flags[p]
    Cp = ps.C[p]
    if base[1] <= contact_row and (fl & FLAG_CONTACT_PIC) != 0:
        Cp = spin[ps.field[p]]  # the body's own spin, not the particle's C (spin_solve)
    affine = (-dt * ps.vol[p] * 4.0 * grid.inv_dx * grid.inv_dx) * ps.tau[p] + (apic * m) * Cp
    mv = m * ps.v[p]
    if (fl & FLAG_RIGID) == 0:
        mv = mv + dt * f_ext[p]  # a rigid body takes its external forces directly (rigid_reduce)
    anchored = (fl & FLAG_ANCHORED) != 0
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = wx[i] * wy[j] * wz[k]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * grid.dx
                ix = base[0] + i - layer_lo[0]
                iy = base[1] + j - layer_lo[1]
                iz = base[2] + k - layer_lo[2]
                wp.atomic_add(grid_m, slot, ix, iy, iz, w * m)
                wp.atomic_add(grid_mv, slot, ix, iy, iz, w * (mv + affine * dpos))
                if fields > 1:
                    gw = wp.vec3(dwx[i] * wy[j] * wz[k], wx[i] * dwy[j] * wz[k], wx[i] * wy[j] * dwz[k])
                    wp.atomic_add(grid_g, slot, ix, iy, iz, (m * grid.inv_dx) * gw)
                if anchored:
                    wp.atomic_add(grid_fix, layer, ix, iy, iz, w * m)
                    wp.atomic_add(grid_fix_v, layer, ix, iy, iz, (w * m) * ps.anchor_v[p])


@wp.func
def contact_velocity(v: wp.vec3, n: wp.vec3, contact: int, mu: float) -> wp.vec3:
    """Grid-node velocity after contact with a boundary whose normal n points into the domain."""
    if contact == CONTACT_STICKY:
        return wp.vec3(0.0, 0.0, 0.0)
    vn = wp.dot(v, n)
    if vn >= 0.0:
        return v  # separating: no constraint
    vt = v - vn * n
    if contact == CONTACT_SLIP:
        return vt
    # Coulomb friction: the tangential speed drops by mu |vn|, and stops if that is not enough.
    vt_len = wp.length(vt)
    if vt_len <= mu * (-vn):
        return wp.vec3(0.0, 0.0, 0.0)
    return vt * (1.0 - mu * (-vn) / vt_len)


@wp.func
def wall_velocity(v: wp.vec3, i: int, j: int, k: int, grid: GridInfo, bc: Boundary) -> wp.vec3:
    """Domain walls (x, z sides and the top; the bottom too when there is no ground)."""
    if i < bc.pad:
        v = contact_velocity(v, wp.vec3(1.0, 0.0, 0.0), bc.wall_contact, bc.wall_friction)
    if i >= grid.nx - bc.pad:
        v = contact_velocity(v, wp.vec3(-1.0, 0.0, 0.0), bc.wall_contact, bc.wall_friction)
    if k < bc.pad:
        v = contact_velocity(v, wp.vec3(0.0, 0.0, 1.0), bc.wall_contact, bc.wall_friction)
    if k >= grid.nz - bc.pad:
        v = contact_velocity(v, wp.vec3(0.0, 0.0, -1.0), bc.wall_contact, bc.wall_friction)
    if j >= grid.ny - bc.pad:
        v = contact_velocity(v, wp.vec3(0.0, -1.0, 0.0), bc.wall_contact, bc.wall_friction)
    if bc.has_ground == 0 and j < bc.pad:
        v = contact_velocity(v, wp.vec3(0.0, 1.0, 0.0), bc.wall_contact, bc.wall_friction)
    # With a ground, its contact is per column of nodes, in ground_contact.
    return v


@wp.func
def field_contact(v: wp.vec3, vcm: wp.vec3, n: wp.vec3, contact: int, mu: float) -> wp.vec3:
    """A field's node velocity v after contact with the other fields at the node (their centre of mass
    moves at vcm; n: the field's outward unit normal). Contact only acts while the field approaches
    the rest, (v − vcm)·n > 0 (Bardenhagen et al. 2000): the normal part of its velocity relative to
    vcm is removed, and the tangential part is kept (slip), removed (sticky) or reduced by μ times the
    normal part removed, down to zero (Coulomb friction). With two fields the normals are opposite and
    the corrections, m (v − vcm) parts, cancel: momentum is conserved exactly."""
    dv = v - vcm
    dn = wp.dot(dv, n)
    if dn <= 0.0:
        return v  # separating (or moving apart tangentially): the fields move freely
    if contact == CONTACT_STICKY:
        return vcm
    vt = dv - dn * n
    if contact == CONTACT_SLIP:
        return vcm + vt
    vt_len = wp.length(vt)
    if vt_len <= mu * dn:
        return vcm
    return vcm + vt * (1.0 - mu * dn / vt_len)


@wp.func
def update_node_fields(
    i: int,
    j: int,
    k: int,
    fields: int,
    grid_m: wp.array4d(dtype=float),
    grid_mv: wp.array4d(dtype=wp.vec3),
    grid_g: wp.array4d(dtype=wp.vec3),
    grid_v: wp.array4d(dtype=wp.vec3),
    ground_m: wp.array4d(dtype=float),
    grid: GridInfo,
    bc: Boundary,
    gravity: wp.vec3,
    dt: float,
    layer_box: wp.array2d(dtype=int),
    layer_lo: wp.vec3i,
    field_inv_rho: wp.array(dtype=float),
):
    """update_node for several velocity fields (one per object; no anchors): each field's mass,
    momentum and mass gradient summed over the layers; each field's free velocity; where two or more
    fields have mass and their material fills the node, contact between them (field_contact, normals
    from the mass gradients); then the walls, per field. Pass 1 leaves each field's sums in layer 0's
    slot, pass 2 reads and clears them (only this thread touches this node's slots).

    The fill check (a volume gap check): a field's nodal mass over its rest density,
    m_f / ρ_f (``field_inv_rho``), is the volume of its material that the node's B-spline holds,
    dx³ for a node deep inside a body. Two bodies touch at a node when their volumes there add up to
    the node's, Σ m_f / ρ_f ≥ dx³; with less, a gap lies between them within the node's reach, and
    they move freely. Without the check every node that both bodies' stencils reach (two node rows
    along an interface, more at a body's edges, where the mass-gradient normal tilts towards the
    sliding) took part, and a block sliding over another stopped at a third of Coulomb's distance
    (issue 37; docs/accuracy.md, "Contact between objects")."""
    layers = grid_m.shape[0] // fields
    li = i - layer_lo[0]
    lj = j - layer_lo[1]
    lk = k - layer_lo[2]
    M = float(0.0)
    P = wp.vec3(0.0, 0.0, 0.0)
    G = wp.vec3(0.0, 0.0, 0.0)
    present = int(0)
    fill = float(0.0)
    for f in range(fields):
        m = float(0.0)
        mv = wp.vec3(0.0, 0.0, 0.0)
        g = wp.vec3(0.0, 0.0, 0.0)
        for l in range(layers):
            if layers > 1:
                if i < layer_box[l, 0] or i > layer_box[l, 3] + 2 or j < layer_box[l, 1] or j > layer_box[l, 4] + 2 or \
                        k < layer_box[l, 2] or k > layer_box[l, 5] + 2:
                    continue
            s = l * fields + f
            m += grid_m[s, li, lj, lk]
            mv += grid_mv[s, li, lj, lk]
            g += grid_g[s, li, lj, lk]
            grid_m[s, li, lj, lk] = 0.0
            grid_mv[s, li, lj, lk] = wp.vec3(0.0, 0.0, 0.0)
            grid_g[s, li, lj, lk] = wp.vec3(0.0, 0.0, 0.0)
        v = wp.vec3(0.0, 0.0, 0.0)
        if m > 0.0:
            v = mv / m + dt * gravity
            present += 1
            fill += m * field_inv_rho[f]
            M += m
            P += m * v
            G += g
        # Layer 0's slot keeps the field's sums for pass 2.
        grid_m[f, li, lj, lk] = m
        grid_mv[f, li, lj, lk] = v
        grid_g[f, li, lj, lk] = g
    vcm = wp.vec3(0.0, 0.0, 0.0)
    if M > 0.0:
        vcm = P / M
    for f in range(fields):
        m = grid_m[f, li, lj, lk]
        v = grid_mv[f, li, lj, lk]
        g = grid_g[f, li, lj, lk]
        grid_m[f, li, lj, lk] = 0.0
        grid_mv[f, li, lj, lk] = wp.vec3(0.0, 0.0, 0.0)
        grid_g[f, li, lj, lk] = wp.vec3(0.0, 0.0, 0.0)
        if bc.has_ground != 0 and j <= bc.ground_node + 1:
            ground_m[f, i, j, k] = m
        if m > 0.0:
            if present > 1 and fill >= grid.dx * grid.dx * grid.dx:
                # The field's outward normal against the others': its own mass gradient minus theirs
                # (with two fields the two normals are exactly opposite).
                n = 2.0 * g - G
                nl = wp.length(n)
                if nl > 0.0:
                    v = field_contact(v, vcm, n / nl, bc.object_contact, bc.object_friction)
            v = wall_velocity(v, i, j, k, grid, bc)
        grid_v[f, i, j, k] = v


@wp.func
def update_node(
    i: int,
    j: int,
    k: int,
    grid_m: wp.array4d(dtype=float),
    grid_mv: wp.array4d(dtype=wp.vec3),
    grid_v: wp.array4d(dtype=wp.vec3),
    grid_fix: wp.array4d(dtype=float),
    grid_fix_v: wp.array4d(dtype=wp.vec3),
    ground_m: wp.array4d(dtype=float),
    grid: GridInfo,
    bc: Boundary,
    gravity: wp.vec3,
    dt: float,
    layer_box: wp.array2d(dtype=int),
    layer_lo: wp.vec3i,
    anchors: int,
    anchor_lo: wp.vec3i,
    anchor_hi: wp.vec3i,
):
    m = float(0.0)
    mv = wp.vec3(0.0, 0.0, 0.0)
    fix_m = float(0.0)
    fix_mv = wp.vec3(0.0, 0.0, 0.0)
    layers = grid_m.shape[0]
    # Only anchored particles scatter into the grid_fix accumulators, and their stencils lie in the anchor's
    # span (kernels.track_anchored): elsewhere those stay zero and are neither read nor cleared.
    in_anchor = anchors != 0 and node_in_span(wp.vec3i(i, j, k), anchor_lo, anchor_hi)
    for l in range(layers):
        if layers > 1:
            # Nodes outside this layer's stencils were never written: skip them.
            if i < layer_box[l, 0] or i > layer_box[l, 3] + 2 or j < layer_box[l, 1] or j > layer_box[l, 4] + 2 or \
                    k < layer_box[l, 2] or k > layer_box[l, 5] + 2:
                continue
        li = i - layer_lo[0]
        lj = j - layer_lo[1]
        lk = k - layer_lo[2]
        m += grid_m[l, li, lj, lk]
        mv += grid_mv[l, li, lj, lk]
        # Leave the accumulators clean for the next substep's p2g.
        grid_m[l, li, lj, lk] = 0.0
        grid_mv[l, li, lj, lk] = wp.vec3(0.0, 0.0, 0.0)
        if in_anchor:
            fix_m += grid_fix[l, li, lj, lk]
            fix_mv += grid_fix_v[l, li, lj, lk]
            grid_fix[l, li, lj, lk] = 0.0
            grid_fix_v[l, li, lj, lk] = wp.vec3(0.0, 0.0, 0.0)
    v = wp.vec3(0.0, 0.0, 0.0)
    if bc.has_ground != 0 and j <= bc.ground_node + 1:
        ground_m[0, i, j, k] = m
    if m > 0.0:
        v = mv / m + dt * gravity
        # Domain walls (x, z sides and the top; the bottom too when there is no ground).
        v = wall_velocity(v, i, j, k, grid, bc)
    grid_v[0, i, j, k] = v
    if in_anchor:
        # Keep the node's sums and free velocity in layer 0 for anchor_pin and anchor_update, which
        # set the anchored nodes' velocities (anchor_clear then empties layer 0), over the anchor's span
        # (the anchored particles' stencils and a node around them, all those passes read or set).
        li = i - layer_lo[0]
        lj = j - layer_lo[1]
        lk = k - layer_lo[2]
        grid_m[0, li, lj, lk] = m
        grid_mv[0, li, lj, lk] = v
        grid_fix[0, li, lj, lk] = fix_m
        grid_fix_v[0, li, lj, lk] = fix_mv


@wp.kernel
def grid_update(
    grid_m: wp.array4d(dtype=float),
    grid_mv: wp.array4d(dtype=wp.vec3),
    grid_v: wp.array4d(dtype=wp.vec3),
    grid_fix: wp.array4d(dtype=float),
    grid_fix_v: wp.array4d(dtype=wp.vec3),
    ground_m: wp.array4d(dtype=float),
    lo: wp.vec3i,
    grid: GridInfo,
    bc: Boundary,
    gravity: wp.vec3,
    dt_arr: wp.array(dtype=float),
    layer_box: wp.array2d(dtype=int),
    layer_lo: wp.vec3i,
    run: int,
    k_end: int,
    anchors: int,
    anchor_lo: wp.vec3i,
    anchor_hi: wp.vec3i,
    fields: int,
    grid_g: wp.array4d(dtype=wp.vec3),
    field_inv_rho: wp.array(dtype=float),
):
    """Node velocities from the accumulated mass and momentum (one velocity field, or one per object
    with ``fields`` > 1: update_node_fields). The accumulators have one layer per
    particle chunk (one in all on CUDA, where p2g's atomics are real; a chunk each for the CPU's
    threads, whose adds are not atomic); they are summed here in layer order, so the result does
    not depend on which thread scattered which chunk.

    Each thread updates a run of ``run`` nodes along z, up to node ``k_end`` (exclusive): one node
    on CUDA, a whole column of the span on the CPU, where a thread per node would spend more on
    turning its linear index into (i, j, k) than on the node.

    Every node gets its free velocity here; with ``anchors`` the sums stay in layer 0 for the
    anchor's passes (anchor_pin, anchor_update, anchor_clear) over the anchor's span ``anchor_lo`` ..
    ``anchor_hi`` (inclusive)."""
    a, b, c = wp.tid()
    dt = dt_arr[0]
    i = lo[0] + a
    j = lo[1] + b
    k0 = lo[2] + c * run
    for k in range(k0, wp.min(k0 + run, k_end)):
        if fields > 1:
            update_node_fields(i, j, k, fields, grid_m, grid_mv, grid_g, grid_v, ground_m, grid, bc, gravity, dt,
                               layer_box, layer_lo, field_inv_rho)
        else:
            update_node(i, j, k, grid_m, grid_mv, grid_v, grid_fix, grid_fix_v, ground_m, grid, bc, gravity, dt,
                        layer_box, layer_lo, anchors, anchor_lo, anchor_hi)


@wp.func
def static_friction(v: wp.vec3, m: float, mu: float, credit: float, decay: float) -> wp.vec4:
    """Coulomb friction on a ground column (normal +y) of mass m and free velocity v, with a memory
    (issue 37). Each substep the column's friction budget is μ J_n, J_n the normal impulse that stops its
    approach, plus ``credit``: the budget its earlier substeps left unused, fading by ``decay`` (exp(−dt/τ),
    τ about one period of the bodies' slowest vertical ringing). It sticks if the budget covers the impulse
    m |v_t| that stops it (and keeps the rest as credit), else it slips, its tangential velocity lowered
    by budget / m (credit spent). So over any stretch of substeps the friction impulse stays within μ
    times the normal impulse (less what faded); with no memory (decay 0) this is Coulomb's law on each
    substep's impulses, as before.

    Why: on the grid a column's normal impulse comes in bursts whenever the body rings vertically (a tall
    elastic body released on the ground rings at c / 4H), and in a burst the column only needs to stop
    its own small mass, so most of μ J_n went unused while the substeps between the bursts, with little
    or no normal impulse, let it slip. A 10-cells-tall jelly block at 0.9 μ crept 60 mm/s without end, the
    friction feeding its ringing (docs/accuracy.md, "Friction on a slope"). A body sliding steadily spends
    its whole budget every substep and keeps Coulomb's kinetic friction. The price: after resting, a column
    holds up to τ μ N of credit, so a push beyond friction starts the slide up to τ later (a 5 cm jelly
    block pushed at 2 μ m g: 3.5 % short after 0.2 s). Returns (velocity, new credit) as a vec4."""
    vn = v[1]
    jn = m * wp.max(-vn, 0.0)  # the normal impulse that stops the column's approach
    vy = wp.max(vn, 0.0)
    vt = wp.vec3(v[0], 0.0, v[2])
    vt_len = wp.length(vt)
    budget = credit * decay + mu * jn  # impulse
    if m * vt_len <= budget:
        return wp.vec4(0.0, vy, 0.0, budget - m * vt_len)
    keep = 1.0 - budget / (m * vt_len)
    return wp.vec4(v[0] * keep, vy, v[2] * keep, 0.0)


@wp.func
def ground_column(
    grid_v: wp.array4d(dtype=wp.vec3),
    ground_m: wp.array4d(dtype=float),
    grid_mv: wp.array4d(dtype=wp.vec3),
    f: int,
    i: int,
    k: int,
    lo: wp.vec3i,
    bc: Boundary,
    layer_lo: wp.vec3i,
    anchors: int,
    anchor_lo: wp.vec3i,
    anchor_hi: wp.vec3i,
    ground_credit: wp.array3d(dtype=float),
    decay: float,
    touch: float,
):
    m = float(0.0)
    p = wp.vec3(0.0, 0.0, 0.0)
    for j in range(lo[1], bc.ground_node + 1):
        mj = ground_m[f, i, j, k]
        if mj > 0.0:
            m += mj
            p += mj * grid_v[f, i, j, k]
    if m <= 0.0:
        ground_credit[f, i, k] = 0.0
        return
    v = p / m
    if m < touch * ground_m[f, i, bc.ground_node + 1, k] and -v[1] <= bc.ground_impact:
        # A gap: the material's underside lies above the plane, within the nodes' reach but not on it,
        # and it approaches no faster than a fall through that reach gives. The column moves freely (its
        # unused friction budget fades as it would in contact).
        ground_credit[f, i, k] = ground_credit[f, i, k] * decay
        return
    if bc.ground_contact == CONTACT_FRICTION:
        r = static_friction(v, m, bc.ground_friction, ground_credit[f, i, k], decay)
        v = wp.vec3(r[0], r[1], r[2])
        ground_credit[f, i, k] = r[3]
    else:
        v = contact_velocity(v, wp.vec3(0.0, 1.0, 0.0), bc.ground_contact, bc.ground_friction)
    for j in range(lo[1], bc.ground_node + 1):
        if ground_m[f, i, j, k] > 0.0:
            grid_v[f, i, j, k] = v
            if anchors != 0 and node_in_span(wp.vec3i(i, j, k), anchor_lo, anchor_hi):
                # The anchor's passes read each node's free velocity from layer 0 (update_node).
                l = wp.vec3i(i, j, k) - layer_lo
                grid_mv[0, l[0], l[1], l[2]] = v


@wp.kernel
def ground_contact(
    grid_v: wp.array4d(dtype=wp.vec3),
    ground_m: wp.array4d(dtype=float),
    grid_mv: wp.array4d(dtype=wp.vec3),
    lo: wp.vec3i,
    bc: Boundary,
    layer_lo: wp.vec3i,
    anchors: int,
    anchor_lo: wp.vec3i,
    anchor_hi: wp.vec3i,
    ground_credit: wp.array3d(dtype=float),
    dt_arr: wp.array(dtype=float),
    ctl: wp.array(dtype=wp.float64),
    field_touch: wp.array(dtype=float),
):
    """The ground's contact, one decision per column of nodes at and below the ground plane (a
    thread per (i, k) of the span; the span's lowest node row is ``lo[1]``, at or below the ground).

    The material on the ground takes its velocity from the ground node and the one below it (and
    the one above). Deciding stick or slip node by node let the node below the ground, which only
    the tails of the bottom particles' B-splines reach (~5 % of a layer's mass), slide under the
    stress impulses of its neighbours (its velocity is a small mass's share of them): a stiff jelly
    on a μ = 0.5 slope crept downhill at 20° (tan θ = 0.73 μ), its bottom dragged by those nodes at
    50-180 mm/s while the ground nodes above them stuck. The nodes of a column are one contact: their
    momentum and mass are summed, Coulomb's law (sticky, slip) acts on the sum once, and every node
    of the column with mass moves at the result (issue 37). For a body sliding uniformly nothing
    changes (every node of a column then has the same velocity). With one velocity field per object,
    each field's column is a contact of its own. Coulomb friction keeps each column's unused budget
    for about one period of the bodies' vertical ringing (``ground_credit``, static_friction).

    The gap test (ground_column): the nodes at the plane carry mass from particles up to 1.5 cells
    above it, so a column was held wherever a body came within that reach, and a stiff body, which
    the held nodes carry whole, rested a cell above the ground after a drop and hovered near its peak
    after a throw from the ground, for ever. A column now meets the ground only when its mass at and
    below the plane is at least ``field_touch[f]`` times the mass of the row above (the underside
    within MPMSolver.ground_gap cells of the plane; mpm.ground_touch_ratio; 0 for fields of flows,
    mpm.FLOW_MODELS, which keep the plain contact), or when it approaches
    faster than a fall through the reach gives (``bc.ground_impact``; an impact is met where the
    nodes first reach it, as before, which keeps the bounce)."""
    a, c = wp.tid()
    i = lo[0] + a
    k = lo[2] + c
    tau = float(ctl[C_GROUND_TAU])
    decay = float(0.0)
    if tau > 0.0:
        decay = wp.exp(-dt_arr[0] / tau)
    for f in range(ground_m.shape[0]):
        ground_column(grid_v, ground_m, grid_mv, f, i, k, lo, bc, layer_lo, anchors, anchor_lo, anchor_hi,
                      ground_credit, decay, field_touch[f])


# ----------------------------------------------------------------------------------------------
# Anchors: a Dirichlet condition at the held material's edge, to a fraction of a cell
# ----------------------------------------------------------------------------------------------


@wp.func
def held_fraction(grid_m: wp.array4d(dtype=float), grid_fix: wp.array4d(dtype=float), n: wp.vec3i,
                  span_lo: wp.vec3i, span_hi: wp.vec3i, layer_lo: wp.vec3i) -> float:
    """The anchored particles' share of node n's mass (layer 0 after grid_update), in [0, 1];
    −1 for a node without mass (or outside the span) and −2 for a pinned node (see anchor_pin)."""
    if not node_in_span(n, span_lo, span_hi):
        return -1.0
    l = n - layer_lo
    m = grid_m[0, l[0], l[1], l[2]]
    if m <= 0.0:
        return -1.0
    f = grid_fix[0, l[0], l[1], l[2]]
    if f < 0.0:
        return -2.0
    return wp.min(f / m, 1.0)


@wp.func
def axis_step(d: int) -> wp.vec3i:
    """The six neighbours of a node: d = 0..5 → −x, +x, −y, +y, −z, +z."""
    s = 2 * (d % 2) - 1
    a = d / 2
    if a == 0:
        return wp.vec3i(s, 0, 0)
    if a == 1:
        return wp.vec3i(0, s, 0)
    return wp.vec3i(0, 0, s)


@wp.func
def held_side(f: float) -> bool:
    return f >= ANCHOR_LEVEL


@wp.func
def free_side(f: float) -> bool:
    return f >= 0.0 and f < ANCHOR_LEVEL


@wp.func
def link_weight(f: float, fn: float) -> float:
    """A link's weight: (φk − φj)⁴. The held fraction changes by ½-⅔ across the edge (from ~0.5 at 45°)
    and hardly along it, so the weight keeps the links that cross the edge and all but drops those
    between nodes of a layer the edge runs through, whose fractions scatter about ½."""
    d = f - fn
    return d * d * d * d


@wp.func
def link_weights(grid_m: wp.array4d(dtype=float), grid_fix: wp.array4d(dtype=float), n: wp.vec3i, f: float,
                 held: bool, span_lo: wp.vec3i, span_hi: wp.vec3i, layer_lo: wp.vec3i) -> float:
    """The summed weights of node n's links (its neighbours across the anchor's edge; n's held
    fraction is f)."""
    total = float(0.0)
    for d in range(6):
        fn = held_fraction(grid_m, grid_fix, n + axis_step(d), span_lo, span_hi, layer_lo)
        if (held and free_side(fn)) or ((not held) and held_side(fn)):
            total += link_weight(f, fn)
    return total


@wp.kernel
def anchor_pin(
    ps: Particles,
    grid: GridInfo,
    grid_m: wp.array4d(dtype=float),
    grid_fix: wp.array4d(dtype=float),
    span_lo: wp.vec3i,
    span_hi: wp.vec3i,
    layer_lo: wp.vec3i,
):
    """An anchored particle none of whose stencil's nodes is held (an anchor thinner than about a
    cell: no node where anchored particles carry half the mass) pins its nearest node, which then
    moves at the anchor's velocity. The mark is the anchored mass's sign, set the same by every
    particle that sets it, and the test reads its magnitude: the result does not depend on order."""
    p = wp.tid()
    if (ps.flags[p] & FLAG_ANCHORED) == 0:
        return
    base = stencil_base(ps.x[p], grid)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                l = base + wp.vec3i(i, j, k) - layer_lo
                m = grid_m[0, l[0], l[1], l[2]]
                if m > 0.0 and wp.abs(grid_fix[0, l[0], l[1], l[2]]) >= ANCHOR_LEVEL * m:
                    return
    l = base + wp.vec3i(1, 1, 1) - layer_lo
    grid_fix[0, l[0], l[1], l[2]] = -wp.abs(grid_fix[0, l[0], l[1], l[2]])


@wp.kernel
def anchor_update(
    grid_m: wp.array4d(dtype=float),
    grid_mv: wp.array4d(dtype=wp.vec3),
    grid_v: wp.array4d(dtype=wp.vec3),
    grid_fix: wp.array4d(dtype=float),
    grid_fix_v: wp.array4d(dtype=wp.vec3),
    lo: wp.vec3i,
    span_lo: wp.vec3i,
    span_hi: wp.vec3i,
    layer_lo: wp.vec3i,
    run: int,
    k_end: int,
):
    """The anchored nodes' velocities, from the sums and free velocities grid_update left in layer 0.

    A node where the anchored particles carry at least ANCHOR_LEVEL (half) of the mass lies on the
    held side of the anchor's edge: for a straight edge with material on both sides that fraction is
    exactly ½ on the edge (the B-spline is symmetric), so the edge crosses every grid link between a
    held-side node k and a free-side node j, at δ = (φk − ½) / (φk − φj) of the link from k (φ the
    fraction; linear in between). A held-side node with no free-side neighbour moves at the anchor's
    velocity. On each link the two nodes' velocities relative to the anchor's, u, are projected (in
    the nodes' masses) onto δ uj + (1 − δ) uk = 0: their linear interpolant meets the anchor at the
    edge. δ → 0 holds k alone, δ → 1 holds j: the clamp follows the edge continuously as the grid
    slides past it, where holding whole nodes moved it by up to a cell. A node on several links takes
    their projections' mean weighted by (φk − φj)⁴ (``link_weight``); each link uses the nodes'
    masses times its share of their weights, so the result is still a contraction of the kinetic
    energy. Where the edge runs through a layer of nodes, the fractions there scatter about ½ and
    link neighbours within the layer; an unweighted mean let those links loosen the nodes held
    across the edge (the hanging bar's static stretch at that grid offset was 21 % long; weighted by
    φk − φj 11 %, by its square 5 %, by its 4th power 3.5 %, with links along the bar alone 3.4 %).
    Pinned nodes (anchor_pin) move at the anchor's velocity.

    What is left: one constraint per link takes the clamp from "hold k" (δ = 0) to "hold j, k free"
    (δ → 1), and the next cell starts from "hold j and k", so the clamp still steps where the edge
    crosses a node, by a fraction of a cell (in a 1-D model of the hanging bar the effective clamp
    lies 0.08 cell below the edge for δ = 0.2-0.6 and up to 0.2 cell above it as δ → 1), where it
    stepped by most of a cell before. No projection can avoid that step without taking energy out:
    a continuous family of constraints cannot go from one held node to two."""
    a, b, c = wp.tid()
    i = lo[0] + a
    j = lo[1] + b
    k0 = lo[2] + c * run
    for kk in range(k0, wp.min(k0 + run, k_end)):
        n = wp.vec3i(i, j, kk)
        l = n - layer_lo
        m = grid_m[0, l[0], l[1], l[2]]
        fm = grid_fix[0, l[0], l[1], l[2]]
        if m <= 0.0:
            continue
        f = held_fraction(grid_m, grid_fix, n, span_lo, span_hi, layer_lo)
        if f == -2.0:
            grid_v[0, i, j, kk] = grid_fix_v[0, l[0], l[1], l[2]] / wp.abs(fm)
            continue
        held = held_side(f)
        weights = link_weights(grid_m, grid_fix, n, f, held, span_lo, span_hi, layer_lo)
        if weights == 0.0:
            if held:
                grid_v[0, i, j, kk] = grid_fix_v[0, l[0], l[1], l[2]] / fm
            continue
        total = wp.vec3(0.0, 0.0, 0.0)
        for d in range(6):
            nb = n + axis_step(d)
            fn = held_fraction(grid_m, grid_fix, nb, span_lo, span_hi, layer_lo)
            if not ((held and free_side(fn)) or ((not held) and held_side(fn))):
                continue
            ln = nb - layer_lo
            w = link_weight(f, fn)
            if w <= 0.0:
                continue  # (φk − φj)⁴ underflowed: the link has no say
            nb_weights = link_weights(grid_m, grid_fix, nb, fn, not held, span_lo, span_hi, layer_lo)
            mn = grid_m[0, ln[0], ln[1], ln[2]]
            # k: the held-side node of the link, j: the free-side one; each takes the link's share
            # of its mass.
            fk = f
            fj = fn
            mk = m * w / weights
            mj = mn * w / nb_weights
            vk = grid_mv[0, l[0], l[1], l[2]]
            vj = grid_mv[0, ln[0], ln[1], ln[2]]
            va = wp.vec3(0.0, 0.0, 0.0)
            if held:
                va = grid_fix_v[0, l[0], l[1], l[2]] / fm
            else:
                fk = fn
                fj = f
                mk = mn * w / nb_weights
                mj = m * w / weights
                vk = grid_mv[0, ln[0], ln[1], ln[2]]
                vj = grid_mv[0, l[0], l[1], l[2]]
                va = grid_fix_v[0, ln[0], ln[1], ln[2]] / grid_fix[0, ln[0], ln[1], ln[2]]
            delta = (fk - ANCHOR_LEVEL) / (fk - fj)
            uk = vk - va
            uj = vj - va
            s = (delta * uj + (1.0 - delta) * uk) / (delta * delta / mj + (1.0 - delta) * (1.0 - delta) / mk)
            if held:
                total += (w / weights) * (va + uk - ((1.0 - delta) / mk) * s)
            else:
                total += (w / weights) * (va + uj - (delta / mj) * s)
        grid_v[0, i, j, kk] = total


@wp.kernel
def anchor_clear(
    grid_m: wp.array4d(dtype=float),
    grid_mv: wp.array4d(dtype=wp.vec3),
    grid_fix: wp.array4d(dtype=float),
    grid_fix_v: wp.array4d(dtype=wp.vec3),
    lo: wp.vec3i,
    layer_lo: wp.vec3i,
    run: int,
    k_end: int,
):
    """Empty layer 0 over the anchor's span after the anchor's passes, for the next substep's p2g."""
    a, b, c = wp.tid()
    k0 = lo[2] + c * run
    for kk in range(k0, wp.min(k0 + run, k_end)):
        l = wp.vec3i(lo[0] + a, lo[1] + b, kk) - layer_lo
        grid_m[0, l[0], l[1], l[2]] = 0.0
        grid_mv[0, l[0], l[1], l[2]] = wp.vec3(0.0, 0.0, 0.0)
        grid_fix[0, l[0], l[1], l[2]] = 0.0
        grid_fix_v[0, l[0], l[1], l[2]] = wp.vec3(0.0, 0.0, 0.0)


@wp.func
def rounding_left(Fp: wp.mat33, inc: wp.mat33, Ftrial: wp.mat33, Fstored: wp.mat33):
    """What the float32 sum Ftrial = Fp + inc rounded off (exactly, where Ftrial and Fp are within a factor
    of 2 of each other, as for any small increment), when the model stored Ftrial unchanged; else zero."""
    r = wp.mat33(0.0)
    same = True
    for i in range(3):
        for j in range(3):
            if Fstored[i, j] != Ftrial[i, j]:
                same = False
    if same:
        r = inc - (Ftrial - Fp)
    return r


@wp.kernel
def g2p(
    ps: Particles,
    materials: wp.array(dtype=MaterialParams),
    f_ext: wp.array(dtype=wp.vec3),
    grid_v: wp.array4d(dtype=wp.vec3),
    grid: GridInfo,
    dt_arr: wp.array(dtype=float),
    stats: wp.array(dtype=float),
    span_lo: wp.vec3i,
    span_hi: wp.vec3i,
    status: wp.array(dtype=int),
    offset: int,
    anchor_lo: wp.vec3i,
    anchor_hi: wp.vec3i,
):
    """Gather particles offset .. offset + launch dim; ``stats`` takes their reductions (a chunk's
    own row on the CPU, folded in by ``merge_stats``). Anchored particles also check the anchor's span
    (``track_anchored``)."""
    p = wp.tid() + offset
    dt = dt_arr[0]
    base = stencil_base(ps.x[p], grid)
    xp = (ps.x[p] - grid.origin) * grid.inv_dx
    fx = xp - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    wx = bspline_weights(fx, 0)
    wy = bspline_weights(fx, 1)
    wz = bspline_weights(fx, 2)
    fld = int(0)
    if grid_v.shape[0] > 1:
        fld = ps.field[p]

    new_v = wp.vec3(0.0, 0.0, 0.0)
    new_C = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = wx[i] * wy[j] * wz[k]
                dpos = wp.vec3(float(i), float(j), float(k)) - fx
                gv = grid_v[fld, base[0] + i, base[1] + j, base[2] + k]
                new_v += w * gv
                new_C += (4.0 * grid.inv_dx * w) * wp.outer(gv, dpos)

    fl = ps.flags[p]
    anchored = (fl & FLAG_ANCHORED) != 0
    if anchored and (fl & FLAG_RIGID) != 0:
        va = ps.anchor_v[p]
        ps.v[p] = va
        ps.C[p] = wp.mat33(0.0)
        ps.x[p] = ps.x[p] + dt * va
        xa = ps.x[p]
        track_position(xa, grid, span_lo, span_hi, stats, status)
        track_anchored(xa, grid, anchor_lo, anchor_hi, status)
        wp.atomic_max(stats, S_VMAX, wp.length(va))
        return
    mat = materials[ps.mat_id[p]]
    if mat.damping > 0.0:
        # Mass-proportional damping scales the whole local velocity field, so its gradient too: F
        # (updated from C) and the positions (from v) then describe the same strain, and a damped
        # static load settles at the undamped answer.
        decay = wp.exp(-mat.damping * dt)
        new_v = new_v * decay
        new_C = new_C * decay
    fp = f_ext[p]
    if not anchored and (fp[0] != 0.0 or fp[1] != 0.0 or fp[2] != 0.0):
        wp.atomic_add(stats, S_WORK, dt * wp.dot(fp, new_v))  # work done by the external forces
    ps.v[p] = new_v
    ps.C[p] = new_C
    if (fl & FLAG_RIGID) != 0:
        return  # rigid particles move with their body (rigid_apply)
    new_x = ps.x[p] + dt * new_v
    if anchored:
        # A held particle moves with its anchor but otherwise stays material: it takes the grid's
        # velocity and velocity gradient, so F and the stress follow the free material next to it
        # (a stress-free held layer made the clamp compliant), and it hands that velocity back to
        # the nodes it shares with free material instead of draining their momentum every substep.
        new_x = ps.x[p] + dt * ps.anchor_v[p]
    ps.x[p] = new_x
    # F + dt (C F), not (I + dt C) F: forming I + dt C in float32 rounds dt C (~1e-7 per substep at small
    # strain) to float32's step at 1 (1.2e-7), a bias that accumulated into a +10 % creep of an anchored
    # cantilever at 0.2 % sag over 6 periods (tests/test_sim_anchor.py); the same product, summed exactly.
    # The sum is also compensated (Kahan): F near I keeps about 1.2e-7 of resolution, and a slowly loaded
    # stiff beam changes F by less than that per substep, so the part rounded off is carried into the next
    # update (F_err) while the model stores the trial F as it is (an elastic step); a return mapping or a
    # reset that changes F drops it. Without it a slender damped cantilever at 1 % sag crept on past its
    # static deflection (1.12-1.15 of Euler-Bernoulli over 2-4 periods, issue 22).
    Fp = ps.F[p]
    inc = dt * (new_C * Fp) + ps.F_err[p]
    Ftrial = Fp + inc
    c2 = float(0.0)
    if mat.model == MODEL_FIXED_COROTATED:
        # The jelly directly: the small rule inlines here, where the whole dispatch (every model's SVD
        # route) is a call that copies its array arguments.
        c2 = barrier_corotated(mat, Ftrial, new_C, ps.rot[p], dt, p, ps.rot, ps.F, ps.tau)
    else:
        c2 = update_material(mat, Ftrial, new_C, ps.rot[p], ps.plastic[p], dt, p, ps.rot, ps.plastic, ps.F, ps.tau)
    ps.F_err[p] = rounding_left(Fp, inc, Ftrial, ps.F[p])

    # Reductions plan_step reads for the next step: max speed and stiffness (CFL), active box, NaN flag.
    speed = wp.length(new_v)
    if not (speed == speed) or not (c2 == c2):
        stats[S_NAN] = 1.0
    wp.atomic_max(stats, S_VMAX, speed)
    wp.atomic_max(stats, S_C2, c2)
    if not anchored:
        wp.atomic_add(stats, S_MV2, ps.mass[p] * wp.dot(new_v, new_v))
    track_position(new_x, grid, span_lo, span_hi, stats, status)
    if anchored:
        track_anchored(new_x, grid, anchor_lo, anchor_hi, status)


@wp.func
def reset_chunk_stats(rows: wp.array2d(dtype=float), r: int):
    rows[r, S_VMAX] = 0.0
    for a in range(3):
        rows[r, S_BOX_MIN + a] = 1.0e30
        rows[r, S_BOX_MAX + a] = -1.0e30
    rows[r, S_NAN] = 0.0
    rows[r, S_C2] = 0.0
    rows[r, S_MV2] = 0.0
    rows[r, S_WORK] = 0.0


@wp.kernel
def merge_stats(rows: wp.array2d(dtype=float), stats: wp.array(dtype=float)):
    """Fold the per-chunk reductions of a chunked g2p into ``stats`` in chunk order (maxima, box,
    NaN flag, sums), and reset the rows for the next substep."""
    for r in range(rows.shape[0]):
        stats[S_VMAX] = wp.max(stats[S_VMAX], rows[r, S_VMAX])
        for a in range(3):
            stats[S_BOX_MIN + a] = wp.min(stats[S_BOX_MIN + a], rows[r, S_BOX_MIN + a])
            stats[S_BOX_MAX + a] = wp.max(stats[S_BOX_MAX + a], rows[r, S_BOX_MAX + a])
        stats[S_NAN] = wp.max(stats[S_NAN], rows[r, S_NAN])
        stats[S_C2] = wp.max(stats[S_C2], rows[r, S_C2])
        stats[S_MV2] = stats[S_MV2] + rows[r, S_MV2]
        stats[S_WORK] = stats[S_WORK] + rows[r, S_WORK]
        reset_chunk_stats(rows, r)


@wp.kernel
def init_chunk_stats(rows: wp.array2d(dtype=float)):
    reset_chunk_stats(rows, wp.tid())


# ----------------------------------------------------------------------------------------------
# Rigid bodies: particles of a rigid object share one rigid motion
# ----------------------------------------------------------------------------------------------


@wp.kernel
def rigid_reduce(
    ps: Particles,
    f_ext: wp.array(dtype=wp.vec3),
    body: wp.array(dtype=int),
    centre: wp.array(dtype=wp.vec3),
    lin_vel: wp.array(dtype=wp.vec3),
    ang_vel: wp.array(dtype=wp.vec3),
    dt_arr: wp.array(dtype=float),
    d_momentum: wp.array(dtype=wp.vec3),
    d_ang_momentum: wp.array(dtype=wp.vec3),
    ext_momentum: wp.array(dtype=wp.vec3),
    ext_ang_momentum: wp.array(dtype=wp.vec3),
):
    """What this substep changed in each rigid body's linear and angular momentum (about its
    centre): the grid's exchange, m (v_grid − v_body), where v_body = V + ω × r is the velocity the
    body gave the particle (so a body alone in free flight gets exactly m g dt from the grid and no
    torque), plus the impulse of the external forces (applied here exactly, not through the grid),
    which is also summed on its own (the constant part integrated at the half step)."""
    p = wp.tid()
    b = body[p]
    if b < 0:
        return
    r = ps.x[p] - centre[b]
    v_body = lin_vel[b] + wp.cross(ang_vel[b], r)
    imp = dt_arr[0] * f_ext[p]
    dmv = ps.mass[p] * (ps.v[p] - v_body) + imp
    wp.atomic_add(d_momentum, b, dmv)
    wp.atomic_add(d_ang_momentum, b, wp.cross(r, dmv))
    wp.atomic_add(ext_momentum, b, imp)
    wp.atomic_add(ext_ang_momentum, b, wp.cross(r, imp))


@wp.func
def body_axes(q: wp.quat, axes0: wp.mat33) -> wp.mat33:
    """The body's principal axes in the world frame (columns), from its rotation q and the axes
    at rest."""
    return wp.quat_to_matrix(q) * axes0


@wp.func
def body_omega(A: wp.mat33, moments: wp.vec3, L: wp.vec3) -> wp.vec3:
    """ω = I(t)⁻¹ L with I(t) = A diag(moments) Aᵀ (A: the principal axes in the world frame)."""
    lb = wp.transpose(A) * L
    return A * wp.vec3(lb[0] / moments[0], lb[1] / moments[1], lb[2] / moments[2])


@wp.func
def body_iinv(A: wp.mat33, moments: wp.vec3) -> wp.mat33:
    return A * wp.diag(wp.vec3(1.0 / moments[0], 1.0 / moments[1], 1.0 / moments[2])) * wp.transpose(A)


@wp.kernel
def rigid_velocity(
    orient: wp.array(dtype=wp.quat),
    axes0: wp.array(dtype=wp.mat33),
    moments: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    d_momentum: wp.array(dtype=wp.vec3),
    d_ang_momentum: wp.array(dtype=wp.vec3),
    ang_momentum: wp.array(dtype=wp.vec3),
    lin_vel: wp.array(dtype=wp.vec3),
    ang_vel: wp.array(dtype=wp.vec3),
):
    """Each body's momenta take the substep's change: V += ΔP / M, L += ΔL (L is kept in the world
    frame); its spin is ω = I(t)⁻¹ L, with the inertia tensor turned with the body."""
    b = wp.tid()
    L = ang_momentum[b] + d_ang_momentum[b]
    ang_momentum[b] = L
    lin_vel[b] = lin_vel[b] + d_momentum[b] / body_mass[b]
    ang_vel[b] = body_omega(body_axes(orient[b], axes0[b]), moments[b], L)
    d_momentum[b] = wp.vec3(0.0, 0.0, 0.0)
    d_ang_momentum[b] = wp.vec3(0.0, 0.0, 0.0)


@wp.func
def body_impulse(V: wp.vec3, w: wp.vec3, Iinv: wp.mat33, inv_m: float, r: wp.vec3, d: wp.vec3,
                 target: float) -> float:
    """Impulse along unit d at offset r that brings the point velocity's d-component to ``target``."""
    vd = wp.dot(V + wp.cross(w, r), d)
    k = inv_m + wp.dot(wp.cross(Iinv * wp.cross(r, d), r), d)
    return (target - vd) / k


@wp.func
def plane_impulse(V: wp.vec3, w: wp.vec3, Iinv: wp.mat33, inv_m: float, r: wp.vec3, n: wp.vec3,
                  contact: int, mu: float) -> wp.vec3:
    """Impulse that stops a rigid body point moving into a plane of normal n (with friction)."""
    vp = V + wp.cross(w, r)
    vn = wp.dot(vp, n)
    if vn >= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    jn = body_impulse(V, w, Iinv, inv_m, r, n, 0.0)
    J = jn * n
    if contact != CONTACT_SLIP:
        vt = vp - vn * n
        vt_len = wp.length(vt)
        if vt_len > 1.0e-9:
            t = vt / vt_len
            jt = body_impulse(V, w, Iinv, inv_m, r, t, 0.0)  # impulse that stops the sliding
            if contact == CONTACT_FRICTION:
                jt = wp.max(jt, -mu * jn)  # Coulomb: |jt| <= μ jn (jt < 0, jn > 0)
            J = J + jt * t
    return J


@wp.kernel
def rigid_contacts(
    ps: Particles,
    body_start: wp.array(dtype=int),
    body_end: wp.array(dtype=int),
    centre: wp.array(dtype=wp.vec3),
    orient: wp.array(dtype=wp.quat),
    axes0: wp.array(dtype=wp.mat33),
    moments: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    lin_vel: wp.array(dtype=wp.vec3),
    ang_vel: wp.array(dtype=wp.vec3),
    ang_momentum: wp.array(dtype=wp.vec3),
    contact: wp.array(dtype=int),
    grid: GridInfo,
    bc: Boundary,
    iterations: int,
):
    """Rigid bodies against the ground and the walls (one thread per body; its particles are a
    contiguous range).

    The grid alone couples a rigid body to a boundary only through the layer of particles next to
    it, so its weight would push it slowly through the ground; contacts are therefore also
    resolved at the body level. Each iteration computes, from the same body velocity, the impulse
    every touching particle needs (normal, plus sticky / Coulomb friction as the boundary says)
    and applies their average (Jacobi): unlike sequential impulses this does not depend on the
    particles' order, so a body resting flat does not start to spin or creep.
    """
    b = wp.tid()
    Iinv = body_iinv(body_axes(orient[b], axes0[b]), moments[b])
    inv_m = 1.0 / body_mass[b]
    L = ang_momentum[b]
    touched = int(0)
    lo = grid.origin + float(bc.pad) * grid.dx * wp.vec3(1.0, 1.0, 1.0)
    hi = grid.origin + wp.vec3(float(grid.nx - bc.pad), float(grid.ny - bc.pad), float(grid.nz - bc.pad)) * grid.dx
    ground_y = grid.origin[1] + float(bc.ground_node) * grid.dx
    c = centre[b]
    for it in range(iterations):
        V = lin_vel[b]
        w = ang_vel[b]
        dV = wp.vec3(0.0, 0.0, 0.0)
        dw = wp.vec3(0.0, 0.0, 0.0)
        dL = wp.vec3(0.0, 0.0, 0.0)
        count = float(0.0)
        for p in range(body_start[b], body_end[b]):
            xp = ps.x[p]
            r = xp - c
            skin = 0.5 * wp.pow(ps.vol[p], 1.0 / 3.0)
            J = wp.vec3(0.0, 0.0, 0.0)
            if bc.has_ground != 0:
                if xp[1] - skin <= ground_y:
                    J += plane_impulse(V, w, Iinv, inv_m, r, wp.vec3(0.0, 1.0, 0.0), bc.ground_contact,
                                       bc.ground_friction)
            elif xp[1] - skin <= lo[1]:
                J += plane_impulse(V, w, Iinv, inv_m, r, wp.vec3(0.0, 1.0, 0.0), bc.wall_contact, bc.wall_friction)
            if xp[1] + skin >= hi[1]:
                J += plane_impulse(V, w, Iinv, inv_m, r, wp.vec3(0.0, -1.0, 0.0), bc.wall_contact, bc.wall_friction)
            if xp[0] - skin <= lo[0]:
                J += plane_impulse(V, w, Iinv, inv_m, r, wp.vec3(1.0, 0.0, 0.0), bc.wall_contact, bc.wall_friction)
            if xp[0] + skin >= hi[0]:
                J += plane_impulse(V, w, Iinv, inv_m, r, wp.vec3(-1.0, 0.0, 0.0), bc.wall_contact, bc.wall_friction)
            if xp[2] - skin <= lo[2]:
                J += plane_impulse(V, w, Iinv, inv_m, r, wp.vec3(0.0, 0.0, 1.0), bc.wall_contact, bc.wall_friction)
            if xp[2] + skin >= hi[2]:
                J += plane_impulse(V, w, Iinv, inv_m, r, wp.vec3(0.0, 0.0, -1.0), bc.wall_contact, bc.wall_friction)
            if wp.length(J) > 0.0:
                dV += inv_m * J
                dw += Iinv * wp.cross(r, J)
                dL += wp.cross(r, J)
                count += 1.0
        if count == 0.0:
            break
        touched = 1
        lin_vel[b] = V + dV / count
        ang_vel[b] = w + dw / count
        L = L + dL / count
    ang_momentum[b] = L
    contact[b] = touched


@wp.func
def turn_about(q: wp.quat, axis: wp.vec3, angle: float) -> wp.quat:
    """q turned by ``angle`` about the world axis ``axis`` (unit)."""
    if wp.abs(angle) > 0.0:
        return wp.quat_from_axis_angle(axis, angle) * q
    return q


@wp.kernel
def rigid_integrate(
    centre: wp.array(dtype=wp.vec3),
    orient: wp.array(dtype=wp.quat),
    axes0: wp.array(dtype=wp.mat33),
    moments: wp.array(dtype=wp.vec3),
    body_mass: wp.array(dtype=float),
    lin_vel: wp.array(dtype=wp.vec3),
    ang_vel: wp.array(dtype=wp.vec3),
    ang_momentum: wp.array(dtype=wp.vec3),
    ext_momentum: wp.array(dtype=wp.vec3),
    ext_ang_momentum: wp.array(dtype=wp.vec3),
    contact: wp.array(dtype=int),
    gravity: wp.vec3,
    dt_arr: wp.array(dtype=float),
):
    """Move each body over the substep, from the momenta at its end (V, L).

    Translation: a body that touched nothing moves by dt (V − ½ dt a), a the constant part of its
    acceleration (gravity and the external forces): exact for constant acceleration, where plain
    dt V overshoots by ½ a dt² per step. A body in contact moves by dt V (its impulses act at the
    step's start).

    Rotation: the free rigid body's exact flow for L constant, by splitting its kinetic energy
    H = Σ L_k² / (2 I_k) (principal moments I1 ≤ I2 ≤ I3, L_k = L · a_k on the principal axes a_k) as
    |L|² / (2 I2) + L1² (1/I1 − 1/I2) / 2 + L3² (1/I3 − 1/I2) / 2. Each part's flow is exact (a turn
    about the world axis L̂, or about the body axis a_1 or a_3, by a fixed angle), so L is kept
    exactly; the symmetric Strang composition a_1 (½) · a_3 (1) · a_1 (½), then L̂, is second order,
    symplectic (the energy error stays bounded, no drift) and exact for a symmetric top (the axial
    part vanishes: the precession comes out at the analytic rate). Under a torque the same uses
    L − ½ ΔL_ext, the momentum at the half step (exact for a constant torque about a principal axis).
    The spin the particles get is ω = I(t)⁻¹ L at the new orientation."""
    b = wp.tid()
    dt = dt_arr[0]
    V = lin_vel[b]
    L = ang_momentum[b]
    if contact[b] == 0:
        V = V - 0.5 * (dt * gravity + ext_momentum[b] / body_mass[b])
        L = L - 0.5 * ext_ang_momentum[b]
    centre[b] = centre[b] + dt * V
    I = moments[b]
    q = orient[b]
    c1 = 1.0 / I[0] - 1.0 / I[1]
    c3 = 1.0 / I[2] - 1.0 / I[1]
    A = body_axes(q, axes0[b])
    a1 = wp.vec3(A[0, 0], A[1, 0], A[2, 0])
    q = turn_about(q, a1, 0.5 * dt * c1 * wp.dot(L, a1))
    A = body_axes(q, axes0[b])
    a3 = wp.vec3(A[0, 2], A[1, 2], A[2, 2])
    q = turn_about(q, a3, dt * c3 * wp.dot(L, a3))
    A = body_axes(q, axes0[b])
    a1 = wp.vec3(A[0, 0], A[1, 0], A[2, 0])
    q = turn_about(q, a1, 0.5 * dt * c1 * wp.dot(L, a1))
    nL = wp.length(L)
    if nL > 0.0:
        q = turn_about(q, L / nL, dt * nL / I[1])
    q = wp.normalize(q)
    orient[b] = q
    ang_vel[b] = body_omega(body_axes(q, axes0[b]), I, ang_momentum[b])
    ext_momentum[b] = wp.vec3(0.0, 0.0, 0.0)
    ext_ang_momentum[b] = wp.vec3(0.0, 0.0, 0.0)
    contact[b] = 0


@wp.kernel
def rigid_apply(
    ps: Particles,
    body: wp.array(dtype=int),
    offset: wp.array(dtype=wp.vec3),
    centre: wp.array(dtype=wp.vec3),
    orient: wp.array(dtype=wp.quat),
    lin_vel: wp.array(dtype=wp.vec3),
    ang_vel: wp.array(dtype=wp.vec3),
    grid: GridInfo,
    stats: wp.array(dtype=float),
    span_lo: wp.vec3i,
    span_hi: wp.vec3i,
    status: wp.array(dtype=int),
):
    """Place rigid particles exactly: x = c + R r₀, v = V + ω × (x − c), C = [ω]×, F = R."""
    p = wp.tid()
    b = body[p]
    if b < 0:
        return
    R = wp.quat_to_matrix(orient[b])
    r = R * offset[p]
    new_x = centre[b] + r
    w = ang_vel[b]
    new_v = lin_vel[b] + wp.cross(w, r)
    ps.x[p] = new_x
    ps.v[p] = new_v
    ps.C[p] = wp.skew(w)
    ps.F[p] = R
    speed = wp.length(new_v)
    if not (speed == speed):
        stats[S_NAN] = 1.0
    wp.atomic_max(stats, S_VMAX, speed)
    track_position(new_x, grid, span_lo, span_hi, stats, status)


# ----------------------------------------------------------------------------------------------
# Torques: f_p = m_p (I⁻¹τ) × (x_p − c) over the region, so Σf = 0 and Σ r×f = τ exactly
# ----------------------------------------------------------------------------------------------


# Columns of the torque sums, one row per torque region.
T_MASS = wp.constant(0)  # Σ m
T_MOMENT = wp.constant(1)  # 1..3 Σ m x
T_SECOND_MOMENT = wp.constant(4)  # 4..12 Σ m x xᵀ, row-major
N_TORQUE_SUMS = 13


@wp.kernel
def torque_reduce(
    ps: Particles,
    torque_mask: wp.array(dtype=int),
    n_torques: int,
    sums: wp.array2d(dtype=float),
):
    """Per torque region: mass, first moment Σ m x and second moment Σ m x xᵀ (13 numbers)."""
    p = wp.tid()
    bits = torque_mask[p]
    if bits == 0:
        return
    m = ps.mass[p]
    xp = ps.x[p]
    for t in range(n_torques):
        if (bits >> t) & 1 != 0:
            wp.atomic_add(sums, t, T_MASS, m)
            for a in range(3):
                wp.atomic_add(sums, t, T_MOMENT + a, m * xp[a])
                for b in range(3):
                    wp.atomic_add(sums, t, T_SECOND_MOMENT + 3 * a + b, m * xp[a] * xp[b])


@wp.kernel
def apply_torques(
    ps: Particles,
    torque_mask: wp.array(dtype=int),
    n_torques: int,
    sums: wp.array2d(dtype=float),
    taus: wp.array(dtype=wp.vec3),
    f_static: wp.array(dtype=wp.vec3),
    f_out: wp.array(dtype=wp.vec3),
):
    p = wp.tid()
    f = f_static[p]
    bits = torque_mask[p]
    for t in range(n_torques):
        if (bits >> t) & 1 != 0:
            M = sums[t, T_MASS]
            c = wp.vec3(sums[t, T_MOMENT], sums[t, T_MOMENT + 1], sums[t, T_MOMENT + 2]) / M
            k = T_SECOND_MOMENT
            S = wp.mat33(sums[t, k], sums[t, k + 1], sums[t, k + 2], sums[t, k + 3], sums[t, k + 4], sums[t, k + 5],
                         sums[t, k + 6], sums[t, k + 7], sums[t, k + 8])
            # Second moment about the centre of mass, then the inertia tensor tr(S) I − S.
            Sc = S - M * wp.outer(c, c)
            inertia = (Sc[0, 0] + Sc[1, 1] + Sc[2, 2]) * wp.identity(n=3, dtype=float) - Sc
            alpha = wp.inverse(inertia) * taus[t]
            f = f + ps.mass[p] * wp.cross(alpha, ps.x[p] - c)
    f_out[p] = f


@wp.kernel
def zero_sums(sums: wp.array2d(dtype=float)):
    i, j = wp.tid()
    sums[i, j] = 0.0


# Each velocity field's spin, for the contact layer's transfer (p2g): sums over its elastic solids' particles
SPIN_MASS, SPIN_MOMENT, SPIN_MOMENTUM, SPIN_ANGULAR, SPIN_SECOND = 0, 1, 4, 7, 10
N_SPIN_SUMS = 19


@wp.kernel
def spin_reduce(ps: Particles, sums: wp.array2d(dtype=float), stride: int, n: int):
    """Per field, over every ``stride``-th particle of the elastic solids (FLAG_CONTACT_PIC): mass, Σ m x,
    Σ m v, Σ m x × v and Σ m x xᵀ (spin_solve). The stride keeps the atomic adds on these few addresses
    to about SPIN_SAMPLES particles' worth whatever the scene's size; the fill orders particles through
    the body, so a stride samples all of it."""
    p = wp.tid() * stride
    if p >= n:
        return
    if (ps.flags[p] & FLAG_CONTACT_PIC) == 0:
        return
    f = ps.field[p]
    m = ps.mass[p]
    xp = ps.x[p]
    vp = ps.v[p]
    L = wp.cross(xp, vp)
    wp.atomic_add(sums, f, SPIN_MASS, m)
    for a in range(3):
        wp.atomic_add(sums, f, SPIN_MOMENT + a, m * xp[a])
        wp.atomic_add(sums, f, SPIN_MOMENTUM + a, m * vp[a])
        wp.atomic_add(sums, f, SPIN_ANGULAR + a, m * L[a])
        for b in range(3):
            wp.atomic_add(sums, f, SPIN_SECOND + 3 * a + b, m * xp[a] * xp[b])


@wp.kernel
def spin_solve(sums: wp.array2d(dtype=float), spin: wp.array(dtype=wp.mat33)):
    """Each field's angular velocity ω = I⁻¹ L about its centre of mass, from spin_reduce's sums, as the
    velocity gradient of that rigid turn, [ω]× (what p2g gives the contact layer's particles for C:
    a rolling body keeps its spin there, the friction's velocity jump is not carried); clears the sums."""
    f = wp.tid()
    M = sums[f, SPIN_MASS]
    w = wp.vec3(0.0, 0.0, 0.0)
    if M > 0.0:
        c = wp.vec3(sums[f, SPIN_MOMENT], sums[f, SPIN_MOMENT + 1], sums[f, SPIN_MOMENT + 2]) / M
        P = wp.vec3(sums[f, SPIN_MOMENTUM], sums[f, SPIN_MOMENTUM + 1], sums[f, SPIN_MOMENTUM + 2])
        L = wp.vec3(sums[f, SPIN_ANGULAR], sums[f, SPIN_ANGULAR + 1], sums[f, SPIN_ANGULAR + 2]) - wp.cross(c, P)
        S = wp.mat33(sums[f, SPIN_SECOND], sums[f, SPIN_SECOND + 1], sums[f, SPIN_SECOND + 2],
                     sums[f, SPIN_SECOND + 3], sums[f, SPIN_SECOND + 4], sums[f, SPIN_SECOND + 5],
                     sums[f, SPIN_SECOND + 6], sums[f, SPIN_SECOND + 7], sums[f, SPIN_SECOND + 8]) - M * wp.outer(c, c)
        I = wp.trace(S) * wp.identity(n=3, dtype=float) - S
        if wp.determinant(I) > 0.0:
            w = wp.inverse(I) * L
    spin[f] = wp.mat33(0.0, -w[2], w[1], w[2], 0.0, -w[0], -w[1], w[0], 0.0)
    for k in range(N_SPIN_SUMS):
        sums[f, k] = 0.0
