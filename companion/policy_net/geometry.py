"""Pad-relative geometry and the controller's input features (numpy only, no torch).

The camera gives the pad's bearing, the radar the scale: :func:`position_from_bearing` turns
them into the vehicle position relative to the pad (NED), and :func:`control_features` the
position, velocity, attitude and IMU into the controller's input vector (:data:`FEATURE_NAMES`,
in the heading frame).
"""

from __future__ import annotations

import math

import numpy as np

from companion.contract import rotation_zyx

__all__ = [
    "FEATURE_NAMES",
    "HOVER_FEATURE",
    "HOVER_FEATURE_SCALE",
    "control_features",
    "feature_names",
    "position_at_altitude",
    "position_from_bearing",
    "rotation_zyx",
]

FEATURE_NAMES = (
    "x_h/10",
    "y_h/10",
    "alt/50",
    "min(alt,5)/5",
    "x_h/(alt+1)",
    "y_h/(alt+1)",
    "vx_h/3",
    "vy_h/3",
    "vz/3",
    "roll",
    "pitch",
    "p",
    "q",
    "r",
    "fx/g0",
    "fy/g0",
    "fz/g0",
    "visibility",
)
"""The controller's inputs, in order (``x_h``/``y_h``: vehicle position relative to the pad in
the heading frame — NED rotated by the current yaw —, ``alt`` above the pad, velocities in the
same frame, attitude and rates from ATTITUDE, specific force from HIGHRES_IMU in g0 units)."""

HOVER_FEATURE = "hover_thrust/0.4"
HOVER_FEATURE_SCALE = 0.4
"""The input a ``hover_input`` controller adds after :data:`FEATURE_NAMES`: the autopilot's hover
thrust over 0.4 (about 1 for the Table 1 vehicle on Earth, 0.38 on Mars)."""


def feature_names(hover_input: bool) -> tuple[str, ...]:
    """The controller's inputs, in order, for a config with or without ``hover_input``."""
    return (*FEATURE_NAMES, HOVER_FEATURE) if hover_input else FEATURE_NAMES


_G0 = 9.80665


def position_from_bearing(
    tan_right: float, tan_forward: float, attitude_rad: np.ndarray, range_m: float
) -> np.ndarray | None:
    """Vehicle position relative to the pad (NED, m) from the pad's bearing in the camera.

    The camera looks along body down with image up = body forward, so a pad seen at
    ``(tan_right, tan_forward)`` lies along body ``(tan_forward, tan_right, 1)``. The radar range
    is along body down, so the altitude is ``range * cos(roll) cos(pitch)``. Returns ``None`` when
    the geometry is degenerate (invalid range, ray not pointing at the ground).
    """
    if not math.isfinite(range_m) or range_m < 0:
        return None
    rot = rotation_zyx(*(float(a) for a in attitude_rad))
    return _on_ray(rot, tan_right, tan_forward, range_m * rot[2, 2])


def position_at_altitude(
    tan_right: float, tan_forward: float, attitude_rad: np.ndarray, altitude_m: float
) -> np.ndarray | None:
    """As :func:`position_from_bearing`, with the altitude above the pad given (e.g. the radar's
    altitude carried back to an image's exposure time) instead of the range along body down."""
    if not math.isfinite(altitude_m):
        return None
    return _on_ray(
        rotation_zyx(*(float(a) for a in attitude_rad)), tan_right, tan_forward, altitude_m
    )


def _on_ray(rot: np.ndarray, tan_right: float, tan_forward: float, alt: float) -> np.ndarray | None:
    ray = rot @ np.array([tan_forward, tan_right, 1.0])
    if ray[2] <= 1e-3 or alt <= 0:
        return None
    to_pad = ray * (alt / ray[2])
    return np.array([-to_pad[0], -to_pad[1], -alt])


def control_features(
    pos_ned_m: np.ndarray,
    vel_ned_m_s: np.ndarray,
    attitude_rad: np.ndarray,
    rate_frd_rad_s: np.ndarray,
    accel_frd_m_s2: np.ndarray,
    visibility: float,
    hover_thrust_norm: float | None = None,
) -> np.ndarray:
    """The controller's input vector, float32: :data:`FEATURE_NAMES`, then
    :data:`HOVER_FEATURE` when ``hover_thrust_norm`` is given (a ``hover_input`` controller)."""
    roll, pitch, yaw = (float(a) for a in attitude_rad)
    c, s = math.cos(yaw), math.sin(yaw)
    x_h = c * pos_ned_m[0] + s * pos_ned_m[1]
    y_h = -s * pos_ned_m[0] + c * pos_ned_m[1]
    vx_h = c * vel_ned_m_s[0] + s * vel_ned_m_s[1]
    vy_h = -s * vel_ned_m_s[0] + c * vel_ned_m_s[1]
    alt = -float(pos_ned_m[2])
    inv = 1.0 / (max(alt, 0.0) + 1.0)
    extra = () if hover_thrust_norm is None else (hover_thrust_norm / HOVER_FEATURE_SCALE,)
    return np.array(
        [
            x_h / 10,
            y_h / 10,
            alt / 50,
            min(max(alt, 0.0), 5.0) / 5,
            x_h * inv,
            y_h * inv,
            vx_h / 3,
            vy_h / 3,
            float(vel_ned_m_s[2]) / 3,
            roll,
            pitch,
            float(rate_frd_rad_s[0]),
            float(rate_frd_rad_s[1]),
            float(rate_frd_rad_s[2]),
            float(accel_frd_m_s2[0]) / _G0,
            float(accel_frd_m_s2[1]) / _G0,
            float(accel_frd_m_s2[2]) / _G0,
            float(visibility),
            *extra,
        ],
        dtype=np.float32,
    )
