"""A Material's translation into the kernels' parameter table (``constitutive.MaterialParams``).

What a material is (its parameters, the constitutive models, the presets, the overrides users type)
lives in ``physmotion_core/types/material.py``; this is only how the kernels receive it.
"""

from __future__ import annotations

import math

from ..types.material import Material, model_id

def kernel_params(mat: Material):
    """The kernels' MaterialParams struct for a validated Material."""
    from .constitutive import MaterialParams

    p = MaterialParams()
    p.model = model_id(mat.model)
    p.mu = mat.mu
    p.lam = mat.lam
    p.density = mat.density
    p.yield_stress = mat.yield_stress if math.isfinite(mat.yield_stress) else 1.0e30
    p.hardening = mat.hardening
    p.softening = mat.softening
    s = math.sin(math.radians(mat.friction_angle))
    # The cone |dev τ| <= α (−tr τ). Matched to Mohr–Coulomb in triaxial compression (Klár et al. 2016):
    # α = √(2/3) 2 sinφ / (3 − sinφ). In plane strain with the mapping's volume-preserving flow the
    # out-of-plane deviatoric stress vanishes at yield, so √J2 = (σ1 − σ3)/2 and tr τ / 3 = (σ1 + σ3)/2,
    # and Mohr–Coulomb's (σ1 − σ3)/2 = −(σ1 + σ3)/2 · sinφ gives α = √2 sinφ / 3 (0.71× the former at 32°).
    if mat.yield_surface == "plane_strain":
        p.dp_alpha = math.sqrt(2.0) * s / 3.0
    else:
        p.dp_alpha = math.sqrt(2.0 / 3.0) * 2.0 * s / (3.0 - s)
    p.cohesion_tr = 3.0 * mat.cohesion / (3.0 * mat.lam + 2.0 * mat.mu)
    p.viscosity = mat.viscosity
    p.bulk = mat.bulk_modulus
    p.gamma = mat.gamma
    p.theta_c = mat.crit_compression
    p.theta_s = mat.crit_stretch
    p.xi = mat.hardening_xi
    p.fracture_stretch = mat.fracture_stretch if mat.fracture_stretch > 0 else 1.0e30
    p.damping = mat.damping
    return p
