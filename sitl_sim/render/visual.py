"""The ``[visual]`` scenario section: ground, sun, pad and camera effects drawn per episode.

Keys (all optional, a key left out keeps its nominal value; ranges ``[lo, hi]`` are drawn
uniformly per episode; the generated table: ``docs/config_keys.md``):

``terrain``               list of ground families to pick from
(:data:`sitl_sim.render.terrain.FAMILIES`,
                          or ``"nominal"``: the original ground, which ignores the seed and sun;
                          default ``["nominal"]``)
``texture_seed``          ``[lo, hi]`` integers, inclusive (default ``[0, 999]``): disjoint ranges
                          give grounds never seen in training
``sun_elevation_deg``     degrees above the horizon, in [1, 90] (default ``[90, 90]``: overhead)
``sun_azimuth_deg``       where the sun stands, from north clockwise (default ``[0, 360]``)
``brightness``            gain on the image (default ``[1, 1]``)
``contrast``              gain on the deviation from mid-grey (default ``[1, 1]``)
``pad_scale``             factor on the pad's size (default ``[1, 1]``)
``pad_colour_jitter``     each pad colour channel x a factor in [1 - j, 1 + j] (default 0)
``haze``                  share of the airlight at 100 m slant range, in [0, 0.95]: dust or haze
                          that greys the view with distance (default ``[0, 0]``)
``exposure_noise``        std of the per-frame log exposure gain (auto-exposure flicker)
``motion_blur_ms``        exposure time (ms): the body rates smear the image over it
``lens_k1``               radial distortion ``x_d = x (1 + k1 r^2)`` in normalised coordinates
                          (negative: barrel), in [-0.5, 0.5]
``ground_image``          a user's ground picture(s), PNG or JPEG, grey or RGB, one drawn per
                          episode instead of a terrain family (paths relative to the scenario
                          file; :mod:`sitl_sim.render.ground_image`): mirrored beyond its edges,
                          a random point of it under the pad, a random rotation; lit by the sun's
                          light level, and every camera effect applies
``ground_m_per_px``       the picture's metres per pixel, drawn per episode (default 0.05)
``markings``              the chance that an episode's terrain carries painted markings (parking
                          bays, lane lines, outlined boxes: :func:`sitl_sim.render.terrain.
                          terrain_map`), in [0, 1] (default 0); any family but water and the
                          nominal ground; a ground picture shows only its own paint

The pad's design comes from the ``[pad]`` section (:mod:`sitl_sim.render.pad_section`);
``pad_scale`` and ``pad_colour_jitter`` apply to any design.

Absent section: the nominal world, bit for bit. The draw comes from its own generator
``(seed, episode, VISUAL_STREAM)``; the per-frame exposure flicker from a second stream of that
key, so neither touches the sensor noise, the initial state or the wind.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np

from companion.table import Section, choice_list, file_list, integer_span, number, span
from sitl_sim.config import CameraConfig
from sitl_sim.errors import ConfigError
from sitl_sim.render.ground import GroundMap, PadGeometry, PadLook, nominal_ground
from sitl_sim.render.ground_image import check_ground_image, ground_image_map
from sitl_sim.render.pads import PadDesign, find_file
from sitl_sim.render.terrain import FAMILIES, MARKED_FAMILIES, Sun, terrain_map

__all__ = [
    "VISUAL_STREAM",
    "CameraEffects",
    "VisualConfig",
    "VisualSample",
    "visual_config_from_table",
]

VISUAL_STREAM = 0x5649_5355  # "VISU"
NOMINAL_TERRAIN = "nominal"
_HAZE_REFERENCE_M = 100.0
_AIRLIGHT = 190.0  # grey level of the haze itself in full light (a bright dusty sky)


def _range(default: tuple[float, float], unit: str, lo: float, hi: float, doc: str) -> Any:
    return span(default, unit=unit, lo=lo, hi=hi, doc=doc)


@dataclass(frozen=True)
class VisualConfig(Section):
    """The checked ``[visual]`` section: what each episode's look is drawn from (a key left
    out keeps its nominal value; units, defaults and ranges: the declarations below)."""

    SECTION: ClassVar[str] = "visual"

    terrain: tuple[str, ...] = choice_list(
        (NOMINAL_TERRAIN,),
        (NOMINAL_TERRAIN, *FAMILIES),
        doc="ground families to pick from per episode (nominal: the original ground, which "
        "ignores the seed and the sun)",
    )
    texture_seed: tuple[int, int] = integer_span(
        (0, 999),
        unit="1",
        lo=0,
        hi=2**31 - 1,
        doc="terrain seed, inclusive; disjoint ranges give grounds never seen in training",
    )
    sun_elevation_deg: tuple[float, float] = _range(
        (90.0, 90.0), "deg", 1.0, 90.0, "sun above the horizon (90: overhead)"
    )
    sun_azimuth_deg: tuple[float, float] = _range(
        (0.0, 360.0), "deg", -360.0, 720.0, "where the sun stands, from north clockwise"
    )
    brightness: tuple[float, float] = _range((1.0, 1.0), "1", 0.05, 5.0, "gain on the image")
    contrast: tuple[float, float] = _range(
        (1.0, 1.0), "1", 0.05, 5.0, "gain on the deviation from mid-grey (128)"
    )
    pad_scale: tuple[float, float] = _range((1.0, 1.0), "1", 0.1, 10.0, "factor on the pad size")
    pad_colour_jitter: float = number(
        0.0, unit="1", lo=0.0, hi=0.9, doc="each pad colour channel x U(1 - j, 1 + j)"
    )
    haze: tuple[float, float] = _range(
        (0.0, 0.0), "1", 0.0, 0.95, "airlight share at 100 m slant range (dust, haze)"
    )
    exposure_noise: float = number(
        0.0, unit="1", lo=0.0, hi=1.0, doc="std of the per-frame log exposure gain (flicker)"
    )
    motion_blur_ms: tuple[float, float] = _range(
        (0.0, 0.0), "ms", 0.0, 200.0, "exposure time over which the body rates smear the image"
    )
    lens_k1: tuple[float, float] = _range(
        (0.0, 0.0), "1", -0.5, 0.5, "radial distortion x_d = x (1 + k1 r^2) (negative: barrel)"
    )
    ground_image: tuple[str, ...] | None = file_list(
        doc="ground picture(s) (PNG/JPEG, grey or RGB), one drawn per episode instead of a "
        "terrain; relative to the scenario file; mirrored beyond its edges, random offset and "
        "rotation"
    )
    ground_m_per_px: tuple[float, float] = span(
        (0.05, 0.05),
        unit="m",
        lo=0.0,
        lo_open=True,
        hi=10.0,
        doc="metres per pixel of the ground picture",
    )
    markings: float = number(
        0.0,
        unit="1",
        lo=0.0,
        hi=1.0,
        doc="chance of painted markings (parking bays, lane lines, boxes) on an episode's "
        "terrain (not water, the nominal ground or a picture)",
    )
    ground_paths: tuple[Path, ...] = field(default=(), init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.ground_image:
            return
        if self.terrain != (NOMINAL_TERRAIN,):
            raise ConfigError(
                f"{self.source}: [visual] terrain = {list(self.terrain)} and ground_image; "
                "expected one of them (a ground picture replaces the terrain)"
            )
        where = f"{self.source}: [visual] ground_image"
        paths = tuple(find_file(name, self.source, where) for name in self.ground_image)
        for path in paths:
            check_ground_image(path, self.ground_m_per_px[0], where)
        object.__setattr__(self, "ground_paths", paths)

    def draw(self, seed: int, index: int) -> VisualSample:
        """Episode ``index`` of ``seed``: a pure function of the three."""
        rng = np.random.default_rng([int(seed), int(index), VISUAL_STREAM])

        def u(rg: tuple[float, float]) -> float:
            return float(rg[0] + (rg[1] - rg[0]) * rng.random())

        terrain = self.terrain[int(rng.integers(len(self.terrain)))]
        texture_seed = int(rng.integers(self.texture_seed[0], self.texture_seed[1] + 1))
        sun = (u(self.sun_elevation_deg), u(self.sun_azimuth_deg) % 360.0)
        gains = (u(self.brightness), u(self.contrast))
        pad_scale = u(self.pad_scale)
        j = self.pad_colour_jitter
        jitter = tuple(float(v) for v in rng.uniform(1.0 - j, 1.0 + j, 6))
        sample = VisualSample(
            terrain=terrain,
            texture_seed=texture_seed,
            sun_elevation_deg=sun[0],
            sun_azimuth_deg=sun[1],
            brightness=gains[0],
            contrast=gains[1],
            pad_scale=pad_scale,
            pad_colour_gain=jitter,  # type: ignore[arg-type]
            haze=u(self.haze),
            exposure_noise=self.exposure_noise,
            motion_blur_s=u(self.motion_blur_ms) / 1000.0,
            lens_k1=u(self.lens_k1),
            frame_seed=(int(seed), int(index), VISUAL_STREAM + 1),
        )
        # drawn after everything else: a section without pictures or markings draws what it
        # always did
        if self.ground_paths:
            path = self.ground_paths[int(rng.integers(len(self.ground_paths)))]
            return replace(
                sample,
                ground_image=str(path),
                ground_m_per_px=u(self.ground_m_per_px),
                ground_anchor=(float(rng.random()), float(rng.random())),
                ground_rotation_deg=float(rng.uniform(0.0, 360.0)),
            )
        if self.markings > 0.0 and rng.random() < self.markings:
            return replace(sample, markings=terrain in MARKED_FAMILIES)
        return sample


@dataclass(frozen=True)
class VisualSample:
    """One episode's look (what :meth:`VisualConfig.draw` drew)."""

    terrain: str
    texture_seed: int
    sun_elevation_deg: float
    sun_azimuth_deg: float
    brightness: float
    contrast: float
    pad_scale: float
    pad_colour_gain: tuple[float, float, float, float, float, float]
    haze: float
    exposure_noise: float
    motion_blur_s: float
    lens_k1: float
    frame_seed: tuple[int, int, int]
    ground_image: str = ""
    ground_m_per_px: float = 0.0
    ground_anchor: tuple[float, float] = (0.0, 0.0)
    ground_rotation_deg: float = 0.0
    markings: bool = False
    pad_design: PadDesign | None = None

    @property
    def sun(self) -> Sun:
        return Sun(self.sun_elevation_deg, self.sun_azimuth_deg)

    @property
    def light(self) -> float:
        """The flat-ground light level (1.0 on the nominal ground: it has no sun)."""
        if self.ground_image:
            return self.sun.flat_light
        return 1.0 if self.terrain == NOMINAL_TERRAIN else self.sun.flat_light

    def ground(self) -> GroundMap:
        if self.ground_image:
            return ground_image_map(
                Path(self.ground_image),
                self.ground_m_per_px,
                self.ground_anchor,
                self.ground_rotation_deg,
            )
        if self.terrain == NOMINAL_TERRAIN:
            return nominal_ground()
        return terrain_map(self.terrain, self.texture_seed, self.sun, self.markings)

    def pad(self, base: PadGeometry | None = None) -> PadLook:
        """The pad the renderers draw: ``[pad]``'s design (or ``base``, else the paper's pad)
        scaled by ``pad_scale``, its colours jittered."""
        if self.pad_design is not None and base is None:
            return self.pad_design.scene_pad(self.pad_scale, self.pad_colour_gain)
        return (base or PadGeometry()).scaled(self.pad_scale).recoloured(self.pad_colour_gain)

    def to_dict(self) -> dict[str, Any]:
        """The record of the draw (the ground picture's, the markings' and the pad's keys only
        when set, so the records of scenarios without them are unchanged)."""
        d = asdict(replace(self, pad_design=None))
        d["pad_colour_gain"] = list(self.pad_colour_gain)
        d["frame_seed"] = list(self.frame_seed)
        d["ground_anchor"] = list(self.ground_anchor)
        if not self.ground_image:
            for key in ("ground_image", "ground_m_per_px", "ground_anchor", "ground_rotation_deg"):
                del d[key]
        if not self.markings:
            del d["markings"]
        del d["pad_design"]
        if self.pad_design is not None:
            d["pad"] = self.pad_design.name
            d["pad_file"] = str(self.pad_design.path) if self.pad_design.path else None
        return d


class CameraEffects:
    """The image-side effects of a :class:`VisualSample`, applied to a noise-free mono8 render
    before the sensor noise: haze by slant range, lens distortion, motion blur from the body
    rates over the exposure, brightness/contrast and the per-frame exposure flicker."""

    def __init__(self, sample: VisualSample, cfg: CameraConfig, light: float) -> None:
        from sitl_sim.render.render_fast import camera_intrinsics

        self.sample = sample
        self._cfg = cfg
        self._rng = np.random.default_rng(list(sample.frame_seed))
        k = camera_intrinsics(cfg)
        self._f = float(k[0, 0])
        v, u = np.mgrid[0 : cfg.height_px, 0 : cfg.width_px].astype(np.float64)
        x, y = (u - k[0, 2]) / self._f, (v - k[1, 2]) / self._f
        # unit rays in the body frame (image right = body right, image down = body back)
        rays = np.stack([-y, x, np.ones_like(x)], axis=-1)
        self._rays_body = (rays / np.linalg.norm(rays, axis=-1, keepdims=True)).reshape(-1, 3)
        self._airlight = np.float32(_AIRLIGHT * light)
        self._haze_per_m = (
            -math.log(1.0 - sample.haze) / _HAZE_REFERENCE_M if sample.haze > 0.0 else 0.0
        )
        self._lens_maps = None
        if sample.lens_k1 != 0.0:
            # output (distorted) pixel <- source (ideal) pixel at x_u = x_d (1 + k1 r_d^2)
            r2 = x * x + y * y
            scale = 1.0 + sample.lens_k1 * r2
            self._lens_maps = (
                (x * scale * self._f + k[0, 2]).astype(np.float32),
                (y * scale * self._f + k[1, 2]).astype(np.float32),
            )

    def apply(
        self, image: np.ndarray, pos_ned_m, rot_body_to_ned: np.ndarray, rate_frd
    ) -> np.ndarray:
        s = self.sample
        if (
            self._haze_per_m == 0.0
            and self._lens_maps is None
            and s.motion_blur_s <= 0.0
            and s.exposure_noise == 0.0
            and s.brightness == 1.0
            and s.contrast == 1.0
        ):
            return image  # no effect: the same bytes, without the round trip through floats
        img = image.astype(np.float32)
        if self._haze_per_m > 0.0:
            cos_down = (self._rays_body @ rot_body_to_ned[2]).reshape(img.shape)
            altitude = max(0.0, -float(pos_ned_m[2]))
            with np.errstate(divide="ignore"):
                slant = np.where(cos_down > 1e-3, altitude / np.maximum(cos_down, 1e-3), np.inf)
            t = np.exp(-self._haze_per_m * slant).astype(np.float32)
            img = img * t + self._airlight * (1.0 - t)
        if self._lens_maps is not None:
            img = cv2.remap(img, *self._lens_maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if s.motion_blur_s > 0.0:
            img = self._blur(img, rate_frd)
        gain = s.brightness
        if s.exposure_noise > 0.0:
            gain *= math.exp(s.exposure_noise * float(self._rng.standard_normal()))
        img = ((img - 128.0) * s.contrast + 128.0) * gain
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def _blur(self, img: np.ndarray, rate_frd) -> np.ndarray:
        """Smear along the image motion of a rotation at the body rates over the exposure
        (roll moves the image across, pitch along; yaw's smear at the edges is left out)."""
        dx = self._f * float(rate_frd[0]) * self.sample.motion_blur_s
        dy = self._f * float(rate_frd[1]) * self.sample.motion_blur_s
        length = math.hypot(dx, dy)
        if length < 1.0:
            return img
        n = math.ceil(length) | 1
        kernel = np.zeros((n, n), np.float32)
        c = n // 2
        for t in np.linspace(-0.5, 0.5, 4 * n):
            kernel[round(c + t * dy), round(c + t * dx)] += 1.0
        return cv2.filter2D(img, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)


def visual_config_from_table(table: Any, where: str) -> VisualConfig:
    """Check and type a ``[visual]`` table; ``where`` (the file) starts every error."""
    return VisualConfig.from_table(table, where)
