"""Pad designs: the landing pad as printed, seen from above, read from ``configs/pads/NAME.toml``.

A pad file gives the whole printed pad's size and either one of the built-in procedural
patterns or an image (path relative to the pad file)::

    name = "helipad_1m"
    size_m = [1.0, 1.0]          # width across east, height across north (metres)
    pattern = "helipad"          # "paper", "helipad" or "quadrant" ...
    # image = "my_pad.png"       # ... or an RGB / grey PNG or JPEG, row 0 = the pad's north edge

Patterns (drawn in fractions of the pad, so they scale with ``size_m``; colours as printed,
matte, in 8-bit sRGB):

``paper``     the paper's target: a red cross (arms 0.8 and 0.15 of the side) on a green square,
              the colours of :class:`~sitl_sim.render.ground.PadGeometry`
``helipad``   a white H in a white ring on a dark square
``quadrant``  black and white quadrants (north-west and south-east white): a high-contrast target
              that keeps its edges under a low sun

:data:`DEFAULT_PAD` (``paper``, 4 m) is the pad every scenario without a ``[pad]`` section flies;
the renderers keep drawing it from :class:`~sitl_sim.render.ground.PadGeometry`'s boxes, so the
nominal images are unchanged. Any other design is drawn as a textured layer of its true size
(:meth:`PadDesign.scene_pad`).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sitl_sim.errors import ConfigError
from sitl_sim.render.ground import PadGeometry, PadLook, PadTexture, luma

__all__ = [
    "ACQUIRE_PX",
    "DEFAULT_PAD",
    "PADS_DIR",
    "PATTERNS",
    "REFERENCE",
    "START_FRACTION",
    "PadDesign",
    "acquire_altitude_m",
    "builtin_pad_paths",
    "default_pad",
    "fill_altitude_m",
    "find_file",
    "load_pad",
    "pad_width_px",
    "read_image_rgb",
    "start_altitudes_m",
]

DEFAULT_PAD = "paper"
REPO_DIR = Path(__file__).resolve().parent.parent.parent
PADS_DIR = REPO_DIR / "configs" / "pads"
"""Where the shipped pad files live (``configs/pads``)."""

PAPER_SIDE_M = 4.0
_KEYS = ("name", "size_m", "pattern", "image")
_MAX_IMAGE_PX = 8192
_PATTERN_TEXEL_M = 0.01  # a procedural pad's texture in the renderers: 1 cm texels

_GREEN = tuple(int(c * 255.0) for c in PadGeometry().green_rgb)  # as TinyRenderer truncates
_RED = tuple(int(c * 255.0) for c in PadGeometry().red_rgb)
_WHITE = (232, 232, 226)  # matte white paint / paper
_DARK = (38, 40, 44)  # dark grey matte (rubber mat, painted plywood)
_BLACK = (24, 24, 24)


# --------------------------------------------------------------------------- patterns
# Each takes (east, north) in units of the pad's smaller half side (so a square pad spans
# [-1, 1] both ways; the axes run east and north) and returns an int label per point; the
# pattern's palette maps labels to colours and names.


def _paper(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    arm, half_width = 0.8, 0.15
    cross = ((np.abs(x) <= arm) & (np.abs(y) <= half_width)) | (
        (np.abs(y) <= arm) & (np.abs(x) <= half_width)
    )
    return cross.astype(np.uint8)


def _helipad(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    r = np.hypot(x, y)
    ring = (r >= 0.76) & (r <= 0.9)
    posts = (np.abs(x) >= 0.26) & (np.abs(x) <= 0.42) & (np.abs(y) <= 0.5)
    bar = (np.abs(x) <= 0.42) & (np.abs(y) <= 0.07)
    return np.where(ring, 1, np.where(posts | bar, 2, 0)).astype(np.uint8)


def _quadrant(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return ((x >= 0) == (y >= 0)).astype(np.uint8)  # 1 = north-east or south-west: black


_PATTERN_DRAW: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "paper": _paper,
    "helipad": _helipad,
    "quadrant": _quadrant,
}
_PALETTES: dict[str, tuple[tuple[str, tuple[int, int, int]], ...]] = {
    "paper": (("square", _GREEN), ("cross", _RED)),
    "helipad": (("square", _DARK), ("ring", _WHITE), ("H", _WHITE)),
    "quadrant": (("white quadrants", _WHITE), ("black quadrants", _BLACK)),
}
PATTERNS = tuple(_PATTERN_DRAW)
"""The built-in procedural patterns of a pad file's ``pattern`` key."""


# --------------------------------------------------------------------------- the design


@dataclass(frozen=True, eq=False)
class PadDesign:
    """One printed pad: its name, its whole size and what is printed on it.

    Attributes:
        name: e.g. ``"paper"``, ``"helipad_1m"``.
        size_m: (width across east, height across north) of the whole printed pad, metres.
        path: the pad file it came from (None for the built-in default).
        pattern: the procedural pattern (:data:`PATTERNS`), or None for an image pad.
        image: the image file of an image pad (None for a pattern).
        pixels: the image's (rows, cols, 3) uint8 RGB, row 0 = the north edge (image pads).
    """

    name: str
    size_m: tuple[float, float]
    path: Path | None
    pattern: str | None = DEFAULT_PAD
    image: Path | None = None
    pixels: np.ndarray | None = field(default=None, repr=False)

    def _shape(self, m_per_px: float) -> tuple[int, int]:
        if not (math.isfinite(m_per_px) and m_per_px > 0.0):
            raise ValueError(f"m_per_px = {m_per_px!r}; expected a number > 0")
        w, h = self.size_m
        return max(1, round(h / m_per_px)), max(1, round(w / m_per_px))

    def _labels(self, rows: int, cols: int) -> np.ndarray:
        """The pattern's label per texel of a (rows, cols) top view (point-sampled at centres)."""
        w, h = self.size_m
        unit = min(w, h) / 2
        east = ((np.arange(cols) + 0.5) * (w / cols) - w / 2) / unit
        north = (h / 2 - (np.arange(rows) + 0.5) * (h / rows)) / unit
        return _PATTERN_DRAW[self.pattern](east[None, :], north[:, None])

    def top_view(self, m_per_px: float) -> np.ndarray:
        """(rows, cols, 3) uint8 RGB of the pad as printed (matte colours), seen from above, at
        ``m_per_px``; row 0 is the pad's north edge, column 0 its west edge;
        ``rows = round(size_m[1] / m_per_px)``, ``cols = round(size_m[0] / m_per_px)``."""
        rows, cols = self._shape(m_per_px)
        if self.pixels is not None:
            return _resample(self.pixels, rows, cols)
        palette = np.array([c for _, c in _PALETTES[self.pattern]], dtype=np.uint8)
        return palette[self._labels(rows, cols)]

    def luma_view(self, m_per_px: float) -> np.ndarray:
        """(rows, cols) uint8: :meth:`top_view` as the mono8 camera sees it (ITU-R BT.601)."""
        return luma(self.top_view(m_per_px))

    def parts(self) -> list[tuple[str, float]]:
        """The named parts of the pattern and each part's luma in 0..255; for an image pad its
        dominant luma levels (1-D k-means, darkest first), named ``"level 1"``, ..."""
        if self.pixels is None:
            return [
                (n, float(luma(np.array(c, dtype=np.uint8)))) for n, c in _PALETTES[self.pattern]
            ]
        levels = _luma_levels(luma(self.pixels))
        return [(f"level {i + 1}", v) for i, v in enumerate(levels)]

    @property
    def is_nominal_pad(self) -> bool:
        """The paper's pattern on a square: drawn from :class:`PadGeometry`'s boxes, as today."""
        return self.pattern == "paper" and self.size_m[0] == self.size_m[1]

    def scene_pad(self, scale: float = 1.0, colour_gain: tuple[float, ...] = (1.0,) * 6) -> PadLook:
        """What the renderers draw: this pad ``scale`` times its size, its colours jittered.

        The paper's pattern on a square is :class:`PadGeometry` (the green square's colour
        times ``colour_gain[:3]``, the cross's times ``colour_gain[3:]``; the 4 m default with
        no jitter is ``PadGeometry()`` itself). Any other pad is a :class:`PadTexture`: each
        texel's colour times a gain blended from ``colour_gain[:3]`` (at the pad's darkest luma)
        to ``colour_gain[3:]`` (at its brightest), so a two-colour pad jitters each colour
        independently as the paper's does.
        """
        if self.is_nominal_pad:
            base = PadGeometry().scaled(self.size_m[0] / PAPER_SIDE_M * scale)
            if all(g == 1.0 for g in colour_gain):
                return base
            return base.recoloured(colour_gain)
        rgb = self.pixels if self.pixels is not None else self.top_view(_PATTERN_TEXEL_M)
        if any(g != 1.0 for g in colour_gain):
            rgb = _jitter(rgb, colour_gain)
        w, h = self.size_m
        return PadTexture(rgb=rgb, size_m=(w * scale, h * scale), name=self.name)


def default_pad() -> PadDesign:
    """The built-in default: the paper's 4 m pad (``configs/pads/paper.toml`` is the same)."""
    return PadDesign(DEFAULT_PAD, (PAPER_SIDE_M, PAPER_SIDE_M), None)


def _resample(rgb: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Nearest texel when enlarging, box average when shrinking (PIL)."""
    from PIL import Image

    if (rows, cols) == rgb.shape[:2]:
        return rgb.copy()
    shrink = rows < rgb.shape[0] or cols < rgb.shape[1]
    method = Image.Resampling.BOX if shrink else Image.Resampling.NEAREST
    return np.asarray(Image.fromarray(rgb, "RGB").resize((cols, rows), method), dtype=np.uint8)


def _jitter(rgb: np.ndarray, gain: tuple[float, ...]) -> np.ndarray:
    y = luma(rgb).astype(np.float32)
    lo, hi = float(y.min()), float(y.max())
    t = (y - lo) / (hi - lo) if hi > lo else np.zeros_like(y)
    g = (
        np.asarray(gain[:3], np.float32) * (1 - t[..., None])
        + np.asarray(gain[3:6], np.float32) * t[..., None]
    )
    return np.clip(np.rint(rgb.astype(np.float32) * g), 0, 255).astype(np.uint8)


def _luma_levels(y: np.ndarray, k: int = 3) -> list[float]:
    """Dominant grey levels: 1-D k-means on the luma histogram, started from the lowest,
    median and highest grey present; empty clusters dropped, close ones merged."""
    counts = np.bincount(y.ravel(), minlength=256).astype(np.float64)
    grey = np.arange(256, dtype=np.float64)
    present = grey[counts > 0]
    centres = np.quantile(present, np.linspace(0.0, 1.0, k))
    for _ in range(50):
        label = np.argmin(np.abs(grey[:, None] - centres[None, :]), axis=1)
        new = np.array(
            [
                np.average(grey, weights=counts * (label == i)) if counts[label == i].sum() else c
                for i, c in enumerate(centres)
            ]
        )
        if np.allclose(new, centres):
            break
        centres = new
    label = np.argmin(np.abs(grey[:, None] - centres[None, :]), axis=1)
    used = sorted(c for i, c in enumerate(centres) if counts[label == i].sum() > 0)
    out: list[float] = []
    for c in used:
        if not out or c - out[-1] > 8.0:
            out.append(round(float(c), 1))
    return out


# --------------------------------------------------------------------------- the envelope
# Acquiring a pad is defined by a pixel width measured from the shipped model on the paper pad:
# it acquires the 4 m pad from the scenario's start altitudes, 75-100 m, so at 100 m the pad
# spans ACQUIRE_PX = 128 x 4 / (2 x 100 x tan 22.5 deg) = 6.18 pixels of its 128 px, 45 deg
# image. A pad of width w is acquirable up to the altitude where it spans that many pixels, and a
# flight should start between START_FRACTION of that altitude and that altitude. ``visland pad
# info`` reports it; a pipeline that teaches a pad starts its flights there.

REFERENCE = {"pad_m": 4.0, "altitude_m": 100.0, "hfov_deg": 45.0, "resolution_px": 128}
"""The measurement that defines "can acquire": the shipped model acquires the 4 m paper pad from
the scenario's start altitudes, whose top is 100 m, with the 128 px, 45° camera."""

START_FRACTION = 0.75
"""The bottom of the start altitudes as a share of the acquire altitude (the scenario's 75 of
100 m)."""


def pad_width_px(
    width_m: float, altitude_m: float, hfov_deg: float = 45.0, resolution_px: int = 128
) -> float:
    """Pixels a ``width_m`` pad spans seen straight down from ``altitude_m`` by a camera of
    ``resolution_px`` across ``hfov_deg`` (pinhole)."""
    return resolution_px * width_m / (2.0 * altitude_m * math.tan(math.radians(hfov_deg) / 2.0))


ACQUIRE_PX = pad_width_px(
    REFERENCE["pad_m"], REFERENCE["altitude_m"], REFERENCE["hfov_deg"], REFERENCE["resolution_px"]
)
"""The pad width in pixels at which the model acquires a pad (6.18 px; :data:`REFERENCE`)."""


def acquire_altitude_m(width_m: float, hfov_deg: float = 45.0, resolution_px: int = 128) -> float:
    """The highest altitude from which a ``width_m`` pad spans :data:`ACQUIRE_PX` pixels."""
    return resolution_px * width_m / (2.0 * ACQUIRE_PX * math.tan(math.radians(hfov_deg) / 2.0))


def start_altitudes_m(
    width_m: float, hfov_deg: float = 45.0, resolution_px: int = 128
) -> tuple[float, float]:
    """The start altitude range for a ``width_m`` pad: ``[START_FRACTION, 1] x`` its acquire
    altitude (for the 4 m paper pad at 128 px / 45°: the scenario's 75-100 m)."""
    top = acquire_altitude_m(width_m, hfov_deg, resolution_px)
    return START_FRACTION * top, top


def fill_altitude_m(width_m: float, hfov_deg: float = 45.0) -> float:
    """The altitude at which the pad spans the whole image (below it the camera sees a part)."""
    return width_m / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))


# --------------------------------------------------------------------------- files


def builtin_pad_paths() -> dict[str, Path]:
    """name -> ``configs/pads/NAME.toml`` for every shipped pad file."""
    return {p.stem: p for p in sorted(PADS_DIR.glob("*.toml"))}


def find_file(name: str, source: str, where: str) -> Path:
    """The file a scenario names: an absolute path as is; a relative one in the folder of the
    scenario file ``source`` (``"dir/x.toml"``, or ``"dir/suite.toml: [conditions.a]"`` for a
    table inline in a suite), else in the repository root, else in the working directory.

    Raises:
        ConfigError: ``"<where> = 'name'; expected a file, found none (looked in ...)"``.
    """
    path = Path(name).expanduser()
    if path.is_absolute():
        places = [path]
    else:
        scenario_file = Path(source.split(": [", 1)[0])
        dirs = [scenario_file.parent] if scenario_file.is_file() else []
        places = [d / path for d in (*dirs, REPO_DIR, Path.cwd())]
    for p in places:
        if p.is_file():
            return p.resolve()
    looked = ", ".join(dict.fromkeys(str(p.parent) for p in places))
    raise ConfigError(f"{where} = {name!r}; expected a file, found none (looked in {looked})")


def read_image_rgb(path: Path, where: str) -> np.ndarray:
    """An image file (PNG, JPEG, ...; grey, RGB or with alpha, which is dropped) as (rows, cols,
    3) uint8 RGB. A missing or unreadable file is a ConfigError starting with ``where``."""
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise ConfigError(f"{where} = {str(path)!r}; expected an image file, found none")
    try:
        with Image.open(path) as im:
            im.load()
            if max(im.size) > _MAX_IMAGE_PX:
                raise ConfigError(
                    f"{where} = {str(path)!r}: {im.size[0]} x {im.size[1]} px; expected at "
                    f"most {_MAX_IMAGE_PX} px a side"
                )
            rgb = np.asarray(im.convert("RGB"), dtype=np.uint8)
    except (OSError, UnidentifiedImageError, ValueError) as err:
        if isinstance(err, ConfigError):
            raise
        raise ConfigError(
            f"{where} = {str(path)!r}; expected a readable PNG or JPEG image, got: {err}"
        ) from err
    return rgb


def load_pad(path: str | Path) -> PadDesign:
    """Read a pad file (``configs/pads/NAME.toml``).

    Raises:
        ConfigError: naming the file and the key: a missing or malformed file, an unknown key,
            a size that is not two positive numbers, neither or both of ``pattern`` and
            ``image``, an unknown pattern, a missing or unreadable image.
    """
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise ConfigError(f"{path}: pad file not found") from err
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        raise ConfigError(f"{path}: not a readable TOML pad file: {err}") from err
    unknown = sorted(set(data) - set(_KEYS))
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {unknown}; expected {list(_KEYS)} (typo?)")
    name = data.get("name", path.stem)
    if not (isinstance(name, str) and name.strip()):
        raise ConfigError(f"{path}: name = {name!r}; expected a non-empty string")
    size = data.get("size_m")
    good = (
        isinstance(size, list)
        and len(size) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in size)
        and all(math.isfinite(v) and v > 0 for v in size)
    )
    if not good:
        raise ConfigError(
            f"{path}: size_m = {size!r}; expected [width, height] (two numbers > 0, metres)"
        )
    size_m = (float(size[0]), float(size[1]))
    has_pattern, has_image = "pattern" in data, "image" in data
    if has_pattern == has_image:
        raise ConfigError(
            f"{path}: expected exactly one of pattern = one of {list(PATTERNS)} or "
            f'image = "FILE.png", got {"both" if has_pattern else "neither"}'
        )
    if has_pattern:
        pattern = data["pattern"]
        if pattern not in PATTERNS:
            raise ConfigError(f"{path}: pattern = {pattern!r}; expected one of {list(PATTERNS)}")
        return PadDesign(name, size_m, path, pattern=pattern)
    image = data["image"]
    if not (isinstance(image, str) and image):
        raise ConfigError(f'{path}: image = {image!r}; expected a file name ("my_pad.png")')
    file = (path.parent / image).resolve()
    pixels = read_image_rgb(file, f"{path}: image")
    pixels.setflags(write=False)
    return PadDesign(name, size_m, path, pattern=None, image=file, pixels=pixels)
