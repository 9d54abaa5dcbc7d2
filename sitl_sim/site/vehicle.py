"""The vehicle that carries the pad, as convex prisms in the pad frame.

The pad frame is x forward, y right, z down, its origin the centre of the surface the pad lies
on (the roof, the deck, the platform's top). A :class:`Solid` is a convex polygon in (x, y)
extruded from ``z_top`` down to ``z_bottom``; a vehicle is a tuple of them, sized from the pad:

- :func:`rover` — a flatbed whose top holds the pad with a margin, ``height`` above the ground,
  a cab standing on it ahead of the pad (a dark windscreen on its roof), four dark wheels;
- :func:`hull` — a ship: a deck (the pad aft, a pointed bow ahead) ``height`` above the water,
  its sides reaching 1 m below it, and a small deckhouse ahead of the pad;
- :func:`platform` — a block under a still pad raised ``height`` above the ground.

Both renderers draw these solids and the site's ray cast hits them (:meth:`Solid.ray`). Colours
are linear RGB in [0, 1] under full light.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sitl_sim.site.convex import clip_ray

__all__ = ["Solid", "hull", "platform", "rover"]


@dataclass(frozen=True, eq=False)
class Solid:
    """A convex prism: ``outline`` (k, 2) polygon in pad-frame (x, y), from ``z_top`` down to
    ``z_bottom`` (pad-frame z, down positive; ``z_top < z_bottom``); ``rgb`` its sides' colour,
    ``top_rgb`` its top's."""

    name: str
    outline: np.ndarray
    z_top: float
    z_bottom: float
    rgb: tuple[float, float, float]
    top_rgb: tuple[float, float, float]

    def faces(self) -> list[tuple[np.ndarray, np.ndarray, bool]]:
        """``(vertices (m, 3), outward normal (3,), is_top)`` of each face, in the pad frame
        (the top, the bottom, then one side per edge of the outline)."""
        pts = np.asarray(self.outline, dtype=float)
        top = np.column_stack([pts, np.full(len(pts), self.z_top)])
        bottom = np.column_stack([pts, np.full(len(pts), self.z_bottom)])
        out = [(top, np.array([0.0, 0.0, -1.0]), True), (bottom, np.array([0.0, 0.0, 1.0]), False)]
        for i, (nrm, _) in enumerate(self._edges()):
            j = (i + 1) % len(pts)
            out.append((np.array([top[i], bottom[i], bottom[j], top[j]]), nrm, False))
        return out

    def _edges(self) -> list[tuple[np.ndarray, float]]:
        """Per edge of the outline: its outward unit normal (3,) and ``normal . point``."""
        pts = np.asarray(self.outline, dtype=float)
        centre = pts.mean(axis=0)
        out = []
        for i in range(len(pts)):
            a, b = pts[i], pts[(i + 1) % len(pts)]
            nrm = np.array([b[1] - a[1], a[0] - b[0]]) / math.hypot(*(b - a))
            if float(nrm @ (0.5 * (a + b) - centre)) < 0.0:
                nrm = -nrm
            out.append((np.array([nrm[0], nrm[1], 0.0]), float(nrm @ a)))
        return out

    def planes(self) -> tuple[np.ndarray, np.ndarray]:
        """Half-spaces ``normals @ x <= offsets`` whose intersection is the solid."""
        edges = self._edges()
        normals = [n for n, _ in edges] + [np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.0])]
        offsets = [o for _, o in edges] + [-self.z_top, self.z_bottom]
        return np.array(normals), np.array(offsets)

    def ray(self, origin, direction) -> float:
        """Distance along ``direction`` (pad frame) from ``origin`` to the solid, inf if missed
        (0 from inside)."""
        normals, offsets = self.planes()
        num = offsets - normals @ np.asarray(origin, dtype=float)  # >= 0: inside that plane
        den = normals @ np.asarray(direction, dtype=float)
        return clip_ray(zip(num, den, strict=True))


def _rect(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


ROVER_RGB = (0.93, 0.72, 0.10)  # a yellow body
ROOF_RGB = (0.30, 0.30, 0.32)
WHEEL_RGB = (0.07, 0.07, 0.07)
GLASS_RGB = (0.10, 0.13, 0.16)
HULL_RGB = (0.90, 0.90, 0.88)
DECK_RGB = (0.34, 0.36, 0.40)
HOUSE_RGB = (0.85, 0.85, 0.83)


def rover(pad_length_m: float, pad_width_m: float, height_m: float) -> tuple[Solid, ...]:
    """A rover (a flatbed truck for a 4 m pad): a bed whose top (``height_m`` above the ground)
    holds the pad with a margin, a cab standing on the bed ahead of the pad with a dark
    windscreen on its roof, and four dark wheels under the bed, flush with its sides.

    Each solid stands on another or lies under it within its outline, so drawing them lowest
    first is right from any view above the ground (the fast renderer's painter's order)."""
    width = pad_width_m + 0.3
    cab = max(0.8, 0.35 * pad_length_m)
    rear = -(0.5 * pad_length_m + 0.15)
    cab_back = 0.5 * pad_length_m + 0.25
    front = cab_back + cab
    wheel_r = min(0.4 * height_m, 0.15 * (front - rear))
    body_bottom = height_m - max(0.6 * wheel_r, 0.05)
    wheel_w = max(0.15, 0.1 * width)
    bed = _rect(rear, front, -0.5 * width, 0.5 * width)
    cab_top = -min(0.45, 0.3 * height_m + 0.1)
    screen = _rect(front - 0.4 * cab, front - 0.05, -0.42 * width, 0.42 * width)
    solids = [
        Solid("body", bed, 0.0, body_bottom, ROVER_RGB, ROOF_RGB),
        Solid(
            "cab",
            _rect(cab_back, front, -0.5 * width, 0.5 * width),
            cab_top,
            0.0,
            ROVER_RGB,
            ROVER_RGB,
        ),
        Solid("windscreen", screen, cab_top - 0.01, cab_top, GLASS_RGB, GLASS_RGB),
    ]
    y_out = 0.5 * width - 0.01  # just inside the bed's side: the bed's face is in front
    for ax in (rear + 1.2 * wheel_r, front - 1.2 * wheel_r):
        for sy in (-1.0, 1.0):
            y0, y1 = sorted((sy * (y_out - wheel_w), sy * y_out))
            solids.append(
                Solid(
                    "wheel",
                    _rect(ax - wheel_r, ax + wheel_r, y0, y1),
                    height_m - 2 * wheel_r,
                    height_m,
                    WHEEL_RGB,
                    WHEEL_RGB,
                )
            )
    return tuple(solids)


def hull(pad_length_m: float, pad_width_m: float, height_m: float) -> tuple[Solid, ...]:
    """A ship whose deck (``height_m`` above the water) holds the pad aft, a bow ahead."""
    width = pad_width_m + 1.6
    stern = -(0.5 * pad_length_m + 0.8)
    shoulder = 0.5 * pad_length_m + 0.8 + 0.6 * pad_length_m + 1.0
    bow = shoulder + 0.8 * width
    outline = np.array(
        [
            [stern, -width / 2],
            [shoulder, -width / 2],
            [bow, 0.0],
            [shoulder, width / 2],
            [stern, width / 2],
        ]
    )
    house_x0 = 0.5 * pad_length_m + 0.6
    house = _rect(house_x0, house_x0 + 0.4 * pad_length_m + 0.8, -0.3 * width, 0.3 * width)
    return (
        Solid("hull", outline, 0.0, height_m + 1.0, HULL_RGB, DECK_RGB),
        Solid("deckhouse", house, -min(1.2, 0.5 + 0.2 * pad_length_m), 0.0, HOUSE_RGB, HOUSE_RGB),
    )


def platform(pad_length_m: float, pad_width_m: float, height_m: float) -> tuple[Solid, ...]:
    """A block under a still pad ``height_m`` above the ground."""
    x, y = 0.5 * pad_length_m + 0.15, 0.5 * pad_width_m + 0.15
    return (Solid("platform", _rect(-x, x, -y, y), 0.0, height_m, HOUSE_RGB, ROOF_RGB),)
