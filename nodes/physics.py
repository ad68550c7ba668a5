"""Material, condition and simulation nodes."""

from __future__ import annotations

from ._util import CATEGORY, progress_callback, sim_device


def _chain(conditions):
    from physmotion_core.types import Conditions

    return conditions if conditions is not None else Conditions()


class PhysMotionMaterial:
    """A material preset with optional SI overrides."""

    @classmethod
    def INPUT_TYPES(cls):
        from physmotion_core.sim.materials import material_names

        return {"required": {
            "preset": (material_names(), {"default": "jelly", "tooltip": "Material preset (SI parameters)."}),
            "youngs_modulus": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 1e12, "step": 100.0,
                                         "tooltip": "Young's modulus E in Pa; 0 keeps the preset's value "
                                                    "(jelly ~2e4, rubber ~1e6, metal ~1e10)."}),
            "poissons_ratio": ("FLOAT", {"default": -1.0, "min": -1.0, "max": 0.499, "step": 0.01,
                                         "tooltip": "Poisson's ratio ν in [0, 0.5); -1 keeps the preset's value."}),
            "density": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 1e5, "step": 10.0,
                                  "tooltip": "Density in kg/m³; 0 keeps the preset's value (water 1000)."}),
        }}

    RETURN_TYPES = ("PM_MATERIAL",)
    RETURN_NAMES = ("material",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, preset, youngs_modulus, poissons_ratio, density):
        from physmotion_core.types import Material

        over = {}
        if youngs_modulus > 0:
            over["E"] = float(youngs_modulus)
        if poissons_ratio >= 0:
            over["nu"] = float(poissons_ratio)
        if density > 0:
            over["density"] = float(density)
        return (Material.preset(preset, **over),)


class PhysMotionForce:
    """A push: a force in newtons on part of the object over a time window."""

    @classmethod
    def INPUT_TYPES(cls):
        vec = {"default": 0.0, "min": -1e7, "max": 1e7, "step": 0.5}
        return {
            "required": {
                "fx": ("FLOAT", {**vec, "default": 40.0, "tooltip": "Force along +x (image right), newtons."}),
                "fy": ("FLOAT", {**vec, "tooltip": "Force along +y (up), newtons."}),
                "fz": ("FLOAT", {**vec, "tooltip": "Force along +z (towards the camera), newtons."}),
                "region": (["image point", "whole object"], {
                    "default": "image point",
                    "tooltip": "image point: the part of the object under pixel (u, v) within radius_px, "
                               "through its whole depth. whole object: spread over all of it."}),
                "u": ("INT", {"default": 0, "min": 0, "max": 16384,
                              "tooltip": "Pixel column in the input image where the force is applied."}),
                "v": ("INT", {"default": 0, "min": 0, "max": 16384,
                              "tooltip": "Pixel row in the input image where the force is applied."}),
                "radius_px": ("FLOAT", {"default": 25.0, "min": 1.0, "max": 4096.0, "step": 1.0,
                                        "tooltip": "Radius of the image-point region in pixels."}),
                "t_start": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 1e4, "step": 0.01,
                                      "tooltip": "When the force starts, seconds."}),
                "t_end": ("FLOAT", {"default": 0.25, "min": 0.001, "max": 1e4, "step": 0.01,
                                    "tooltip": "When the force stops, seconds (a push lasts ~0.1-0.3 s)."}),
            },
            "optional": {"conditions": ("PM_CONDITIONS", {"tooltip": "Conditions to add this force to."})},
        }

    RETURN_TYPES = ("PM_CONDITIONS",)
    RETURN_NAMES = ("conditions",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, fx, fy, fz, region, u, v, radius_px, t_start, t_end, conditions=None):
        from physmotion_core.types import Force, Region

        r = Region.at_pixel(u, v, radius_px) if region == "image point" else Region()
        return (_chain(conditions) + Force((fx, fy, fz), r, float(t_start), float(t_end)),)


class PhysMotionGround:
    """The ground plane under the object and how it touches it."""

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "contact": (["friction", "slip", "sticky"], {
                    "default": "friction",
                    "tooltip": "friction: Coulomb friction μ (slides, then stops). slip: frictionless. "
                               "sticky: glued to the ground."}),
                "friction": ("FLOAT", {"default": 0.5, "min": 0.0, "max": 10.0, "step": 0.05,
                                       "tooltip": "Coulomb friction coefficient μ (wood on wood ≈ 0.4)."}),
                "height": ("FLOAT", {"default": 0.0, "min": -100.0, "max": 100.0, "step": 0.01,
                                     "tooltip": "Height of the ground plane in metres (the lift puts the "
                                                "object's lowest point at 0)."}),
            },
            "optional": {"conditions": ("PM_CONDITIONS", {"tooltip": "Conditions to add the ground to."})},
        }

    RETURN_TYPES = ("PM_CONDITIONS",)
    RETURN_NAMES = ("conditions",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, contact, friction, height, conditions=None):
        from physmotion_core.types import Ground

        return (_chain(conditions) + Ground(float(height), contact, float(friction)),)


class PhysMotionGravity:
    """Gravity as a vector (default Earth's, -y)."""

    @classmethod
    def INPUT_TYPES(cls):
        g = {"min": -1000.0, "max": 1000.0, "step": 0.01}
        return {
            "required": {
                "gx": ("FLOAT", {**g, "default": 0.0, "tooltip": "Gravity along x, m/s²."}),
                "gy": ("FLOAT", {**g, "default": -9.81, "tooltip": "Gravity along y (up), m/s²; Earth -9.81."}),
                "gz": ("FLOAT", {**g, "default": 0.0, "tooltip": "Gravity along z, m/s²."}),
            },
            "optional": {"conditions": ("PM_CONDITIONS", {"tooltip": "Conditions to add gravity to."})},
        }

    RETURN_TYPES = ("PM_CONDITIONS",)
    RETURN_NAMES = ("conditions",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, gx, gy, gz, conditions=None):
        from physmotion_core.types import Gravity

        return (_chain(conditions) + Gravity((gx, gy, gz)),)


class PhysMotionMPMSimulate:
    """Simulate the object with the Material Point Method (Warp; CPU or CUDA)."""

    DESCRIPTION = ("Fills the object with particles and simulates it with MLS-MPM. The time step adapts every "
                   "substep to the stability (CFL) limit, so stiff materials do not crash; invalid states are "
                   "reported with the frame and the likely cause.")

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "gaussians": ("PM_GAUSSIANS", {"tooltip": "The object as 3D Gaussians (from a lift node)."}),
                "material": ("PM_MATERIAL", {"tooltip": "What the object is made of."}),
                "frames": ("INT", {"default": 48, "min": 1, "max": 100000,
                                   "tooltip": "Number of output frames (frame 0 is the rest state)."}),
                "fps": ("FLOAT", {"default": 24.0, "min": 1.0, "max": 1000.0, "step": 1.0,
                                  "tooltip": "Frames per second of the output."}),
                "grid_res": ("INT", {"default": 0, "min": 0, "max": 512,
                                     "tooltip": "Grid cells across the object's largest extent (cost ~ res³); "
                                                "0 = auto (24 on CPU, 48 on CUDA)."}),
                "particles_per_cell": ([8, 1, 27], {"default": 8, "tooltip": "Particles per grid cell (n³)."}),
                "cfl": ("FLOAT", {"default": 0.4, "min": 0.05, "max": 1.0, "step": 0.05,
                                  "tooltip": "Fraction of the stability limit each time step uses."}),
                "domain_margin": ("FLOAT", {"default": 1.0, "min": 0.1, "max": 20.0, "step": 0.1,
                                            "tooltip": "Free space around the object, in object sizes."}),
                "device": (["auto", "cpu", "cuda"], {"default": "auto",
                                                     "tooltip": "Where the simulation runs (auto follows ComfyUI)."}),
                "seed": ("INT", {"default": 0, "min": 0, "max": 2**31 - 1,
                                 "tooltip": "Seed of the particle jitter (same seed, same result)."}),
            },
            "optional": {
                "conditions": ("PM_CONDITIONS", {"tooltip": "Forces, ground, gravity... (default: gravity only)."}),
                "camera": ("PM_CAMERA", {"tooltip": "The input camera; needed by image-point regions."}),
            },
        }

    RETURN_TYPES = ("PM_SIM",)
    RETURN_NAMES = ("simulation",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, gaussians, material, frames, fps, grid_res, particles_per_cell, cfl, domain_margin, device, seed,
            conditions=None, camera=None):
        from physmotion_core.sim import simulate
        from physmotion_core.types import SimSettings

        settings = SimSettings(frames=int(frames), fps=float(fps), grid_res=int(grid_res),
                               particles_per_cell=int(particles_per_cell), cfl=float(cfl),
                               domain_margin=float(domain_margin), device=sim_device(device), seed=int(seed))
        return (simulate(gaussians, material, _chain(conditions), settings, camera=camera,
                         progress=progress_callback()),)


NODE_CLASS_MAPPINGS = {
    "PhysMotionMaterial": PhysMotionMaterial,
    "PhysMotionForce": PhysMotionForce,
    "PhysMotionGround": PhysMotionGround,
    "PhysMotionGravity": PhysMotionGravity,
    "PhysMotionMPMSimulate": PhysMotionMPMSimulate,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PhysMotionMaterial": "PhysMotion Material",
    "PhysMotionForce": "PhysMotion Force (push)",
    "PhysMotionGround": "PhysMotion Ground",
    "PhysMotionGravity": "PhysMotion Gravity",
    "PhysMotionMPMSimulate": "PhysMotion MPM Simulate",
}
