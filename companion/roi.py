"""Beyond the 128 px image: a region of interest (ROI) of the camera's full resolution, cut
around the pad the estimator predicts and resampled to the policy's 128 x 128 input.

The policy's CNN sees a 128 px, 45° image: a 1 m pad spans its 6 px acquisition width at 25 m.
A 640 x 480 camera has 3.4 times as many pixels across the same angle, thrown away by the
area resize of :func:`companion.camera.fit_to_policy`. With ROI on, the policy chooses, after
every step, the window of the full frame its next image is cut from — as a tracker does:

* **search** (no horizontal estimate yet, or the pad unseen for ``lost_frames``): one tile of
  ``tile_px`` full-resolution pixels after another (nearest the image centre first) across the
  whole frame, so a pad too small for the resampled view is found at the camera's own
  resolution; the policy's 45° view (exactly ``fit_to_policy``'s crop, bit for bit) instead
  when the radar's altitude makes the pad wider than a third of a tile, and every other frame
  while the altitude is not known;
* **track**: a square centred on the estimator's predicted pad (position + velocity x one
  control period, through the attitude) and sized so the pad spans ``span_px`` of the 128 px
  window, at least ``min_side_px`` (at most 2x upsampling), at least the pad plus ``sigma_k``
  times the estimate's horizontal uncertainty either side, at most the 45° view; shifted to lie
  inside the frame.

The CNN's output is a bearing in the window's own 45° geometry; :meth:`RoiWindow.to_camera`
maps it through the window's centre offset and scale to the full camera's bearing, which is
what the estimator and the controller get. Pinhole geometry makes that exact: a crop of a
pinhole image is a pinhole image, its principal point shifted.

The window travels in the policy's state (:attr:`companion.policy_net.core.PolicyState.roi`):
the step that answers a frame maps the CNN's output through the window of the state it starts
from, and the loop cuts every frame with that same window (:func:`roi_window`). With ROI off
(``PolicyCore.roi`` None, the default) nothing of this runs and the policy is unchanged.

The shipped CNN was trained on 45° views only: a zoomed window shows the pad larger and
blurrier (upsampled) than any training image of that altitude; ``visland pad acquire``
measures what it makes of them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from companion.camera import (
    CameraError,
    OpenCvCameraSource,
    ReceivedFrame,
    _resize_area,
    focal_px_from_fov,
)
from companion.contract import CAMERA_FOV_DEG, IMAGE_SIZE_PX

__all__ = [
    "RoiCameraSource",
    "RoiConfig",
    "RoiState",
    "RoiWindow",
    "cut",
    "mono8",
    "roi_window",
    "rotated_geometry",
]

_TAN_HALF = math.tan(math.radians(CAMERA_FOV_DEG) / 2.0)
Search = Literal["tiles", "view"]


@dataclass(frozen=True)
class RoiWindow:
    """A square of the full frame: columns ``x0 .. x0+side-1``, rows ``y0 .. y0+side-1``, of a
    camera of focal length ``fx_px`` and principal point ``(cx_px, cy_px)`` (top = forward);
    ``kind``: ``view`` (the policy's 45° view), ``tile`` (search) or ``track``."""

    x0: int
    y0: int
    side: int
    fx_px: float
    cx_px: float
    cy_px: float
    kind: str = "view"

    @property
    def scale(self) -> float:
        """Tangent units of the camera per tangent unit of the window's 45° image."""
        return self.side / (2.0 * self.fx_px * _TAN_HALF)

    @property
    def centre_tan(self) -> tuple[float, float]:
        """(tan right, tan forward) of the window's centre in the full camera."""
        u = self.x0 + (self.side - 1) / 2.0
        v = self.y0 + (self.side - 1) / 2.0
        return (u - self.cx_px) / self.fx_px, (self.cy_px - v) / self.fx_px

    def to_camera(self, raw: np.ndarray) -> np.ndarray:
        """The CNN's (tan_right, tan_forward, logit) on this window -> the same in the full
        camera (the logit unchanged)."""
        r0, f0 = self.centre_tan
        s = self.scale
        return np.array([r0 + float(raw[0]) * s, f0 + float(raw[1]) * s, float(raw[2])])

    def cut(self, image: np.ndarray, size: int = IMAGE_SIZE_PX) -> np.ndarray:
        """This window of a full frame as the policy's image (:func:`cut`)."""
        return cut(image, self, size)

    def from_camera(self, tan_right: float, tan_forward: float) -> tuple[float, float]:
        """A camera bearing in the window's own 45° tangent units (the inverse of
        :meth:`to_camera`)."""
        r0, f0 = self.centre_tan
        return (tan_right - r0) / self.scale, (tan_forward - f0) / self.scale


@dataclass(frozen=True)
class RoiState:
    """The ROI part of a policy's state: the window the next frame is cut with, the search
    tiles seen before it and the frames since the pad was last seen."""

    window: RoiWindow
    search_step: int = 0
    unseen: int = 0


def roi_window(state: Any) -> RoiWindow | None:
    """The window the next frame is to be cut with, from a policy state (None: ROI off, or a
    policy without one — cut nothing, the policy takes the 45° view)."""
    roi = getattr(state, "roi", None)
    return roi.window if isinstance(roi, RoiState) else None


def mono8(image: np.ndarray, rotate_deg: int = 0) -> np.ndarray:
    """A camera frame as mono8 (BT.601 luma of BGR, as :func:`~companion.camera.fit_to_policy`)
    rotated counter-clockwise by ``rotate_deg`` so that its top is body forward."""
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] != 3):
        raise CameraError(f"image: expected uint8 (H, W) or (H, W, 3), got {img.shape} {img.dtype}")
    if img.ndim == 3:
        b, g, r = (img[..., k].astype(np.float32) for k in range(3))
        img = np.clip(np.rint(0.299 * r + 0.587 * g + 0.114 * b), 0, 255).astype(np.uint8)
    if rotate_deg % 90 != 0:
        raise CameraError(f"rotate_deg = {rotate_deg}; expected a multiple of 90")
    return np.ascontiguousarray(np.rot90(img, k=(rotate_deg // 90) % 4))


def rotated_geometry(
    width_px: int, height_px: int, cx_px: float, cy_px: float, rotate_deg: int
) -> tuple[int, int, float, float]:
    """A frame's size and principal point after :func:`mono8`'s rotation (``np.rot90``)."""
    w, h, cx, cy = width_px, height_px, cx_px, cy_px
    for _ in range((rotate_deg // 90) % 4):
        w, h, cx, cy = h, w, cy, w - 1 - cx
    return w, h, cx, cy


def _resize_linear(img: np.ndarray, size: int) -> np.ndarray:
    """Bilinear upsampling of a square uint8 image (pixel centres aligned, edges clamped)."""
    n = img.shape[0]
    pos = np.clip((np.arange(size) + 0.5) * (n / size) - 0.5, 0.0, n - 1.0)
    lo = np.floor(pos).astype(int)
    hi = np.minimum(lo + 1, n - 1)
    w = pos - lo
    src = img.astype(np.float64)
    rows = src[lo] * (1.0 - w)[:, None] + src[hi] * w[:, None]
    out = rows[:, lo] * (1.0 - w)[None, :] + rows[:, hi] * w[None, :]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def cut(image: np.ndarray, window: RoiWindow, size: int = IMAGE_SIZE_PX) -> np.ndarray:
    """The policy's (size, size) image of ``window``: its pixels area-averaged when it is at
    least ``size`` wide (the view: bit for bit ``fit_to_policy``), bilinearly upsampled when
    smaller."""
    h, w = image.shape[:2]
    n = window.side
    if window.x0 < 0 or window.y0 < 0 or window.x0 + n > w or window.y0 + n > h:
        raise CameraError(f"ROI window {window} does not lie in the {w}x{h} frame")
    crop = np.ascontiguousarray(image[window.y0 : window.y0 + n, window.x0 : window.x0 + n])
    if n >= size:
        return np.ascontiguousarray(_resize_area(crop, size))
    return _resize_linear(crop, size)


@dataclass(frozen=True)
class RoiConfig:
    """A full-resolution camera and how the policy's window is chosen in it.

    Attributes:
        width_px / height_px: the frame as the policy's loop gets it (top = body forward).
        fx_px: focal length in pixels; ``cx_px`` / ``cy_px`` the principal point.
        pad_m: the pad's width, metres (the track window is sized for it).
        span_px: the pad's width in the 128 px window while tracking.
        min_side_px: the smallest window, full-resolution pixels.
        tile_px: a search tile's side, full-resolution pixels.
        search: ``tiles`` (tiles, or the 45° view when the pad is too big for them) or
            ``view`` (always the 45° view).
        lost_frames: frames without the pad before the search starts again.
        sigma_k: the track window holds the pad ``sigma_k`` standard deviations of the
            estimate either side.
    """

    width_px: int
    height_px: int
    fx_px: float
    cx_px: float
    cy_px: float
    pad_m: float = 1.0
    span_px: float = 24.0
    min_side_px: int = 64
    tile_px: int = 128
    search: Search = "tiles"
    lost_frames: int = 10
    sigma_k: float = 3.0

    def __post_init__(self) -> None:
        def bad(key: str, value: Any, expected: str) -> CameraError:
            return CameraError(f"ROI {key} = {value!r}; expected {expected}")

        for key in ("width_px", "height_px"):
            if getattr(self, key) < IMAGE_SIZE_PX:
                raise bad(key, getattr(self, key), f">= {IMAGE_SIZE_PX} (the policy's image)")
        for key in ("fx_px", "pad_m", "span_px", "sigma_k"):
            v = getattr(self, key)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise bad(key, v, "a number > 0")
        if not 0.0 < self.span_px <= IMAGE_SIZE_PX:
            raise bad("span_px", self.span_px, f"in (0, {IMAGE_SIZE_PX}]")
        short = min(self.width_px, self.height_px)
        if not 8 <= self.min_side_px <= self.view_side:
            raise bad("min_side_px", self.min_side_px, f"in [8, {self.view_side}] px")
        if not 8 <= self.tile_px <= short:
            raise bad("tile_px", self.tile_px, f"in [8, {short}] px")
        if self.search not in ("tiles", "view"):
            raise bad("search", self.search, "'tiles' or 'view'")
        if self.lost_frames < 1:
            raise bad("lost_frames", self.lost_frames, ">= 1")
        self.view()  # the 45° view must fit the frame

    @classmethod
    def from_hfov(cls, width_px: int, height_px: int, hfov_deg: float, **kw: Any) -> RoiConfig:
        """A camera given by its horizontal field of view, principal point at the centre."""
        fx = focal_px_from_fov(width_px, hfov_deg)
        return cls(width_px, height_px, fx, (width_px - 1) / 2.0, (height_px - 1) / 2.0, **kw)

    # windows ------------------------------------------------------------------------------

    @property
    def view_side(self) -> int:
        """The side of the policy's 45° view, full-resolution pixels."""
        return round(2.0 * self.fx_px * _TAN_HALF)

    def window(self, x0: float, y0: float, side: int, kind: str = "track") -> RoiWindow:
        """A window of ``side`` px with its corner near (x0, y0), shifted into the frame."""
        x = min(max(round(x0), 0), self.width_px - side)
        y = min(max(round(y0), 0), self.height_px - side)
        return RoiWindow(x, y, side, self.fx_px, self.cx_px, self.cy_px, kind)

    def view(self) -> RoiWindow:
        """The policy's 45° view: ``fit_to_policy``'s crop, centred on the principal point."""
        n = self.view_side
        x0 = round(self.cx_px - (n - 1) / 2.0)
        y0 = round(self.cy_px - (n - 1) / 2.0)
        if n < 1 or x0 < 0 or y0 < 0 or x0 + n > self.width_px or y0 + n > self.height_px:
            raise CameraError(
                f"ROI: a {CAMERA_FOV_DEG:g}° view needs {n} px around ({self.cx_px:.0f}, "
                f"{self.cy_px:.0f}) but the frame is {self.width_px}x{self.height_px}: the "
                "camera's field of view is too narrow"
            )
        return RoiWindow(x0, y0, n, self.fx_px, self.cx_px, self.cy_px, "view")

    def tiles(self) -> list[RoiWindow]:
        """The search tiles: ``tile_px`` squares covering the frame, each overlapping its
        neighbours by at least a quarter, nearest the principal point first."""
        t = self.tile_px

        def starts(extent: int) -> list[int]:
            if extent <= t:
                return [0]
            count = math.ceil((extent - t) / (0.75 * t)) + 1
            return [round(i * (extent - t) / (count - 1)) for i in range(count)]

        out = [
            RoiWindow(x, y, t, self.fx_px, self.cx_px, self.cy_px, "tile")
            for y in starts(self.height_px)
            for x in starts(self.width_px)
        ]

        def dist(w: RoiWindow) -> float:
            return math.hypot(w.x0 + (t - 1) / 2 - self.cx_px, w.y0 + (t - 1) / 2 - self.cy_px)

        return sorted(out, key=lambda w: (dist(w), w.y0, w.x0))

    def search_window(
        self, tiles_seen: int, altitude_m: float | None = None, last_kind: str = "tile"
    ) -> RoiWindow:
        """The next search window after ``tiles_seen`` tiles: the next tile; the 45° view when
        the pad at ``altitude_m`` spans more than a third of a tile; without an altitude, the
        view after a tile (``last_kind``) and the next tile after the view."""
        tiles = self.tiles()
        if self.search == "view":
            return self.view()
        if altitude_m is None or not (math.isfinite(altitude_m) and altitude_m > 0.0):
            return self.view() if last_kind == "tile" else tiles[tiles_seen % len(tiles)]
        if self.fx_px * self.pad_m / altitude_m > self.tile_px / 3.0:
            return self.view()
        return tiles[tiles_seen % len(tiles)]

    def track_window(
        self,
        pad_body_m: np.ndarray,
        sigma_m: float,
    ) -> RoiWindow | None:
        """The window around a pad at ``pad_body_m`` (FRD, from the camera; None when it is not
        below the camera), holding it with a horizontal uncertainty ``sigma_m`` (m)."""
        f, r, d = (float(v) for v in pad_body_m)
        if not (math.isfinite(f) and math.isfinite(r) and math.isfinite(d)) or d < 0.5:
            return None
        u = self.cx_px + self.fx_px * r / d
        v = self.cy_px - self.fx_px * f / d
        span = self.fx_px * self.pad_m / d
        side = span * IMAGE_SIZE_PX / self.span_px
        sigma_px = self.fx_px * max(sigma_m, 0.0) / d
        side = max(side, 2.0 * self.sigma_k * sigma_px + 2.0 * span, self.min_side_px)
        n = int(min(round(side), self.view_side))
        return self.window(u - (n - 1) / 2.0, v - (n - 1) / 2.0, n, "track")

    # the policy's side ------------------------------------------------------------------

    def start(self) -> RoiState:
        """A flight's first window: the 45° view."""
        return RoiState(self.search_window(0), 0, self.lost_frames)

    def next_state(
        self,
        state: RoiState,
        seen: bool,
        estimate: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None,
        rot_body_to_ned: np.ndarray,
        dt_s: float,
    ) -> RoiState:
        """The window for the next frame after a step.

        Args:
            state: this step's ROI state (the window its frame was cut with).
            seen: the pad was detected in this step's frame (a horizontal fix).
            estimate: the estimator's (position, velocity, horizontal position variance (2,),
                initialised (3,)): vehicle relative to the pad, NED; None: no estimator.
            rot_body_to_ned: the attitude the next frame is predicted to be taken at.
            dt_s: time to the next frame (the control period).
        """
        unseen = 0 if seen else state.unseen + 1
        altitude = None
        if estimate is not None and bool(estimate[3][2]):
            altitude = -float(estimate[0][2])
        if estimate is not None and unseen < self.lost_frames:
            pos, vel, var_ne, init = estimate
            if bool(np.all(init)):
                ahead = np.asarray(pos, float) + np.asarray(vel, float) * dt_s
                pad_body = np.asarray(rot_body_to_ned, float).T @ (-ahead)
                sigma = math.sqrt(max(float(np.max(var_ne)), 0.0))
                window = self.track_window(pad_body, sigma)
                if window is not None:
                    return RoiState(window, 0, unseen)
        # a new search starts the sweep at the centre tile; search_step counts the tiles seen
        kind = state.window.kind
        seen_tiles = 0 if kind == "track" else state.search_step + (kind == "tile")
        last = "tile" if kind == "track" else kind
        return RoiState(self.search_window(seen_tiles, altitude, last), seen_tiles, unseen)


# --------------------------------------------------------------------------- a real camera


class RoiCameraSource(OpenCvCameraSource):
    """An OpenCV camera whose frames are cut to the policy's window at full resolution.

    The reader thread turns each frame to mono8 and rotates it (no crop, no resize); ``poll()``
    cuts every frame it hands on with the window the policy asks for next (:meth:`follow`:
    the :class:`~companion.runtime.PolicyRuntime` whose state says it; ``visland companion``
    with ``camera_roi`` follows its runtime), so frames leave as
    128 x 128 images like any source's. Until it follows a policy it cuts the 45° view, the
    image :class:`~companion.camera.OpenCvCameraSource` gives. ``roi`` is the
    :class:`RoiConfig` of the rotated frame: set it on the policy (``PolicyCore.roi``).

    Args:
        spec, fx_px, hfov_deg, cx_px, cy_px, rotate_deg, rate_hz, realtime, loop: as
            :class:`~companion.camera.OpenCvCameraSource`.
        pad_m / span_px: :class:`RoiConfig`'s.
    """

    def __init__(self, spec: str, *, pad_m: float = 1.0, span_px: float = 24.0, **kw: Any):
        self._pad_m = pad_m
        self._span_px = span_px
        self._window_fn = None
        super().__init__(spec, **kw)

    def _fit(self, raw: np.ndarray) -> np.ndarray:
        img = mono8(raw, self._rot)
        if not hasattr(self, "roi"):
            self.roi = self._roi_config(raw.shape[1], raw.shape[0])
        if img.shape != (self.roi.height_px, self.roi.width_px):
            raise CameraError(f"frame {img.shape}: expected the first frame's size")
        return img

    def _roi_config(self, w: int, h: int) -> RoiConfig:
        cx = (w - 1) / 2.0 if self._cx is None else self._cx
        cy = (h - 1) / 2.0 if self._cy is None else self._cy
        w, h, cx, cy = rotated_geometry(w, h, cx, cy, self._rot)
        return RoiConfig(w, h, self.fx_px, cx, cy, pad_m=self._pad_m, span_px=self._span_px)

    def follow(self, runtime: Any) -> None:
        """Cut with the window of the state ``runtime`` (a PolicyRuntime) answers the next
        frame from, and give its policy this camera's :class:`RoiConfig`."""
        runtime.policy.roi = self.roi
        self._window_fn = lambda: roi_window(runtime.next_state())

    def poll(self) -> list[ReceivedFrame]:
        """The frames since the last call, each cut with the window the next step maps its
        CNN output through: answer only the newest (older ones share it; log them)."""
        frames = super().poll()
        if not frames:
            return frames
        window = (self._window_fn() if self._window_fn is not None else None) or self.roi.view()
        return [ReceivedFrame(f.frame_id, f.time_s, cut(f.image, window), f.rx_s) for f in frames]
