"""lift stage: one image + mask → 3D Gaussians and the input camera.

``silhouette_lift`` needs no weights (the stand-in for LGM); a learned lift returns the same
``LiftResult``.
"""

from .silhouette import LiftResult, inflation_profile, silhouette_lift

__all__ = ["LiftResult", "inflation_profile", "silhouette_lift"]
