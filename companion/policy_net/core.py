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
)

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


_MAX_CAMERA_LAG_S = 0.5
"""A camera lag (ATTITUDE time minus image exposure time) beyond this, or negative, is taken as
clocks that do not compare (e.g. a companion-clock camera): the fix is used as of now."""
_ATTITUDE_HISTORY = 4


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


class PolicyCore(ABC):
    """A learned policy's ``initial_state`` / ``act`` over a backend's two networks.

    ``groundtruth`` (a :class:`companion.contract.GroundTruth`: the simulator's, or the
    companion's ODOMETRY record) is read only by privileged policies. Vision policies ignore it
    (pass ``None`` on hardware). Subclasses set ``config`` and call :meth:`_init_core`.
    """

    config: NetConfig

    def _init_core(self) -> None:
        self._estimator = PadEstimator(self.config)

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
        return PolicyState(lstm=self.zero_state(), estimator=est)

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
            feats = control_features(
                np.asarray(groundtruth.pos_ned_m, float),
                np.asarray(groundtruth.vel_ned_m_s, float),
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
        )

    def _fix(
        self,
        raw: np.ndarray,
        attitude_rad: np.ndarray,
        range_m: float,
        state: PolicyState,
        image_time_s: float,
        attitude_time_s: float,
    ) -> tuple[np.ndarray | None, bool, float, PolicyState]:
        """The position fix of this step, whether its horizontal part is new, how old that
        horizontal part is (s), and the state with the attitude history advanced.

        With ``latency_compensation`` the horizontal fix is where the vehicle was at the
        image's exposure: the bearing through the attitude then, scaled by the altitude then
        (the radar's, less the estimated descent since); the estimator takes it as a delayed
        measurement. The vertical fix is the radar's, now."""
        cfg = self.config
        fix = position_from_bearing(float(raw[0]), float(raw[1]), attitude_rad, range_m)
        if not (
            cfg.latency_compensation
            and math.isfinite(image_time_s)
            and math.isfinite(attitude_time_s)
        ):
            return fix, True, 0.0, state
        history = (*state.attitudes, (float(attitude_time_s), np.asarray(attitude_rad, float)))
        state = replace(state, attitudes=history[-_ATTITUDE_HISTORY:])
        last = state.last_image_time_s
        if last is not None and image_time_s <= last:
            return fix, False, 0.0, state  # the same image again (a lost frame): radar only
        state = replace(state, last_image_time_s=float(image_time_s))
        lag = attitude_time_s - image_time_s
        if fix is None or not 0.0 < lag <= _MAX_CAMERA_LAG_S:
            return fix, True, 0.0, state
        est = state.estimator
        assert est is not None
        descent = float(est.x[2, 1]) * lag if est.initialised[2] else 0.0
        seen_from = position_at_altitude(
            float(raw[0]),
            float(raw[1]),
            attitude_at(history, image_time_s),
            -float(fix[2]) + descent,
        )
        if seen_from is None:
            return fix, False, 0.0, state
        return np.array([seen_from[0], seen_from[1], fix[2]]), True, lag, state

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
    ) -> tuple[np.ndarray, PolicyState]:
        """Controller input from the CNN's output (``perceive``) and the sensors; estimator step.

        Split from :meth:`features` so training can batch the CNN over a recorded flight and
        still run exactly this code for the rest. The times are the Observation's (used with
        ``latency_compensation``), ``hover_thrust_norm`` its hover thrust (``hover_input``).
        """
        vis = 1.0 / (1.0 + math.exp(-float(np.clip(raw[2], -30, 30))))
        dt = None  # the step's own time (its ATTITUDE's), not the image's: a repeated image
        if math.isfinite(attitude_time_s):  # still comes one period after the previous step
            if state.last_step_time_s is not None:
                dt = attitude_time_s - state.last_step_time_s
            state = replace(state, last_step_time_s=float(attitude_time_s))
        fix, fresh, lag, state = self._fix(
            raw, attitude_rad, range_m, state, image_time_s, attitude_time_s
        )
        seen = fresh and vis >= self.config.visibility_threshold
        assert state.estimator is not None
        est = self._estimator.step(
            state.estimator, fix, seen, attitude_rad, accel_frd_m_s2, fix_lag_s=lag, dt_s=dt
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
        return feats, replace(state, estimator=est, last_perception=raw)

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
        return command, replace(state, lstm=lstm)
