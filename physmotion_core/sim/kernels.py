"""Warp kernels of the MLS-MPM solver (quadratic B-splines, APIC affine transfer).

The same kernels run on ``cpu`` and ``cuda``. One substep is:

  p2g         particles -> grid: mass, momentum, stress impulse, external forces
  grid_update grid velocities, gravity, ground and wall contact (sticky / slip / Coulomb friction)
  g2p         grid -> particles: velocity, affine matrix C, position, F = (I + dt C) F, plasticity

Grid kernels are launched over the particles' active box only (``lo`` offset + launch dims), and
``grid_update`` zeroes the mass/momentum it consumed, so the next ``p2g`` starts from a clean grid
without a separate clearing pass over the whole domain.

Materials are a table of structs indexed by each particle's material id; the constitutive model is
an integer switch so that new models (plasticity return mappings) extend ``kirchhoff_stress`` and
``project_plastic`` without touching the transfer code.
"""

from __future__ import annotations

import warp as wp

# Constitutive model ids (see materials.MODEL_IDS).
MODEL_FIXED_COROTATED = wp.constant(0)
MODEL_NEO_HOOKEAN = wp.constant(1)

# Contact ids.
CONTACT_STICKY = wp.constant(0)
CONTACT_SLIP = wp.constant(1)
CONTACT_FRICTION = wp.constant(2)


@wp.struct
class MaterialParams:
    model: int
    mu: float
    lam: float
    density: float


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


@wp.func
def extract_rotation(A: wp.mat33, q0: wp.quat) -> wp.quat:
    """Rotation part of A (the R maximising tr(RᵀA) over SO(3)), warm-started from q0.

    Müller et al. 2016, "A Robust Method to Extract the Rotational Part of Deformations": each
    iteration rotates the estimate about ω = Σ rᵢ×aᵢ / |Σ rᵢ·aᵢ|. F changes little per substep, so
    two iterations from the previous substep's rotation track it; this is ~3x cheaper than a 3x3
    SVD on CPU and, unlike the SVD's sign conventions, never flips between substeps. It converges
    to the same R as the signed polar decomposition R = U Vᵀ (U, V proper rotations).
    """
    q = q0
    for it in range(2):
        R = wp.quat_to_matrix(q)
        r0 = wp.vec3(R[0, 0], R[1, 0], R[2, 0])
        r1 = wp.vec3(R[0, 1], R[1, 1], R[2, 1])
        r2 = wp.vec3(R[0, 2], R[1, 2], R[2, 2])
        a0 = wp.vec3(A[0, 0], A[1, 0], A[2, 0])
        a1 = wp.vec3(A[0, 1], A[1, 1], A[2, 1])
        a2 = wp.vec3(A[0, 2], A[1, 2], A[2, 2])
        denom = wp.abs(wp.dot(r0, a0) + wp.dot(r1, a1) + wp.dot(r2, a2)) + 1.0e-9
        omega = (wp.cross(r0, a0) + wp.cross(r1, a1) + wp.cross(r2, a2)) * (1.0 / denom)
        w = wp.length(omega)
        if w > 1.0e-9:
            q = wp.normalize(wp.quat_from_axis_angle(omega / w, w) * q)
    return q


@wp.func
def kirchhoff_stress(mat: MaterialParams, F: wp.mat33, R: wp.mat33) -> wp.mat33:
    """Kirchhoff stress tau = P F^T for the particle's model (R: the rotation part of F)."""
    J = wp.determinant(F)
    I = wp.identity(n=3, dtype=float)
    if mat.model == MODEL_NEO_HOOKEAN:
        # tau = mu (F F^T - I) + lam log(J) I ; J is kept positive by the caller's safeguards.
        return mat.mu * (F * wp.transpose(F) - I) + mat.lam * wp.log(wp.max(J, 1.0e-6)) * I
    # fixed corotated: tau = 2 mu (F - R) F^T + lam (J - 1) J I
    return 2.0 * mat.mu * (F - R) * wp.transpose(F) + mat.lam * (J - 1.0) * J * I


@wp.func
def contact_velocity(v: wp.vec3, n: wp.vec3, contact: int, mu: float) -> wp.vec3:
    """Grid-node velocity after contact with a boundary of outward-facing normal n (pointing into the domain)."""
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
def bspline_weights(fx: wp.vec3, axis: int):
    f = fx[axis]
    return wp.vec3(0.5 * (1.5 - f) * (1.5 - f), 0.75 - (f - 1.0) * (f - 1.0), 0.5 * (f - 0.5) * (f - 0.5))


@wp.kernel
def p2g(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    rot: wp.array(dtype=wp.quat),
    mass: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mat_id: wp.array(dtype=int),
    materials: wp.array(dtype=MaterialParams),
    f_ext: wp.array(dtype=wp.vec3),
    grid: GridInfo,
    dt: float,
    grid_m: wp.array3d(dtype=float),
    grid_mv: wp.array3d(dtype=wp.vec3),
):
    p = wp.tid()
    mat = materials[mat_id[p]]
    xp = (x[p] - grid.origin) * grid.inv_dx
    base = wp.vec3i(int(xp[0] - 0.5), int(xp[1] - 0.5), int(xp[2] - 0.5))
    fx = xp - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    wx = bspline_weights(fx, 0)
    wy = bspline_weights(fx, 1)
    wz = bspline_weights(fx, 2)

    Fp = F[p]
    R = wp.identity(n=3, dtype=float)
    if mat.model == MODEL_FIXED_COROTATED:
        q = extract_rotation(Fp, rot[p])
        rot[p] = q
        R = wp.quat_to_matrix(q)
    tau = kirchhoff_stress(mat, Fp, R)
    m = mass[p]
    # MLS-MPM: the stress enters as an affine momentum term -dt * V * (4/dx^2) * tau.
    affine = (-dt * vol[p] * 4.0 * grid.inv_dx * grid.inv_dx) * tau + m * C[p]
    mv = m * v[p] + dt * f_ext[p]

    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = wx[i] * wy[j] * wz[k]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * grid.dx
                ix = base[0] + i
                iy = base[1] + j
                iz = base[2] + k
                wp.atomic_add(grid_m, ix, iy, iz, w * m)
                wp.atomic_add(grid_mv, ix, iy, iz, w * (mv + affine * dpos))


@wp.kernel
def grid_update(
    grid_m: wp.array3d(dtype=float),
    grid_mv: wp.array3d(dtype=wp.vec3),
    grid_v: wp.array3d(dtype=wp.vec3),
    lo: wp.vec3i,
    grid: GridInfo,
    bc: Boundary,
    gravity: wp.vec3,
    dt: float,
):
    a, b, c = wp.tid()
    i = lo[0] + a
    j = lo[1] + b
    k = lo[2] + c
    m = grid_m[i, j, k]
    v = wp.vec3(0.0, 0.0, 0.0)
    if m > 0.0:
        v = grid_mv[i, j, k] / m + dt * gravity
        # Domain walls (x, z sides and the top; the bottom too when there is no ground).
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
        if bc.has_ground != 0:
            if j <= bc.ground_node:
                v = contact_velocity(v, wp.vec3(0.0, 1.0, 0.0), bc.ground_contact, bc.ground_friction)
        elif j < bc.pad:
            v = contact_velocity(v, wp.vec3(0.0, 1.0, 0.0), bc.wall_contact, bc.wall_friction)
    grid_v[i, j, k] = v
    # Leave the accumulators clean for the next substep's p2g.
    grid_m[i, j, k] = 0.0
    grid_mv[i, j, k] = wp.vec3(0.0, 0.0, 0.0)


@wp.kernel
def g2p(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    grid_v: wp.array3d(dtype=wp.vec3),
    grid: GridInfo,
    dt: float,
    stats: wp.array(dtype=float),
):
    p = wp.tid()
    xp = (x[p] - grid.origin) * grid.inv_dx
    base = wp.vec3i(int(xp[0] - 0.5), int(xp[1] - 0.5), int(xp[2] - 0.5))
    fx = xp - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    wx = bspline_weights(fx, 0)
    wy = bspline_weights(fx, 1)
    wz = bspline_weights(fx, 2)

    new_v = wp.vec3(0.0, 0.0, 0.0)
    new_C = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = wx[i] * wy[j] * wz[k]
                dpos = wp.vec3(float(i), float(j), float(k)) - fx
                gv = grid_v[base[0] + i, base[1] + j, base[2] + k]
                new_v += w * gv
                new_C += (4.0 * grid.inv_dx * w) * wp.outer(gv, dpos)

    v[p] = new_v
    C[p] = new_C
    new_x = x[p] + dt * new_v
    x[p] = new_x
    F[p] = (wp.identity(n=3, dtype=float) + dt * new_C) * F[p]

    # Reductions the host reads each substep: max speed (CFL), active box, and a NaN flag.
    speed = wp.length(new_v)
    if not (speed == speed) or not (new_x[0] == new_x[0]):
        stats[7] = 1.0
    wp.atomic_max(stats, 0, speed)
    wp.atomic_min(stats, 1, new_x[0])
    wp.atomic_min(stats, 2, new_x[1])
    wp.atomic_min(stats, 3, new_x[2])
    wp.atomic_max(stats, 4, new_x[0])
    wp.atomic_max(stats, 5, new_x[1])
    wp.atomic_max(stats, 6, new_x[2])


@wp.kernel
def reset_stats(stats: wp.array(dtype=float)):
    """Reset the reduction slots g2p fills: max speed, box min, box max, NaN flag."""
    stats[0] = 0.0
    for a in range(3):
        stats[1 + a] = 1.0e30
        stats[4 + a] = -1.0e30
    stats[7] = 0.0
