"""Core data types shared by every stage.

Conventions (README.md, "Conventions"): right-handed world in metres/seconds/kilograms, +y up, gravity -y.
Cameras follow OpenGL: a camera looks down its local -z axis, +y up in the image. Gaussians store
scales in metres (not log), quaternions as wxyz, opacities in [0, 1] and SH coefficients (N, K, 3)
with the usual 3DGS DC convention rgb = 0.5 + C0 * sh[:, 0].
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Iterable, Iterator, Optional, Sequence, Union

import numpy as np
import torch

from .errors import InputError

SH_C0 = 0.28209479177387814

Vec3 = tuple[float, float, float]


def _as_vec3(value, name: str) -> Vec3:
    try:
        v = tuple(float(x) for x in value)
    except TypeError as exc:
        raise InputError(f"{name} must be three numbers (x, y, z); got {value!r}") from exc
    if len(v) != 3:
        raise InputError(f"{name} must be three numbers (x, y, z); got {len(v)} values: {value!r}")
    if not all(math.isfinite(x) for x in v):
        raise InputError(f"{name} must be finite; got {v}. Replace NaN/Inf with a real value.")
    return v  # type: ignore[return-value]


# ----------------------------------------------------------------------------------------------
# Gaussians
# ----------------------------------------------------------------------------------------------


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """wxyz quaternions (N,4), any norm, to rotation matrices (N,3,3)."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (N,3,3) to unit wxyz quaternions (N,4) with w >= 0 (Shepperd's method)."""
    R = R.reshape(-1, 3, 3)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    trace = m00 + m11 + m22
    cands = torch.stack([trace, m00, m11, m22], dim=-1)
    best = cands.argmax(dim=-1)
    q = torch.empty(R.shape[0], 4, dtype=R.dtype, device=R.device)
    # Each branch uses the largest diagonal term as the pivot, which keeps the sqrt well away from 0.
    for k in range(4):
        sel = best == k
        if not bool(sel.any()):
            continue
        r = R[sel]
        if k == 0:
            s = torch.sqrt(1.0 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2]) * 2
            q[sel] = torch.stack([0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s,
                                  (r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 1, 0] - r[:, 0, 1]) / s], -1)
        elif k == 1:
            s = torch.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2]) * 2
            q[sel] = torch.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s,
                                  (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s], -1)
        elif k == 2:
            s = torch.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2]) * 2
            q[sel] = torch.stack([(r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s,
                                  0.25 * s, (r[:, 1, 2] + r[:, 2, 1]) / s], -1)
        else:
            s = torch.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1]) * 2
            q[sel] = torch.stack([(r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s,
                                  (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s], -1)
    q = torch.where(q[:, :1] < 0, -q, q)
    return torch.nn.functional.normalize(q, dim=-1)


@dataclass
class Gaussians:
    """A set of 3D Gaussians.

    ``covars`` (N,3,3), when set, overrides quats/scales as the shape of each Gaussian. The
    simulator produces deformed Gaussians this way (Σ = F Σ₀ Fᵀ is not a rotation+scale of the
    original axes in general); ``with_covariance_as_rotscale`` converts back when a file needs it.
    ``object_ids`` (N,) int64 labels which object of a multi-object scene each Gaussian belongs to.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    covars: Optional[torch.Tensor] = None
    object_ids: Optional[torch.Tensor] = None

    def __post_init__(self) -> None:
        n = self.means.shape[0]
        checks = {
            "means": (self.means, (n, 3)),
            "quats": (self.quats, (n, 4)),
            "scales": (self.scales, (n, 3)),
            "opacities": (self.opacities, (n,)),
        }
        for name, (t, shape) in checks.items():
            if tuple(t.shape) != shape:
                raise InputError(f"Gaussians.{name} must have shape {shape}; got {tuple(t.shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise InputError(f"Gaussians.sh must have shape ({n}, K, 3); got {tuple(self.sh.shape)}")
        if self.covars is not None and tuple(self.covars.shape) != (n, 3, 3):
            raise InputError(f"Gaussians.covars must have shape ({n}, 3, 3); got {tuple(self.covars.shape)}")
        if self.object_ids is not None and tuple(self.object_ids.shape) != (n,):
            raise InputError(f"Gaussians.object_ids must have shape ({n},); got {tuple(self.object_ids.shape)}")

    # -- construction -----------------------------------------------------------------------
    @classmethod
    def from_rgb(
        cls,
        means: torch.Tensor,
        rgb: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        quats: Optional[torch.Tensor] = None,
    ) -> "Gaussians":
        """Build degree-0 Gaussians from linear RGB in [0,1] (stored as SH DC)."""
        n = means.shape[0]
        if quats is None:
            quats = torch.zeros(n, 4, dtype=means.dtype, device=means.device)
            quats[:, 0] = 1.0
        sh = ((rgb - 0.5) / SH_C0).reshape(n, 1, 3)
        return cls(means=means, quats=quats, scales=scales, opacities=opacities, sh=sh)

    # -- derived quantities -----------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def rgb(self) -> torch.Tensor:
        """View-independent colour (N,3) from the SH DC term (not clamped, to keep gradients)."""
        return 0.5 + SH_C0 * self.sh[:, 0, :]

    def covariance(self) -> torch.Tensor:
        """World-space covariance (N,3,3)."""
        if self.covars is not None:
            return self.covars
        R = quat_to_rotmat(self.quats)
        M = R * self.scales[:, None, :]
        return M @ M.transpose(-1, -2)

    def with_covariance_as_rotscale(self) -> "Gaussians":
        """Replace ``covars`` by the eigen-decomposition Σ = R diag(s²) Rᵀ (for .ply export)."""
        if self.covars is None:
            return self
        sym = 0.5 * (self.covars + self.covars.transpose(-1, -2))
        evals, evecs = torch.linalg.eigh(sym.double())
        evecs = evecs * torch.sign(torch.linalg.det(evecs))[:, None, None]  # proper rotation
        scales = evals.clamp_min(1e-20).sqrt().to(self.means.dtype)
        quats = rotmat_to_quat(evecs).to(self.means.dtype)
        return dataclasses.replace(self, quats=quats, scales=scales, covars=None)

    # -- container helpers -------------------------------------------------------------------
    def _map(self, fn) -> "Gaussians":
        return Gaussians(
            means=fn(self.means),
            quats=fn(self.quats),
            scales=fn(self.scales),
            opacities=fn(self.opacities),
            sh=fn(self.sh),
            covars=None if self.covars is None else fn(self.covars),
            object_ids=None if self.object_ids is None else fn(self.object_ids),
        )

    def to(self, device) -> "Gaussians":
        return self._map(lambda t: t.to(device))

    def detach(self) -> "Gaussians":
        return self._map(lambda t: t.detach())

    def clone(self) -> "Gaussians":
        return self._map(lambda t: t.clone())

    def subset(self, index: torch.Tensor) -> "Gaussians":
        return self._map(lambda t: t[index])

    @staticmethod
    def cat(items: Sequence["Gaussians"]) -> "Gaussians":
        if not items:
            raise InputError("Gaussians.cat needs at least one set of Gaussians")
        k = max(g.sh.shape[1] for g in items)
        sh = [torch.nn.functional.pad(g.sh, (0, 0, 0, k - g.sh.shape[1])) for g in items]
        any_cov = any(g.covars is not None for g in items)
        ids = None
        if any(g.object_ids is not None for g in items):
            ids = torch.cat([
                g.object_ids if g.object_ids is not None
                else torch.zeros(len(g), dtype=torch.int64, device=g.device) for g in items])
        return Gaussians(
            means=torch.cat([g.means for g in items]),
            quats=torch.cat([g.quats for g in items]),
            scales=torch.cat([g.scales for g in items]),
            opacities=torch.cat([g.opacities for g in items]),
            sh=torch.cat(sh),
            covars=torch.cat([g.covariance() for g in items]) if any_cov else None,
            object_ids=ids,
        )

    def validate(self, name: str = "Gaussians") -> None:
        """Raise InputError if any value is non-finite or out of range."""
        if len(self) == 0:
            raise InputError(f"{name} is empty: the lift produced no Gaussians. Check that the mask "
                             "covers the object (it may be empty or a few pixels).")
        for field_name in ("means", "quats", "scales", "opacities", "sh"):
            t = getattr(self, field_name)
            if not bool(torch.isfinite(t).all()):
                raise InputError(f"{name}.{field_name} contains NaN or Inf values")
        if bool((self.scales <= 0).any()):
            raise InputError(f"{name}.scales must be positive metres (not log-scales)")
        if bool(((self.opacities < 0) | (self.opacities > 1)).any()):
            raise InputError(f"{name}.opacities must lie in [0, 1] (not logits)")

    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.means.min(dim=0).values, self.means.max(dim=0).values


# ----------------------------------------------------------------------------------------------
# Camera
# ----------------------------------------------------------------------------------------------

# OpenGL camera axes (x right, y up, looking down -z) to OpenCV axes (x right, y down, looking +z).
_GL_TO_CV = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))


@dataclass
class Camera:
    """A pinhole camera: intrinsics in pixels and a camera-to-world pose in OpenGL convention."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    c2w: torch.Tensor = field(default_factory=lambda: torch.eye(4))
    near: float = 0.01
    far: float = 100.0

    def __post_init__(self) -> None:
        if int(self.width) < 1 or int(self.height) < 1:
            raise InputError(f"Camera size must be at least 1x1 pixels; got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise InputError(f"Camera focal lengths must be positive; got fx={self.fx}, fy={self.fy}")
        self.width = int(self.width)
        self.height = int(self.height)
        self.c2w = torch.as_tensor(self.c2w, dtype=torch.float32).reshape(4, 4).cpu()

    @classmethod
    def from_fov(cls, width: int, height: int, fov_y_deg: float, c2w=None, **kw) -> "Camera":
        if not (0.5 <= fov_y_deg <= 170.0):
            raise InputError(f"fov_y must be between 0.5 and 170 degrees; got {fov_y_deg}")
        fy = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2)
        return cls(width, height, fy, fy, width / 2.0, height / 2.0,
                   torch.eye(4) if c2w is None else c2w, **kw)

    @classmethod
    def look_at(cls, eye, target, up=(0.0, 1.0, 0.0), *, width: int, height: int,
                fov_y_deg: float = 49.1, **kw) -> "Camera":
        eye_t = torch.tensor(_as_vec3(eye, "eye"))
        fwd = torch.tensor(_as_vec3(target, "target")) - eye_t
        if float(fwd.norm()) < 1e-12:
            raise InputError("Camera.look_at: eye and target coincide")
        fwd = fwd / fwd.norm()
        right = torch.linalg.cross(fwd, torch.tensor(_as_vec3(up, "up")))
        if float(right.norm()) < 1e-9:
            raise InputError("Camera.look_at: the up vector is parallel to the viewing direction")
        right = right / right.norm()
        true_up = torch.linalg.cross(right, fwd)
        c2w = torch.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -fwd, eye_t
        return cls.from_fov(width, height, fov_y_deg, c2w, **kw)

    @property
    def fov_y_deg(self) -> float:
        return math.degrees(2 * math.atan(0.5 * self.height / self.fy))

    @property
    def position(self) -> torch.Tensor:
        return self.c2w[:3, 3].clone()

    def K(self) -> torch.Tensor:
        return torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def w2c_opencv(self) -> torch.Tensor:
        """World-to-camera matrix in OpenCV axes (what gsplat and our rasterizer consume)."""
        return torch.linalg.inv(self.c2w @ _GL_TO_CV)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points (N,3) to pixel coordinates (N,2) (pixel centres at +0.5) and depth z (N,)."""
        w2c = self.w2c_opencv().to(points.device, points.dtype)
        pc = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        uv = torch.stack([self.fx * pc[:, 0] / z + self.cx, self.fy * pc[:, 1] / z + self.cy], dim=-1)
        return uv, z

    def unproject(self, uv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Pixel coordinates (N,2) and camera depth z (N,) to world points (N,3)."""
        x = (uv[:, 0] - self.cx) / self.fx * depth
        y = (uv[:, 1] - self.cy) / self.fy * depth
        pc = torch.stack([x, y, depth], dim=-1)
        c2w = (self.c2w @ _GL_TO_CV).to(uv.device, uv.dtype)
        return pc @ c2w[:3, :3].T + c2w[:3, 3]

    def resized(self, width: int, height: int) -> "Camera":
        """The same view at another resolution (intrinsics scaled)."""
        sx, sy = width / self.width, height / self.height
        return dataclasses.replace(self, width=width, height=height, fx=self.fx * sx, fy=self.fy * sy,
                                   cx=self.cx * sx, cy=self.cy * sy, c2w=self.c2w.clone())

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "c2w": self.c2w.tolist(), "near": self.near, "far": self.far}

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        return cls(**{**d, "c2w": torch.tensor(d["c2w"])})


# ----------------------------------------------------------------------------------------------
# Materials
# ----------------------------------------------------------------------------------------------

CONSTITUTIVE_MODELS = (
    "fixed_corotated", "neo_hookean", "von_mises", "drucker_prager", "snow", "plasticine",
    "fracture", "viscoplastic", "fluid", "rigid",
)


@dataclass
class Material:
    """Physical material in SI units. ``model`` selects the constitutive + return-mapping rule.

    Only the fields a model uses matter; presets (``Material.preset``) carry sensible values.
    """

    name: str = "jelly"
    model: str = "fixed_corotated"
    E: float = 2.0e4  # Young's modulus, Pa
    nu: float = 0.3  # Poisson's ratio
    density: float = 1000.0  # kg/m^3
    yield_stress: float = float("inf")  # Pa, von Mises equivalent (metal, plasticine, viscoplastic)
    hardening: float = 0.0  # Pa of yield stress gained per unit equivalent plastic strain (metal)
    softening: float = 0.0  # Pa of yield stress lost per unit equivalent plastic strain (plasticine)
    friction_angle: float = 30.0  # degrees (Drucker-Prager sand)
    cohesion: float = 0.0  # Pa of tensile mean stress the sand can carry (Drucker-Prager)
    yield_surface: str = "triaxial"  # Drucker-Prager cone matched to Mohr-Coulomb in "triaxial" compression
    #                                  (Klár et al. 2016, PhysGaussian) or in "plane_strain" (weaker; see docs/materials.md)
    viscosity: float = 0.0  # Pa*s (fluid: dynamic viscosity; viscoplastic: Perzyna plastic viscosity)
    bulk_modulus: float = 0.0  # Pa (fluid equation of state)
    gamma: float = 7.0  # fluid equation-of-state exponent (Tait)
    crit_compression: float = 2.5e-2  # snow theta_c
    crit_stretch: float = 7.5e-3  # snow theta_s
    hardening_xi: float = 10.0  # snow xi
    fracture_stretch: float = 0.0  # principal stretch beyond which the material tears (fracture model)
    damping: float = 0.0  # mass-proportional velocity damping, 1/s (0 = physical)

    @classmethod
    def preset(cls, name: str, **overrides) -> "Material":
        from .sim.materials import material_preset  # local import: sim depends on types

        return material_preset(name, **overrides)

    @property
    def mu(self) -> float:
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lam(self) -> float:
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    def wave_speed(self) -> float:
        """Sound speed at rest, m/s (the CFL limit uses it): sqrt((λ+2μ)/ρ), or sqrt(Kγ/ρ) for a
        fluid, 0 for a rigid body (its step is limited by its speed and acceleration only)."""
        if self.model == "rigid":
            return 0.0
        if self.model == "fluid":
            return math.sqrt(self.bulk_modulus * self.gamma / self.density)
        return math.sqrt((self.lam + 2.0 * self.mu) / self.density)

    def validate(self) -> None:
        if self.model not in CONSTITUTIVE_MODELS:
            raise InputError(f"Material '{self.name}': unknown model '{self.model}'. "
                             f"Choose one of: {', '.join(CONSTITUTIVE_MODELS)}")
        for key in dataclasses.fields(self):
            value = getattr(self, key.name)
            if isinstance(value, float) and math.isnan(value):
                raise InputError(f"Material '{self.name}': {key.name} is NaN; give a number")
        if not (math.isfinite(self.E) and self.E > 0):
            raise InputError(f"Material '{self.name}': Young's modulus E must be a finite positive "
                             f"number of pascals (jelly ~1e4, rubber ~1e6, metal ~1e10); got {self.E}")
        if not (0.0 <= self.nu < 0.5):
            raise InputError(f"Material '{self.name}': Poisson's ratio nu must be in [0, 0.5) "
                             f"(0.5 is perfectly incompressible and makes λ infinite); got {self.nu}")
        if not (math.isfinite(self.density) and self.density > 0):
            raise InputError(f"Material '{self.name}': density must be a finite positive kg/m³ value "
                             f"(water 1000, steel 7850); got {self.density}")
        if not (0.0 <= self.friction_angle < 90.0):
            raise InputError(f"Material '{self.name}': friction_angle must be in [0, 90) degrees; "
                             f"got {self.friction_angle}")
        if self.yield_surface not in ("triaxial", "plane_strain"):
            raise InputError(f"Material '{self.name}': yield_surface must be 'triaxial' or 'plane_strain'; "
                             f"got {self.yield_surface!r}")
        if not self.yield_stress > 0:
            raise InputError(f"Material '{self.name}': yield_stress must be positive Pa; got {self.yield_stress}")
        if self.model in ("von_mises", "plasticine", "viscoplastic") and not math.isfinite(self.yield_stress):
            raise InputError(f"Material '{self.name}': the {self.model} model needs a finite yield_stress in Pa "
                             "(metal ~1e5-1e8, clay ~1e4, toothpaste ~100)")
        if self.model == "fluid" and not self.bulk_modulus > 0:
            raise InputError(f"Material '{self.name}': a fluid needs bulk_modulus > 0 Pa (water preset: 2e5)")
        if self.model == "fracture" and not self.fracture_stretch > 1.0:
            raise InputError(f"Material '{self.name}': fracture_stretch must be > 1 (the principal stretch at "
                             f"which it tears, e.g. 1.1 = 10 %); got {self.fracture_stretch}")
        if self.model == "snow" and not (0 < self.crit_compression < 1 and self.crit_stretch > 0):
            raise InputError(f"Material '{self.name}': snow needs 0 < crit_compression < 1 and crit_stretch > 0")
        if not (1.0 <= self.gamma <= 20.0):
            raise InputError(f"Material '{self.name}': gamma must be in [1, 20] (water: 7); got {self.gamma}")
        for key in ("hardening", "softening", "cohesion", "viscosity", "bulk_modulus", "damping",
                    "fracture_stretch", "crit_compression", "crit_stretch", "hardening_xi"):
            v = getattr(self, key)
            if not (math.isfinite(v) and v >= 0):
                raise InputError(f"Material '{self.name}': {key} must be a finite non-negative number; got {v}")


# ----------------------------------------------------------------------------------------------
# Physical conditions
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Region:
    """Which part of the object a condition acts on.

    kind:
      - "all": every particle (of ``object_id`` if set).
      - "box": axis-aligned box ``lo``..``hi`` (metres, world).
      - "sphere": ``center``, ``radius`` (metres, world).
      - "image": particles whose projection in the input camera lies within ``radius_px`` of any of
        ``points`` (pixel coordinates u, v in the input image), through the whole depth; or inside
        ``mask`` (H, W) when given.
    """

    kind: str = "all"
    lo: Optional[Vec3] = None
    hi: Optional[Vec3] = None
    center: Optional[Vec3] = None
    radius: float = 0.0
    points: tuple[tuple[float, float], ...] = ()
    radius_px: float = 20.0
    mask: Optional[np.ndarray] = field(default=None, compare=False, hash=False)
    object_id: Optional[int] = None

    def __post_init__(self) -> None:
        kinds = ("all", "box", "sphere", "image")
        if self.kind not in kinds:
            raise InputError(f"Region kind must be one of {kinds}; got '{self.kind}'")
        if self.kind == "box":
            if self.lo is None or self.hi is None:
                raise InputError("A box region needs lo=(x,y,z) and hi=(x,y,z)")
            lo, hi = _as_vec3(self.lo, "box lo"), _as_vec3(self.hi, "box hi")
            if any(a >= b for a, b in zip(lo, hi)):
                raise InputError(f"Box region: every lo must be below hi; got lo={lo}, hi={hi}")
        if self.kind == "sphere":
            if self.center is None:
                raise InputError("A sphere region needs center=(x,y,z)")
            _as_vec3(self.center, "sphere center")
            if not (math.isfinite(self.radius) and self.radius > 0):
                raise InputError(f"Sphere region radius must be positive metres; got {self.radius}")
        if self.kind == "image":
            if not self.points and self.mask is None:
                raise InputError("An image region needs points=[(u, v), ...] in pixels or a mask")
            if not (math.isfinite(self.radius_px) and self.radius_px > 0):
                raise InputError(f"Image region radius_px must be positive; got {self.radius_px}")

    @classmethod
    def whole(cls, object_id: Optional[int] = None) -> "Region":
        return cls(kind="all", object_id=object_id)

    @classmethod
    def at_pixel(cls, u: float, v: float, radius_px: float = 20.0) -> "Region":
        return cls(kind="image", points=((float(u), float(v)),), radius_px=float(radius_px))


@dataclass(frozen=True)
class Force:
    """A total force (N) spread over the region's particles in proportion to their mass."""

    vector: Vec3
    region: Region = field(default_factory=Region)
    t_start: float = 0.0
    t_end: float = float("inf")

    def __post_init__(self) -> None:
        object.__setattr__(self, "vector", _as_vec3(self.vector, "Force vector"))
        _check_window(self.t_start, self.t_end, "Force")


@dataclass(frozen=True)
class Torque:
    """A torque (N·m) about the region's centre of mass: net force zero, net torque exact."""

    vector: Vec3
    region: Region = field(default_factory=Region)
    t_start: float = 0.0
    t_end: float = float("inf")

    def __post_init__(self) -> None:
        object.__setattr__(self, "vector", _as_vec3(self.vector, "Torque vector"))
        _check_window(self.t_start, self.t_end, "Torque")


@dataclass(frozen=True)
class InitialVelocity:
    """Initial linear velocity v (m/s) and angular velocity ω (rad/s, about the region's centre of mass)."""

    velocity: Vec3 = (0.0, 0.0, 0.0)
    angular_velocity: Vec3 = (0.0, 0.0, 0.0)
    region: Region = field(default_factory=Region)

    def __post_init__(self) -> None:
        object.__setattr__(self, "velocity", _as_vec3(self.velocity, "InitialVelocity velocity"))
        object.__setattr__(self, "angular_velocity",
                           _as_vec3(self.angular_velocity, "InitialVelocity angular_velocity"))


@dataclass(frozen=True)
class Anchor:
    """Particles of the region are held (a clamp, a hand): fixed, or moved at a prescribed
    ``velocity`` (m/s) from ``t_start`` to ``t_end``; outside that window they move freely."""

    region: Region = field(default_factory=Region)
    velocity: Vec3 = (0.0, 0.0, 0.0)
    t_start: float = 0.0
    t_end: float = float("inf")

    def __post_init__(self) -> None:
        object.__setattr__(self, "velocity", _as_vec3(self.velocity, "Anchor velocity"))
        _check_window(self.t_start, self.t_end, "Anchor")


CONTACTS = ("sticky", "slip", "friction")


@dataclass(frozen=True)
class Ground:
    """A horizontal ground plane y = height. contact: sticky, slip, or Coulomb friction μ."""

    height: float = 0.0
    contact: str = "friction"
    friction: float = 0.5

    def __post_init__(self) -> None:
        if self.contact not in CONTACTS:
            raise InputError(f"Ground contact must be one of {CONTACTS}; got '{self.contact}'")
        if not math.isfinite(self.height):
            raise InputError(f"Ground height must be finite; got {self.height}")
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise InputError(f"Ground friction μ must be a non-negative number; got {self.friction}")


@dataclass(frozen=True)
class Walls:
    """The simulation box's side and top walls (the domain boundary). contact as for Ground."""

    contact: str = "slip"
    friction: float = 0.0

    def __post_init__(self) -> None:
        if self.contact not in CONTACTS:
            raise InputError(f"Walls contact must be one of {CONTACTS}; got '{self.contact}'")
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise InputError(f"Walls friction μ must be a non-negative number; got {self.friction}")


@dataclass(frozen=True)
class Gravity:
    vector: Vec3 = (0.0, -9.81, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "vector", _as_vec3(self.vector, "Gravity vector"))


Condition = Union[Force, Torque, InitialVelocity, Anchor, Ground, Walls, Gravity]
CONDITION_TYPES = (Force, Torque, InitialVelocity, Anchor, Ground, Walls, Gravity)


def _check_window(t0: float, t1: float, what: str) -> None:
    if math.isnan(t0) or math.isnan(t1) or t0 < 0 or t1 <= t0:
        raise InputError(f"{what}: the time window must satisfy 0 <= t_start < t_end; got "
                         f"t_start={t0}, t_end={t1}")


class Conditions:
    """An ordered collection of physical conditions (what flows on a PM_CONDITIONS link)."""

    def __init__(self, items: Iterable[Condition] = ()):
        items = tuple(items)
        for c in items:
            if not isinstance(c, CONDITION_TYPES):
                raise InputError(f"Not a physical condition: {c!r}")
        self.items: tuple[Condition, ...] = items

    def __iter__(self) -> Iterator[Condition]:
        return iter(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def __add__(self, other) -> "Conditions":
        if isinstance(other, Conditions):
            return Conditions(self.items + other.items)
        if isinstance(other, CONDITION_TYPES):
            return Conditions(self.items + (other,))
        return Conditions(self.items + tuple(other))

    def __repr__(self) -> str:
        return f"Conditions({list(self.items)!r})"

    def of(self, kind) -> list:
        return [c for c in self.items if isinstance(c, kind)]

    def gravity(self) -> Vec3:
        g = self.of(Gravity)
        if len(g) > 1:
            raise InputError("Only one Gravity condition may be given; remove the extra ones")
        return g[0].vector if g else Gravity().vector

    def ground(self) -> Optional[Ground]:
        g = self.of(Ground)
        if len(g) > 1:
            raise InputError("Only one Ground condition may be given; remove the extra ones")
        return g[0] if g else None

    def walls(self) -> Walls:
        w = self.of(Walls)
        if len(w) > 1:
            raise InputError("Only one Walls condition may be given; remove the extra ones")
        return w[0] if w else Walls()


# ----------------------------------------------------------------------------------------------
# Simulation settings and results
# ----------------------------------------------------------------------------------------------


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
    domain_margin: float = 1.0  # free space around the object, in object sizes, for it to move into
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
        if self.transfer not in ("apic", "pic"):
            raise InputError(f"transfer must be 'apic' or 'pic'; got '{self.transfer}'")
        if not (math.isfinite(self.fixed_dt) and 0.0 <= self.fixed_dt <= 0.1):
            raise InputError(f"fixed_dt must be 0 (adaptive) or a substep length in (0, 0.1] s; got {self.fixed_dt}")
        if not (isinstance(self.max_substeps_per_frame, int) and 1 <= self.max_substeps_per_frame <= 10_000_000):
            raise InputError(f"max_substeps_per_frame must be an integer in [1, 10000000]; got "
                             f"{self.max_substeps_per_frame}")
        if not (math.isfinite(self.rest_speed) and self.rest_speed >= 0):
            raise InputError(f"rest_speed must be a non-negative speed in m/s (0 turns rest detection off); "
                             f"got {self.rest_speed}")

    def resolved_grid_res(self, device: str) -> int:
        if self.grid_res:
            return int(self.grid_res)
        scale, _ = QUALITY[self.quality]
        return max(4, int(round(AUTO_GRID_RES["cuda" if device.startswith("cuda") else "cpu"] * scale)))


MAX_SPLAT_STRETCH = 3.0


def splat_deformation(F: torch.Tensor, limit: float, rotation_free: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The deformation applied to splats: F = U S Vᵀ with S clamped to [1/limit, limit]; where
    ``rotation_free`` (…,) is true, only the stretch V S Vᵀ (the polar factor without its rotation)."""
    U, S, Vh = torch.linalg.svd(F.double())
    S = S.clamp(1.0 / limit, limit)
    out = U @ torch.diag_embed(S) @ Vh
    if rotation_free is not None and bool(rotation_free.any()):
        stretch = Vh.transpose(-1, -2) @ torch.diag_embed(S) @ Vh
        out = torch.where(rotation_free[..., None, None], stretch, out)
    return out.to(F.dtype)


@dataclass
class SimResult:
    """The simulated trajectory.

    Physics particles carry the state (positions ``x`` and deformation gradients ``F`` per frame);
    each rendered Gaussian follows a weighted blend of its nearest particles' local affine maps:
    x_g = Σ_k w_k (x_k + F_k (X_g − X_k)), Σ_g = F̄ Σ_g⁰ F̄ᵀ with F̄ = Σ_k w_k F_k.
    """

    rest: Gaussians
    times: torch.Tensor  # (T,)
    x: torch.Tensor  # (T, P, 3) particle positions
    F: torch.Tensor  # (T, P, 3, 3) deformation gradients
    binding: torch.Tensor  # (N,) index of each Gaussian's particle
    rest_particles: torch.Tensor  # (P, 3) particle rest positions
    material: Material  # the first object's material (all of them in ``materials``)
    stats: dict = field(default_factory=dict)
    materials: list = field(default_factory=list)
    plastic: Optional[torch.Tensor] = None  # (T, P) per-particle plastic state of the recorded particles
    particle_object: Optional[torch.Tensor] = None  # (P,) object id of each recorded particle
    rotation_free: Optional[torch.Tensor] = None  # (P,) bool: the particle's material flows (see gaussians_at)
    liquid: Optional[torch.Tensor] = None  # (P,) bool: a liquid, whose splats are round (see gaussians_at)
    neighbours: Optional[torch.Tensor] = None  # (N, K) particles each Gaussian interpolates from
    weights: Optional[torch.Tensor] = None  # (N, K) their weights (rows sum to 1)

    @property
    def num_frames(self) -> int:
        return int(self.x.shape[0])

    def gaussians_at(self, frame: int) -> Gaussians:
        """The Gaussians at ``frame``: each follows its particle's position and deformation.

        The rule that keeps splats sane (no needles):
        * F is the *elastic* deformation gradient: plastic models store F_E after their return
          mapping, fluids and torn material an isotropic one, so plastic flow moves splats without
          smearing them.
        * Material that flows (sand, snow, viscoplastic pastes, fluids: ``rotation_free``) uses only
          the stretch part of F_E: its splats keep their rest orientation. Grains tumbling in a
          slumping heap would otherwise turn thin surface splats edge-on to the camera.
        * Each principal stretch applied to a splat is clamped to [1/MAX_SPLAT_STRETCH,
          MAX_SPLAT_STRETCH].
        * Liquids (``liquid``): a liquid has no shape memory, so its splats are round, of the radius
          of the splat's two larger axes at rest (√(s₁s₂): a surface disc of radius a becomes a
          ball of radius a, covering the same area face-on), scaled by J^(1/3). Thin surface discs
          kept at their rest orientation would otherwise show up edge-on as flat plates in a splash.
        Solids (elastic, metal, plasticine, fracture before it tears, rigid) follow F fully.
        """
        if not (-self.num_frames <= frame < self.num_frames):
            raise InputError(f"frame {frame} is out of range: the simulation has {self.num_frames} frames")
        dtype = self.rest.means.dtype
        F = splat_deformation(self.F[frame], MAX_SPLAT_STRETCH, self.rotation_free)
        x, X, Xg = self.x[frame], self.rest_particles, self.rest.means
        if self.neighbours is None:
            nb = self.binding[:, None]
            w = torch.ones(nb.shape, dtype=dtype)
        else:
            nb, w = self.neighbours, self.weights.to(dtype)
            # Neighbours torn away from the Gaussian's own particle (now more than twice as far from it
            # as at rest, plus one spacing) no longer pull on it: a crack stays a crack.
            x0, X0 = x[nb[:, :1]], X[nb[:, :1]]
            rest_d = (X[nb] - X0).norm(dim=-1)
            now_d = (x[nb] - x0).norm(dim=-1)
            spacing = float(self.stats.get("particle_spacing", 0.0))
            w = torch.where(now_d <= 2.0 * rest_d + spacing, w, torch.zeros_like(w))
            w[:, 0] = torch.clamp_min(w[:, 0], 1e-6)
            w = w / w.sum(dim=1, keepdim=True)
        Fk = F[nb].to(dtype)  # (N, K, 3, 3)
        pos = x[nb] + (Fk @ (Xg[:, None, :] - X[nb])[..., None])[..., 0]
        means = (w[..., None] * pos).sum(dim=1)
        Fg = (w[..., None, None] * Fk).sum(dim=1)
        rest_cov = self.rest.covariance()
        if self.liquid is not None and bool(self.liquid.any()):
            own = self.liquid[nb[:, 0]]
            if bool(own.any()):
                s = torch.linalg.eigvalsh(rest_cov[own].double()).clamp_min(0).sqrt()  # ascending σ
                r2 = (s[:, 1] * s[:, 2]).to(dtype)
                ball = r2[:, None, None] * torch.eye(3, dtype=dtype)
                rest_cov = rest_cov.clone()
                rest_cov[own] = ball
        covars = Fg @ rest_cov @ Fg.transpose(-1, -2)
        return dataclasses.replace(self.rest, means=means, covars=covars)


@dataclass
class FrameSet:
    """Rendered frames: rgb (T,H,W,3) premultiplied by alpha, alpha (T,H,W), depth (T,H,W) (0 where empty)."""

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    fps: float = 24.0
