"""The pinhole camera: intrinsics in pixels and a camera-to-world pose in the OpenGL convention (a camera
looks down its local -z axis, +y up in the image; README.md, "Conventions")."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import torch

from ..errors import InputError
from ._checks import as_vec3

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
        eye_t = torch.tensor(as_vec3(eye, "eye"))
        fwd = torch.tensor(as_vec3(target, "target")) - eye_t
        if float(fwd.norm()) < 1e-12:
            raise InputError("Camera.look_at: eye and target coincide")
        fwd = fwd / fwd.norm()
        right = torch.linalg.cross(fwd, torch.tensor(as_vec3(up, "up")))
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
