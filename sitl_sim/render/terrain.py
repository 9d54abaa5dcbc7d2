"""Procedural ground families: periodic tiles of albedo and relief, lit by the episode's sun.

A terrain is drawn from ``(family, texture_seed)`` alone — the same seed is the same ground in
every process — as a square tile of :data:`TILE_PX` texels of :data:`TEXEL_M` metres (81.92 m)
that repeats edge to edge over the whole ground: a texture built by spectral synthesis (white
noise shaped by a power law in the Fourier domain) is periodic by construction, and features
placed on it (rocks, craters, patches) wrap around its edges. The tile's corner lies at a
seed-drawn offset, so no tile edge is tied to the pad.

Relief (a height field in metres) is lit by the sun and baked into the texture, the way a
renderer with a directional light and shadow maps would show it from above: Lambert shading
relative to flat ground (slopes toward the sun brighter, away darker) and cast shadows (a texel
is in shadow when the relief toward the sun rises above the sun's ray). The flat-ground light
level itself (``ambient + diffuse * sin(elevation)``) is applied by the renderer to the whole
image, pad included. Families:

``regolith``    reddish-brown dust and sand, gentle undulation (the nominal ground's colours)
``mars_rocks``  regolith with impact craters (bowl + raised rim) and scattered dark rocks
``sand``        pale sand with wind ripples and dune swell
``grass``       mottled green turf with darker clumps and dry patches (close to the pad's green)
``asphalt``     dark grey fine-grained asphalt with repair patches and cracks
``gravel``      grey-brown gravel: dense small stones
``water``       the sea: dark blue-grey, wind waves and swell catching the light, flecks of foam
                (a ship's deck, ``[pad] motion = "deck"``, floats on it)

Any family but water can carry **painted markings** (``terrain_map(..., markings=True)``;
``[visual] markings``): what people paint on the ground near a landing site — rows and lots of
parking bays, dashed and solid lane lines, outlined rectangles — white or yellow, worn, flat (lit
like the ground under them), drawn from the texture seed on a stream of their own, wrapping
around the tile like every other feature. They are the straight bright edges a CNN that has
only seen natural ground can take for a pad.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable

import cv2
import numpy as np

from sitl_sim.render.ground import GroundMap

__all__ = ["FAMILIES", "MARKED_FAMILIES", "TEXEL_M", "TILE_PX", "Sun", "terrain_map"]

TILE_PX = 1024
TEXEL_M = 0.08
MARKINGS_STREAM = 0x4D41_524B  # "MARK": the painted markings' entropy, apart from the ground's
TERRAIN_STREAM = 0x5445_5252  # "TERR": the terrain generator's entropy, apart from every other
AMBIENT = 0.45
"""Share of the light that does not come from the sun's direction (sky, scattered dust)."""
DIFFUSE = 1.0 - AMBIENT


class Sun:
    """The sun's direction: elevation above the horizon and azimuth (from north, clockwise)."""

    __slots__ = ("azimuth_deg", "elevation_deg")

    def __init__(self, elevation_deg: float, azimuth_deg: float) -> None:
        self.elevation_deg = float(elevation_deg)
        self.azimuth_deg = float(azimuth_deg)

    @property
    def toward_ned(self) -> np.ndarray:
        """Unit vector from the ground toward the sun (NED)."""
        el, az = math.radians(self.elevation_deg), math.radians(self.azimuth_deg)
        return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), -math.sin(el)])

    @property
    def flat_light(self) -> float:
        """Light on flat ground relative to the sun at the zenith (1.0)."""
        return AMBIENT + DIFFUSE * max(0.0, math.sin(math.radians(self.elevation_deg)))


# --------------------------------------------------------------------------- building blocks


def _spectral(rng: np.random.Generator, n: int, beta: float, lo_m: float = 0.0) -> np.ndarray:
    """Periodic noise with power spectrum ~ 1/f^beta, zero mean, unit std. ``lo_m``: drop
    wavelengths longer than this (0: keep all)."""
    fx = np.fft.fftfreq(n)[:, None]
    fy = np.fft.rfftfreq(n)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2)
    amp[0, 0] = 0.0
    if lo_m > 0.0:
        amp[f < TEXEL_M / lo_m] = 0.0
    spec = (rng.standard_normal(amp.shape) + 1j * rng.standard_normal(amp.shape)) * amp
    field = np.fft.irfft2(spec, s=(n, n))
    return (field - field.mean()) / (field.std() + 1e-12)


def _stamp(target: np.ndarray, r: float, c: float, radius_px: float, profile, value) -> None:
    """Add ``value * profile(d / radius)`` (d = distance in texels) around (r, c), wrapping."""
    n = target.shape[0]
    k = math.ceil(radius_px) + 1
    rows = np.arange(int(r) - k, int(r) + k + 1)
    cols = np.arange(int(c) - k, int(c) + k + 1)
    d = np.hypot(rows[:, None] - r, cols[None, :] - c) / radius_px
    target[np.ix_(rows % n, cols % n)] += value * profile(d)


def _dome(d: np.ndarray) -> np.ndarray:
    return np.sqrt(np.clip(1.0 - d * d, 0.0, None))


def _disc(d: np.ndarray) -> np.ndarray:
    return (d < 1.0).astype(float)


def _crater(d: np.ndarray) -> np.ndarray:
    """A bowl (depth -1 at the centre) with a raised rim (+0.25 at r = 1) fading outside."""
    bowl = np.where(d < 1.0, d * d - 1.0, 0.0)
    rim = 0.25 * np.exp(-(((d - 1.0) / 0.25) ** 2))
    return bowl + rim


def _rocks(rng, height, albedo, count, r_lo_m, r_hi_m, shade) -> None:
    """Scatter ``count`` rocks (domes ~0.6 x radius high) of radius in [r_lo, r_hi] m."""
    n = height.shape[0]
    radii = np.exp(rng.uniform(math.log(r_lo_m), math.log(r_hi_m), count)) / TEXEL_M
    centres = rng.uniform(0, n, (count, 2))
    tones = rng.uniform(*shade, count)
    for (r, c), rad, tone in zip(centres, radii, tones, strict=True):
        _stamp(height, r, c, rad, _dome, 0.6 * rad * TEXEL_M)
        _stamp(albedo, r, c, rad, _disc, tone)


def _cracks(rng, albedo, count, depth) -> None:
    """Dark random-walk lines (asphalt cracks), one texel wide, wrapping."""
    n = albedo.shape[0]
    for _ in range(count):
        r, c = rng.uniform(0, n, 2)
        heading = rng.uniform(0, 2 * math.pi)
        for _ in range(int(rng.integers(80, 400))):
            heading += rng.normal(0.0, 0.25)
            r, c = r + math.sin(heading), c + math.cos(heading)
            albedo[int(r) % n, int(c) % n] -= depth


# --------------------------------------------------------------------------- families
# Each returns (albedo_rgb (n, n, 3) float in 0..255, height (n, n) metres).


def _regolith(rng: np.random.Generator, n: int):
    tone = 0.8 + 0.12 * _spectral(rng, n, 2.6) + 0.06 * _spectral(rng, n, 1.2)
    base = np.array([128.0, 92.0, 68.0])
    height = 0.35 * _spectral(rng, n, 3.2)
    return base * tone[..., None], height


def _mars_rocks(rng: np.random.Generator, n: int):
    albedo_rgb, height = _regolith(rng, n)
    tone = np.zeros((n, n))
    for _ in range(int(rng.integers(6, 14))):  # craters 1.5-9 m across
        radius = math.exp(rng.uniform(math.log(0.75), math.log(4.5))) / TEXEL_M
        r, c = rng.uniform(0, n, 2)
        _stamp(height, r, c, radius, _crater, 0.25 * radius * TEXEL_M)
        _stamp(tone, r, c, 1.6 * radius, lambda d: np.exp(-d * d), 0.08)  # bright ejecta
    _rocks(rng, height, tone, int(rng.integers(500, 1100)), 0.06, 0.5, (-0.35, -0.15))
    return albedo_rgb * (1.0 + tone)[..., None], height


def _sand(rng: np.random.Generator, n: int):
    wavelength_px = rng.uniform(0.5, 1.2) / TEXEL_M
    # an integer number of ripples per tile along a direction that tiles: (kx, ky) integers
    kx, ky = (int(v) for v in rng.integers(1, 4, 2))
    waves = max(1, round(n / wavelength_px / math.hypot(kx, ky)))  # whole ripples per tile
    rows, cols = np.mgrid[0:n, 0:n] / n
    phase = 2 * math.pi * waves * (kx * cols + ky * rows) + 1.2 * _spectral(rng, n, 3.0)
    height = 0.025 * np.sin(phase) + 0.5 * _spectral(rng, n, 3.4)
    tone = 0.92 + 0.04 * _spectral(rng, n, 1.6)
    return np.array([206.0, 184.0, 142.0]) * tone[..., None], height


def _grass(rng: np.random.Generator, n: int):
    patch = _spectral(rng, n, 2.8)
    blade = _spectral(rng, n, 0.4)
    tone = 0.85 + 0.12 * patch + 0.10 * blade
    green = np.array([62.0, 112.0, 38.0])
    dry = np.array([140.0, 128.0, 74.0])
    dryness = np.clip(0.6 * _spectral(rng, n, 3.0) - 0.4, 0.0, 1.0)[..., None]
    rgb = (green * (1 - dryness) + dry * dryness) * tone[..., None]
    height = 0.04 * blade + 0.2 * _spectral(rng, n, 3.2)
    return rgb, height


def _asphalt(rng: np.random.Generator, n: int):
    tone = 1.0 + 0.10 * _spectral(rng, n, 0.2) + 0.05 * _spectral(rng, n, 2.4)
    patches = np.zeros((n, n))
    for _ in range(int(rng.integers(4, 10))):
        r0, c0 = (int(v) for v in rng.integers(0, n, 2))
        h, w = (int(v) for v in rng.integers(20, 150, 2))
        rows, cols = np.arange(r0, r0 + h) % n, np.arange(c0, c0 + w) % n
        patches[np.ix_(rows, cols)] = rng.uniform(-0.15, 0.12)
    _cracks(rng, patches, int(rng.integers(10, 30)), 0.35)
    rgb = np.array([74.0, 74.0, 78.0]) * (tone + patches)[..., None]
    return rgb, 0.01 * _spectral(rng, n, 1.0)


def _gravel(rng: np.random.Generator, n: int):
    height = 0.05 * _spectral(rng, n, 3.0)
    tone = 0.06 * _spectral(rng, n, 2.0)
    _rocks(rng, height, tone, int(rng.integers(4000, 6000)), 0.05, 0.14, (-0.25, 0.25))
    return np.array([132.0, 122.0, 108.0]) * (1.0 + tone)[..., None], height


def _water(rng: np.random.Generator, n: int):
    # wave trains about a wind direction (whole waves per tile: it stays periodic), 4-14 m long,
    # steep enough for the sun to pick out their faces, on a fine chop; foam on the highest crests
    rows, cols = np.mgrid[0:n, 0:n] / n
    wind = rng.uniform(0.0, 2 * math.pi)
    height = 0.03 * _spectral(rng, n, 2.0)
    for _ in range(7):
        heading = wind + rng.normal(0.0, 0.35)
        waves = rng.uniform(n * TEXEL_M / 14.0, n * TEXEL_M / 4.0)  # per tile
        kx, ky = round(waves * math.cos(heading)), round(waves * math.sin(heading))
        length = n * TEXEL_M / max(math.hypot(kx, ky), 1.0)
        phase = 2 * math.pi * (kx * cols + ky * rows) + rng.uniform(0.0, 2 * math.pi)
        height += 0.09 * length / (2 * math.pi) * rng.uniform(0.4, 1.0) * np.sin(phase)
    crest = (height - height.mean()) / (height.std() + 1e-12)
    foam = np.clip(crest - 2.0, 0.0, None) * np.clip(_spectral(rng, n, 2.4) - 0.3, 0.0, 1.0)
    tone = 0.95 + 0.05 * _spectral(rng, n, 2.5)
    rgb = np.array([30.0, 55.0, 70.0]) * tone[..., None]
    rgb = rgb + np.clip(foam, 0.0, 0.8)[..., None] * (np.array([215.0, 222.0, 226.0]) - rgb)
    return rgb, height


FAMILIES: dict[str, Callable[[np.random.Generator, int], tuple[np.ndarray, np.ndarray]]] = {
    "regolith": _regolith,
    "mars_rocks": _mars_rocks,
    "sand": _sand,
    "grass": _grass,
    "asphalt": _asphalt,
    "gravel": _gravel,
    "water": _water,
}
"""The named ground families of ``[visual] terrain``."""

MARKED_FAMILIES = tuple(f for f in FAMILIES if f != "water")
"""The families that can carry painted markings (no paint on the sea)."""

_PAINTS = (np.array([228.0, 228.0, 222.0]), np.array([222.0, 184.0, 58.0]))  # white, yellow


def _bays(bays: int, width: float, depth: float, at: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """A row of ``bays`` parking bays ``width`` wide along x at ``y = at``: the line along the
    row and the stall lines ``depth`` long (negative: the other way)."""
    segs = [(np.array([0.0, at]), np.array([bays * width, at]))]
    segs += [
        (np.array([k * width, at]), np.array([k * width, at + depth])) for k in range(bays + 1)
    ]
    return segs


def _segments(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """One marking's line segments (start, end in metres, line width in metres) about the
    origin: a row of parking bays, a lot (double rows of them), a dashed lane line, a solid (or
    double) line or an outlined rectangle, at a random heading."""
    kind = int(rng.choice(5, p=(0.25, 0.25, 0.2, 0.15, 0.15)))
    w = float(rng.uniform(0.10, 0.20))
    segs: list[tuple[np.ndarray, np.ndarray]] = []
    if kind == 0:  # a row of bays: a line along the row, a stall line every 2.3-3.2 m
        bays, width, depth = int(rng.integers(3, 16)), rng.uniform(2.3, 3.2), rng.uniform(4.5, 5.5)
        segs += _bays(bays, width, depth, 0.0)
    elif kind == 4:  # a lot: double rows of bays back to back, 6-8 m aisles between them
        bays, width, depth = int(rng.integers(6, 14)), rng.uniform(2.3, 3.2), rng.uniform(4.5, 5.5)
        aisle = rng.uniform(6.0, 8.0)
        for k in range(int(rng.integers(2, 5))):
            base = k * (2 * depth + aisle)
            segs += _bays(bays, width, depth, base) + _bays(bays, width, -depth, base + 2 * depth)
    elif kind == 1:  # a dashed lane line
        dash, gap = rng.uniform(1.5, 3.5), rng.uniform(2.0, 6.0)
        for k in range(int(rng.integers(4, 12))):
            a = k * (dash + gap)
            segs.append((np.array([a, 0.0]), np.array([a + dash, 0.0])))
    elif kind == 2:  # a solid line, sometimes doubled
        length = rng.uniform(10.0, 60.0)
        segs.append((np.array([0.0, 0.0]), np.array([length, 0.0])))
        if rng.random() < 0.4:
            segs.append((np.array([0.0, 3 * w]), np.array([length, 3 * w])))
    else:  # an outlined rectangle (a marked area, a loading box)
        a, b = rng.uniform(2.0, 10.0, 2)
        corners = [np.array(c) for c in ((0.0, 0.0), (a, 0.0), (a, b), (0.0, b))]
        segs += [(corners[k], corners[(k + 1) % 4]) for k in range(4)]
    heading = rng.uniform(0.0, 2 * math.pi)
    c, s = math.cos(heading), math.sin(heading)
    rot = np.array([[c, -s], [s, c]])
    return [(rot @ p, rot @ q, w) for p, q in segs]


def _markings(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(cover in [0, 1], paint premultiplied by its cover) over an ``n`` x ``n`` tile: 6-18
    markings, each drawn at its place and at its copies one tile away so that it wraps; worn
    (cover < 1, patchy). The marked albedo is ``albedo (1 - cover) + paint``."""
    cover = np.zeros((n, n))
    paint = np.zeros((n, n, 3))
    shift = 4  # cv2's fixed-point sub-texel coordinates
    for _ in range(int(rng.integers(6, 19))):
        mark = np.zeros((n, n), np.float32)
        at = rng.uniform(0.0, n * TEXEL_M, 2)
        for p, q, w in _segments(rng):
            thick = max(1, round(w / TEXEL_M))
            for dr in (-n, 0, n):
                for dc in (-n, 0, n):
                    a = (p + at) / TEXEL_M + (dc, dr)
                    b = (q + at) / TEXEL_M + (dc, dr)
                    cv2.line(
                        mark,
                        tuple(int(v * 2**shift) for v in a),
                        tuple(int(v * 2**shift) for v in b),
                        1.0,
                        thick,
                        cv2.LINE_AA,
                        shift,
                    )
        mark = np.clip(mark, 0.0, 1.0) * rng.uniform(0.55, 0.95)
        colour = _PAINTS[int(rng.random() < 0.3)] * rng.uniform(0.85, 1.05)
        paint += (mark * (1.0 - cover))[..., None] * colour  # earlier paint stays on top
        cover += mark * (1.0 - cover)
    wear = np.clip(1.0 - 0.5 * np.clip(_spectral(rng, n, 2.6), 0.0, None), 0.3, 1.0)
    return cover * wear, paint * wear[..., None]


# --------------------------------------------------------------------------- lighting


def _lit(albedo_rgb: np.ndarray, height: np.ndarray, sun: Sun) -> np.ndarray:
    """Albedo x (Lambert shade and cast shadow, relative to flat ground under this sun)."""
    s = sun.toward_ned
    # slopes: columns run north, rows run west (terrain_map's texel layout)
    dh_dn = (np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)) / (2 * TEXEL_M)
    dh_de = -(np.roll(height, -1, axis=0) - np.roll(height, 1, axis=0)) / (2 * TEXEL_M)
    # the surface z_up = h(n, e): normal (NED) ~ (dh_dn, dh_de, -1) normalised
    norm = np.sqrt(dh_dn * dh_dn + dh_de * dh_de + 1.0)
    cos_inc = np.clip((dh_dn * s[0] + dh_de * s[1] - s[2]) / norm, 0.0, None)
    flat = sun.flat_light
    shade = (AMBIENT + DIFFUSE * cos_inc) / flat
    shadow = _cast_shadow(height, sun)
    shade = np.where(shadow, AMBIENT / flat, shade)
    return np.clip(albedo_rgb * shade[..., None], 0.0, 255.0)


def _cast_shadow(height: np.ndarray, sun: Sun) -> np.ndarray:
    """Texels whose line toward the sun passes below the relief (periodic ray march)."""
    el = math.radians(sun.elevation_deg)
    if el >= math.radians(89.0):
        return np.zeros(height.shape, dtype=bool)
    az = math.radians(sun.azimuth_deg)
    # one-texel steps toward the sun: +north is +column, +east is -row
    dc, dr = math.cos(az), -math.sin(az)
    rise_per_step = TEXEL_M * math.tan(el)
    relief = float(np.ptp(height))
    steps = int(min(96, math.ceil(relief / max(rise_per_step, 1e-6)))) if relief > 0 else 0
    shadow = np.zeros(height.shape, dtype=bool)
    for k in range(1, steps + 1):
        shifted = np.roll(height, (-round(k * dr), -round(k * dc)), axis=(0, 1))
        shadow |= shifted > height + k * rise_per_step
    return shadow


# --------------------------------------------------------------------------- maps

_RELIEF_CACHE: OrderedDict[tuple[str, int, bool], tuple[np.ndarray, np.ndarray, np.ndarray]] = (
    OrderedDict()
)
_CACHE_SIZE = 8


def _relief(
    family: str, texture_seed: int, markings: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(albedo, height, tile offset) of a family and seed, painted when ``markings``, memoised
    (LRU) per process."""
    key = (family, int(texture_seed), bool(markings))
    if key in _RELIEF_CACHE:
        _RELIEF_CACHE.move_to_end(key)
        return _RELIEF_CACHE[key]
    if markings:
        if family not in MARKED_FAMILIES:
            raise ValueError(f"markings on {family!r}; expected one of {list(MARKED_FAMILIES)}")
        albedo, height, offset = _relief(family, texture_seed)
        rng = np.random.default_rng([int(texture_seed), MARKINGS_STREAM, _family_index(family)])
        cover, paint = _markings(rng, TILE_PX)
        albedo = albedo * (1.0 - cover)[..., None] + paint
    else:
        rng = np.random.default_rng([int(texture_seed), TERRAIN_STREAM, _family_index(family)])
        albedo, height = FAMILIES[family](rng, TILE_PX)
        offset = rng.uniform(0.0, TILE_PX * TEXEL_M, 2)
    _RELIEF_CACHE[key] = (albedo, height, offset)
    if len(_RELIEF_CACHE) > _CACHE_SIZE:
        _RELIEF_CACHE.popitem(last=False)
    return _RELIEF_CACHE[key]


def _family_index(family: str) -> int:
    if family not in FAMILIES:
        raise ValueError(f"terrain family {family!r}; expected one of {sorted(FAMILIES)}")
    return sorted(FAMILIES).index(family)


def terrain_map(family: str, texture_seed: int, sun: Sun, markings: bool = False) -> GroundMap:
    """The periodic ground of ``family`` drawn from ``texture_seed``, lit by ``sun``; with
    ``markings``, the same ground with paint on it (:data:`MARKED_FAMILIES`).

    Texel columns run north, rows run west (pybullet's uv directions); texel (0, 0)'s corner
    sits at the seed's tile offset.
    """
    albedo, height, (n0, e0) = _relief(family, texture_seed, markings)
    rgb = np.rint(_lit(albedo, height, sun)).astype(np.uint8)
    s = TEXEL_M
    # texel centre (col, row) -> north = n0 + (col + 0.5) s, east = e0 - (row + 0.5) s
    texel_to_ne = np.array([[s, 0.0, n0 + 0.5 * s], [0.0, -s, e0 - 0.5 * s], [0.0, 0.0, 1.0]])
    return GroundMap(
        rgb=rgb,
        texel_to_ne=texel_to_ne,
        periodic=True,
        name=f"{family}#{int(texture_seed)}{'+markings' if markings else ''}",
        tile_m=TILE_PX * s,
    )
