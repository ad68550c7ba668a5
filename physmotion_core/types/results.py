"""What the stages produce: the simulated trajectory (SimResult) and rendered frames (FrameSet)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Optional

import torch

from ..errors import InputError
from .gaussians import Gaussians
from .material import Material

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
