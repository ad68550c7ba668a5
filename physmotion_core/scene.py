"""Multi-object scenes: several objects, each with its own material, in one simulation."""

from __future__ import annotations

import dataclasses
from typing import Sequence, Union

import torch

from .errors import InputError
from .types.gaussians import Gaussians
from .types.material import Material

MaterialSpec = Union[Material, Sequence[Material]]


def _materials(spec: MaterialSpec, n_objects: int, what: str) -> list[Material]:
    mats = list(spec) if isinstance(spec, (list, tuple)) else [spec]
    if len(mats) == 1 and n_objects > 1:
        mats = mats * n_objects
    if len(mats) != n_objects:
        raise InputError(f"{what} has {n_objects} objects but {len(mats)} materials")
    return mats


def _ids(g: Gaussians) -> torch.Tensor:
    return g.object_ids if g.object_ids is not None else torch.zeros(len(g), dtype=torch.int64, device=g.device)


def combine_objects(g_a: Gaussians, mat_a: MaterialSpec, g_b: Gaussians, mat_b: MaterialSpec,
                    offset: Sequence[float] = (0.0, 0.0, 0.0)) -> tuple[Gaussians, list[Material]]:
    """Scene a plus scene b (moved by ``offset`` metres): b's objects are numbered after a's."""
    ids_a, ids_b = _ids(g_a), _ids(g_b)
    n_a = int(ids_a.max()) + 1 if len(g_a) else 0
    n_b = int(ids_b.max()) + 1 if len(g_b) else 0
    mats = _materials(mat_a, n_a, "the first scene") + _materials(mat_b, n_b, "the added object")
    moved = dataclasses.replace(g_b, means=g_b.means + torch.as_tensor(offset, dtype=g_b.means.dtype,
                                                                       device=g_b.device))
    a = dataclasses.replace(g_a, object_ids=ids_a)
    b = dataclasses.replace(moved, object_ids=ids_b + n_a)
    return Gaussians.cat([a, b]), mats
