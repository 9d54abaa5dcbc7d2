"""The ``[terrain]`` scenario section and the drawn ground: slope, rolling relief, craters, rocks.

Keys (all optional; a key left out keeps its nominal value, flat and bare; spans ``[lo, hi]`` are
drawn uniformly per episode from the section's own generator ``(seed, episode,
TERRAIN_STREAM)``; the generated table: ``docs/config_keys.md``):

``slope_deg``         the ground at the pad tilted this much, uphill toward a random azimuth; a
                      plane through the origin, everywhere (the pad lies on it)
``relief_m``          RMS height of rolling ground (wavelengths 8-128 m) away from the pad: none
                      within a few metres of the pad's start, all of it beyond ~10 m more
``rocks_per_100m2``   rocks per 100 m^2, none on the pad (its start) nor within 0.5 m of it
``rock_height_m``     each rock's height, log-uniform within the span; 1.1-1.8 x as wide each
                      way (faceted stones: :mod:`sitl_sim.site.rocks`)
``craters_per_km2``   impact craters (bowl and raised rim, 1.5-10 m radius, a quarter of the
                      radius deep), none under the pad

Relief, craters and rocks lie within :data:`SITE_HALF_M` of the pad's start (what a camera sees of
a landing from 100 m), fading out over the last 10 m of it; beyond it the ground is the slope
plane. Heights are up-positive metres (NED down = -height). The relief and craters are a
heightfield sampled every :data:`GRID_M` (bilinear between nodes: the surface the renderers draw
and the ray cast hits); a rock is a convex faceted stone standing on the ground under its centre
(:class:`~sitl_sim.site.rocks.Rocks`). Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from companion.table import Section, amount, span
from sitl_sim.site.rocks import Rocks

__all__ = ["GRID_M", "SITE_HALF_M", "TERRAIN_STREAM", "Terrain", "TerrainConfig"]

TERRAIN_STREAM = 0x5349_5445  # "SITE"
SITE_HALF_M = 60.0
"""Relief, craters and rocks lie within +-60 m (north and east) of the pad's start."""
GRID_M = 1.0
"""Spacing of the relief and crater heightfield (m)."""
_FADE_M = 10.0
_CRATER_RADIUS_M = (1.5, 10.0)


@dataclass(frozen=True)
class TerrainConfig(Section):
    """The checked ``[terrain]`` section (units, defaults and ranges: the declarations)."""

    SECTION: ClassVar[str] = "terrain"

    slope_deg: tuple[float, float] = amount(
        unit="deg",
        hi=30.0,
        doc="the ground's tilt at the pad (a plane), uphill toward a random azimuth",
    )
    relief_m: tuple[float, float] = amount(
        unit="m", hi=5.0, doc="RMS height of rolling ground away from the pad"
    )
    rocks_per_100m2: tuple[float, float] = amount(
        unit="1/100m2", hi=20.0, doc="rocks per 100 m2 (none on the pad)"
    )
    rock_height_m: tuple[float, float] = span(
        (0.1, 0.4),
        unit="m",
        lo=0.0,
        lo_open=True,
        hi=2.0,
        doc="each rock's height, log-uniform in the span (1.1-1.8 x as wide each way)",
    )
    craters_per_km2: tuple[float, float] = amount(
        unit="1/km2", hi=20000.0, doc="impact craters per km2 (radius 1.5-10 m, none under the pad)"
    )

    def draw(self, seed: int, index: int, clear_radius_m: float) -> Terrain:
        """Episode ``index`` of ``seed``: a pure function of the three (and the pad's clear
        radius: no rock or crater within it of the origin, no relief either)."""
        rng = np.random.default_rng([int(seed), int(index), TERRAIN_STREAM])

        def u(rg: tuple[float, float]) -> float:
            return float(rg[0] + (rg[1] - rg[0]) * rng.random())

        slope = u(self.slope_deg)
        azimuth = float(rng.uniform(0.0, 360.0))
        relief = u(self.relief_m)
        rock_density = u(self.rocks_per_100m2)
        crater_density = u(self.craters_per_km2)
        area_m2 = (2 * SITE_HALF_M) ** 2
        n_nodes = round(2 * SITE_HALF_M / GRID_M) + 1
        grid = np.arange(n_nodes) * GRID_M - SITE_HALF_M
        nn, ee = np.meshgrid(grid, grid, indexing="ij")
        r = np.hypot(nn, ee)
        edge = SITE_HALF_M - np.maximum(np.abs(nn), np.abs(ee))
        inner = clear_radius_m + 2.0
        heights = relief * _rolling(rng, n_nodes) * _smooth((r - inner) / _FADE_M)
        craters = []
        for _ in range(int(rng.poisson(crater_density * area_m2 / 1e6))):
            radius = math.exp(rng.uniform(*np.log(_CRATER_RADIUS_M)))
            cn, ce = rng.uniform(-SITE_HALF_M, SITE_HALF_M, 2)
            if math.hypot(cn, ce) < clear_radius_m + 1.4 * radius:
                continue  # none under the pad
            d = np.hypot(nn - cn, ee - ce) / radius
            heights = heights + 0.25 * radius * _crater(d)
            craters.append((float(cn), float(ce), radius))
        heights = heights * _smooth(edge / _FADE_M)
        heights = heights if np.any(heights != 0.0) else None
        count = int(rng.poisson(rock_density * area_m2 / 100.0))
        lo, hi = self.rock_height_m
        h = np.exp(rng.uniform(math.log(lo), math.log(hi), count))
        pos = rng.uniform(-SITE_HALF_M, SITE_HALF_M, (count, 2))
        gradient = _gradient(slope, azimuth)
        rocks = Rocks.draw(
            rng, pos[:, 0], pos[:, 1], h, lambda n, e: _base_heights(gradient, heights, n, e)
        )
        keep = (np.hypot(pos[:, 0], pos[:, 1]) > clear_radius_m + 0.5 + rocks.extent) & (
            np.max(np.abs(pos), axis=1) < SITE_HALF_M - rocks.extent
        )
        return Terrain(
            slope_deg=slope,
            slope_azimuth_deg=azimuth,
            relief_m=relief,
            heights=heights,
            rocks=rocks.subset(keep),
            craters=tuple(craters),
            rocks_per_100m2=rock_density,
            craters_per_km2=crater_density,
        )


def _smooth(x: np.ndarray) -> np.ndarray:
    """0 below 0, 1 above 1, smoothstep between."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _crater(d: np.ndarray) -> np.ndarray:
    """A bowl (depth -1 at the centre) with a raised rim (+0.25 at d = 1) fading outside."""
    bowl = np.where(d < 1.0, d * d - 1.0, 0.0)
    return bowl + 0.25 * np.exp(-(((d - 1.0) / 0.25) ** 2))


def _rolling(rng: np.random.Generator, n: int) -> np.ndarray:
    """Unit-RMS rolling ground on an n x n grid of GRID_M: 1/f^3 noise, wavelengths 8-128 m."""
    size = 128
    fx = np.fft.fftfreq(size, GRID_M)[:, None]
    fy = np.fft.rfftfreq(size, GRID_M)[None, :]
    f = np.hypot(fx, fy)
    amp = np.where((f > 0) & (f <= 1.0 / 8.0), np.maximum(f, 1e-9) ** -1.5, 0.0)
    spec = (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape)) * amp
    field = np.fft.irfft2(spec, s=(size, size))
    field = (field - field.mean()) / (field.std() + 1e-12)
    return field[:n, :n]


def _gradient(slope_deg: float, azimuth_deg: float) -> tuple[float, float]:
    """(dh/dn, dh/de) of a plane tilted ``slope_deg`` uphill toward ``azimuth_deg``."""
    t = math.tan(math.radians(slope_deg))
    az = math.radians(azimuth_deg)
    return (t * math.cos(az), t * math.sin(az))


def _base_heights(gradient, heights: np.ndarray | None, n, e) -> np.ndarray:
    """Heights (up, m) of the slope plane plus the bilinear heightfield at arrays of points."""
    n = np.asarray(n, dtype=float)
    e = np.asarray(e, dtype=float)
    out = gradient[0] * n + gradient[1] * e
    if heights is None:
        return out
    m = heights.shape[0] - 1
    x = np.clip((n + SITE_HALF_M) / GRID_M, 0.0, m)
    y = np.clip((e + SITE_HALF_M) / GRID_M, 0.0, m)
    i = np.minimum(x.astype(int), m - 1)
    j = np.minimum(y.astype(int), m - 1)
    fx, fy = x - i, y - j
    h = heights
    rel = (h[i, j] * (1 - fx) + h[i + 1, j] * fx) * (1 - fy) + (
        h[i, j + 1] * (1 - fx) + h[i + 1, j + 1] * fx
    ) * fy
    return out + rel


class Terrain:
    """One episode's ground (see the module docstring); queries take north/east in metres."""

    def __init__(
        self,
        slope_deg: float,
        slope_azimuth_deg: float,
        relief_m: float,
        heights: np.ndarray | None,
        rocks: Rocks,
        craters: tuple[tuple[float, float, float], ...] = (),
        rocks_per_100m2: float = 0.0,
        craters_per_km2: float = 0.0,
    ) -> None:
        self.slope_deg = float(slope_deg)
        self.slope_azimuth_deg = float(slope_azimuth_deg)
        self.relief_m = float(relief_m)
        self.rocks_per_100m2 = float(rocks_per_100m2)
        self.craters_per_km2 = float(craters_per_km2)
        self.gradient = _gradient(self.slope_deg, self.slope_azimuth_deg)
        """The slope plane's (dh/dn, dh/de): height = gradient . (n, e)."""
        self.heights = heights
        """Relief + craters at the nodes (i, j) = (-L + i G, -L + j G) north, east; None: flat."""
        self.craters = craters
        self.rocks = rocks
        self._index_rocks()
        grid_slope = 0.0
        if heights is not None:
            gn = np.abs(np.diff(heights, axis=0)).max() / GRID_M
            ge = np.abs(np.diff(heights, axis=1)).max() / GRID_M
            grid_slope = math.hypot(gn, ge)
        self.max_gradient = math.hypot(*self.gradient) + grid_slope
        """A bound on |grad height| of the ground without rocks (the ray cast's step)."""

    # ------------------------------------------------------------------ the ground, rocks aside

    def base_heights(self, n, e) -> np.ndarray:
        """Heights (up, m) of the ground without rocks at arrays of points (bilinear relief)."""
        return _base_heights(self.gradient, self.heights, n, e)

    def ground(self, n: float, e: float) -> tuple[float, tuple[float, float]]:
        """Height and gradient ``(dh/dn, dh/de)`` of the ground without rocks at one point (what
        a rover's wheels follow)."""
        gn, ge = self.gradient
        base = gn * n + ge * e
        h = self.heights
        if h is None or abs(n) >= SITE_HALF_M or abs(e) >= SITE_HALF_M:
            return base, (gn, ge)
        x, y = (n + SITE_HALF_M) / GRID_M, (e + SITE_HALF_M) / GRID_M
        i, j = min(int(x), h.shape[0] - 2), min(int(y), h.shape[1] - 2)
        fx, fy = x - i, y - j
        h00, h10, h01, h11 = h[i, j], h[i + 1, j], h[i, j + 1], h[i + 1, j + 1]
        rel = (h00 * (1 - fx) + h10 * fx) * (1 - fy) + (h01 * (1 - fx) + h11 * fx) * fy
        dn = ((h10 - h00) * (1 - fy) + (h11 - h01) * fy) / GRID_M
        de = ((h01 - h00) * (1 - fx) + (h11 - h10) * fx) / GRID_M
        return base + float(rel), (gn + float(dn), ge + float(de))

    # ------------------------------------------------------------------ rocks

    def _index_rocks(self) -> None:
        """Rocks by cell of a square grid over the site, cells at least twice the largest
        extent: a point lies in a rock of the (at most) 2 x 2 cells within half a cell of it."""
        rocks = self.rocks
        self._cell = max(1.0, 2.0 * float(rocks.extent.max())) if len(rocks) else 1.0
        self._cells: dict[tuple[int, int], list[int]] = {}
        for k, (n, e) in enumerate(zip(rocks.north.tolist(), rocks.east.tolist(), strict=True)):
            key = (math.floor(n / self._cell), math.floor(e / self._cell))
            self._cells.setdefault(key, []).append(k)
        self._top = float(np.max(rocks.base + rocks.height)) if len(rocks) else -math.inf

    def _rocks_in(self, n0: float, e0: float, n1: float, e1: float) -> list[int]:
        """The rocks whose cell meets [n0, n1] x [e0, e1] grown by half a cell."""
        c = self._cell
        i0, i1 = math.floor((n0 - c / 2) / c), math.floor((n1 + c / 2) / c)
        j0, j1 = math.floor((e0 - c / 2) / c), math.floor((e1 + c / 2) / c)
        if (i1 - i0 + 1) * (j1 - j0 + 1) > len(self._cells):
            return [k for ks in self._cells.values() for k in ks]
        cells = self._cells
        return [
            k for i in range(i0, i1 + 1) for j in range(j0, j1 + 1) for k in cells.get((i, j), ())
        ]

    def rock_top(self, n: float, e: float) -> float:
        """The highest rock surface above (n, e) (up, m), or -inf where no rock is."""
        if not self._cells:
            return -math.inf
        return max((self.rocks.top(k, n, e) for k in self._rocks_in(n, e, n, e)), default=-math.inf)

    def height(self, n: float, e: float) -> float:
        """The ground's surface height (up, m) at (n, e): slope, relief, craters and rocks."""
        return max(self.ground(n, e)[0], self.rock_top(n, e))

    # ------------------------------------------------------------------ ray cast

    def ray(self, origin, direction, max_range: float) -> float:
        """Distance along the unit ``direction`` (NED) from ``origin`` (NED) to the ground or a
        rock, inf if none within ``max_range``."""
        o = [float(v) for v in origin]
        d = [float(v) for v in direction]
        s = self._march(o, d, max_range)
        return min(s, self._ray_rocks(o, d, min(s, max_range)))

    def _march(self, o, d, max_range: float) -> float:
        """The first hit of the ground without rocks: steps that cannot pass it (|grad h| is
        bounded by :attr:`max_gradient`)."""
        on, oe, od = o
        dn, de, dd = d
        rate = dd + self.max_gradient * math.hypot(dn, de)  # the fastest the gap can close
        s = 0.0
        for _ in range(20000):
            gap = -(od + s * dd) - self.ground(on + s * dn, oe + s * de)[0]
            if gap <= 1e-6:
                return s
            if rate <= 0.0 or s > max_range:
                return math.inf
            s += max(gap / rate, 1e-6)
        return math.inf

    def _ray_rocks(self, o, d, s_end: float) -> float:
        """The first entry into a rock before ``s_end``."""
        if not self._cells:
            return math.inf
        on, oe, od = o
        dn, de, dd = d
        # the part of the ray below the highest rock top
        s0 = 0.0 if dd <= 0.0 else max(0.0, (-self._top - od) / dd)
        s1 = s_end if math.isfinite(s_end) else s0 + 4.0 * self._cell
        if s1 < s0:
            return math.inf
        na, nb = on + s0 * dn, on + s1 * dn
        ea, eb = oe + s0 * de, oe + s1 * de
        near = self._rocks_in(min(na, nb), min(ea, eb), max(na, nb), max(ea, eb))
        best = min((self.rocks.ray(k, o, d) for k in near), default=math.inf)
        return best if best <= s_end else math.inf

    # ------------------------------------------------------------------ the log

    def record(self) -> dict[str, Any]:
        """What was drawn (for the episode's log)."""
        out: dict[str, Any] = {
            "slope_deg": self.slope_deg,
            "slope_azimuth_deg": self.slope_azimuth_deg,
            "relief_m": self.relief_m,
            "rocks_per_100m2": self.rocks_per_100m2,
            "rocks": len(self.rocks),
            "craters_per_km2": self.craters_per_km2,
            "craters": [list(c) for c in self.craters],
        }
        if len(self.rocks):
            heights = self.rocks.height
            out["rock_height_m"] = [float(heights.min()), float(heights.max())]
        return out
