"""Never land blind: the learned policy descends below a floor only with a confirmed pad.

A vision policy that never acquires the pad (sand under a low sun, a pad it was not taught) still
descends: its estimate starts at "above the pad" and its controller flies it down, and the
flight ends on whatever lies under it, tens of metres from the pad. :class:`LandingGuard` stands
between the controller and the autopilot:

* above ``NetConfig.land_floor_m`` (the estimator's altitude, from the radar) the network flies,
  pad or no pad — the view is wide and the pad may still come in;
* below it, only with a **confirmed** pad: the estimator holds a horizontal position built
  from at least ``confirm_fixes`` fixes it took (a CNN bearing at or above the fix threshold,
  or an unsure one that the innovation gate let through). Without one the guard takes over: it
  levels the vehicle, damps the horizontal velocity where the estimator has one, and climbs to
  ``search_altitude_m`` to widen the view, where it holds. The network keeps perceiving and
  its recurrent state keeps stepping; the moment the pad is confirmed the network flies again;
* after ``pad_timeout_s`` of guard without a confirmed pad the policy gives up: ``act`` raises
  :class:`PadNotFound`. In process the episode ends as an abort (``failsafe = pad_not_found``,
  a failure, never a touchdown); on the companion it is the failsafe of that name, and the
  autopilot's offboard-loss action applies (docs/deploy.md says which to set).

A flight that confirms the pad above the floor never meets the guard: its commands are the
network's, bit for bit. ``land_floor_m = None`` turns the guard off (training's expert-state
features never run it; an ablation can). The guard's settings are :data:`ESTIMATOR_FIELDS`:
no weight depends on them, so ``visland eval --estimator land_floor_m=15`` flies a checkpoint
with another floor.

The hold is a plain cascade on the estimator's state (no ground truth): vertical speed to a
climb-rate target with an integral for the hover-thrust error (another planet, a heavier
airframe), attitude to a level (or velocity-damping) target through body rates. It is not a
position hold — without the pad nothing knows the position —, so in wind the vehicle drifts
with the air while it holds and searches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.contract import Command
from companion.policy_net.config import NetConfig
from companion.policy_net.estimator import EstimatorState

__all__ = ["GuardState", "LandingGuard", "PadNotFound"]


class PadNotFound(RuntimeError):
    """The guard held for ``pad_timeout_s`` without a confirmed pad: the flight must end
    without landing (a failsafe named ``pad_not_found``)."""


@dataclass(frozen=True)
class GuardState:
    """The guard's part of a policy state (never mutated in place)."""

    holding: bool = False
    """The guard, not the network, flies this step."""
    held_s: float = 0.0
    """Time in the guard since the flight began (steps x the control period)."""
    thrust_i: float = 0.0
    """Integral of the vertical-speed error (m/s^2): the hover thrust the report got wrong."""
    engaged: int = 0
    """How many times the guard took over in this flight."""


_KV = 1.2
"""Vertical speed gain, (m/s^2) per (m/s)."""
_KI = 0.4
"""Integral gain of the vertical-speed error, 1/s."""
_MAX_ACCEL_UP = 3.0
"""Largest vertical acceleration the hold asks for, m/s^2 either way."""
_CLIMB_GAIN = 0.5
"""Climb-rate target per metre below the search altitude, 1/s."""
_MAX_CLIMB_M_S = 2.0
_MAX_SINK_M_S = 1.0
_KD_HORIZONTAL = 0.8
"""Horizontal velocity damping (m/s^2 per m/s) where the estimator has a velocity."""
_MAX_TILT_RAD = math.radians(10.0)
_KP_ATTITUDE = 4.0
"""Roll/pitch rate per radian of attitude error, 1/s."""


class LandingGuard:
    """The guard of one policy (its :class:`NetConfig`); the state travels in the policy's."""

    def __init__(self, cfg: NetConfig) -> None:
        self.cfg = cfg

    def confirmed(self, est: EstimatorState, fixes: int) -> bool:
        """The estimator has a horizontal position from at least ``confirm_fixes`` fixes."""
        return bool(np.all(est.initialised[:2])) and fixes >= self.cfg.confirm_fixes

    def step(
        self,
        state: GuardState,
        est: EstimatorState,
        fixes: int,
        attitude_rad: np.ndarray,
        hover_thrust_norm: float,
        command: Command,
    ) -> tuple[Command, GuardState]:
        """The command to fly: the network's ``command``, or the hold's below the floor without
        a confirmed pad. Raises :class:`PadNotFound` once the guard has held too long."""
        cfg = self.cfg
        floor = cfg.land_floor_m
        if floor is None or not est.initialised[2]:
            return command, state  # no altitude yet: the first radar fix comes with step one
        altitude = -float(est.x[2, 0])
        if not state.holding and (altitude >= floor or self.confirmed(est, fixes)):
            return command, state
        if self.confirmed(est, fixes):  # the pad came into view while holding: the network
            return command, GuardState(held_s=state.held_s, engaged=state.engaged)
        held = state.held_s + cfg.control_dt_s
        if held >= cfg.pad_timeout_s:
            raise PadNotFound(
                f"pad not found: no confirmed pad ({fixes} of {cfg.confirm_fixes} fixes) "
                f"after {held:.1f} s below the {floor:g} m floor or climbing back above it"
            )
        hover = hover_thrust_norm
        if not (math.isfinite(hover) and 0.0 < hover < 1.0):
            hover = cfg.hover_thrust_norm
        v_up = -float(est.x[2, 1])
        target = float(
            np.clip(
                _CLIMB_GAIN * (cfg.search_altitude_m - altitude), -_MAX_SINK_M_S, _MAX_CLIMB_M_S
            )
        )
        err = target - v_up
        thrust_i = float(np.clip(state.thrust_i + _KI * err * cfg.control_dt_s, -2.0, 2.0))
        a_up = float(np.clip(_KV * err + thrust_i, -_MAX_ACCEL_UP, _MAX_ACCEL_UP))
        roll, pitch, yaw = (float(a) for a in attitude_rad)
        cos_tilt = max(math.cos(roll) * math.cos(pitch), 0.5)
        thrust = float(np.clip(hover * (1.0 + a_up / cfg.gravity_m_s2) / cos_tilt, 0.05, 0.95))
        # level, or lean against the estimated horizontal velocity
        a_fwd = a_right = 0.0
        if np.all(est.initialised[:2]):
            a_n, a_e = (-_KD_HORIZONTAL * float(est.x[i, 1]) for i in (0, 1))
            c, s = math.cos(yaw), math.sin(yaw)
            a_fwd, a_right = c * a_n + s * a_e, -s * a_n + c * a_e
        g = cfg.gravity_m_s2
        roll_t = float(np.clip(math.atan2(a_right, g), -_MAX_TILT_RAD, _MAX_TILT_RAD))
        pitch_t = float(np.clip(-math.atan2(a_fwd, g), -_MAX_TILT_RAD, _MAX_TILT_RAD))
        limits = np.asarray(cfg.max_rate_rad_s, float)
        rates = np.clip(
            [_KP_ATTITUDE * (roll_t - roll), _KP_ATTITUDE * (pitch_t - pitch), 0.0],
            -limits,
            limits,
        )
        engaged = state.engaged + (not state.holding)
        return Command(thrust_norm=thrust, rate_frd_rad_s=rates), GuardState(
            holding=True, held_s=held, thrust_i=thrust_i, engaged=engaged
        )
