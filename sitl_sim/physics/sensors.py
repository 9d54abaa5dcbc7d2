"""Sensor models with seeded noise: IMU, attitude estimate, radar altimeter.

Each model takes the ground truth and a ``numpy.random.Generator`` it was given; none keeps a
global random state, so a seed reproduces every reading bit for bit. A scenario's ``[sensors]``
faults (:mod:`sitl_sim.physics.sensor_faults`) come in as the IMU's turn-on biases and the radar's
``faults``; they draw from their own generators, never from these.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from sitl_sim.config import AttitudeConfig, ImuConfig, RadarConfig
from sitl_sim.physics.dynamics import euler_from_quat, quat_to_rotation
from sitl_sim.physics.sensor_faults import SensorFaults

__all__ = ["AttitudeReading", "AttitudeSensor", "Imu", "ImuReading", "RadarAltimeter"]


@dataclass(frozen=True)
class ImuReading:
    """HIGHRES_IMU content: specific force (m/s^2) and angular rate (rad/s), both FRD."""

    time_s: float
    accel_frd_m_s2: np.ndarray
    gyro_frd_rad_s: np.ndarray


@dataclass(frozen=True)
class AttitudeReading:
    """ATTITUDE content: the autopilot estimator's roll/pitch/yaw and body rates."""

    time_s: float
    attitude_rad: np.ndarray
    rate_frd_rad_s: np.ndarray


class Imu:
    """Accelerometer + gyro: white noise plus a bias that random-walks (per sqrt(s)) from its
    turn-on value (``accel_bias_frd_m_s2`` / ``gyro_bias_frd_rad_s``; None: zero)."""

    def __init__(
        self,
        cfg: ImuConfig,
        rng: np.random.Generator,
        accel_bias_frd_m_s2: np.ndarray | None = None,
        gyro_bias_frd_rad_s: np.ndarray | None = None,
    ) -> None:
        self._cfg = cfg
        self._rng = rng
        self._accel_bias = _turn_on(accel_bias_frd_m_s2)
        self._gyro_bias = _turn_on(gyro_bias_frd_rad_s)
        self._last_t: float | None = None

    def read(
        self, time_s: float, quat_wxyz, accel_ned_m_s2, rate_frd_rad_s, gravity_m_s2: float
    ) -> ImuReading:
        """Specific force ``R^T (a - g)`` and gyro, with noise and drifting biases."""
        cfg = self._cfg
        if self._last_t is not None and time_s > self._last_t:
            sq = math.sqrt(time_s - self._last_t)
            self._accel_bias += self._rng.normal(0.0, cfg.accel_bias_walk_m_s2_sqrt_s * sq, 3)
            self._gyro_bias += self._rng.normal(0.0, cfg.gyro_bias_walk_rad_s_sqrt_s * sq, 3)
        self._last_t = time_s
        rot = quat_to_rotation(quat_wxyz)
        specific_ned = np.asarray(accel_ned_m_s2, dtype=float) - np.array([0.0, 0.0, gravity_m_s2])
        accel = (
            rot.T @ specific_ned
            + self._accel_bias
            + self._rng.normal(0.0, cfg.accel_noise_std_m_s2, 3)
        )
        gyro = (
            np.asarray(rate_frd_rad_s, dtype=float)
            + self._gyro_bias
            + self._rng.normal(0.0, cfg.gyro_noise_std_rad_s, 3)
        )
        return ImuReading(time_s, accel, gyro)


def _turn_on(bias: np.ndarray | None) -> np.ndarray:
    return np.zeros(3) if bias is None else np.array(bias, dtype=float).reshape(3)


class AttitudeSensor:
    """The autopilot's attitude estimate: true Euler angles and rates plus white noise."""

    def __init__(self, cfg: AttitudeConfig, rng: np.random.Generator) -> None:
        self._cfg = cfg
        self._rng = rng

    def read(self, time_s: float, quat_wxyz, rate_frd_rad_s) -> AttitudeReading:
        att = euler_from_quat(quat_wxyz) + self._rng.normal(0.0, self._cfg.angle_noise_std_rad, 3)
        att[2] = (att[2] + math.pi) % (2 * math.pi) - math.pi
        rate = np.asarray(rate_frd_rad_s, dtype=float) + self._rng.normal(
            0.0, self._cfg.rate_noise_std_rad_s, 3
        )
        return AttitudeReading(time_s, att, rate)


Surface = Callable[[Any, tuple[float, float, float], float, float], float]
"""``(origin_ned, direction_ned, time_s, max_range) -> range`` to a site's first surface (inf:
none within ``max_range``): :meth:`sitl_sim.site.site.Site.range_along`."""


class RadarAltimeter:
    """Downward radar: range along the body down axis to the ground (the flat plane, or with
    ``surface`` a site's terrain, rocks, rover roof, deck or water), 0..max_range.

    ``range = altitude / cos(tilt)`` for the beam along body +z; the reading is NaN (invalid) when
    the beam does not hit the ground (tilt >= 90 deg) or the range exceeds ``max_range_m``.
    Noise: ``noise_std_m + noise_fraction * range`` (1-sigma), never below zero. ``faults``
    (the episode's :class:`~sitl_sim.physics.sensor_faults.SensorFaults`, or None) then replaces a
    reading by a dropout (NaN) or a spurious return; the noise is drawn as without faults, so
    the readings a fault leaves alone are those of the same flight without it.
    """

    def __init__(
        self,
        cfg: RadarConfig,
        rng: np.random.Generator,
        faults: SensorFaults | None = None,
        surface: Surface | None = None,
    ) -> None:
        self._cfg = cfg
        self._rng = rng
        self._faults = faults
        self._surface = surface

    @property
    def max_range_m(self) -> float:
        return self._cfg.max_range_m

    def true_range(self, pos_ned_m, quat_wxyz, time_s: float = 0.0) -> float:
        """Noise-free beam length to the ground (inf when the beam misses it): on a site
        (``surface``), to whatever surface the body's down axis meets first at ``time_s``."""
        qw, qx, qy, qz = (float(v) for v in quat_wxyz)
        cos_tilt = 1.0 - 2.0 * (qx * qx + qy * qy)
        if self._surface is not None:
            down = (2.0 * (qx * qz + qw * qy), 2.0 * (qy * qz - qw * qx), cos_tilt)
            return self._surface(pos_ned_m, down, time_s, self._cfg.max_range_m)
        altitude = max(0.0, -float(pos_ned_m[2]))
        if cos_tilt <= 1e-6:
            return math.inf
        return altitude / cos_tilt

    def read(self, pos_ned_m, quat_wxyz, time_s: float = 0.0) -> float:
        """One reading at ``time_s`` (sim time: where a moving surface is)."""
        reading = self._read(pos_ned_m, quat_wxyz, time_s)
        if self._faults is None:
            return reading
        return self._faults.radar_reading(reading, self._cfg.max_range_m)

    def _read(self, pos_ned_m, quat_wxyz, time_s: float) -> float:
        rng_true = self.true_range(pos_ned_m, quat_wxyz, time_s)
        if not rng_true <= self._cfg.max_range_m:
            return math.nan
        sigma = self._cfg.noise_std_m + self._cfg.noise_fraction * rng_true
        return max(0.0, rng_true + float(self._rng.normal(0.0, sigma)) if sigma > 0 else rng_true)
