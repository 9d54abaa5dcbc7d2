"""The ground under the camera: a texture, where it lies, and the landing pad on it.

Both renderers read the same :class:`GroundMap` and :class:`PadGeometry`, which is what lets a
test hold them to the same image:

- :class:`sitl_sim.render.scene.Scene` (pybullet's TinyRenderer, the reference) textures its ground
  geometry with :attr:`GroundMap.rgb` and builds the pad from boxes;
- :class:`sitl_sim.render.render_fast.FastRenderer` warps the same texels onto the image with the
  ground plane's homography and paints the pad's two layers the same way.

A map's :attr:`~GroundMap.texel_to_ne` is the affine map from texel coordinates (column, row;
integer = texel centre, OpenCV's convention) to north/east metres on the ground. Texels are
sampled nearest-neighbour, as TinyRenderer does.

The nominal ground (no ``[visual]`` section) is the project's original texture on the original
600 m box: pybullet's box mesh maps its top face to the last quarter of the texture in u and v
(measured: texel column ``896 + n * 256/600``, row ``896 - e * 256/600``), so the nominal ground
shows 256 x 256 texels of 2.34 m — kept exactly, so the flights and the policy trained on them
see the world they always did. Procedural terrains (:mod:`sitl_sim.render.terrain`) are periodic
tiles
laid edge to edge over the whole ground, mapped texel for texel.
"""

from __future__ import annotations

import functools
import hashlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "GROUND_HALF_SIDE_M",
    "LUMA_Q8",
    "GroundMap",
    "PadGeometry",
    "PadLook",
    "PadTexture",
    "luma",
    "nominal_ground",
]

GROUND_HALF_SIDE_M = 300.0
"""Half the side of the square ground (m); the pad is at its centre."""

LUMA_Q8 = (77, 150, 29)
"""ITU-R BT.601 luma weights 0.299, 0.587, 0.114 in 1/256ths (colour to mono8)."""

_NOMINAL_TEXTURE_PX = 1024
_NOMINAL_SEED = 7


def luma(rgb: np.ndarray) -> np.ndarray:
    """mono8 of a uint8 RGB array (..., 3), rounded as the camera rounds."""
    c = rgb.astype(np.uint16)
    r, g, b = LUMA_Q8
    return ((r * c[..., 0] + g * c[..., 1] + b * c[..., 2] + 128) >> 8).astype(np.uint8)


@dataclass(frozen=True)
class PadGeometry:
    """The paper's landing target: a red cross on a green square, centred on the origin.

    The square's top is ``square_top_m`` above the ground and the cross's ``cross_top_m``
    (the boxes of the reference scene); both renderers draw each layer at its own height.
    """

    side_m: float = 4.0
    cross_length_m: float = 3.2
    cross_width_m: float = 0.6
    green_rgb: tuple[float, float, float] = (0.25, 0.85, 0.25)
    red_rgb: tuple[float, float, float] = (0.80, 0.08, 0.08)
    square_top_m: float = 0.02
    cross_top_m: float = 0.04

    def scaled(self, factor: float) -> PadGeometry:
        """The same pad ``factor`` times as large across (heights unchanged)."""
        return PadGeometry(
            side_m=self.side_m * factor,
            cross_length_m=self.cross_length_m * factor,
            cross_width_m=self.cross_width_m * factor,
            green_rgb=self.green_rgb,
            red_rgb=self.red_rgb,
            square_top_m=self.square_top_m,
            cross_top_m=self.cross_top_m,
        )

    def recoloured(self, gains) -> PadGeometry:
        """The same pad, the square's colour x ``gains[:3]`` and the cross's x ``gains[3:]``
        (each channel capped at 1)."""

        def jit(rgb, g):
            return tuple(float(min(1.0, c * k)) for c, k in zip(rgb, g, strict=True))

        return PadGeometry(
            side_m=self.side_m,
            cross_length_m=self.cross_length_m,
            cross_width_m=self.cross_width_m,
            green_rgb=jit(self.green_rgb, gains[:3]),
            red_rgb=jit(self.red_rgb, gains[3:]),
            square_top_m=self.square_top_m,
            cross_top_m=self.cross_top_m,
        )


@dataclass(frozen=True, eq=False)
class PadTexture:
    """A pad drawn from a picture (:meth:`sitl_sim.render.pads.PadDesign.scene_pad`): a flat
    textured rectangle of ``size_m`` (width across east, height across north) centred on the
    origin, its top ``top_m`` above the ground; texel row 0 is its north edge, column 0 its west
    edge. Equal when the pictures, sizes and heights are (renderers rebuild only on a change)."""

    rgb: np.ndarray = field(repr=False)
    size_m: tuple[float, float]
    name: str = "pad"
    top_m: float = 0.02

    @functools.cached_property
    def mono(self) -> np.ndarray:
        return luma(self.rgb)

    @functools.cached_property
    def digest(self) -> str:
        return _digest(self.rgb)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PadTexture):
            return NotImplemented
        return (self.size_m, self.top_m, self.rgb.shape, self.digest) == (
            other.size_m,
            other.top_m,
            other.rgb.shape,
            other.digest,
        )

    def __hash__(self) -> int:
        return hash((self.size_m, self.top_m, self.digest))

    @property
    def texel_to_ne(self) -> np.ndarray:
        """(3, 3) affine: texel (col, row, 1), integer = texel centre -> (north, east, 1)."""
        rows, cols = self.rgb.shape[:2]
        w, h = self.size_m
        se, sn = w / cols, h / rows
        return np.array(
            [[0.0, -sn, h / 2 - 0.5 * sn], [se, 0.0, -w / 2 + 0.5 * se], [0.0, 0.0, 1.0]]
        )

    def png(self) -> Path:
        """The picture as a PNG file (for pybullet), written once per content."""
        return _png(self.rgb, "pad")


PadLook = PadGeometry | PadTexture
"""What the renderers draw as the pad: its geometry (the paper's pad) or a picture."""


@dataclass(frozen=True, eq=False)
class GroundMap:
    """A ground texture and its placement.

    Attributes:
        rgb: (rows, cols, 3) uint8 texture, the ground's colour under full light.
        texel_to_ne: (3, 3) affine map, texel (col, row, 1) -> (north, east, 1) metres.
        periodic: the texture repeats edge to edge over the whole ground (a tile); otherwise it
            covers the ground once and nothing lies beyond it.
        name: what it is, for logs (e.g. ``"nominal"``, ``"mars_rocks#12"``).
        tile_m: the side of one tile in metres (periodic maps whose tile is an axis-aligned
            square: the terrain families); 0 for any other periodic map (a ground image's
            mirrored tile, rotated and of any shape).
    """

    rgb: np.ndarray
    texel_to_ne: np.ndarray
    periodic: bool
    name: str
    tile_m: float = 0.0

    @functools.cached_property
    def mono(self) -> np.ndarray:
        """The texture in mono8 (computed once)."""
        return luma(self.rgb)

    def png(self) -> Path:
        """The texture as a PNG file (for pybullet), written once per content."""
        return _png(self.rgb, "ground")


def _png(rgb: np.ndarray, kind: str) -> Path:
    from PIL import Image

    path = Path(tempfile.gettempdir()) / f"visland_{kind}_{_digest(rgb)}.png"
    if not path.exists():
        tmp = path.with_suffix(f".{os.getpid()}.tmp.png")
        Image.fromarray(np.ascontiguousarray(rgb), "RGB").save(tmp, compress_level=1)
        tmp.replace(path)  # atomic: parallel workers never read a half-written file
    return path


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()[:16]


@functools.cache
def nominal_ground() -> GroundMap:
    """The original ground: seed-7 value noise, reddish brown, on pybullet's box UVs (one
    object per process: renderers recognise it by identity)."""
    rgb = _nominal_texture(_NOMINAL_SEED, _NOMINAL_TEXTURE_PX)
    used = _NOMINAL_TEXTURE_PX // 4  # the box's top face spans the last quarter in u and v
    s = 2 * GROUND_HALF_SIDE_M / used  # metres per texel
    c = _NOMINAL_TEXTURE_PX - used / 2 - 0.5  # texel coordinate of the ground's centre
    texel_to_ne = np.array([[s, 0.0, -c * s], [0.0, -s, c * s], [0.0, 0.0, 1.0]])
    return GroundMap(rgb=rgb, texel_to_ne=texel_to_ne, periodic=False, name="nominal")


_NOMINAL_CACHE: dict[tuple[int, int], np.ndarray] = {}


def _nominal_texture(seed: int, size: int) -> np.ndarray:
    """A deterministic, terrain-like texture (multi-octave value noise) — the original ground."""
    key = (seed, size)
    if key not in _NOMINAL_CACHE:
        rng = np.random.default_rng(seed)
        f = np.zeros((size, size))
        for octave, weight in ((8, 1.0), (32, 0.6), (128, 0.35), (512, 0.2)):
            coarse = rng.random((octave, octave))
            reps = size // octave
            f += weight * np.kron(coarse, np.ones((reps, reps)))
        f = (f - f.min()) / (np.ptp(f) + 1e-9)
        # Dry, reddish-brown terrain (Mars-like): in mono8 always darker than the pad's green.
        base = np.array([100.0, 80.0, 65.0])
        rgb = base[None, None, :] * (0.6 + 0.8 * f[..., None])
        _NOMINAL_CACHE[key] = np.clip(rgb, 0, 255).astype(np.uint8)
    return _NOMINAL_CACHE[key]
