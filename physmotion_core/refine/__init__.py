"""refine stage: colour + hard-depth refinement of lifted Gaussians (paper §3.2, DNGaussian)."""

from .losses import colour_loss, hard_depth_loss, patch_depth_loss, ssim
from .refine import RefineResult, RefineSettings, RefineView, build_views, prune_floaters, refine_gaussians

__all__ = ["RefineResult", "RefineSettings", "RefineView", "build_views", "colour_loss", "hard_depth_loss", "patch_depth_loss",
           "prune_floaters", "refine_gaussians", "ssim"]
