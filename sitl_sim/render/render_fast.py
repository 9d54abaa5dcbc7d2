"""The fast camera: the flat ground and the pad warped onto the image by plane homographies.

The world under a landing camera is a plane (the ground) and two thin layers on it (the pad's
green square and red cross, a few centimetres up). A point on the horizontal plane at depth
``d0`` maps to the image by a 3x3 homography, so the whole frame is three
``cv2.warpPerspective`` calls of a 128 x 128 image — tens of microseconds each, independent of
the texture's size — instead of rasterising the scene:

    pixel ~ K · C · Rᵀ · [[1, 0, -n], [0, 1, -e], [0, 0, d0 - d]] · (north, east, 1)

with ``R`` the body-to-NED rotation, ``(n, e, d)`` the camera position, ``C`` the body-to-image
axes (image right = body right, image down = body back, optical axis = body down) and ``K`` the
pinhole intrinsics of :class:`~sitl_sim.config.CameraConfig` (vertical field of view, pixel
centres at integers). Texels are sampled nearest-neighbour like pybullet's TinyRenderer, which
stays the reference renderer (:class:`sitl_sim.render.scene.Scene`); ``tests/test_render_fast.py``
holds the two to the same image across the visual conditions.

Points behind the camera never reach the image: the homography is only valid for a camera
above the plane looking at it; a camera at or below a layer's height sees none of that layer
(the pad's layers vanish when the camera is on them, as in a render from inside the box).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from sitl_sim.config import CameraConfig
from sitl_sim.physics.dynamics import quat_to_rotation
from sitl_sim.render.fast_site import BODY_TO_IMAGE as _BODY_TO_IMAGE
from sitl_sim.render.fast_site import FastSite
from sitl_sim.render.ground import GroundMap, PadGeometry, PadLook, PadTexture, luma, nominal_ground
from sitl_sim.render.site_look import SiteLook
from sitl_sim.render.terrain import Sun
from sitl_sim.site.site import Site

__all__ = ["FastRenderer", "camera_intrinsics", "plane_homography"]

_PAD_TEXELS_PER_M = 100  # 1 cm texels: the pad's edges stay sharp down to touchdown


def camera_intrinsics(cfg: CameraConfig) -> np.ndarray:
    """K: focal length from the vertical field of view, square pixels, and the principal point
    on TinyRenderer's pixel grid: ``(w/2, h/2 - 1)`` in OpenCV's integer-centre pixels (measured
    by fitting renders; the half pixel either side of ``(w-1)/2`` is its rasteriser's rounding
    and the bottom-up row order of its frame buffer). Within a pixel of the ideal centre."""
    f = 0.5 * cfg.height_px / math.tan(math.radians(cfg.fov_deg) / 2)
    return np.array(
        [[f, 0.0, cfg.width_px / 2], [0.0, f, cfg.height_px / 2 - 1.0], [0.0, 0.0, 1.0]]
    )


def plane_homography(
    k: np.ndarray, pos_ned_m, rot_body_to_ned: np.ndarray, depth_m: float
) -> np.ndarray:
    """The homography from (north, east, 1) on the plane at NED depth ``depth_m`` to pixels."""
    n, e, d = (float(v) for v in pos_ned_m)
    shift = np.array([[1.0, 0.0, -n], [0.0, 1.0, -e], [0.0, 0.0, depth_m - d]])
    return k @ _BODY_TO_IMAGE @ rot_body_to_ned.T @ shift


class FastRenderer:
    """Renders a :class:`GroundMap` and a :class:`PadGeometry` to mono8 (no pybullet), under
    the reference scene's full, overhead light (the camera applies the episode's light level);
    with a landing site (:mod:`sitl_sim.site`), its slope, relief, rocks, vehicle and the pad
    where it is at the frame's time (:mod:`sitl_sim.render.fast_site`)."""

    def __init__(
        self,
        ground: GroundMap | None = None,
        pad: PadLook | None = None,
        site: Site | None = None,
        sun: Sun | None = None,
    ) -> None:
        self._k_cache: tuple[CameraConfig, np.ndarray] | None = None
        self._site: FastSite | None = None
        self.configure(ground or nominal_ground(), pad or PadGeometry(), site, sun)

    def configure(
        self, ground: GroundMap, pad: PadLook, site: Site | None = None, sun: Sun | None = None
    ) -> None:
        """Show ``ground`` and ``pad`` from now on (a new episode's world), on ``site`` (None:
        the pad still on flat ground) lit by ``sun`` (None: overhead)."""
        self.ground = ground
        self.pad = pad
        self._ground_mono = ground.mono
        self._set_layers(pad)
        self._site = FastSite(SiteLook(ground, site, sun), self._layers) if site else None

    def _set_layers(self, pad: PadLook) -> None:
        if isinstance(pad, PadTexture):
            # one layer: inside << 8 | grey per texel in one uint16 channel (OpenCV warps one
            # channel several times faster than two)
            packed = pad.mono.astype(np.uint16) | np.uint16(0x100)
            self._layers = [(packed, pad.texel_to_ne, pad.top_m, None)]
            return
        square, square_to_ne = _pad_layer(pad, cross=False)
        cross, cross_to_ne = _pad_layer(pad, cross=True)
        # TinyRenderer turns a float colour into bytes by truncation (0.25 -> 63)
        greys = [luma((np.array(c) * 255.0).astype(np.uint8)) for c in (pad.green_rgb, pad.red_rgb)]
        # label -> grey level: 0 = ground (painted separately), 1 = green, 2 = red (a LUT)
        grey = np.zeros(256, dtype=np.uint8)
        grey[1:3] = greys
        self._layers = [
            (square, square_to_ne, pad.square_top_m, grey),
            (cross, cross_to_ne, pad.cross_top_m, grey),
        ]

    def _k(self, cfg: CameraConfig) -> np.ndarray:
        if self._k_cache is None or self._k_cache[0] != cfg:
            self._k_cache = (cfg, camera_intrinsics(cfg))
        return self._k_cache[1]

    def render(self, pos_ned_m, quat_wxyz, cfg: CameraConfig, time_s: float = 0.0) -> np.ndarray:
        """Noise-free mono8 image (height, width), row 0 = body forward; ``time_s``: the sim
        time the frame shows (where a moving pad is)."""
        k = self._k(cfg)
        rot = quat_to_rotation(quat_wxyz)
        size = (cfg.width_px, cfg.height_px)
        if self._site is not None:
            return self._site.render(k, pos_ned_m, rot, size, time_s)
        g = self.ground
        h_ground = plane_homography(k, pos_ned_m, rot, 0.0) @ g.texel_to_ne
        image = cv2.warpPerspective(
            self._ground_mono,
            h_ground,
            size,
            flags=cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_WRAP if g.periodic else cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        altitude = -float(pos_ned_m[2])
        for texels, to_ne, top, grey in self._layers:
            if altitude <= top:
                continue
            h = plane_homography(k, pos_ned_m, rot, -top) @ to_ne
            layer = cv2.warpPerspective(
                texels, h, size, flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT
            )
            if grey is None:  # a picture: inside << 8 | grey
                np.copyto(image, layer.astype(np.uint8), where=layer >= 0x100)
            else:  # labels: 0 = none, else the grey of grey[label]
                np.copyto(image, cv2.LUT(layer, grey), where=layer != 0)
        return image

    def close(self) -> None:
        """Nothing to release (the same interface as :class:`sitl_sim.render.scene.Scene`)."""

    def __enter__(self) -> FastRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _pad_layer(pad: PadGeometry, cross: bool) -> tuple[np.ndarray, np.ndarray]:
    """A label texture of one pad layer (1 = green square, 2 = red cross) and its texel->NE map.

    Box edges follow TinyRenderer's fill rule closely enough at 1 cm texels (< 0.1 px at any
    altitude the camera flies above the pad).
    """
    half = pad.side_m / 2 if not cross else pad.cross_length_m / 2
    n = max(2, math.ceil(2 * half * _PAD_TEXELS_PER_M))
    s = 2 * half / n
    coords = (np.arange(n) + 0.5) * s - half  # texel centres
    north = coords[None, :] * np.ones((n, 1))  # columns: north
    east = -coords[:, None] * np.ones((1, n))  # rows: east downwards negative, like the ground
    if cross:
        w = pad.cross_width_m / 2
        inside = (np.abs(north) <= w) | (np.abs(east) <= w)
        labels = np.where(inside, 2, 0).astype(np.uint8)
    else:
        labels = np.ones((n, n), dtype=np.uint8)
    c = (n - 1) / 2
    to_ne = np.array([[s, 0.0, -c * s], [0.0, -s, c * s], [0.0, 0.0, 1.0]])
    return labels, to_ne
