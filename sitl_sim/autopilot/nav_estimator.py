"""The autopilot's own position estimate without GPS: inertial dead reckoning + the radar.

What a PX4 without GPS or optical flow has: the accelerometer (HIGHRES_IMU's specific force),
the attitude estimate (ATTITUDE) and a downward range finder. Horizontally it can only integrate
the acceleration, so its velocity carries the error it had when it was initialised plus the
integrated sensor noise and bias, and its position drifts without bound — which is why a
precision landing needs the landing target at all. Vertically the radar pins the altitude (flat
ground: the local origin is on the ground under the vehicle's start, so ``-z`` is the height).

The precision land (:mod:`sitl_sim.autopilot.precland`) flies on this estimate, never on ground
truth.
The one ground-truth input is the initial velocity, given *with an error* drawn from the
episode's generator (``initial_vel_sigma_m_s``): the velocity the estimator held when its last
aiding source was lost. A static landing target's relative velocity can aid the horizontal
velocity (:meth:`NavEstimator.fuse_velocity_ne`, PX4's ``LTEST_MODE = Stationary``).

Per axis (N, E, D) a 2-state Kalman filter (position, velocity) predicted with the NED
acceleration ``R(attitude) f + g``; sim time in, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.table import Bounded, bounded
from sitl_sim.physics.dynamics import quat_from_euler, quat_to_rotation

__all__ = ["NavConfig", "NavEstimator", "rotation_from_euler"]


def rotation_from_euler(attitude_rad: np.ndarray) -> np.ndarray:
    """(3, 3) body FRD -> NED from MAVLink ATTITUDE's (roll, pitch, yaw)."""
    return quat_to_rotation(quat_from_euler(*(float(a) for a in attitude_rad)))


@dataclass(frozen=True)
class NavConfig(Bounded):
    """Noise model of the GPS-less estimator (1-sigma).

    Attributes:
        initial_vel_sigma_m_s: horizontal velocity error at initialisation (per axis): the
            velocity known when GPS/flow was lost. 0.3 m/s is a typical optical-flow velocity
            accuracy at 10-20 m; it is the drift a landing target has to correct.
        accel_noise_m_s2: process noise of the prediction (accelerometer noise 0.05 m/s² plus
            the attitude estimate's 2 mrad seen through gravity, ≈ 0.02 m/s², rounded up with
            margin for the bias walk).
        radar_noise_m: altitude fix noise floor; ``radar_noise_fraction`` of the range is added
            (the radar of configs/sim.toml: 2 cm + 0.2 %).
        gravity_m_s2: the gravity the estimator assumes (Earth: a PX4 does not know the planet).
    """

    initial_vel_sigma_m_s: float = bounded(0.3, 0.0)
    accel_noise_m_s2: float = bounded(0.3, 0.0)
    radar_noise_m: float = bounded(0.05, 0.0)
    radar_noise_fraction: float = 0.002
    gravity_m_s2: float = 9.80665


class NavEstimator:
    """Position and velocity in the local NED frame (origin: on the ground below the start).

    Args:
        cfg: the noise model.
        altitude_m: height above the ground at initialisation (from the radar).
        vel_ned_m_s: (3,) initial velocity (already with its error).
    """

    def __init__(self, cfg: NavConfig, altitude_m: float, vel_ned_m_s: np.ndarray) -> None:
        if not math.isfinite(altitude_m):
            raise ValueError(f"initial altitude {altitude_m}: the estimator needs a radar fix")
        vel = np.asarray(vel_ned_m_s, dtype=float).reshape(3)
        self.cfg = cfg
        self.x = np.zeros((3, 2))
        """(3, 2): per NED axis (position m, velocity m/s)."""
        self.x[:, 1] = vel
        self.x[2, 0] = -float(altitude_m)
        sv = max(cfg.initial_vel_sigma_m_s, 0.05) ** 2
        self.cov = np.stack(
            [np.diag([0.01, sv]), np.diag([0.01, sv]), np.diag([cfg.radar_noise_m**2, 0.25])]
        )
        """(3, 2, 2) covariance per axis."""
        self.accel_ned_m_s2 = np.zeros(3)
        """The last NED acceleration used to predict (the landing-target filter's input)."""
        self.attitude_rad = np.zeros(3)
        """The last attitude estimate (roll, pitch, yaw) it was given."""

    @property
    def pos_ned_m(self) -> np.ndarray:
        return self.x[:, 0].copy()

    @property
    def vel_ned_m_s(self) -> np.ndarray:
        return self.x[:, 1].copy()

    @property
    def altitude_m(self) -> float:
        return -float(self.x[2, 0])

    def predict(self, dt_s: float, attitude_rad: np.ndarray, accel_frd_m_s2: np.ndarray) -> None:
        """Advance ``dt_s`` with the IMU's specific force rotated by the attitude estimate.
        A non-finite reading is skipped (the state coasts at constant velocity)."""
        att = np.asarray(attitude_rad, dtype=float)
        f = np.asarray(accel_frd_m_s2, dtype=float)
        acc = np.zeros(3)
        if np.all(np.isfinite(att)) and np.all(np.isfinite(f)):
            self.attitude_rad = att.copy()
            acc = rotation_from_euler(att) @ f + np.array([0.0, 0.0, self.cfg.gravity_m_s2])
        self.accel_ned_m_s2 = acc
        fm = np.array([[1.0, dt_s], [0.0, 1.0]])
        q = self.cfg.accel_noise_m_s2**2 * np.array(
            [[dt_s**4 / 4, dt_s**3 / 2], [dt_s**3 / 2, dt_s * dt_s]]
        )
        self.x[:, 0] += self.x[:, 1] * dt_s + 0.5 * acc * dt_s * dt_s
        self.x[:, 1] += acc * dt_s
        for axis in range(3):
            self.cov[axis] = fm @ self.cov[axis] @ fm.T + q

    def fuse_range(self, range_m: float, attitude_rad: np.ndarray) -> bool:
        """The radar range along body down → height above the flat ground. Returns whether it
        was used (a NaN reading, a dropout, is not)."""
        if not (math.isfinite(range_m) and range_m >= 0):
            return False
        roll, pitch = float(attitude_rad[0]), float(attitude_rad[1])
        height = range_m * math.cos(roll) * math.cos(pitch)
        sigma = self.cfg.radar_noise_m + self.cfg.radar_noise_fraction * range_m
        self._update(2, 0, -height, sigma**2)
        return True

    def fuse_velocity_ne(self, vel_ne_m_s: np.ndarray, var_ne: np.ndarray) -> None:
        """A horizontal velocity measurement (north, east) with its variances (m/s)²."""
        for axis in (0, 1):
            v, r = float(vel_ne_m_s[axis]), float(var_ne[axis])
            if math.isfinite(v) and math.isfinite(r) and r > 0:
                self._update(axis, 1, v, r)

    def _update(self, axis: int, index: int, z: float, r: float) -> None:
        p = self.cov[axis]
        s = p[index, index] + r
        k = p[:, index] / s
        self.x[axis] += k * (z - self.x[axis, index])
        self.cov[axis] = p - np.outer(k, p[index, :])
