"""lift stage: one image + mask → 3D Gaussians and the input camera.

``silhouette_lift`` needs no weights (the stand-in for LGM); ``learned_lift`` (ImageDream + LGM,
``learned.py``, ``lgm.py``, ``imagedream.py``) returns the same ``LiftResult`` plus the generated
views. The learned modules import torch-heavy code only when used.
"""

from .silhouette import LiftResult, inflation_profile, silhouette_lift

__all__ = ["LiftResult", "inflation_profile", "silhouette_lift", "learned_lift", "load_lgm", "load_imagedream"]


def __getattr__(name):
    if name == "learned_lift":
        from .learned import learned_lift

        return learned_lift
    if name == "load_lgm":
        from .lgm import load_lgm

        return load_lgm
    if name == "load_imagedream":
        from .imagedream import load_imagedream

        return load_imagedream
    raise AttributeError(name)
