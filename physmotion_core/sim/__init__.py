"""MPM simulation (NVIDIA Warp; the same kernels on cpu and cuda)."""

from .fill import ParticleSet, fill_particles
from ..types.material import CONSTITUTIVE_MODELS as IMPLEMENTED_MODELS
from ..types.material import PRESETS, material_names, material_preset
from .mpm import Domain, MPMSolver, resolve_device
from .simulate import simulate

__all__ = ["simulate", "fill_particles", "ParticleSet", "MPMSolver", "Domain", "resolve_device",
           "material_preset", "material_names", "PRESETS", "IMPLEMENTED_MODELS"]
