"""The learned policy without its networks: geometry, estimator and checks behind ``act``.

:class:`PolicyCore` is everything of a learned policy but the two networks: the bearing → position
geometry, the pad estimator (Kalman), the latency compensation, the controller's input features,
the checks and clamps of ``act``. A backend supplies the networks through two methods:

* ``perceive(image) -> (tan_right, tan_forward, visibility_logit)`` — the CNN on one image;
* ``control_step(features (F,), state) -> (command (4,), state)`` — one step of the LSTM, its
  recurrent state opaque to this code, with ``zero_state()`` its start.

:class:`companion.policy_net.LearnedPolicy` runs them in torch (training and the ``torch``
runtime); :class:`companion.onnx_runtime.OnnxPolicy` in ONNX Runtime (the board runtime). This
module imports no torch: the board flies this exact code.
"""

from __future__ import annotations

import copy
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from itertools import pairwise
from typing import Any

import numpy as np

from companion.contract import Command, Observation
from companion.policy_net.config import NetConfig
from companion.policy_net.estimator import EstimatorState, PadEstimator
from companion.policy_net.geometry import (
    control_features,
    position_at_altitude,
    position_from_bearing,
    rotation_zyx,
)
from companion.policy_net.guard import GuardState, LandingGuard
from companion.roi import RoiConfig, RoiState

__all__ = ["PolicyCore", "PolicyState", "attitude_at"]


@dataclass(frozen=True)
class PolicyState:
    """Recurrent state of a learned policy (never mutated in place)."""

    lstm: tuple[Any, ...]
    """The controller's recurrent state, as its backend holds it (torch or numpy arrays)."""
    estimator: EstimatorState | None = None
    last_perception: np.ndarray | None = None
    """The CNN's last raw output (tan_right, tan_forward, visibility logit), for logs."""
    attitudes: tuple[tuple[float, np.ndarray], ...] = ()
    """The last few (ATTITUDE time, attitude) samples, oldest first (``latency_compensation``:
    the attitude at an image's exposure time is interpolated from them)."""
    last_image_time_s: float | None = None
    """Exposure time of the newest image used for a fix (a repeated image gives none)."""
    last_step_time_s: float | None = None
    """ATTITUDE time of the previous vision step: the estimator predicts across the real gap,
    two periods after a frame lost on the link."""
    last_range_time_s: float | None = None
    """Time stamp of the newest radar reading used as an altitude fix: over a real link the
    reading at hand is often the previous one again (DISTANCE_SENSOR late or lost), and a
    reading is measured once."""
    fixes: int = 0
    """Horizontal fixes the estimator took this flight (with ``confirm_reset_on_reacquire``:
    since its last re-acquisition) at a pad probability of at least ``confirm_threshold`` (the
    landing guard's confirmation of the pad)."""
    guard: GuardState | None = None
    """The landing guard's state (:mod:`companion.policy_net.guard`); None: no guard (a
    privileged policy, ``land_floor_m`` None)."""
    roi: RoiState | None = None
    """With ``PolicyCore.roi``: the full-resolution window this step's frame is cut with
    (:mod:`companion.roi`); the step maps the CNN's bearing through it and sets the next."""


_MAX_CAMERA_LAG_S = 0.5
"""A camera lag (ATTITUDE time minus image exposure time) beyond this, or negative, is taken as
clocks that do not compare (e.g. a companion-clock camera): the fix is used as of now."""
_ATTITUDE_HISTORY = 4


@dataclass(frozen=True)
class _Fix:
    """One step's measurements for the estimator (see :meth:`PolicyCore._fix`)."""

    position: np.ndarray | None
    """(north, east) of the vehicle from the pad at the image's exposure, and down = minus the
    radar's altitude at the reading's time; None: no geometry (invalid range, degenerate ray)."""
    horizontal: bool
    """The horizontal part is a new measurement (not a repeated image)."""
    lag_s: float
    """Age of the horizontal part at this step (s)."""
    vertical: bool = True
    """The radar reading is new (not the previous one again)."""
    vertical_lag_s: float = 0.0
    """Age of the radar reading at this step (s)."""
    vertical_sigma_m: float = 0.0
    """Extra altitude noise (m) from not knowing the attitude at the reading's own time."""
    horizontal_sigma_m: float = 0.0
    """Extra horizontal noise (m) from not knowing the attitude at the image's own time."""


def _angle_lerp(a0: np.ndarray, a1: np.ndarray, w: float) -> np.ndarray:
    d = (a1 - a0 + math.pi) % (2 * math.pi) - math.pi
    return a0 + w * d


def attitude_at(history: tuple[tuple[float, np.ndarray], ...], t: float) -> np.ndarray:
    """The attitude at time ``t``, linearly interpolated (angles wrapped) between the samples of
    ``history`` (oldest first) that bracket it; the oldest / newest sample outside them."""
    if t <= history[0][0]:
        return history[0][1]
    for (t0, a0), (t1, a1) in pairwise(history):
        if t <= t1:
            return a0 if t1 <= t0 else _angle_lerp(a0, a1, (t - t0) / (t1 - t0))
    return history[-1][1]


def _attitude_error_m(
    history: tuple[tuple[float, np.ndarray], ...],
    t: float,
    rate_frd_rad_s: np.ndarray | None,
    size_m: float,
    kind: int,
) -> float:
    """The error (m) of a measurement at ``t`` made through :func:`attitude_at` of the step's
    ATTITUDE samples (one per frame) when none is of time ``t`` — on a real link the radar
    reading and the image come with other periods' samples, and at 1-2 rad/s an attitude
    20 ms off is 1-2 degrees: metres at 90 m. The attitude is taken as off by ``roll/pitch
    rate x gap``, the gap being to the nearest sample (``kind`` 1, an altitude from a range
    ``size_m`` along body down: ``size_m x sin(tilt) x angle``) or beyond the newest (``kind``
    2, a bearing fix at altitude ``size_m``: ``size_m x angle / cos^2(tilt)``; an image between
    samples, a camera latency, is interpolated as before). 0 when every reading has a sample of
    its own time, as always in lockstep and in process."""
    if kind == 1:
        gap = min(abs(t - ti) for ti, _ in history)
    else:
        gap = max(t - history[-1][0], history[0][0] - t, 0.0)
    if gap <= 1e-6 or rate_frd_rad_s is None:
        return 0.0
    held = attitude_at(history, t)
    cos_tilt = max(math.cos(float(held[0])) * math.cos(float(held[1])), 0.1)
    angle = math.hypot(float(rate_frd_rad_s[0]), float(rate_frd_rad_s[1])) * gap
    if kind == 1:
        return size_m * math.sqrt(1.0 - cos_tilt**2) * angle
    return size_m * angle / cos_tilt**2


class PolicyCore(ABC):
    """A learned policy's ``initial_state`` / ``act`` over a backend's two networks.

    ``groundtruth`` (a :class:`companion.contract.GroundTruth`: the simulator's, or the
    companion's ODOMETRY record) is read only by privileged policies. Vision policies ignore it
    (pass ``None`` on hardware). Subclasses set ``config`` and call :meth:`_init_core`.
    """

    config: NetConfig
    roi: RoiConfig | None = None
    """A full-resolution camera's region of interest (:mod:`companion.roi`); None: the 128 px
    45° image as it comes (the default, every shipped flight)."""

    def with_settings(self, settings: dict[str, Any]) -> PolicyCore:
        """This policy (the same networks) flying with :data:`ESTIMATOR_FIELDS` values
        replaced (``--estimator KEY=VALUE``: ``visland eval``, the companion); a bad key or
        value is a :class:`~companion.policy_net.config.CheckpointError` naming it."""
        if not settings:
            return self
        other = copy.copy(self)
        other.config = self.config.with_settings(settings)
        other._init_core()
        return other

    def _init_core(self) -> None:
        self._estimator = PadEstimator(self.config)
        self._guard = LandingGuard(self.config)

    # the backend's networks -------------------------------------------------------------

    @abstractmethod
    def perceive(self, image: np.ndarray) -> np.ndarray:
        """The CNN's raw output for one image: (tan_right, tan_forward, visibility logit)."""

    @abstractmethod
    def zero_state(self) -> tuple[Any, ...]:
        """The controller's recurrent state at the start of a flight."""

    @abstractmethod
    def control_step(
        self, features: np.ndarray, state: tuple[Any, ...]
    ) -> tuple[np.ndarray, tuple[Any, ...]]:
        """One controller step: features (F,) float32 → raw command (4,) and the next state."""

    # the policy ---------------------------------------------------------------------------

    @property
    def privileged(self) -> bool:
        return self.config.kind == "privileged"

    def initial_state(self) -> PolicyState:
        est = None if self.privileged else self._estimator.initial_state()
        roi = None if self.privileged or self.roi is None else self.roi.start()
        guard = None if self.privileged or self.config.land_floor_m is None else GuardState()
        return PolicyState(lstm=self.zero_state(), estimator=est, roi=roi, guard=guard)

    def features(
        self, observation: Observation, groundtruth: Any, state: PolicyState
    ) -> tuple[np.ndarray, PolicyState]:
        """The controller input for this step and the state with the estimator advanced."""
        if self.privileged:
            if groundtruth is None:
                raise ValueError(
                    "privileged policy: needs ground truth (position/velocity); it cannot fly "
                    "on hardware — use a vision policy"
                )
            # relative to the pad (a rover's, a deck's): what the vision estimator estimates
            pos, vel = groundtruth.pad_relative
            feats = control_features(
                np.asarray(pos, float),
                np.asarray(vel, float),
                observation.attitude_rad,
                observation.rate_frd_rad_s,
                observation.accel_frd_m_s2,
                1.0,
                self.config.hover_feature(observation.hover_thrust_norm),
            )
            return feats, state
        raw = self.perceive(observation.image)
        return self.vision_features(
            raw,
            observation.attitude_rad,
            observation.rate_frd_rad_s,
            observation.accel_frd_m_s2,
            observation.range_m,
            state,
            hover_thrust_norm=observation.hover_thrust_norm,
            image_time_s=observation.image_time_s,
            attitude_time_s=observation.attitude_time_s,
            range_time_s=observation.range_time_s,
        )

    def _fix(
        self,
        raw: np.ndarray,
        attitude_rad: np.ndarray,
        range_m: float,
        state: PolicyState,
        image_time_s: float,
        attitude_time_s: float,
        range_time_s: float = math.nan,
        rate_frd_rad_s: np.ndarray | None = None,
    ) -> tuple[_Fix, PolicyState]:
        """This step's measurements and the state with the attitude history advanced.

        With ``latency_compensation`` each measurement is taken at its own time: the horizontal
        fix is where the vehicle was at the image's exposure (the bearing through the attitude
        then, scaled by the altitude then); the vertical fix is the radar's altitude at the
        reading's time (its range through the attitude then), a reading used once — over a
        real link the newest DISTANCE_SENSOR at a frame is often the previous period's, and
        taking it again as "now" freezes the altitude and then jumps it, which the estimator
        reads as a vertical velocity. The estimator carries both to now. Without it (or
        without times), every fix is as of now.

        The range is turned into an altitude through the attitude at the reading's time,
        interpolated from the ATTITUDE samples around it; a reading between or beyond them
        (their times differ on a real link) gets the altitude error of an attitude off by
        ``roll/pitch rate x gap``: ``altitude x tan(tilt) x rate x gap``; the image's bearing
        likewise, ``altitude x rate x gap / cos^2(tilt)`` horizontally. Both are zero when the
        reading and the image have an attitude sample of their own time (always in lockstep
        and in process)."""
        cfg = self.config
        if not (
            cfg.latency_compensation
            and math.isfinite(image_time_s)
            and math.isfinite(attitude_time_s)
        ):
            fix = position_from_bearing(float(raw[0]), float(raw[1]), attitude_rad, range_m)
            return _Fix(fix, True, 0.0), state
        history = (*state.attitudes, (float(attitude_time_s), np.asarray(attitude_rad, float)))
        state = replace(state, attitudes=history[-_ATTITUDE_HISTORY:])
        est = state.estimator
        assert est is not None
        v_down = float(est.x[2, 1]) if est.initialised[2] else 0.0
        # the radar reading: its age, whether it is new, how well its attitude is known
        r_lag, vertical, sigma_v = 0.0, True, 0.0
        if math.isfinite(range_time_s) and math.isfinite(range_m):
            sigma_v = _attitude_error_m(history, range_time_s, rate_frd_rad_s, range_m, 1)
            last_r = state.last_range_time_s
            vertical = last_r is None or range_time_s > last_r
            if vertical:
                state = replace(state, last_range_time_s=float(range_time_s))
            age = attitude_time_s - range_time_s
            if 0.0 < age <= _MAX_CAMERA_LAG_S:
                r_lag = age
            elif age > _MAX_CAMERA_LAG_S:
                vertical = False  # too old to measure with; it still scales the bearing
        if r_lag > 0.0:
            alt_r = range_m * float(rotation_zyx(*attitude_at(history, range_time_s))[2, 2])
            fix = position_at_altitude(
                float(raw[0]), float(raw[1]), attitude_rad, alt_r - v_down * r_lag
            )
            if fix is not None:
                fix[2] = -alt_r
        else:
            fix = position_from_bearing(float(raw[0]), float(raw[1]), attitude_rad, range_m)
        last = state.last_image_time_s
        if last is not None and image_time_s <= last:
            # the same image again (a lost frame): radar only
            return _Fix(fix, False, 0.0, vertical, r_lag, sigma_v), state
        state = replace(state, last_image_time_s=float(image_time_s))
        lag = attitude_time_s - image_time_s
        if fix is None or not -_MAX_CAMERA_LAG_S < lag <= _MAX_CAMERA_LAG_S:
            return _Fix(fix, True, 0.0, vertical, r_lag, sigma_v), state
        # the image is newer than the newest ATTITUDE (it came first over the link): the fix
        # is as of now, through the newest attitude, with the error of that attitude's age
        sigma_h = _attitude_error_m(history, image_time_s, rate_frd_rad_s, -float(fix[2]), 2)
        if lag <= 0.0:
            return _Fix(fix, True, 0.0, vertical, r_lag, sigma_v, sigma_h), state
        # the altitude at the exposure: the radar's, carried from its time to the image's
        alt_img = -float(fix[2]) + v_down * ((attitude_time_s - r_lag) - image_time_s)
        seen_from = position_at_altitude(
            float(raw[0]), float(raw[1]), attitude_at(history, image_time_s), alt_img
        )
        if seen_from is None:
            return _Fix(fix, False, 0.0, vertical, r_lag, sigma_v), state
        return _Fix(
            np.array([seen_from[0], seen_from[1], fix[2]]),
            True,
            lag,
            vertical,
            r_lag,
            sigma_v,
            sigma_h,
        ), state

    def fix_threshold(self, estimator: EstimatorState) -> float:
        """The pad probability a bearing needs to be a horizontal fix: ``acquire_threshold``
        while the estimate has no horizontal position yet, ``visibility_threshold`` after."""
        cfg = self.config
        if cfg.acquire_threshold is not None and not bool(np.all(estimator.initialised[:2])):
            return cfg.acquire_threshold
        return cfg.visibility_threshold

    def unsure_fix(self, vis: float, estimator: EstimatorState) -> bool:
        """Whether a bearing of pad probability ``vis`` is an unsure fix: at or above
        ``unsure_threshold``, below the fix threshold, and the estimate has a horizontal
        position for the innovation gate to hold it against."""
        cfg = self.config
        return (
            cfg.unsure_threshold is not None
            and cfg.unsure_threshold <= vis < self.fix_threshold(estimator)
            and bool(np.all(estimator.initialised[:2]))
        )

    def vision_features(
        self,
        raw: np.ndarray,
        attitude_rad: np.ndarray,
        rate_frd_rad_s: np.ndarray,
        accel_frd_m_s2: np.ndarray,
        range_m: float,
        state: PolicyState,
        hover_thrust_norm: float = math.nan,
        image_time_s: float = math.nan,
        attitude_time_s: float = math.nan,
        range_time_s: float = math.nan,
    ) -> tuple[np.ndarray, PolicyState]:
        """Controller input from the CNN's output (``perceive``) and the sensors; estimator step.

        Split from :meth:`features` so training can batch the CNN over a recorded flight and
        still run exactly this code for the rest. The times are the Observation's (used with
        ``latency_compensation``), ``hover_thrust_norm`` its hover thrust (``hover_input``).
        With an ROI state, ``raw`` is the CNN's output on the window and is mapped to the
        camera's bearing first.
        """
        if state.roi is not None:
            raw = state.roi.window.to_camera(raw)
        vis = 1.0 / (1.0 + math.exp(-float(np.clip(raw[2], -30, 30))))
        dt = None  # the step's own time (its ATTITUDE's), not the image's: a repeated image
        if math.isfinite(attitude_time_s):  # still comes one period after the previous step
            if state.last_step_time_s is not None:
                dt = attitude_time_s - state.last_step_time_s
            state = replace(state, last_step_time_s=float(attitude_time_s))
        fix, state = self._fix(
            raw,
            attitude_rad,
            range_m,
            state,
            image_time_s,
            attitude_time_s,
            range_time_s,
            rate_frd_rad_s,
        )
        assert state.estimator is not None
        seen = fix.horizontal and vis >= self.fix_threshold(state.estimator)
        unsure = self.unsure_fix(vis, state.estimator) and fix.horizontal and not seen
        est = self._estimator.step(
            state.estimator,
            fix.position,
            seen or unsure,
            attitude_rad,
            accel_frd_m_s2,
            fix_lag_s=fix.lag_s,
            dt_s=dt,
            vertical_fix=fix.vertical,
            vertical_lag_s=fix.vertical_lag_s,
            vertical_sigma_m=fix.vertical_sigma_m,
            horizontal_sigma_m=fix.horizontal_sigma_m,
            unsure=unsure,
        )
        feats = control_features(
            est.x[:, 0],
            est.x[:, 1],
            attitude_rad,
            rate_frd_rad_s,
            accel_frd_m_s2,
            vis,
            self.config.hover_feature(hover_thrust_norm),
        )
        if state.roi is not None and self.roi is not None:
            var_ne = np.array([est.cov[0][0, 0], est.cov[1][0, 0]])
            estimate = (est.x[:, 0], est.x[:, 1], var_ne, est.initialised)
            roi = self.roi.next_state(
                state.roi, seen, estimate, rotation_zyx(*attitude_rad), self.config.control_dt_s
            )
            state = replace(state, roi=roi)
        return feats, replace(
            state,
            estimator=est,
            last_perception=raw,
            fixes=self._guard.count(state.fixes, est, vis),
        )

    def act(
        self, observation: Observation, groundtruth: Any, state: PolicyState
    ) -> tuple[Command, PolicyState]:
        feats, state = self.features(observation, groundtruth, state)
        if not np.all(np.isfinite(feats)):
            raise ValueError(f"policy input not finite at frame {observation.frame_id}: {feats}")
        cmd, lstm = self.control_step(np.asarray(feats, np.float32), state.lstm)
        cmd = np.asarray(cmd, float)
        if not np.all(np.isfinite(cmd)):
            raise ValueError(f"policy output not finite at frame {observation.frame_id}: {cmd}")
        command = Command(thrust_norm=float(np.clip(cmd[0], 0.0, 1.0)), rate_frd_rad_s=cmd[1:])
        if state.guard is not None and state.estimator is not None:
            command, guard = self._guard.step(
                state.guard,
                state.estimator,
                state.fixes,
                observation.attitude_rad,
                observation.hover_thrust_norm,
                command,
            )
            state = replace(state, guard=guard)
        return command, replace(state, lstm=lstm)
