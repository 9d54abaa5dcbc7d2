"""The pad estimator: a Kalman filter of pad-relative position and velocity (numpy, no torch)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.policy_net.config import NetConfig
from companion.policy_net.geometry import rotation_zyx

__all__ = ["EstimatorState", "PadEstimator"]


@dataclass(frozen=True)
class EstimatorState:
    """Kalman state per NED axis: ``x`` (3, n) = (position, velocity[, acceleration bias]),
    ``cov`` (3, n, n); n = 3 with ``NetConfig.accel_bias_states``, else 2."""

    x: np.ndarray
    cov: np.ndarray
    initialised: np.ndarray
    """(3,) bool: the axis has had a measurement."""
    rejected: int = 0
    """Consecutive horizontal fixes refused by the innovation gate."""
    rejected_altitude: int = 0
    """Consecutive altitude (radar) fixes refused by ``radar_gate_sigma``."""
    took_horizontal: bool = False
    """This step's horizontal fix (sure or unsure) was taken: it started or updated the
    estimate's position (the landing guard counts them to confirm the pad)."""
    reacquired: bool = False
    """This step's fix restarted the horizontal estimate after ``gate_reset_steps`` refusals in
    a row (``NetConfig.confirm_reset_on_reacquire``: the pad is confirmed again)."""


_MAX_BEAM_TILT_RAD = math.radians(80.0)
"""The radar beam's reach (``radar_terrain_slope_deg``) is taken at no more than this tilt."""

MAX_STEP_DT_S = 1.0
"""Longest gap between two steps the estimator predicts across (a longer one — a restarted
camera, clocks that do not compare — is taken as one control period)."""


class PadEstimator:
    """Pad-relative position and velocity from position fixes and the IMU (3 decoupled axes).

    Predict with the NED acceleration ``R f + g`` (specific force from HIGHRES_IMU rotated by
    ATTITUDE), update with the geometric fix; the horizontal fix noise grows with altitude (a
    fixed angular error of the bearing). A missing fix (pad not visible, invalid range) only
    predicts. A horizontal fix further than ``gate_sigma`` (Mahalanobis) from the prediction is
    refused — one confidently wrong CNN answer (a tilted view without the pad) would otherwise
    move the estimate by tens of metres —, and after ``gate_reset_steps`` refusals in a row the
    estimate re-acquires from the fix (the prediction, not the camera, was wrong).

    With ``accel_bias_states`` each axis also carries a bias added to the measured acceleration
    (a random walk): an IMU turn-on bias, and on Mars the 6.1 m/s^2 between its gravity and the
    configured Earth gravity, which a two-state filter would integrate into a velocity error.
    """

    def __init__(self, cfg: NetConfig) -> None:
        self.cfg = cfg
        self._n = 3 if cfg.accel_bias_states else 2
        self._f, self._b, self._q = self._model(cfg.control_dt_s)

    def _model(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Transition, acceleration input and process noise of one axis over ``dt`` seconds."""
        cfg = self.cfg
        q = cfg.accel_noise_m_s2**2
        q_pv = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt * dt]])
        if self._n == 3:
            f = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
            b = np.array([0.5 * dt * dt, dt, 0.0])
            qm = np.zeros((3, 3))
            qm[:2, :2] = q_pv
            qm[2, 2] = cfg.accel_bias_walk_m_s2**2 * dt
            return f, b, qm
        return np.array([[1.0, dt], [0.0, 1.0]]), np.array([0.5 * dt * dt, dt]), q_pv

    def initial_state(self) -> EstimatorState:
        n = self._n
        return EstimatorState(
            x=np.zeros((3, n)),
            cov=np.tile(np.eye(n) * 1e6, (3, 1, 1)),
            initialised=np.zeros(3, bool),
        )

    def _acquire(self, axis: int, z: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
        """State and covariance of an axis started from a fix ``z`` (velocity 0 +- 2 m/s)."""
        if self._n == 2:
            return np.array([z, 0.0]), np.diag([sigma**2, 4.0])
        bias_sigma = self.cfg.accel_bias_sigma_m_s2[axis]
        return np.array([z, 0.0, 0.0]), np.diag([sigma**2, 4.0, bias_sigma**2])

    @staticmethod
    def _beam_reach_m(x: np.ndarray, init: np.ndarray, rot: np.ndarray, alt: float) -> float:
        """Horizontal distance from the pad to where the radar's beam (body +z) meets ground
        level ``alt`` below the vehicle: the vehicle's offset (the estimate's, once it has one)
        plus the beam's lean, ``alt x tan(tilt)`` along the tilt (a beam near the horizon
        reaches no further than at :data:`_MAX_BEAM_TILT_RAD`)."""
        down = max(float(rot[2, 2]), math.cos(_MAX_BEAM_TILT_RAD))
        reach = alt * rot[:2, 2] / down
        if init[0] and init[1]:
            reach = reach + x[:2, 0]
        return float(math.hypot(float(reach[0]), float(reach[1])))

    def step(
        self,
        state: EstimatorState,
        fix_ned_m: np.ndarray | None,
        horizontal_fix: bool,
        attitude_rad: np.ndarray,
        accel_frd_m_s2: np.ndarray,
        fix_lag_s: float = 0.0,
        dt_s: float | None = None,
        vertical_fix: bool = True,
        vertical_lag_s: float = 0.0,
        vertical_sigma_m: float = 0.0,
        horizontal_sigma_m: float = 0.0,
        unsure: bool = False,
    ) -> EstimatorState:
        """One control period: predict from the last period's acceleration, then update.

        ``fix_lag_s``: the horizontal fix is where the vehicle was that long ago (a camera
        image's exposure time): it is measured as ``position - lag * velocity``, so the filter
        itself carries it to now. ``vertical_lag_s`` does the same for the vertical fix (the
        radar reading's age); ``vertical_fix=False``: the vertical part is not a new
        measurement (the same radar reading again) and only scales the horizontal one;
        ``vertical_sigma_m`` / ``horizontal_sigma_m`` add to the fixes' noise (in quadrature).
        ``dt_s``: the time since the previous step when it is not the control period (a frame
        lost on the link: two periods); None, or outside (0, MAX_STEP_DT_S], is one period.
        ``unsure``: the horizontal fix is an unsure one (``NetConfig.unsure_threshold``): it
        never starts the estimate, is not used from a view tilted beyond
        ``unsure_max_tilt_deg``, its noise is ``unsure_sigma_scale`` times larger, and a gate
        refusal drops it without counting towards a re-acquisition."""
        x, cov, init = state.x.copy(), state.cov.copy(), state.initialised.copy()
        rejected, rejected_alt = state.rejected, state.rejected_altitude
        rot = rotation_zyx(*(float(a) for a in attitude_rad))
        acc = rot @ np.asarray(accel_frd_m_s2, float) + np.array([0.0, 0.0, self.cfg.gravity_m_s2])
        if not np.all(np.isfinite(acc)):
            acc = np.zeros(3)
        f, b, q = self._f, self._b, self._q
        if (
            dt_s is not None
            and 0.0 < dt_s <= MAX_STEP_DT_S
            and abs(dt_s - self.cfg.control_dt_s) > 1e-6
        ):
            f, b, q = self._model(float(dt_s))
        for axis in range(3):
            if init[axis]:
                x[axis] = f @ x[axis] + b * acc[axis]
                cov[axis] = f @ cov[axis] @ f.T + q
        took = reacquired = False
        if fix_ned_m is not None and np.all(np.isfinite(fix_ned_m)):
            alt = max(-float(fix_ned_m[2]), 0.0)
            sigma_h = self.cfg.bearing_noise_floor_m + self.cfg.bearing_noise_rad * alt
            if horizontal_sigma_m > 0.0:
                sigma_h = math.hypot(sigma_h, float(horizontal_sigma_m))
            if unsure:
                sigma_h *= self.cfg.unsure_sigma_scale
                limit = self.cfg.unsure_max_tilt_deg
                level = limit is None or float(rot[2, 2]) >= math.cos(math.radians(limit))
                horizontal_fix = horizontal_fix and bool(init[0] and init[1]) and level
            sigma_v = self.cfg.alt_noise_m + self.cfg.alt_noise_fraction * alt
            if vertical_sigma_m > 0.0:
                sigma_v = math.hypot(sigma_v, float(vertical_sigma_m))
            slope = self.cfg.radar_terrain_slope_deg
            if slope > 0.0:  # the ground the radar's beam meets, not the pad's
                sigma_v = math.hypot(
                    sigma_v, math.tan(math.radians(slope)) * self._beam_reach_m(x, init, rot, alt)
                )
            sigmas = (sigma_h, sigma_h, sigma_v)
            horizontal_fix = horizontal_fix and alt >= self.cfg.min_fix_altitude_m
            axes: tuple[int, ...] = (0, 1, 2) if horizontal_fix else (2,)
            if not vertical_fix:
                axes = axes[:-1]
            h_alt = np.zeros(self._n)
            h_alt[:2] = (1.0, -float(vertical_lag_s))
            if vertical_fix and self.cfg.radar_gate_sigma > 0 and init[2]:
                innov = float(fix_ned_m[2]) - h_alt @ x[2]
                if innov**2 > self.cfg.radar_gate_sigma**2 * (cov[2, 0, 0] + sigmas[2] ** 2):
                    rejected_alt += 1
                    if rejected_alt >= self.cfg.gate_reset_steps and self.cfg.radar_full_reset:
                        # the radar, not the prediction, is right, and what drifted is the
                        # velocity or the bias: the whole axis re-acquires (radar_full_reset)
                        x[2], cov[2] = self._acquire(2, float(fix_ned_m[2]), sigmas[2])
                        rejected_alt = 0
                    elif rejected_alt >= self.cfg.gate_reset_steps:
                        # the radar, not the prediction, is right: the altitude re-acquires
                        # from it; the velocity and bias estimates stay
                        x[2, 0] = float(fix_ned_m[2]) + float(vertical_lag_s) * x[2, 1]
                        cov[2, 0, :] = 0.0
                        cov[2, :, 0] = 0.0
                        cov[2, 0, 0] = sigmas[2] ** 2
                        rejected_alt = 0
                    # the whole fix goes: its horizontal part is scaled by that altitude
                    axes, horizontal_fix = (), False
                else:
                    rejected_alt = 0
            h_lag = np.zeros(self._n)
            h_lag[:2] = (1.0, -float(fix_lag_s))
            if horizontal_fix and self.cfg.gate_sigma > 0 and init[0] and init[1]:
                d2 = sum(
                    (float(fix_ned_m[a]) - h_lag @ x[a]) ** 2
                    / (h_lag @ cov[a] @ h_lag + sigma_h**2)
                    for a in (0, 1)
                )
                if unsure:
                    if d2 > self.cfg.gate_sigma**2:
                        axes = axes[2:]
                elif d2 > self.cfg.gate_sigma**2:
                    rejected += 1
                    if rejected >= self.cfg.gate_reset_steps:
                        init[:2] = False  # re-acquire below from this fix
                        rejected = 0
                        reacquired = True
                    else:
                        axes = axes[2:]
                else:
                    rejected = 0
            took = 0 in axes
            for axis in axes:
                z = float(fix_ned_m[axis])
                if not init[axis]:
                    x[axis], cov[axis] = self._acquire(axis, z, sigmas[axis])
                    init[axis] = True
                    continue
                h = h_alt if axis == 2 else h_lag
                p = cov[axis]
                ph = p @ h
                s = h @ ph + sigmas[axis] ** 2
                k = ph / s
                if axis < 2 and self._n == 3 and alt < self.cfg.bias_learn_min_altitude_m:
                    # the bias is held (a consider state): Joseph form for the gain without it
                    k[2] = 0.0
                    i_kh = np.eye(self._n) - np.outer(k, h)
                    cov[axis] = i_kh @ p @ i_kh.T + np.outer(k, k) * sigmas[axis] ** 2
                else:
                    cov[axis] = p - np.outer(k, ph)
                x[axis] = x[axis] + k * (z - h @ x[axis])
        return EstimatorState(
            x=x,
            cov=cov,
            initialised=init,
            rejected=rejected,
            rejected_altitude=rejected_alt,
            took_horizontal=took,
            reacquired=reacquired,
        )
