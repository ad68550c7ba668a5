"""Material, condition, scene and simulation nodes."""

from __future__ import annotations

from ._gaussian_io import GAUSSIANS_INPUT, GAUSSIANS_TOOLTIP_SUFFIX, SPLAT_AXES_INPUT, as_pm_gaussians
from ._util import CATEGORY, log, node_text, output_path, progress_callback, sim_device

_VEC = {"default": 0.0, "min": -1e7, "max": 1e7, "step": 0.1}


def _chain(conditions):
    from physmotion_core.types.conditions import Conditions

    return conditions if conditions is not None else Conditions()


def _region_inputs(default: str = "image point") -> dict:
    """Region widgets shared by every condition node."""
    from physmotion_core.sim.regions import REGION_MODES

    return {
        "region": (list(REGION_MODES), {
            "default": default,
            "tooltip": "whole object: all of it. image point: the part under pixel (u, v) within radius_px, "
                       "through its whole depth. mask: the part under the painted region_mask."}),
        "u": ("INT", {"default": 0, "min": 0, "max": 16384, "tooltip": "Pixel column in the input image."}),
        "v": ("INT", {"default": 0, "min": 0, "max": 16384, "tooltip": "Pixel row in the input image."}),
        "radius_px": ("FLOAT", {"default": 25.0, "min": 1.0, "max": 4096.0, "step": 1.0,
                                "tooltip": "Radius of the image-point region in pixels."}),
        "object_index": ("INT", {"default": -1, "min": -1, "max": 63,
                           "tooltip": "Only this object of a combined scene (0 = first); -1 = any object."}),
    }


def _optional_region_inputs() -> dict:
    return {
        "conditions": ("PM_CONDITIONS", {"tooltip": "Conditions to add this one to."}),
        "region_mask": ("MASK", {"tooltip": "Painted region (white = where it acts), used when region is 'mask'."}),
    }


def _region(region, u, v, radius_px, obj, region_mask):
    from physmotion_core.sim.regions import region_from_ui

    return region_from_ui(region, u, v, radius_px, region_mask, obj)


def _window():
    return {
        "t_start": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 1e4, "step": 0.01,
                              "tooltip": "When it starts acting, seconds."}),
        "t_end": ("FLOAT", {"default": 0.25, "min": 0.001, "max": 1e4, "step": 0.01,
                            "tooltip": "When it stops acting, seconds."}),
    }


class PhysMotionMaterial:
    """A material preset with optional SI overrides."""

    @classmethod
    def INPUT_TYPES(cls):
        from physmotion_core.types.material import material_names

        return {"required": {
            "preset": (material_names(), {"default": "jelly", "tooltip": "Material preset (SI parameters): "
                                          "elastic, plastic, granular, snow, fracture, viscous, fluid or rigid."}),
            "youngs_modulus": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 1e12, "step": 100.0,
                                         "tooltip": "Young's modulus E in Pa; 0 keeps the preset's value "
                                                    "(jelly 2e4, rubber 1e6, steel 2e11)."}),
            "poissons_ratio": ("FLOAT", {"default": -1.0, "min": -1.0, "max": 0.499, "step": 0.01,
                                         "tooltip": "Poisson's ratio ν in [0, 0.5); -1 keeps the preset's value."}),
            "density": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 1e5, "step": 10.0,
                                  "tooltip": "Density in kg/m³; 0 keeps the preset's value (water 1000)."}),
            "overrides": ("STRING", {"default": "", "multiline": False,
                                     "tooltip": "Any other parameter as key=value, comma-separated: yield_stress, "
                                                "hardening, softening, friction_angle, cohesion, viscosity, "
                                                "bulk_modulus, gamma, crit_compression, crit_stretch, "
                                                "hardening_xi, fracture_stretch, damping; sand's yield_surface=triaxial "
                                                "(default) or plane_strain (the cone matched to Mohr-Coulomb in "
                                                "plane strain, docs/materials.md)."}),
        }}

    RETURN_TYPES = ("PM_MATERIAL",)
    RETURN_NAMES = ("material",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, preset, youngs_modulus, poissons_ratio, density, overrides=""):
        from physmotion_core.types.material import parse_overrides
        from physmotion_core.types.material import Material

        over = parse_overrides(overrides)
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
        return {
            "required": {
                "fx": ("FLOAT", {**_VEC, "default": 20.0, "tooltip": "Force along +x (image right), newtons."}),
                "fy": ("FLOAT", {**_VEC, "tooltip": "Force along +y (up), newtons."}),
                "fz": ("FLOAT", {**_VEC, "tooltip": "Force along +z (towards the camera), newtons."}),
                **_region_inputs(),
                **_window(),
            },
            "optional": _optional_region_inputs(),
        }

    RETURN_TYPES = ("PM_CONDITIONS",)
    RETURN_NAMES = ("conditions",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, fx, fy, fz, region, u, v, radius_px, object_index, t_start, t_end, conditions=None,
            region_mask=None):
        from physmotion_core.types.conditions import Force

        r = _region(region, u, v, radius_px, object_index, region_mask)
        return (_chain(conditions) + Force((fx, fy, fz), r, float(t_start), float(t_end)),)


class PhysMotionTorque:
    """A twist: a torque in N·m about the region's centre of mass (net force zero)."""

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "tx": ("FLOAT", {**_VEC, "tooltip": "Torque about +x (image right), N·m."}),
                "ty": ("FLOAT", {**_VEC, "default": 0.5, "tooltip": "Torque about +y (up), N·m: spins it like "
                                                                    "a turntable."}),
                "tz": ("FLOAT", {**_VEC, "tooltip": "Torque about +z (towards the camera), N·m: turns it in "
                                                    "the image plane."}),
                **_region_inputs("whole object"),
                **_window(),
            },
            "optional": _optional_region_inputs(),
        }

    RETURN_TYPES = ("PM_CONDITIONS",)
    RETURN_NAMES = ("conditions",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, tx, ty, tz, region, u, v, radius_px, object_index, t_start, t_end, conditions=None,
            region_mask=None):
        from physmotion_core.types.conditions import Torque

        r = _region(region, u, v, radius_px, object_index, region_mask)
        return (_chain(conditions) + Torque((tx, ty, tz), r, float(t_start), float(t_end)),)


class PhysMotionInitialVelocity:
    """A throw: the region starts with velocity v and spin ω (about its centre of mass)."""

    @classmethod
    def INPUT_TYPES(cls):
        spin = {**_VEC, "min": -1e4, "max": 1e4}
        return {
            "required": {
                "vx": ("FLOAT", {**_VEC, "tooltip": "Initial velocity along +x (right), m/s."}),
                "vy": ("FLOAT", {**_VEC, "tooltip": "Initial velocity along +y (up), m/s."}),
                "vz": ("FLOAT", {**_VEC, "tooltip": "Initial velocity along +z (towards the camera), m/s."}),
                "wx": ("FLOAT", {**spin, "tooltip": "Initial spin about +x, rad/s."}),
                "wy": ("FLOAT", {**spin, "tooltip": "Initial spin about +y, rad/s."}),
                "wz": ("FLOAT", {**spin, "tooltip": "Initial spin about +z, rad/s."}),
                **_region_inputs("whole object"),
            },
            "optional": _optional_region_inputs(),
        }

    RETURN_TYPES = ("PM_CONDITIONS",)
    RETURN_NAMES = ("conditions",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, vx, vy, vz, wx, wy, wz, region, u, v, radius_px, object_index, conditions=None,
            region_mask=None):
        from physmotion_core.types.conditions import InitialVelocity

        r = _region(region, u, v, radius_px, object_index, region_mask)
        return (_chain(conditions) + InitialVelocity((vx, vy, vz), (wx, wy, wz), r),)


class PhysMotionAnchor:
    """Hold part of the object: fixed (a clamp, a nail) or moved at a set velocity (a hand pulling)."""

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                **_region_inputs(),
                "vx": ("FLOAT", {**_VEC, "tooltip": "Velocity the held part moves at along +x, m/s (0 = fixed)."}),
                "vy": ("FLOAT", {**_VEC, "tooltip": "Velocity along +y (up), m/s."}),
                "vz": ("FLOAT", {**_VEC, "tooltip": "Velocity along +z (towards the camera), m/s."}),
                "t_start": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 1e4, "step": 0.01,
                                      "tooltip": "When the hold starts, seconds."}),
                "t_end": ("FLOAT", {"default": 1e4, "min": 0.001, "max": 1e4, "step": 0.01,
                                    "tooltip": "When the part is released, seconds (10000 = never)."}),
            },
            "optional": _optional_region_inputs(),
        }

    RETURN_TYPES = ("PM_CONDITIONS",)
    RETURN_NAMES = ("conditions",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, region, u, v, radius_px, object_index, vx=0.0, vy=0.0, vz=0.0, t_start=0.0, t_end=1e4,
            conditions=None, region_mask=None):
        from physmotion_core.types.conditions import Anchor

        r = _region(region, u, v, radius_px, object_index, region_mask)
        return (_chain(conditions) + Anchor(r, (vx, vy, vz), float(t_start), float(t_end)),)


# physmotion_core.types.conditions.OBJECT_CONTACTS, spelled here so the node's widgets load without it.
OBJECT_CONTACT_CHOICES = ("friction", "slip", "sticky", "shared")


class PhysMotionGround:
    """The ground plane under the object and the walls of the simulation box."""

    CONTACTS = ["friction", "slip", "sticky"]

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "contact": (cls.CONTACTS, {
                    "default": "friction",
                    "tooltip": "Ground contact. friction: Coulomb friction μ (slides, then stops). slip: "
                               "frictionless. sticky: glued to the ground."}),
                "friction": ("FLOAT", {"default": 0.5, "min": 0.0, "max": 10.0, "step": 0.05,
                                       "tooltip": "Ground Coulomb friction coefficient μ (wood on wood ≈ 0.4)."}),
                "height": ("FLOAT", {"default": 0.0, "min": -100.0, "max": 100.0, "step": 0.01,
                                     "tooltip": "Height of the ground plane in metres (the lift puts the "
                                                "object's lowest point at 0)."}),
                "wall_contact": (cls.CONTACTS, {"default": "slip",
                                                "tooltip": "Contact with the simulation box's walls."}),
                "wall_friction": ("FLOAT", {"default": 0.0, "min": 0.0, "max": 10.0, "step": 0.05,
                                            "tooltip": "Coulomb friction μ of the walls (with wall_contact "
                                                       "'friction')."}),
            },
            "optional": {
                "conditions": ("PM_CONDITIONS", {"tooltip": "Conditions to add the ground to."}),
                "object_contact": (list(OBJECT_CONTACT_CHOICES), {
                    "default": "friction",
                    "tooltip": "How the objects of a combined scene meet (each moves on its own grid velocity "
                               "field). friction: Coulomb friction μ = object_friction, they bounce and separate. "
                               "slip: frictionless. sticky: no sliding while pressed together. shared: one field "
                               "for all objects (they glue where they touch, the behaviour before issue 37)."}),
                "object_friction": ("FLOAT", {"default": 0.3, "min": 0.0, "max": 10.0, "step": 0.05,
                                              "tooltip": "Coulomb friction μ between objects (with object_contact "
                                                         "'friction')."}),
            },
        }

    RETURN_TYPES = ("PM_CONDITIONS",)
    RETURN_NAMES = ("conditions",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, contact, friction, height, wall_contact="slip", wall_friction=0.0, conditions=None,
            object_contact="friction", object_friction=0.3):
        from physmotion_core.types.conditions import Ground, ObjectContact, Walls

        out = _chain(conditions) + Ground(float(height), contact, float(friction))
        out = out + Walls(wall_contact, float(wall_friction))
        contact_between = ObjectContact(object_contact, float(object_friction))
        if contact_between != ObjectContact():
            # The default is what a scene gets without one: adding it only when set keeps a chain
            # that already holds an ObjectContact valid (one is allowed).
            out = out + contact_between
        return (out,)


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
        from physmotion_core.types.conditions import Gravity

        return (_chain(conditions) + Gravity((gx, gy, gz)),)


class PhysMotionCombineObjects:
    """Put a second object (its own material) into the scene: they share one grid and collide."""

    @classmethod
    def INPUT_TYPES(cls):
        off = {"default": 0.0, "min": -100.0, "max": 100.0, "step": 0.01}
        return {"required": {
            "gaussians_a": (GAUSSIANS_INPUT, {"tooltip": "The first object (or a scene already combined)."
                                                         + GAUSSIANS_TOOLTIP_SUFFIX}),
            "material_a": ("PM_MATERIAL", {"tooltip": "Its material (or the combined scene's materials)."}),
            "gaussians_b": (GAUSSIANS_INPUT, {"tooltip": "The object to add." + GAUSSIANS_TOOLTIP_SUFFIX}),
            "material_b": ("PM_MATERIAL", {"tooltip": "The added object's material."}),
            "offset_x": ("FLOAT", {**off, "tooltip": "Move the added object along x (right), metres."}),
            "offset_y": ("FLOAT", {**off, "tooltip": "Move the added object along y (up), metres."}),
            "offset_z": ("FLOAT", {**off, "tooltip": "Move the added object along z (towards the camera), metres."}),
        }, "optional": {"splat_axes": SPLAT_AXES_INPUT}}

    RETURN_TYPES = ("PM_GAUSSIANS", "PM_MATERIAL")
    RETURN_NAMES = ("gaussians", "materials")
    OUTPUT_TOOLTIPS = ("The scene; object ids number the objects 0, 1, ... in the order they were added.",
                       "One material per object.")
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, gaussians_a, material_a, gaussians_b, material_b, offset_x, offset_y, offset_z,
            splat_axes="y_down"):
        from physmotion_core.scene import combine_objects

        return combine_objects(as_pm_gaussians(gaussians_a, "gaussians_a", axes=splat_axes), material_a,
                               as_pm_gaussians(gaussians_b, "gaussians_b", axes=splat_axes), material_b,
                               (offset_x, offset_y, offset_z))


class PhysMotionMPMSimulate:
    """Simulate the object with the Material Point Method (Warp; CPU or CUDA)."""

    DESCRIPTION = ("Fills the object with particles and simulates it with MLS-MPM. The time step adapts every "
                   "substep to the stability (CFL) limit, so stiff materials do not crash; invalid states are "
                   "reported with the frame and the likely cause. A scene that comes to rest stops computing.")

    @classmethod
    def INPUT_TYPES(cls):
        from physmotion_core.types.settings import QUALITY

        return {
            "required": {
                "gaussians": (GAUSSIANS_INPUT, {"tooltip": "The object(s) as 3D Gaussians (a lift or Combine Objects)."
                                                           + GAUSSIANS_TOOLTIP_SUFFIX}),
                "material": ("PM_MATERIAL", {"tooltip": "What it is made of (one per object for a combined scene)."}),
                "frames": ("INT", {"default": 48, "min": 1, "max": 100000,
                                   "tooltip": "Number of output frames (frame 0 is the rest state)."}),
                "fps": ("FLOAT", {"default": 24.0, "min": 1.0, "max": 1000.0, "step": 1.0,
                                  "tooltip": "Frames per second of the output."}),
                "quality": (list(QUALITY), {"default": "standard",
                                            "tooltip": "draft / standard / high: grid resolution when grid_res is "
                                                       "0 (standard: 24 cells on CPU, 48 on CUDA)."}),
                "grid_res": ("INT", {"default": 0, "min": 0, "max": 512,
                                     "tooltip": "Grid cells across the scene's largest extent (cost ~ res³); "
                                                "0 = from quality."}),
                "particles_per_cell": ([8, 1, 27], {"default": 8, "tooltip": "Particles per grid cell (n³)."}),
                "cfl": ("FLOAT", {"default": 0.4, "min": 0.05, "max": 0.7, "step": 0.05,
                                  "tooltip": "Fraction of the stability limit each time step uses."}),
                "domain_margin": ("FLOAT", {"default": 1.0, "min": 0.1, "max": 20.0, "step": 0.1,
                                            "tooltip": "Free space around the object, in object sizes: the least the "
                                                       "simulation box holds. It also reaches one object size past "
                                                       "what the camera sees, so nothing meets its walls in view."}),
                "device": (["auto", "cpu", "cuda"], {"default": "auto",
                                                     "tooltip": "Where the simulation runs (auto follows ComfyUI)."}),
                "seed": ("INT", {"default": 0, "min": 0, "max": 2**31 - 1,
                                 "tooltip": "Seed of the particle jitter (same seed, same result)."}),
            },
            "optional": {
                "conditions": ("PM_CONDITIONS", {"tooltip": "Forces, torques, anchors, ground, gravity... "
                                                            "(default: gravity only)."}),
                "camera": ("PM_CAMERA", {"tooltip": "The input camera; needed by image-point and mask regions."}),
                "hold_cut_edges": ("BOOLEAN", {"default": True,
                                               "tooltip": "Hold the object where the photo's edge cuts it off (a face "
                                                          "filling the frame, a branch entering from the side): the "
                                                          "rest of the body, outside the frame, holds it there. Needs "
                                                          "the camera. Off: only the ground holds it."}),
                "splat_axes": SPLAT_AXES_INPUT,
            },
            "hidden": {"unique_id": "UNIQUE_ID"},
        }

    RETURN_TYPES = ("PM_SIM",)
    RETURN_NAMES = ("simulation",)
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/physics"

    def run(self, gaussians, material, frames, fps, quality, grid_res, particles_per_cell, cfl, domain_margin,
            device, seed, conditions=None, camera=None, hold_cut_edges=True, splat_axes="y_down", unique_id=None):
        from physmotion_core.feedback import after_run, forecast
        from physmotion_core.sim import simulate
        from physmotion_core.support import edge_hold
        from physmotion_core.types.settings import SimSettings

        from ._memory import make_room

        settings = SimSettings(frames=int(frames), fps=float(fps), grid_res=int(grid_res), quality=quality,
                               particles_per_cell=int(particles_per_cell), cfl=float(cfl),
                               domain_margin=float(domain_margin), device=sim_device(device), seed=int(seed))
        g = as_pm_gaussians(gaussians, axes=splat_axes)
        conds = _chain(conditions)
        held, held_edges = False, ()
        shown: list[str] = []  # also on the node itself in ComfyUI (node_text), before the wait and after it
        if hold_cut_edges and camera is not None and (g.object_ids is None or len(set(g.object_ids.tolist())) == 1):
            anchor, edges, line = edge_hold(g, camera, material if not isinstance(material, (list, tuple)) else None)
            log.info("%s", line)
            shown.append(line)
            if anchor is not None:
                conds = conds + anchor
                held, held_edges = True, edges

        def told(facts) -> None:  # what the user reads before the wait: in the console and on the node
            mat = material[0] if isinstance(material, (list, tuple)) else material
            for line in forecast(conds, facts, mat, clip_s=(settings.frames - 1) / settings.fps, camera=camera,
                                 held=held, cfl=settings.cfl, held_edges=held_edges):
                log.info("%s", line)
                shown.append(line)
            node_text(unique_id, shown)

        def slow(message: str) -> None:  # a run whose first seconds say it takes minutes: on the node too
            shown.append("warning: " + message)
            node_text(unique_id, shown)

        sim = simulate(g, material, conds, settings, camera=camera, progress=progress_callback(), make_room=make_room,
                       on_start=told, on_pace=slow)
        if camera is not None:
            for w in after_run(sim, camera).warnings:
                log.warning("%s", w)
                shown.append("warning: " + w)
        node_text(unique_id, shown)
        return (sim,)


class PhysMotionSaveGaussianSequence:
    """Save the simulated Gaussians as one 3DGS .ply per frame (for splat viewers and other tools)."""

    @classmethod
    def INPUT_TYPES(cls):
        return {"required": {
            "simulation": ("PM_SIM", {"tooltip": "The simulated trajectory."}),
            "every_nth_frame": ("INT", {"default": 1, "min": 1, "max": 1000, "tooltip": "Save every n-th frame."}),
            "filename_prefix": ("STRING", {"default": "PhysMotion/sequence",
                                           "tooltip": "Folder/prefix inside the output folder."}),
        }}

    RETURN_TYPES = ("STRING",)
    RETURN_NAMES = ("folder",)
    OUTPUT_NODE = True
    FUNCTION = "run"
    CATEGORY = f"{CATEGORY}/io"

    def run(self, simulation, every_nth_frame, filename_prefix):
        from physmotion_core.ply import write_ply_sequence

        target, name, sub = output_path(filename_prefix, "")
        files = write_ply_sequence(target, simulation, every=int(every_nth_frame), progress=progress_callback())
        rel = f"{sub}/{target.name}" if sub else target.name
        return {"ui": {"text": [f"{len(files)} .ply files in {rel}"]}, "result": (rel,)}


NODE_CLASS_MAPPINGS = {
    "PhysMotionMaterial": PhysMotionMaterial,
    "PhysMotionForce": PhysMotionForce,
    "PhysMotionTorque": PhysMotionTorque,
    "PhysMotionInitialVelocity": PhysMotionInitialVelocity,
    "PhysMotionAnchor": PhysMotionAnchor,
    "PhysMotionGround": PhysMotionGround,
    "PhysMotionGravity": PhysMotionGravity,
    "PhysMotionCombineObjects": PhysMotionCombineObjects,
    "PhysMotionMPMSimulate": PhysMotionMPMSimulate,
    "PhysMotionSaveGaussianSequence": PhysMotionSaveGaussianSequence,
}
NODE_DISPLAY_NAME_MAPPINGS = {
    "PhysMotionMaterial": "PhysMotion Material",
    "PhysMotionForce": "PhysMotion Force (push)",
    "PhysMotionTorque": "PhysMotion Torque (twist)",
    "PhysMotionInitialVelocity": "PhysMotion Initial Velocity (throw)",
    "PhysMotionAnchor": "PhysMotion Anchor (hold fixed)",
    "PhysMotionGround": "PhysMotion Ground & Walls",
    "PhysMotionGravity": "PhysMotion Gravity",
    "PhysMotionCombineObjects": "PhysMotion Combine Objects",
    "PhysMotionMPMSimulate": "PhysMotion MPM Simulate",
    "PhysMotionSaveGaussianSequence": "PhysMotion Save Gaussian Sequence (.ply per frame)",
}
