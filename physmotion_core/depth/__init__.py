"""depth stage: monocular depth from a user-supplied transformers model (never downloaded)."""

from .monocular import DepthMap, DepthModel, estimate_depth, load_depth_model

__all__ = ["DepthMap", "DepthModel", "estimate_depth", "load_depth_model"]
