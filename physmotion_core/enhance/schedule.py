"""Deterministic DDIM steps written as one linear map, so inversion is the exact inverse of sampling.

For every prediction type (``epsilon``, ``v_prediction``, ``sample``) a DDIM step with eta = 0 from
timestep t (ᾱ_t) to the previous one (ᾱ_p) is linear in the current latent x_t and the model
output m:

    x_p = A · x_t + B · m

* epsilon:  A = √(ᾱ_p/ᾱ_t),                     B = √(1-ᾱ_p) - √(ᾱ_p (1-ᾱ_t)/ᾱ_t)
* v:        A = √(ᾱ_p ᾱ_t) + √((1-ᾱ_p)(1-ᾱ_t)),  B = √(1-ᾱ_p) √ᾱ_t - √ᾱ_p √(1-ᾱ_t)
            (with ᾱ = cos²θ this is a rotation by θ_p - θ_t)
* sample:   A = √(1-ᾱ_p)/√(1-ᾱ_t),                B = √ᾱ_p - √(1-ᾱ_p) √ᾱ_t/√(1-ᾱ_t)

Sampling applies the map; inversion solves it for x_t: x_t = (x_p - B·m)/A, with m evaluated at a
guess of x_t (the classic DDIM inversion uses x_p itself; the optional fixed-point iterations of
"DDIM+" re-evaluate m at the new x_t, which makes a following sampling pass reproduce x_p). Treating
a v-prediction output as if it were ε — the usual bug when inverting SD 2.1 768-v — is impossible
here because A and B come from the model's own prediction type.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import torch

from ..errors import InputError

PREDICTION_TYPES = ("epsilon", "v_prediction", "sample")


def step_coefficients(alpha_t: float, alpha_prev: float, prediction_type: str) -> tuple[float, float]:
    """(A, B) of x_prev = A·x_t + B·m for one deterministic DDIM step (see the module docstring)."""
    a, p = float(alpha_t), float(alpha_prev)
    if prediction_type == "epsilon":
        return math.sqrt(p / a), math.sqrt(1 - p) - math.sqrt(p * (1 - a) / a)
    if prediction_type == "v_prediction":
        return (math.sqrt(p * a) + math.sqrt((1 - p) * (1 - a)),
                math.sqrt(1 - p) * math.sqrt(a) - math.sqrt(p) * math.sqrt(1 - a))
    if prediction_type == "sample":
        return math.sqrt(1 - p) / math.sqrt(1 - a), math.sqrt(p) - math.sqrt(1 - p) * math.sqrt(a) / math.sqrt(1 - a)
    raise InputError(f"prediction_type must be one of {PREDICTION_TYPES}; got {prediction_type!r}")


@dataclass
class DDIMSchedule:
    """The sampling timesteps (noisiest first) and ᾱ of a scheduler config, for ``steps`` steps."""

    timesteps: list[int]
    alphas_cumprod: torch.Tensor  # float64, indexed by training timestep
    final_alpha: float
    prediction_type: str
    num_train_timesteps: int

    @classmethod
    def from_config(cls, config: Mapping, steps: int, prediction_type: str | None = None) -> "DDIMSchedule":
        from diffusers import DDIMScheduler

        if int(steps) < 1:
            raise InputError(f"steps must be at least 1; got {steps}")
        cfg = {k: v for k, v in dict(config).items() if not k.startswith("_")}
        sched = DDIMScheduler.from_config(cfg)
        n_train = int(sched.config.num_train_timesteps)
        if int(steps) > n_train:
            raise InputError(f"steps ({steps}) cannot exceed the scheduler's {n_train} training timesteps")
        sched.set_timesteps(int(steps))
        pt = prediction_type or sched.config.prediction_type
        if pt not in PREDICTION_TYPES:
            raise InputError(f"prediction_type must be one of {PREDICTION_TYPES}; got {pt!r}")
        return cls(timesteps=[int(t) for t in sched.timesteps], alphas_cumprod=sched.alphas_cumprod.double(),
                   final_alpha=float(sched.final_alpha_cumprod), prediction_type=pt, num_train_timesteps=n_train)

    @property
    def steps(self) -> int:
        return len(self.timesteps)

    def alpha(self, i: int) -> float:
        return float(self.alphas_cumprod[self.timesteps[i]])

    def alpha_prev(self, i: int) -> float:
        """ᾱ of the step after sampling step i (the final ᾱ after the last step)."""
        return self.alpha(i + 1) if i + 1 < self.steps else self.final_alpha

    def coefficients(self, i: int) -> tuple[float, float]:
        return step_coefficients(self.alpha(i), self.alpha_prev(i), self.prediction_type)

    def step(self, i: int, x_t: torch.Tensor, model_output: torch.Tensor) -> torch.Tensor:
        """Sampling step i: x at timesteps[i] -> x at the next (less noisy) level."""
        A, B = self.coefficients(i)
        return A * x_t + B * model_output

    def invert(self, i: int, x_prev: torch.Tensor, model_output: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`step` for a given model output: the x at timesteps[i]."""
        A, B = self.coefficients(i)
        return (x_prev - B * model_output) / A

    def training_target(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """What the model should output for x_t = √ᾱ x0 + √(1-ᾱ) ε (for fine-tuning)."""
        a = self.alphas_cumprod.to(x0.device)[t].to(x0.dtype).view(-1, *([1] * (x0.ndim - 1)))
        if self.prediction_type == "epsilon":
            return noise
        if self.prediction_type == "v_prediction":
            return a.sqrt() * noise - (1 - a).sqrt() * x0
        return x0

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        a = self.alphas_cumprod.to(x0.device)[t].to(x0.dtype).view(-1, *([1] * (x0.ndim - 1)))
        return a.sqrt() * x0 + (1 - a).sqrt() * noise
