"""A user's own ground imagery (``[visual] ground_image``): a picture laid flat under the pad.

The picture (PNG or JPEG, grey or RGB) is seen from above, row 0 its top edge. It is laid on the
ground at ``m_per_px`` metres per pixel, its top edge toward azimuth ``rotation_deg`` (from north,
clockwise), and a seed-drawn point of it under the pad; beyond its edges it repeats mirrored (the
picture, its left-right mirror, its up-down mirror and both, a periodic tile of twice its size),
so the ground never ends and no seam shows where copies meet. The tile's colours are the ground's
albedo under full light; the episode's sun sets the light level over the whole image, pad
included, as for the procedural families (a photograph carries its own shading).

A picture smaller than :data:`MIN_GROUND_IMAGE_M` across at the smallest m/px drawn, or than
:data:`MIN_GROUND_IMAGE_PX` pixels a side, is refused: its mirrored copies would fill the view.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from pathlib import Path

import numpy as np

from sitl_sim.errors import ConfigError
from sitl_sim.render.ground import GroundMap, luma
from sitl_sim.render.pads import read_image_rgb

__all__ = [
    "MAX_GROUND_IMAGE_PX",
    "MIN_GROUND_IMAGE_M",
    "MIN_GROUND_IMAGE_PX",
    "check_ground_image",
    "ground_image_map",
]

MIN_GROUND_IMAGE_M = 20.0
"""The least ground a picture must cover across its smaller side (m): five 4 m pads, and the
whole view of the 45 degree camera from 24 m up."""
MIN_GROUND_IMAGE_PX = 32
MAX_GROUND_IMAGE_PX = 4096

_TILES: OrderedDict[Path, tuple[np.ndarray, np.ndarray, tuple[int, int]]] = OrderedDict()
_CACHE_SIZE = 4


def _tile(path: Path, where: str) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """(mirrored tile rgb, its mono8, the picture's (rows, cols)), memoised (LRU) per file."""
    if path in _TILES:
        _TILES.move_to_end(path)
        return _TILES[path]
    rgb = read_image_rgb(path, where)
    rows, cols = rgb.shape[:2]
    if min(rows, cols) < MIN_GROUND_IMAGE_PX or max(rows, cols) > MAX_GROUND_IMAGE_PX:
        raise ConfigError(
            f"{where} = {str(path)!r}: {cols} x {rows} px; expected {MIN_GROUND_IMAGE_PX} to "
            f"{MAX_GROUND_IMAGE_PX} px a side"
        )
    top = np.concatenate([rgb, rgb[:, ::-1]], axis=1)
    tile = np.ascontiguousarray(np.concatenate([top, top[::-1]], axis=0))
    tile.setflags(write=False)
    mono = luma(tile)
    mono.setflags(write=False)
    _TILES[path] = (tile, mono, (rows, cols))
    if len(_TILES) > _CACHE_SIZE:
        _TILES.popitem(last=False)
    return _TILES[path]


def check_ground_image(path: Path, min_m_per_px: float, where: str) -> None:
    """Read ``path`` once (cached for the episodes) and check it covers enough ground.

    Raises:
        ConfigError: starting with ``where`` (the file and ``[visual] ground_image``): a missing
            or unreadable picture, one too small or too large in pixels, or one that covers
            less than :data:`MIN_GROUND_IMAGE_M` at ``min_m_per_px``.
    """
    _, _, (rows, cols) = _tile(path, where)
    covered = min(rows, cols) * min_m_per_px
    if covered < MIN_GROUND_IMAGE_M:
        raise ConfigError(
            f"{where} = {str(path)!r}: {cols} x {rows} px at {min_m_per_px:g} m/px covers "
            f"{covered:g} m across; expected >= {MIN_GROUND_IMAGE_M:g} m (a larger picture, "
            f"or ground_m_per_px >= {MIN_GROUND_IMAGE_M / min(rows, cols):.3g})"
        )


def ground_image_map(
    path: Path, m_per_px: float, anchor: tuple[float, float], rotation_deg: float
) -> GroundMap:
    """The ground of picture ``path`` at ``m_per_px``, its top edge toward ``rotation_deg`` and
    the point ``anchor`` (fractions of the mirrored tile across and down, in [0, 1)) on the
    origin. A periodic map (:attr:`GroundMap.tile_m` 0: the tile is rotated and need not be
    square)."""
    tile, mono, _ = _tile(Path(path), f"ground image {path}")
    rows, cols = tile.shape[:2]
    th = math.radians(rotation_deg)
    up = np.array([math.cos(th), math.sin(th)])  # the picture's top, (north, east)
    right = np.array([-math.sin(th), math.cos(th)])
    s = float(m_per_px)
    # texel centre (col, row) -> NE = corner + (col + .5) s right - (row + .5) s up
    corner = -(anchor[0] * cols * s * right - anchor[1] * rows * s * up)
    origin = corner + 0.5 * s * (right - up)
    texel_to_ne = np.array(
        [
            [s * right[0], -s * up[0], origin[0]],
            [s * right[1], -s * up[1], origin[1]],
            [0.0, 0.0, 1.0],
        ]
    )
    ground = GroundMap(
        rgb=tile,
        texel_to_ne=texel_to_ne,
        periodic=True,
        name=f"{Path(path).name}@{s:.3g}m/px",
        tile_m=0.0,
    )
    ground.__dict__["mono"] = mono  # the tile's mono8, computed once per picture
    return ground
