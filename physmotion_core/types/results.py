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
    ``rotation_free`` (…,) is true, only the stretch V S Vᵀ (the polar factor without its rotation).

    Only the matrices the clamp can change go through the SVD: the largest singular value is at most
    |F|_F and the smallest at least 2 |det F| / |F|_F² (σ₁σ₂ <= (σ₁² + σ₂²) / 2), so where
    |F|_F <= limit and |det F| >= |F|_F² / (2 limit) the clamp is the identity and F is returned as it
    is (most particles of most frames: the SVD was most of the cost of posing a frame)."""
    Fd = F.double()
    fro2 = (Fd * Fd).sum(dim=(-2, -1))
    need = ~((fro2 <= limit * limit) & (torch.linalg.det(Fd).abs() >= fro2 / (2.0 * limit)))
    if rotation_free is not None:
        need = need | rotation_free.bool()
    if not bool(need.any()):
        return F.clone()
    rf = rotation_free.bool()[need] if rotation_free is not None else torch.zeros(int(need.sum()), dtype=torch.bool)
    if Fd.device.type == "cpu" and not (torch.is_grad_enabled() and F.requires_grad) and _warp_importable():
        from ..sim.pose import clamp_stretch  # compiled: several times faster than LAPACK's batched 3x3 SVD

        part = clamp_stretch(Fd[need], limit, rf)
    else:
        U, S, Vh = torch.linalg.svd(Fd[need])
        S = torch.diag_embed(S.clamp(1.0 / limit, limit))
        part = U @ S @ Vh
        if bool(rf.any()):
            part = torch.where(rf[:, None, None], Vh.transpose(-1, -2) @ S @ Vh, part)
    out = Fd.clone()
    out[need] = part
    return out.to(F.dtype)


def pose_on_cpu(x: torch.Tensor, F: torch.Tensor, means: torch.Tensor, dtype: torch.dtype) -> bool:
    """Whether a frame is posed by the compiled CPU kernel (sim/pose.py): float32 CPU tensors, Warp
    importable, and not under autograd (nothing here is differentiated, but a caller may ask)."""
    if dtype != torch.float32 or any(t.device.type != "cpu" for t in (x, F, means)):
        return False
    if torch.is_grad_enabled() and any(t.requires_grad for t in (x, F, means)):
        return False
    return _warp_importable()


_WARP: list = []


def _warp_importable() -> bool:
    if not _WARP:
        try:
            import warp  # noqa: F401

            _WARP.append(True)
        except Exception:  # noqa: BLE001 - a broken Warp install: the PyTorch formula still works
            _WARP.append(False)
    return _WARP[0]


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
    particle_piece: Optional[torch.Tensor] = None  # (P,) the separate body of each recorded particle (feedback)

    @property
    def num_frames(self) -> int:
        return int(self.x.shape[0])

    def same_pose(self, a: int, b: int) -> bool:
        """Whether frames ``a`` and ``b`` pose every Gaussian identically: the same particle positions and
        deformation gradients, bit for bit (``gaussians_at`` reads nothing else per frame). Once a scene is at
        rest the simulator stops substepping and repeats its state (sim/simulate.py, REST_FRAMES), and frames
        resampled between equal frames are equal too, so a render of one is a render of the other: the renderers
        copy it instead of drawing it again."""
        return bool(torch.equal(self.x[a], self.x[b]) and torch.equal(self.F[a], self.F[b]))

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
        x = self.x[frame]
        rest = self._rest_state()
        if pose_on_cpu(x, F, self.rest.means, dtype):
            from ..sim.pose import pose_gaussians  # compiled (Warp): several times faster than the formula below

            nb, w = ((self.binding[:, None], torch.ones(self.binding.shape[0], 1)) if self.neighbours is None
                     else (self.neighbours, self.weights))
            means, covars = pose_gaussians(x, self.rest_particles, F, nb, w, rest.get("rest_d"),
                                           float(self.stats.get("particle_spacing", 0.0)), rest["centre"],
                                           self.rest.means, rest["cov"])
        else:
            means, covars = self._pose_torch(x, F, rest)
        return dataclasses.replace(self.rest, means=means, covars=covars)

    def _pose_torch(self, x: torch.Tensor, F: torch.Tensor, rest: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """The posing rule in PyTorch (any device and dtype): means and covariances of every Gaussian."""
        dtype = self.rest.means.dtype
        X, Xg = self.rest_particles, self.rest.means
        if self.neighbours is None:
            nb = self.binding[:, None]
            w = torch.ones(nb.shape, dtype=dtype)
        else:
            nb, w = self.neighbours, self.weights.to(dtype)
            # Neighbours torn away from the Gaussian's own particle (now more than twice as far from it
            # as at rest, plus one spacing) no longer pull on it: a crack stays a crack.
            now_d = (x[nb] - x[nb[:, :1]]).norm(dim=-1)
            spacing = float(self.stats.get("particle_spacing", 0.0))
            w = torch.where(now_d <= 2.0 * rest["rest_d"] + spacing, w, torch.zeros_like(w))
            w[:, 0] = torch.clamp_min(w[:, 0], 1e-6)
            w = w / w.sum(dim=1, keepdim=True)
        # x_g = Σ w_k (x_k + F_k (X_g − X_k)) = Σ w_k (x_k − F_k (X_k − c)) + F̄ (X_g − c): the per-particle
        # part is computed once per particle, in float64, about the rest centre c (so F̄ (X_g − c) is an
        # object's size, not the scene's, and float32 F̄ costs no more than the direct sum did).
        F = F.to(dtype)
        c = rest["centre"]
        b = x.double() - torch.einsum("pij,pj->pi", F.double(), X.double() - c)
        Fg = (w[..., None, None] * F[nb]).sum(dim=1)
        means = ((w.double()[..., None] * b[nb]).sum(dim=1)
                 + torch.einsum("nij,nj->ni", Fg.double(), Xg.double() - c)).to(dtype)
        covars = torch.einsum("nij,njk,nlk->nil", Fg, rest["cov"], Fg)
        return means, covars

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_rest_cache", None)  # derived: recomputed on first use
        return state

    def _rest_state(self) -> dict:
        """What every frame needs from the rest state, computed once: the covariances the frames deform
        (liquid splats made round, see gaussians_at) and each Gaussian's neighbours' rest distances."""
        key = (self.rest, self.liquid, self.neighbours, self.rest_particles)
        cache = self.__dict__.get("_rest_cache")
        if cache is not None and all(a is b for a, b in zip(cache[0], key)):
            return cache[1]
        rest_cov = self.rest.covariance()
        nb = self.binding if self.neighbours is None else self.neighbours[:, 0]
        if self.liquid is not None and bool(self.liquid.any()):
            own = self.liquid[nb]
            if bool(own.any()):
                dtype = rest_cov.dtype
                s = torch.linalg.eigvalsh(rest_cov[own].double()).clamp_min(0).sqrt()  # ascending σ
                r2 = (s[:, 1] * s[:, 2]).to(dtype)
                rest_cov = rest_cov.clone()
                rest_cov[own] = r2[:, None, None] * torch.eye(3, dtype=dtype)
        state = {"cov": rest_cov, "centre": self.rest_particles.double().mean(dim=0)}
        if self.neighbours is not None:
            X = self.rest_particles
            state["rest_d"] = (X[self.neighbours] - X[self.neighbours[:, :1]]).norm(dim=-1)
        self.__dict__["_rest_cache"] = (key, state)
        return state


@dataclass
class FrameSet:
    """Rendered frames: rgb (T,H,W,3) premultiplied by alpha, alpha (T,H,W), depth (T,H,W) (0 where empty)."""

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    fps: float = 24.0
