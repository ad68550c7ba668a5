"""render stage: differentiable Gaussian-splat rasterization (gsplat on CUDA, PyTorch elsewhere)."""

from .rasterize import RenderOutput, gsplat_available, rasterize

__all__ = ["RenderOutput", "gsplat_available", "rasterize"]
