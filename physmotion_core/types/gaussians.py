"""3D Gaussians (the scene's splats) and the quaternion conversions they use.

Scales are in metres (not log), quaternions wxyz, opacities in [0, 1], SH coefficients (N, K, 3) with the
usual 3DGS DC convention rgb = 0.5 + C0 * sh[:, 0] (README.md, "Conventions").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from ..errors import InputError

SH_C0 = 0.28209479177387814


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
