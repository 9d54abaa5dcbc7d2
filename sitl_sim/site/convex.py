"""The ray cast both convex solids of a site share (rocks, the carrying vehicle's prisms)."""

from __future__ import annotations

import math
from collections.abc import Iterable

__all__ = ["clip_ray"]


def clip_ray(
    planes: Iterable[tuple[float, float]], t_in: float = 0.0, t_out: float = math.inf
) -> float:
    """Cyrus-Beck: the distance along a ray to where it enters the intersection of half-spaces
    ``n . x <= offset``, inf if it misses (``t_in`` from inside). ``planes`` gives per plane
    ``(offset - n . origin, n . direction)``; ``[t_in, t_out]`` is the part of the ray already
    admitted (by a base plane, say)."""
    for num, den in planes:
        if abs(den) < 1e-12:
            if num < 0.0:
                return math.inf
            continue
        t = num / den
        if den < 0.0:
            t_in = max(t_in, t)
        else:
            t_out = min(t_out, t)
        if t_in > t_out:
            return math.inf
    return t_in
