"""The materials' constitutive rules and return mappings, as Warp functions.

A material is a row of the ``MaterialParams`` table; its ``model`` picks one rule below, and
``update_material`` (called by g2p for every deformable particle each substep) only dispatches to
it. Every rule takes the trial deformation gradient F = (I + dt C) Fⁿ, writes the projected
(elastic) F, the Kirchhoff stress τ for the next p2g and its state, and returns the squared wave
speed the CFL step must respect:

  model             rule                        return mapping (plasticity)
  fixed_corotated   barrier_corotated (jelly)   none; the volume stops at MIN_J
  neo_hookean       neo_hookean (rubber)        none; the volume stops at MIN_J
  von_mises         Hencky StVK                 von Mises radial return, linear hardening (metal)
  plasticine        Hencky StVK                 von Mises, linear softening (plasticine, clay)
  viscoplastic      Hencky StVK                 von Mises with a Perzyna rate (honey, toothpaste;
                                                relaxation time η/μ: Bingham viscosity η)
  drucker_prager    Hencky StVK                 Drucker-Prager cone with cohesion (sand)
  snow              corotated, hardened         clamped principal stretches (Stomakhin et al. 2013)
  fracture          corotated                   tears past a principal stretch (bread, cookie)
  fluid             Tait pressure + viscosity   F kept isotropic (water)
  rigid             none (rigid_* kernels)      none

The Hencky models take a series route without an SVD while the strain is small
(``hencky_small_strain``) and the SVD route otherwise (``hencky_svd``); snow and fracture likewise
use Newton's polar iteration while no stretch can reach their limits.
"""

from __future__ import annotations

import warp as wp

from ..types.material import CONSTITUTIVE_MODELS

# The simulation is never differentiated: no adjoint code (halves the CUDA build; the forward code
# and its results are unchanged).
wp.set_module_options({"enable_backward": False})

# Constitutive model ids: each model's place in types.material.CONSTITUTIVE_MODELS, the one list of them
# (types.material.model_id gives a name's id; a model added there must be added here too, or this fails).
(MODEL_FIXED_COROTATED, MODEL_NEO_HOOKEAN, MODEL_VON_MISES, MODEL_DRUCKER_PRAGER, MODEL_SNOW, MODEL_PLASTICINE,
 MODEL_FRACTURE, MODEL_VISCOPLASTIC, MODEL_FLUID, MODEL_RIGID) = (wp.constant(i) for i in range(len(CONSTITUTIVE_MODELS)))


@wp.struct
class MaterialParams:
    model: int
    mu: float
    lam: float
    density: float
    yield_stress: float
    hardening: float  # Pa of yield stress gained per unit equivalent plastic strain
    softening: float  # Pa of yield stress lost per unit equivalent plastic strain
    dp_alpha: float  # Drucker-Prager cone slope sqrt(2/3) 2 sin(phi) / (3 - sin(phi))
    cohesion_tr: float  # Drucker-Prager: volumetric Hencky strain the cohesion allows in tension
    viscosity: float
    bulk: float
    gamma: float
    theta_c: float
    theta_s: float
    xi: float
    fracture_stretch: float
    damping: float


# Volume limits (J = det F) every model shares. Below MIN_J (a body crushed to 5 % of its volume by
# a hit no grid resolves, far past any material's validity) stresses and wave speeds stop growing,
# so such a particle costs bounded substeps instead of stalling the run (docs/stability.md); fluid,
# torn material and snow's plastic volume are also kept below MAX_J.
MIN_J = wp.constant(0.05)
MAX_J = wp.constant(20.0)
MIN_STRETCH = wp.constant(1.0e-4)  # principal stretches below this count as this (log of 0 is -inf)
TINY = wp.constant(1.0e-12)  # norms below this are zero (no direction to project along)


# ----------------------------------------------------------------------------------------------
# Building blocks: rotations, stresses, matrix logarithm and exponential
# ----------------------------------------------------------------------------------------------


# The tracked rotation of the corotated models (track_rotation): the corrections a substep accepts after one
# step, and the accuracy and the cap of the full iteration a poor warm start falls back to.
ROT_ONE_STEP = wp.constant(1.0e-3)  # rad: a correction this small leaves ~strain x it, far below float32's stress noise
ROT_CONVERGED = wp.constant(1.0e-6)  # rad: the full iteration stops at a correction this small
ROT_MAX_ITERATIONS = wp.constant(40)


@wp.func
def svd(F: wp.mat33):
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, sig, V)
    return U, sig, V


@wp.func
def nearest_rotation(F: wp.mat33) -> wp.mat33:
    """The rotation nearest F (its polar factor; for an inverted F, the proper rotation with the axis of the
    smallest singular value flipped). Only for the rare crushed particle: it costs an SVD."""
    U, sig, V = svd(F)
    R = U * wp.transpose(V)
    if wp.determinant(R) < 0.0:
        R = U * wp.diag(wp.vec3(1.0, 1.0, -1.0)) * wp.transpose(V)
    return R


@wp.func
def rotation_torque(q: wp.quat, A: wp.mat33):
    """Σ rᵢ×aᵢ and Σ rᵢ·aᵢ over the columns of R(q) and A: the axial vector of the skew part of Rᵀ A
    (in world axes; zero at the rotation part of A) and its trace."""
    R = wp.quat_to_matrix(q)
    r0 = wp.vec3(R[0, 0], R[1, 0], R[2, 0])
    r1 = wp.vec3(R[0, 1], R[1, 1], R[2, 1])
    r2 = wp.vec3(R[0, 2], R[1, 2], R[2, 2])
    a0 = wp.vec3(A[0, 0], A[1, 0], A[2, 0])
    a1 = wp.vec3(A[0, 1], A[1, 1], A[2, 1])
    a2 = wp.vec3(A[0, 2], A[1, 2], A[2, 2])
    return wp.cross(r0, a0) + wp.cross(r1, a1) + wp.cross(r2, a2), wp.dot(r0, a0) + wp.dot(r1, a1) + wp.dot(r2, a2)


@wp.func
def turn_small(q: wp.quat, omega: wp.vec3) -> wp.quat:
    """q turned by the small rotation vector omega, without trigonometry: the unit quaternion along
    (ω/2, 1) turns by 2 atan(|ω|/2) = |ω| (1 − |ω|²/12 + ...) about ω, exact to third order."""
    return wp.normalize(wp.quat(0.5 * omega[0], 0.5 * omega[1], 0.5 * omega[2], 1.0) * q)


@wp.func
def extract_rotation(A: wp.mat33, q0: wp.quat) -> wp.quat:
    """Rotation part of A (the R maximising tr(RᵀA) over SO(3)), iterated to convergence from q0.

    Müller et al. 2016, "A Robust Method to Extract the Rotational Part of Deformations": each
    iteration rotates the estimate about ω = Σ rᵢ×aᵢ / |Σ rᵢ·aᵢ|. About the rotation part R* of
    A = R* S, an error about principal axis k of S shrinks by σ_k / tr S per iteration (a third for
    S near I): slow but safe from any start, so it is the fallback of ``track_rotation`` (a cold or
    poor warm start). It converges to the signed polar factor R = U Vᵀ (U, V proper rotations),
    slowly from a start near half a turn away (the torque vanishes there too): if ROT_MAX_ITERATIONS
    do not converge (about one cold start in 4000 at random), the SVD gives the rotation.
    """
    q = q0
    converged = bool(False)
    for it in range(ROT_MAX_ITERATIONS):
        torque, tr = rotation_torque(q, A)
        omega = torque * (1.0 / (wp.abs(tr) + 1.0e-9))
        w = wp.length(omega)
        if w > 1.0e-9:
            q = wp.normalize(wp.quat_from_axis_angle(omega / w, w) * q)
        if w < ROT_CONVERGED:
            converged = True
            break
    if not converged:
        q = wp.quat_from_matrix(nearest_rotation(A))
    return q


@wp.func
def track_rotation(A: wp.mat33, q_pred: wp.quat) -> wp.quat:
    """Rotation part of A by one Newton step from a close estimate q_pred (the previous substep's
    rotation turned by the particle's spin), with the full iteration as fallback.

    About the rotation part R* of A = R* S (S = diag σ in its axes), the torque Σ rᵢ×aᵢ of an
    estimate off by a small rotation e is −(σ_i + σ_j) e_k about each principal axis k (i, j the
    other two), and Σ rᵢ·aᵢ ≈ tr S. Newton's step divides the torque by σ_i + σ_j; dividing it by
    ⅔ tr S instead (exact for S = σ I) leaves an error of (1 − 3(σ_i + σ_j) / 2 tr S) e_k, of the
    order of the strain times e (a strain of 5 % and a warm start 1e-3 rad off leave ~5e-5 rad),
    and still shrinks any error (the factor lies in (−½, 1)). When the correction is larger than
    ROT_ONE_STEP (the first substep, a hit that turned the particle against its spin) the estimate
    was poor and ``extract_rotation`` iterates to convergence from it.
    """
    torque, tr = rotation_torque(q_pred, A)
    omega = torque * (1.5 / (wp.abs(tr) + 1.0e-9))
    if wp.dot(omega, omega) > ROT_ONE_STEP * ROT_ONE_STEP:
        return extract_rotation(A, q_pred)
    return turn_small(q_pred, omega)


@wp.func
def corotated_stress(F: wp.mat33, R: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """Fixed-corotated Kirchhoff stress 2μ(F − R)Fᵀ + λ(J − 1)J I, symmetrised.

    With the exact polar rotation the stress is symmetric; an R that is off by ε (a tracked
    rotation lagging a spinning body) adds a skew part 2μ·O(ε) that is as large as the elastic
    stress itself at small strains and brakes the spin (angular momentum is lost every step).
    Keeping the symmetric part conserves angular momentum exactly; what remains of the error is
    O(ε · strain).
    """
    J = wp.determinant(F)
    T = 2.0 * mu * (F - R) * wp.transpose(F)
    return 0.5 * (T + wp.transpose(T)) + lam * (J - 1.0) * J * wp.identity(n=3, dtype=float)


@wp.func
def barrier_corotated_stress(F: wp.mat33, R: wp.mat33, J: float, mu: float, lam: float) -> wp.mat33:
    """Fixed-corotated stress with a volumetric term that resists collapse (MODEL_FIXED_COROTATED).

    The plain energy μ Σ(σᵢ − 1)² + λ/2 (J − 1)² stays finite as J → 0 and its Kirchhoff stress
    2μ(F − R)Fᵀ + λ(J − 1)J I vanishes there: a body crushed flat by a hard impact feels no force
    pushing it back and stays a sheet. Under compression (J < 1) the volumetric energy is instead
    λ/2 (log J)², whose Kirchhoff pressure λ log J grows without bound as J → 0 (it matches the
    former term to second order at J = 1: same small-strain stiffness, C² join). Below J = 0.05
    the pressure stops growing (as for neo-Hookean) so the step stays bounded; an inverted F
    (J ≤ 0) gets that full pressure and is pushed back. ``J`` is det F (the caller has it).
    """
    T = 2.0 * mu * (F - R) * wp.transpose(F)
    p = lam * (J - 1.0) * J
    if J < 1.0:
        p = lam * wp.log(wp.max(J, MIN_J))
    return 0.5 * (T + wp.transpose(T)) + p * wp.identity(n=3, dtype=float)


@wp.func
def hencky_stress(U: wp.mat33, eps: wp.vec3, mu: float, lam: float) -> wp.mat33:
    """StVK-Hencky Kirchhoff stress U diag(2μ ε + λ tr(ε)) Uᵀ from the log principal stretches ε."""
    tr = eps[0] + eps[1] + eps[2]
    s = 2.0 * mu * eps + lam * tr * wp.vec3(1.0, 1.0, 1.0)
    return U * wp.diag(s) * wp.transpose(U)


@wp.func
def log_stretches(sig: wp.vec3) -> wp.vec3:
    # Inverted or collapsed elements: plasticity treats them as strongly compressed, never NaN.
    return wp.vec3(wp.log(wp.max(wp.abs(sig[0]), MIN_STRETCH)), wp.log(wp.max(wp.abs(sig[1]), MIN_STRETCH)),
                   wp.log(wp.max(wp.abs(sig[2]), MIN_STRETCH)))


@wp.func
def log_series(X: wp.mat33) -> wp.mat33:
    """log(I + X) for a symmetric X with |X| < LOG_SERIES_MAX, by its Taylor series to X⁸ (Horner).
    Truncation error below |X|⁹ / (9 (1 - |X|)) < 2e-10: under float32 round-off."""
    I = wp.identity(n=3, dtype=float)
    P = I * (1.0 / 8.0)
    P = I * (1.0 / 7.0) - X * P
    P = I * (1.0 / 6.0) - X * P
    P = I * (1.0 / 5.0) - X * P
    P = I * (1.0 / 4.0) - X * P
    P = I * (1.0 / 3.0) - X * P
    P = I * 0.5 - X * P
    P = I - X * P
    return X * P


@wp.func
def exp_series(A: wp.mat33) -> wp.mat33:
    """exp(A) for a small symmetric A (a plastic correction of a strain under ~5 %, plus the sand's
    cohesion strain), to A⁶ (Horner): truncation error below |A|⁷ / 5040 (< 3e-9 for |A| < 0.2)."""
    I = wp.identity(n=3, dtype=float)
    P = I + A * (1.0 / 6.0)
    P = I + (A * P) * (1.0 / 5.0)
    P = I + (A * P) * (1.0 / 4.0)
    P = I + (A * P) * (1.0 / 3.0)
    P = I + (A * P) * 0.5
    return I + A * P


@wp.func
def polar_newton(F: wp.mat33) -> wp.mat33:
    """The rotation R of F = R S (det F > 0) by Newton's iteration X ← (X + X⁻ᵀ) / 2 from X = F
    (Higham 1986): each singular value goes σ ← (σ + 1/σ) / 2, so the error about squares each
    step. Used for stretches within [0.75, 1.2], where four steps reach float32 round-off; five
    are taken."""
    X = F
    for it in range(5):
        X = 0.5 * (X + wp.transpose(wp.inverse(X)))
    return X


@wp.func
def exp_vec(e: wp.vec3) -> wp.vec3:
    return wp.vec3(wp.exp(e[0]), wp.exp(e[1]), wp.exp(e[2]))


@wp.func
def wave_speed_sq(mu: float, lam: float, density: float, J: float) -> float:
    # The P-wave speed, stiffened under compression (density rises as 1/J).
    return (lam + 2.0 * mu) / density * wp.max(1.0, 1.0 / wp.max(J, MIN_J))


# ----------------------------------------------------------------------------------------------
# Elastic models
# ----------------------------------------------------------------------------------------------


@wp.func
def barrier_corotated(mat: MaterialParams, F: wp.mat33, Cp: wp.mat33, q_in: wp.quat, dt: float, p: int,
                      rot: wp.array(dtype=wp.quat), Fout: wp.array(dtype=wp.mat33),
                      tau: wp.array(dtype=wp.mat33)) -> float:
    """Fixed-corotated elasticity with the volumetric barrier (jelly). The rotation of F is tracked
    (``rot``): predicted with this substep's spin (the skew part of C), then refined."""
    spin = wp.vec3(Cp[2, 1] - Cp[1, 2], Cp[0, 2] - Cp[2, 0], Cp[1, 0] - Cp[0, 1]) * (0.5 * dt)
    q = track_rotation(F, turn_small(q_in, spin))
    rot[p] = q
    R = wp.quat_to_matrix(q)
    J = wp.determinant(F)
    # Under compression the bulk stiffness J dτ/dJ = λ grows relative to the density ρ₀/J, hence
    # the extra factor 1/J on the wave speed².
    if J < MIN_J:
        # Crushed past MIN_J of its volume (or inverted) by a hit no mesh resolves: the particle
        # keeps its rotation and MIN_J of its volume, isotropically (energy can only be lost),
        # and the barrier's pressure pushes it back out (docs/materials.md).
        Fe = wp.pow(MIN_J, 1.0 / 3.0) * R
        Fout[p] = Fe
        tau[p] = barrier_corotated_stress(Fe, R, wp.determinant(Fe), mat.mu, mat.lam)
        return wave_speed_sq(mat.mu, mat.lam, mat.density, MIN_J) * wp.max(1.0, 1.0 / MIN_J)
    # Two returns rather than a clamped J: with J clamped by a branch, the CPU compiler folds the
    # NaN of a corrupted F into the wave speed, where the single-function form never did (a NaN F
    # must be reported the substep its velocities turn NaN, tests/test_sim.py).
    Fout[p] = F
    tau[p] = barrier_corotated_stress(F, R, J, mat.mu, mat.lam)
    # wave_speed_sq(..., J) * max(1, 1/J) with J ≥ MIN_J here: one division for both factors (and a NaN J
    # still gives a NaN wave speed: max(1, NaN) is NaN).
    stiff = wp.max(1.0, 1.0 / J)
    return (mat.lam + 2.0 * mat.mu) / mat.density * stiff * stiff


@wp.func
def neo_hookean(mat: MaterialParams, F: wp.mat33, p: int, Fout: wp.array(dtype=wp.mat33),
                tau: wp.array(dtype=wp.mat33)) -> float:
    """Neo-Hookean elasticity (rubber): τ = μ (F Fᵀ − I) + λ log J I. The stress (and wave speed,
    ~1/J) grows without bound as J → 0. A particle crushed past MIN_J of its volume, or inverted, by a
    hit no grid resolves keeps its rotation and MIN_J of its volume, isotropically (as the jelly's
    barrier does: energy can only be lost), and the pressure λ log MIN_J pushes it back out; the
    stress and wave speed stay bounded, so a Mach-10 impact costs bounded substeps (docs/stability.md)."""
    I = wp.identity(n=3, dtype=float)
    J = wp.determinant(F)
    if J < MIN_J:
        Fe = wp.pow(MIN_J, 1.0 / 3.0) * nearest_rotation(F)
        Fout[p] = Fe
        tau[p] = mat.mu * (Fe * wp.transpose(Fe) - I) + mat.lam * wp.log(MIN_J) * I
        return wave_speed_sq(mat.mu, mat.lam, mat.density, MIN_J) * wp.max(1.0, 1.0 / MIN_J)
    Fout[p] = F
    tau[p] = mat.mu * (F * wp.transpose(F) - I) + mat.lam * wp.log(J) * I
    return wave_speed_sq(mat.mu, mat.lam, mat.density, J) * wp.max(1.0, 1.0 / J)


@wp.func
def rigid(F: wp.mat33, p: int, Fout: wp.array(dtype=wp.mat33), tau: wp.array(dtype=wp.mat33)) -> float:
    """No stress: a rigid body's particles move with its rigid motion (rigid_apply)."""
    Fout[p] = F
    tau[p] = wp.mat33(0.0)
    return 0.0


@wp.func
def weakly_compressible_fluid(mat: MaterialParams, F: wp.mat33, Cp: wp.mat33, p: int,
                              Fout: wp.array(dtype=wp.mat33), tau: wp.array(dtype=wp.mat33)) -> float:
    """Tait equation of state, no tension (a free surface separates instead of pulling), plus a
    Newtonian viscous stress from the strain rate. Only the volume matters: F is kept isotropic
    so no shear accumulates."""
    I = wp.identity(n=3, dtype=float)
    J = wp.clamp(wp.determinant(F), MIN_J, MAX_J)
    Fout[p] = wp.pow(J, 1.0 / 3.0) * I
    pressure = wp.max(mat.bulk * (wp.pow(J, -mat.gamma) - 1.0), 0.0)
    D = Cp + wp.transpose(Cp)
    tr = D[0, 0] + D[1, 1] + D[2, 2]
    tau[p] = -pressure * J * I + mat.viscosity * J * (D - (tr / 3.0) * I)
    return mat.bulk * mat.gamma * wp.pow(J, 1.0 - mat.gamma) / mat.density


# ----------------------------------------------------------------------------------------------
# Fracture and snow: corotated elasticity with a limit on the principal stretches
# ----------------------------------------------------------------------------------------------


# Fracture: the state of a torn particle (plastic = 1), and the range where the polar rotation
# comes from Newton's iteration (J above this, fracture stretch below that) instead of an SVD.
FRACTURE_TORN = wp.constant(1.0)
FRACTURE_TORN_ABOVE = wp.constant(0.5)
NEWTON_MIN_J = wp.constant(0.5)
NEWTON_MAX_STRETCH = wp.constant(1.2)


@wp.func
def fracture(mat: MaterialParams, F: wp.mat33, state_in: float, p: int, plastic: wp.array(dtype=float),
             Fout: wp.array(dtype=wp.mat33), tau: wp.array(dtype=wp.mat33)) -> float:
    """Corotated elasticity that tears (state FRACTURE_TORN) once a principal stretch passes
    ``fracture_stretch``; torn material keeps only its resistance to compression."""
    I = wp.identity(n=3, dtype=float)
    J = wp.determinant(F)
    if state_in > FRACTURE_TORN_ABOVE:
        # Torn: no tension or shear, only resistance to compression. F is kept isotropic so
        # the splats of torn material stay round.
        Jc = wp.clamp(J, MIN_J, MAX_J)
        Fout[p] = wp.pow(Jc, 1.0 / 3.0) * I
        t = wp.mat33(0.0)
        if Jc < 1.0:
            t = mat.lam * (Jc - 1.0) * Jc * I
        tau[p] = t
        return wave_speed_sq(0.0, mat.lam, mat.density, Jc)
    # No principal stretch can pass the threshold while |FᵀF - I| stays below fs² - 1 (σ_max² - 1
    # is an eigenvalue of FᵀF - I): then the polar rotation comes from Newton's iteration, with
    # no SVD.
    Cm = wp.transpose(F) * F - I
    fs = mat.fracture_stretch
    if J > NEWTON_MIN_J and fs < NEWTON_MAX_STRETCH and wp.ddot(Cm, Cm) < (fs * fs - 1.0) * (fs * fs - 1.0):
        Fout[p] = F
        tau[p] = corotated_stress(F, polar_newton(F), mat.mu, mat.lam)
        return wave_speed_sq(mat.mu, mat.lam, mat.density, J)
    U, sig, V = svd(F)
    if sig[0] > mat.fracture_stretch:
        plastic[p] = FRACTURE_TORN
    Fout[p] = F
    tau[p] = corotated_stress(F, U * wp.transpose(V), mat.mu, mat.lam)
    return wave_speed_sq(mat.mu, mat.lam, mat.density, J)


# Snow (Stomakhin et al. 2013): the hardening exponent ξ (1 - J_p) is capped so exp() stays finite.
SNOW_MAX_HARDENING_EXPONENT = wp.constant(10.0)


@wp.func
def snow_hardening(mat: MaterialParams, Jp: float) -> float:
    """Stomakhin et al. 2013: the plastic volume change J_p hardens the material by exp(ξ (1 - J_p))."""
    return wp.exp(wp.min(mat.xi * (1.0 - Jp), SNOW_MAX_HARDENING_EXPONENT))


@wp.func
def snow(mat: MaterialParams, F: wp.mat33, state_in: float, p: int, plastic: wp.array(dtype=float),
         Fout: wp.array(dtype=wp.mat33), tau: wp.array(dtype=wp.mat33)) -> float:
    """Stomakhin et al. 2013: principal stretches beyond [1 - θc, 1 + θs] become plastic (state:
    the plastic volume change J_p), and J_p hardens the corotated elasticity."""
    # While no principal stretch can leave [1 - θc, 1 + θs] (σ² - 1 is an eigenvalue of FᵀF - I,
    # bounded by its norm), nothing is clamped: F stays elastic, J_p is unchanged, and the
    # corotated stress needs only the polar rotation (Newton's iteration), no SVD.
    I = wp.identity(n=3, dtype=float)
    Cs = wp.transpose(F) * F - I
    r_el = wp.min((1.0 + mat.theta_s) * (1.0 + mat.theta_s) - 1.0, 1.0 - (1.0 - mat.theta_c) * (1.0 - mat.theta_c))
    J = wp.determinant(F)
    if J > 0.0 and wp.ddot(Cs, Cs) < r_el * r_el:
        hs = snow_hardening(mat, state_in)
        Fout[p] = F
        tau[p] = corotated_stress(F, polar_newton(F), mat.mu * hs, mat.lam * hs)
        return wave_speed_sq(mat.mu * hs, mat.lam * hs, mat.density, J)
    U, sig, V = svd(F)
    lo = 1.0 - mat.theta_c
    hi = 1.0 + mat.theta_s
    sc = wp.vec3(wp.clamp(sig[0], lo, hi), wp.clamp(sig[1], lo, hi), wp.clamp(sig[2], lo, hi))
    Jp = state_in * (sig[0] * sig[1] * sig[2]) / (sc[0] * sc[1] * sc[2])
    Jp = wp.clamp(Jp, MIN_J, MAX_J)
    plastic[p] = Jp
    Fe = U * wp.diag(sc) * wp.transpose(V)
    h = snow_hardening(mat, Jp)
    Fout[p] = Fe
    tau[p] = corotated_stress(Fe, U * wp.transpose(V), mat.mu * h, mat.lam * h)
    return wave_speed_sq(mat.mu * h, mat.lam * h, mat.density, sc[0] * sc[1] * sc[2])


# ----------------------------------------------------------------------------------------------
# Plasticity on the Hencky strain: the von Mises family and Drucker-Prager sand
# ----------------------------------------------------------------------------------------------

SQRT_2_3 = wp.constant(0.816496580927726)  # von Mises: equivalent plastic strain per unit of deviatoric strain
# Below this Frobenius norm of F Fᵀ - I (stretches within about ±5 %), the von Mises family and sand work on
# the matrix logarithm of the left stretch by series instead of an SVD (hencky_small_strain).
LOG_SERIES_MAX = wp.constant(0.1)


@wp.func
def von_mises_flow(mat: MaterialParams, n: float, state: float, dt: float) -> float:
    """The plastic strain increment of the von Mises family's radial return, for a deviatoric
    Hencky strain of norm n and an equivalent plastic strain ``state``; 0 when elastic. Metal
    hardens, plasticine softens, viscoplastic flows by only part of the excess (Perzyna rate)."""
    sy = mat.yield_stress
    if mat.model == MODEL_VON_MISES:
        sy = sy + mat.hardening * state
    elif mat.model == MODEL_PLASTICINE:
        sy = wp.max(sy - mat.softening * state, 0.0)
    dgamma = n - SQRT_2_3 * sy / (2.0 * mat.mu)
    if dgamma <= 0.0 or n <= TINY:
        return 0.0
    if mat.model == MODEL_VISCOPLASTIC:
        # Perzyna / Bingham: the deviatoric Kirchhoff stress is s = 2μ ε (ε the deviatoric Hencky
        # strain) and the plastic strain rate is (|s| − k) / (2η) along s, k = √(2/3) σ_y, so the
        # excess strain e = n − k/(2μ) relaxes as de/dt = D − (μ/η) e: relaxation time η/μ (not
        # η/2μ, which makes the viscosity η/2). Backward Euler over the substep keeps
        # e / (1 + dt μ/η) and removes the fraction dt/(dt + η/μ) of the excess, for any dt. In
        # steady simple shear at rate γ̇ this gives τ = σ_y/√3 + η γ̇: Bingham, viscosity η, shear
        # yield stress σ_y/√3 (σ_y the von Mises equivalent yield stress).
        dgamma = dgamma * dt / (dt + mat.viscosity / mat.mu)
    return dgamma


@wp.func
def drucker_prager_flow(mat: MaterialParams, tr: float, n: float) -> float:
    """Klár et al. 2016 on Hencky strain, with cohesion moving the cone's apex into tension: for a
    volumetric strain ``tr`` and deviatoric norm ``n``, -1 when the strain is in tension past the
    cohesion (project to the apex), else the shear to remove to reach the cone (0 inside it)."""
    tr_s = tr - mat.cohesion_tr
    if tr_s >= 0.0:
        return -1.0
    return wp.max(n + (3.0 * mat.lam + 2.0 * mat.mu) / (2.0 * mat.mu) * tr_s * mat.dp_alpha, 0.0)


@wp.func
def drucker_prager_return_log(mat: MaterialParams, L: wp.mat33, trL: float, devL: wp.mat33, nL: float) -> wp.mat33:
    """The Drucker-Prager return mapping of the log strain L (trace trL, deviator devL of norm nL)."""
    I = wp.identity(n=3, dtype=float)
    Lnew = L
    dg = drucker_prager_flow(mat, trL, nL)
    if dg < 0.0:
        Lnew = (mat.cohesion_tr / 3.0) * I  # tension: the apex
    elif dg > 0.0:
        if nL > TINY:
            Lnew = L - (dg / nL) * devL
        else:
            Lnew = (trL / 3.0) * I
    return Lnew


@wp.func
def von_mises_return_log(mat: MaterialParams, L: wp.mat33, devL: wp.mat33, nL: float, state_in: float, dt: float,
                         p: int, plastic: wp.array(dtype=float)) -> wp.mat33:
    """The von Mises family's radial return of the log strain L; the equivalent plastic strain
    grows by √(2/3) Δγ."""
    Lnew = L
    dgL = von_mises_flow(mat, nL, state_in, dt)
    if dgL > 0.0:
        Lnew = L - (dgL / nL) * devL
        plastic[p] = state_in + SQRT_2_3 * dgL
    return Lnew


@wp.func
def drucker_prager_return_stretches(mat: MaterialParams, eps: wp.vec3, tr: float, dev: wp.vec3,
                                    n: float) -> wp.vec3:
    """The Drucker-Prager return mapping of the log principal stretches eps (Klár et al. 2016;
    cohesion moves the cone's apex into tension)."""
    out = eps
    dgamma = drucker_prager_flow(mat, tr, n)
    if dgamma < 0.0:
        out = (mat.cohesion_tr / 3.0) * wp.vec3(1.0, 1.0, 1.0)  # tension: project to the tip
    elif dgamma > 0.0:
        if n > TINY:
            out = eps - (dgamma / n) * dev
        else:
            out = (tr / 3.0) * wp.vec3(1.0, 1.0, 1.0)
    return out


@wp.func
def von_mises_return_stretches(mat: MaterialParams, eps: wp.vec3, dev: wp.vec3, n: float, state_in: float,
                               dt: float, p: int, plastic: wp.array(dtype=float)) -> wp.vec3:
    """The von Mises family's radial return of the log principal stretches eps: metal (hardening),
    plasticine (softening), viscoplastic (Perzyna rate: only part of the excess flows per substep)."""
    out = eps
    state = state_in
    dgamma = von_mises_flow(mat, n, state, dt)
    if dgamma > 0.0:
        out = eps - (dgamma / n) * dev
        state = state + SQRT_2_3 * dgamma
        plastic[p] = state
    return out


@wp.func
def is_small_strain(F: wp.mat33, X: wp.mat33) -> bool:
    """Is X = F Fᵀ − I within the log series' range (and F not inverted)?"""
    return wp.ddot(X, X) < LOG_SERIES_MAX * LOG_SERIES_MAX and wp.determinant(F) > 0.0


@wp.func
def hencky_small_strain(mat: MaterialParams, F: wp.mat33, X: wp.mat33, state_in: float, dt: float, p: int,
                        plastic: wp.array(dtype=float), Fout: wp.array(dtype=wp.mat33),
                        tau: wp.array(dtype=wp.mat33)) -> float:
    """The Hencky models' return mapping without an SVD, for a small elastic strain (always, for
    materials that yield at a fraction of a percent or carry only their weight, unless a substep
    strains them hard). L = log V = ½ log(F Fᵀ) has the eigenvectors U of F = U Σ Vᵀ and eigenvalues
    log Σ, so a projection of its eigenvalues that keeps their eigenvectors (deviatoric scaling, the
    cone's apex) is one of L itself, the new elastic F is exp(ΔL) F (ΔL commutes with L), and the
    Kirchhoff stress is 2μ L + λ tr(L) I. ``X`` is F Fᵀ − I."""
    I = wp.identity(n=3, dtype=float)
    L = 0.5 * log_series(X)
    trL = L[0, 0] + L[1, 1] + L[2, 2]
    devL = L - (trL / 3.0) * I
    nL = wp.sqrt(wp.ddot(devL, devL))
    Lnew = L
    if mat.model == MODEL_DRUCKER_PRAGER:
        Lnew = drucker_prager_return_log(mat, L, trL, devL, nL)
    else:
        Lnew = von_mises_return_log(mat, L, devL, nL, state_in, dt, p, plastic)
    dL = Lnew - L
    Fe = F
    if wp.ddot(dL, dL) > 0.0:
        Fe = exp_series(dL) * F
    trN = Lnew[0, 0] + Lnew[1, 1] + Lnew[2, 2]
    Fout[p] = Fe
    tau[p] = 2.0 * mat.mu * Lnew + mat.lam * trN * I
    return wave_speed_sq(mat.mu, mat.lam, mat.density, wp.exp(trN))


@wp.func
def hencky_svd(mat: MaterialParams, F: wp.mat33, state_in: float, dt: float, p: int,
               plastic: wp.array(dtype=float), Fout: wp.array(dtype=wp.mat33),
               tau: wp.array(dtype=wp.mat33)) -> float:
    """The Hencky models' return mapping on the SVD F = U Σ Vᵀ: on the log principal stretches,
    then F = U exp(ε) Vᵀ and the StVK-Hencky stress."""
    U, sig, V = svd(F)
    eps = log_stretches(sig)
    tr = eps[0] + eps[1] + eps[2]
    dev = eps - (tr / 3.0) * wp.vec3(1.0, 1.0, 1.0)
    n = wp.length(dev)
    if mat.model == MODEL_DRUCKER_PRAGER:
        eps = drucker_prager_return_stretches(mat, eps, tr, dev, n)
    else:
        eps = von_mises_return_stretches(mat, eps, dev, n, state_in, dt, p, plastic)
    Fout[p] = U * wp.diag(exp_vec(eps)) * wp.transpose(V)
    tau[p] = hencky_stress(U, eps, mat.mu, mat.lam)
    return wave_speed_sq(mat.mu, mat.lam, mat.density, wp.exp(eps[0] + eps[1] + eps[2]))


@wp.func
def hencky_plastic(mat: MaterialParams, F: wp.mat33, state_in: float, dt: float, p: int,
                   plastic: wp.array(dtype=float), Fout: wp.array(dtype=wp.mat33),
                   tau: wp.array(dtype=wp.mat33)) -> float:
    """StVK-Hencky elasticity with the model's return mapping (von Mises family, Drucker-Prager)."""
    I = wp.identity(n=3, dtype=float)
    X = F * wp.transpose(F) - I
    if is_small_strain(F, X):
        return hencky_small_strain(mat, F, X, state_in, dt, p, plastic, Fout, tau)
    return hencky_svd(mat, F, state_in, dt, p, plastic, Fout, tau)


# ----------------------------------------------------------------------------------------------
# The dispatch
# ----------------------------------------------------------------------------------------------


@wp.func
def update_material(
    mat: MaterialParams,
    F: wp.mat33,
    Cp: wp.mat33,
    q_in: wp.quat,
    state_in: float,
    dt: float,
    p: int,
    rot: wp.array(dtype=wp.quat),
    plastic: wp.array(dtype=float),
    Fout: wp.array(dtype=wp.mat33),
    tau: wp.array(dtype=wp.mat33),
) -> float:
    """Return mapping and Kirchhoff stress of particle p for its model; returns its wave speed².

    ``F`` is the trial deformation gradient (I + dt C) Fⁿ, ``Cp`` the particle's velocity
    gradient. Writes the projected F, the stress and the model's state (``plastic``: equivalent
    plastic strain, snow's plastic J, or fracture damage; ``rot``: the warm-started rotation of F
    for corotated models).
    """
    model = mat.model
    if model == MODEL_FIXED_COROTATED:
        return barrier_corotated(mat, F, Cp, q_in, dt, p, rot, Fout, tau)
    if model == MODEL_NEO_HOOKEAN:
        return neo_hookean(mat, F, p, Fout, tau)
    if model == MODEL_RIGID:
        return rigid(F, p, Fout, tau)
    if model == MODEL_FLUID:
        return weakly_compressible_fluid(mat, F, Cp, p, Fout, tau)
    if model == MODEL_FRACTURE:
        return fracture(mat, F, state_in, p, plastic, Fout, tau)
    if model == MODEL_SNOW:
        return snow(mat, F, state_in, p, plastic, Fout, tau)
    return hencky_plastic(mat, F, state_in, dt, p, plastic, Fout, tau)
