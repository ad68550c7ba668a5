"""Checks shared by the data types: a vector of three finite numbers."""

from __future__ import annotations

import math


from ..errors import InputError

Vec3 = tuple[float, float, float]

def as_vec3(value, name: str) -> Vec3:
    try:
        v = tuple(float(x) for x in value)
    except TypeError as exc:
        raise InputError(f"{name} must be three numbers (x, y, z); got {value!r}") from exc
    if len(v) != 3:
        raise InputError(f"{name} must be three numbers (x, y, z); got {len(v)} values: {value!r}")
    if not all(math.isfinite(x) for x in v):
        raise InputError(f"{name} must be finite; got {v}. Replace NaN/Inf with a real value.")
    return v  # type: ignore[return-value]
