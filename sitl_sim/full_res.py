"""A camera of more pixels than the policy's image: rendered at its full resolution, handed to
the policy as 128 x 128.

:class:`FullResSimulator` is a :class:`~sitl_sim.simulator.Simulator` whose ``[camera]``
``width_px`` x ``height_px`` (``fov_deg`` across the height, as every renderer takes it) is
not the policy's 128 x 128: each frame is rendered (and its light, effects and noise applied)
at full resolution, kept as :attr:`~FullResSimulator.full_frame`, and reduced to the policy's
image by the window the policy asked for (:meth:`~FullResSimulator.aim`: a
:class:`companion.roi.RoiWindow`, anything with ``cut(image) -> (128, 128)``), or without one
by the centred square of the policy's 45° field of view, area-resized — what the companion's
``fit_to_policy`` makes of a real camera's frame. :func:`make_simulator` picks it for such a
camera; a 128 x 128 camera gets the plain :class:`~sitl_sim.simulator.Simulator`, unchanged.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import cv2
import numpy as np

from companion.contract import CAMERA_FOV_DEG, IMAGE_SIZE_PX, GroundTruth
from sitl_sim.config import CameraConfig, SimConfig, VehicleConfig
from sitl_sim.errors import ConfigError
from sitl_sim.render.render_fast import camera_intrinsics
from sitl_sim.simulator import CameraFrame, Simulator

__all__ = ["FullResSimulator", "camera_geometry", "is_full_res", "make_simulator"]


def is_full_res(cfg: CameraConfig) -> bool:
    """Whether the camera is not the policy's own 128 x 128 image."""
    return (cfg.width_px, cfg.height_px) != (IMAGE_SIZE_PX, IMAGE_SIZE_PX)


def camera_geometry(cfg: CameraConfig) -> tuple[int, int, float, float, float]:
    """(width, height, focal length, cx, cy) in pixels of the renderers' pinhole camera
    (:func:`sitl_sim.render.render_fast.camera_intrinsics`; image top = body forward)."""
    k = camera_intrinsics(cfg)
    return cfg.width_px, cfg.height_px, float(k[0, 0]), float(k[0, 2]), float(k[1, 2])


def view_crop(cfg: CameraConfig) -> tuple[int, int, int]:
    """(x0, y0, side) of the centred square of the policy's 45° field of view.

    Raises:
        ConfigError: the camera is narrower than 45° (names ``[camera]``).
    """
    w, h, f, cx, cy = camera_geometry(cfg)
    n = round(2.0 * f * math.tan(math.radians(CAMERA_FOV_DEG) / 2.0))
    x0, y0 = round(cx - (n - 1) / 2.0), round(cy - (n - 1) / 2.0)
    if x0 < 0 or y0 < 0 or x0 + n > w or y0 + n > h:
        raise ConfigError(
            f"[camera] {w}x{h} px, fov_deg = {cfg.fov_deg} (vertical): the policy's "
            f"{CAMERA_FOV_DEG:g}° view needs {n} px; expected a wider field of view"
        )
    return x0, y0, n


class FullResSimulator(Simulator):
    """A :class:`Simulator` whose camera renders at full resolution; observations carry the
    128 x 128 image of the window :meth:`aim` set (default: the 45° view)."""

    def __init__(self, vehicle: VehicleConfig, sim: SimConfig, **kw: Any) -> None:
        self._crop = view_crop(sim.camera)
        super().__init__(vehicle, sim, **kw)
        self.full_frame: np.ndarray | None = None
        """The newest frame at full resolution (what the policy's image was cut from)."""
        self.window: Any = None
        """The window the next frame is cut with (None: the 45° view)."""

    def aim(self, window: Any) -> None:
        """Cut the frames from now on with ``window`` (``window.cut(image)``; None: the 45°
        view) — the window the policy's state asks for next."""
        self.window = window

    def capture_frame(self, truth: GroundTruth | None = None) -> CameraFrame:
        frame = super().capture_frame(truth)
        self.full_frame = frame.image
        if self.window is not None:
            image = self.window.cut(frame.image)
        else:
            x0, y0, n = self._crop
            crop = frame.image[y0 : y0 + n, x0 : x0 + n]
            size = (IMAGE_SIZE_PX, IMAGE_SIZE_PX)
            image = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
        return replace(frame, image=np.ascontiguousarray(image))


def make_simulator(vehicle: VehicleConfig, sim: SimConfig, **kw: Any) -> Simulator:
    """The simulator for ``sim``'s camera: :class:`FullResSimulator` when it is not 128 x 128."""
    cls = FullResSimulator if is_full_res(sim.camera) else Simulator
    return cls(vehicle, sim, **kw)
