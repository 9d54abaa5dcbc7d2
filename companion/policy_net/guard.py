"""Never land blind: the learned policy descends below a floor only with a confirmed pad.

A vision policy that never acquires the pad (sand under a low sun, a pad it was not taught) still
descends: its estimate starts at "above the pad" and its controller flies it down, and the
flight ends on whatever lies under it, tens of metres from the pad. :class:`LandingGuard` stands
between the controller and the autopilot:

* above ``NetConfig.land_floor_m`` (the estimator's altitude, from the radar) the network flies,
  pad or no pad — the view is wide and the pad may still come in — as long as the hold could
  still stop its descent above the floor (:func:`_stop_altitude`: at 5 m/s it takes over 4 m
  above it, so the vehicle stops at the floor, not under it);
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

**Never leave the envelope** (``envelope_sink_m_s``, ``envelope_tilt_deg``; off unless set): a
network that has lost the pad can fly states no training flight held — a dive at tens of m/s
after an estimate that jumped between false fixes, a roll past the vertical — and would end in
the ground at that speed. Whenever the estimator's descent speed or the tilt from level is above
its limit, at any altitude, the guard recovers: it levels the vehicle (with the thrust cut while
it is nearly upside down) and arrests the descent, until the descent is under half its limit
and the tilt under :data:`_RECOVERED_TILT_RAD`, or for :data:`_MAX_RECOVERY_S` at most. The
estimate the network flew that on is not to be trusted: the hold flies next, at any altitude,
until ``confirm_fixes`` more fixes confirm the pad (then the network again), and
``pad_timeout_s`` in the hold ends the flight as above. The recovery itself does not count
towards ``pad_timeout_s``.

A flight that confirms the pad above the floor and stays in the envelope never meets the guard:
its commands are the network's, bit for bit. ``land_floor_m = None`` turns the landing part off
(training's expert-state features never run it; an ablation can). The guard's settings are
:data:`ESTIMATOR_FIELDS`: no weight depends on them, so ``visland eval --estimator
land_floor_m=15`` flies a checkpoint with another floor.

The hold is a plain cascade on the estimator's state (no ground truth): vertical speed to a
climb-rate target with an integral for the hover-thrust error (a heavier airframe), attitude to
a level (or velocity-damping) target through body rates; its accelerations are the planet's,
whose gravity the estimator's vertical bias state learns (:meth:`LandingGuard._gravity`). It is
not a position hold — without the pad nothing knows the position —, so in wind the vehicle
drifts with the air while it holds and searches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

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
    recovering: bool = False
    """The guard recovers the vehicle into the envelope this step."""
    recoveries: int = 0
    """How many times the vehicle left the envelope in this flight."""
    recovery_s: float = 0.0
    """Time in the recovery under way."""
    recheck_from: int | None = None
    """After a recovery: the confirming fixes counted then. The network flew the vehicle out of
    its envelope on an estimate it cannot be trusted with, so the guard holds (at any altitude)
    until ``confirm_fixes`` more confirm the pad; None: no recovery to recheck."""


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
_RECOVERED_TILT_RAD = math.radians(15.0)
"""A recovery ends below this tilt (and half the descent limit)."""
_MAX_RECOVERY_S = 3.0
"""A recovery ends after this long whatever the estimate says: its vertical law trusts the
estimator's velocity, which may be what went wrong (a radar reading a slope); the hold, with
its timeout, flies next."""
_MIN_GRAVITY_FRACTION = 0.3
_MAX_GRAVITY_FRACTION = 1.5
"""The hold's gravity (the configured one plus the estimated vertical bias) is kept within
these fractions of the configured one: a bias that diverged must not ask for a thrust of
nothing or of everything."""
_INVERTED_COS = 0.3
"""Below this cosine of the tilt a recovery cuts the thrust to its least: thrust would push the
vehicle down."""


def _stop_altitude(est: EstimatorState) -> float:
    """Where a descent at the estimator's vertical speed would stop under the hold's largest
    upward acceleration, :data:`_MAX_ACCEL_UP` (the altitude itself when climbing): the guard
    takes over once this, not the altitude, is below the floor, so that its hold stops the
    vehicle at the floor rather than metres under it (at 5 m/s, 4 m)."""
    altitude = -float(est.x[2, 0])
    sink = float(est.x[2, 1])
    return altitude - max(sink, 0.0) ** 2 / (2.0 * _MAX_ACCEL_UP)


class LandingGuard:
    """The guard of one policy (its :class:`NetConfig`); the state travels in the policy's."""

    def __init__(self, cfg: NetConfig) -> None:
        self.cfg = cfg

    def count(self, fixes: int, est: EstimatorState, vis: float) -> int:
        """The confirming fixes after an estimator step ``est`` on a bearing of pad probability
        ``vis``: one more where the step took its fix at ``confirm_threshold`` or above; none
        before it where the step re-acquired and ``confirm_reset_on_reacquire`` is set."""
        if est.reacquired and self.cfg.confirm_reset_on_reacquire:
            fixes = 0
        threshold = self.cfg.confirm_threshold
        return fixes + int(est.took_horizontal and vis >= (threshold or 0.0))

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
        """The command to fly: the network's ``command``; the recovery's outside the envelope;
        the hold's below the floor without a confirmed pad (after a recovery, at any altitude
        until the pad is confirmed again). Raises :class:`PadNotFound` once the guard has held
        too long."""
        cfg = self.cfg
        # a recovery goes on for _MAX_RECOVERY_S at most; a new one starts outside the hold
        # that follows it (the hold is the careful law, and has its timeout)
        may = state.recovery_s < _MAX_RECOVERY_S if state.recovering else state.recheck_from is None
        if may and self._outside(state, est, attitude_rad):
            recover, thrust_i = self._fly(
                est, attitude_rad, hover_thrust_norm, state.thrust_i, 0.0, recovering=True
            )
            return recover, replace(
                state,
                holding=False,
                recovering=True,
                thrust_i=thrust_i,
                recoveries=state.recoveries + (not state.recovering),
                recovery_s=state.recovery_s + cfg.control_dt_s if state.recovering else 0.0,
            )
        if state.recovering:  # back in the envelope: the pad is to be confirmed again
            state = replace(
                state, recovering=False, thrust_i=0.0, recheck_from=fixes, recovery_s=0.0
            )
        floor = cfg.land_floor_m
        if floor is None or not est.initialised[2]:
            return command, state  # no altitude yet: the first radar fix comes with step one
        altitude = -float(est.x[2, 0])
        since = state.recheck_from
        counted = fixes - since if since is not None and fixes >= since else fixes
        confirmed = self.confirmed(est, counted)
        if not state.holding and since is None and (_stop_altitude(est) >= floor or confirmed):
            return command, state
        if confirmed:  # the pad came into view (again) while holding: the network
            return command, GuardState(
                held_s=state.held_s, engaged=state.engaged, recoveries=state.recoveries
            )
        held = state.held_s + cfg.control_dt_s
        if held >= cfg.pad_timeout_s:
            where = (
                "since the vehicle left its envelope"
                if since is not None
                else f"below the {floor:g} m floor or climbing back above it"
            )
            raise PadNotFound(
                f"pad not found: no confirmed pad ({counted} of {cfg.confirm_fixes} fixes) "
                f"after {held:.1f} s {where}"
            )
        target = float(
            np.clip(
                _CLIMB_GAIN * (cfg.search_altitude_m - altitude), -_MAX_SINK_M_S, _MAX_CLIMB_M_S
            )
        )
        hold, thrust_i = self._fly(est, attitude_rad, hover_thrust_norm, state.thrust_i, target)
        engaged = state.engaged + (not state.holding)
        return hold, GuardState(
            holding=True,
            held_s=held,
            thrust_i=thrust_i,
            engaged=engaged,
            recoveries=state.recoveries,
            recheck_from=since,
        )

    def _outside(self, state: GuardState, est: EstimatorState, attitude_rad: np.ndarray) -> bool:
        """The vehicle is outside the envelope (a recovery under way ends only once it is well
        inside: below half the descent limit and :data:`_RECOVERED_TILT_RAD`)."""
        cfg = self.cfg
        sink_limit, tilt_limit = cfg.envelope_sink_m_s, cfg.envelope_tilt_deg
        if sink_limit is None and tilt_limit is None:
            return False
        sink = float(est.x[2, 1]) if est.initialised[2] else 0.0
        roll, pitch = float(attitude_rad[0]), float(attitude_rad[1])
        tilt = math.acos(float(np.clip(math.cos(roll) * math.cos(pitch), -1.0, 1.0)))
        if state.recovering:
            return (sink_limit is not None and sink > 0.5 * sink_limit) or (
                tilt_limit is not None and tilt > _RECOVERED_TILT_RAD
            )
        return (sink_limit is not None and sink > sink_limit) or (
            tilt_limit is not None and tilt > math.radians(tilt_limit)
        )

    def _gravity(self, est: EstimatorState) -> float:
        """The planet's gravity (m/s^2): the configured one plus the estimator's vertical
        acceleration bias where it has one (on Mars it learns the 6.1 m/s^2 between the two in
        the first seconds), within [:data:`_MIN_GRAVITY_FRACTION`, :data:`_MAX_GRAVITY_FRACTION`]
        of the configured one. The hover thrust is the autopilot's on this planet, so the
        thrust for ``a_up`` is ``hover x (1 + a_up / g)`` with this g, not Earth's: with
        Earth's the hold on Mars braked at a third of what it asked for."""
        g = self.cfg.gravity_m_s2
        if est.x.shape[1] == 3 and est.initialised[2]:
            local = g + float(est.x[2, 2])
            return float(np.clip(local, _MIN_GRAVITY_FRACTION * g, _MAX_GRAVITY_FRACTION * g))
        return g

    def _fly(
        self,
        est: EstimatorState,
        attitude_rad: np.ndarray,
        hover_thrust_norm: float,
        thrust_i: float,
        climb_m_s: float,
        recovering: bool = False,
    ) -> tuple[Command, float]:
        """The cascade on the estimator's state: vertical speed to ``climb_m_s``; attitude
        leaning against the estimated horizontal velocity where the estimator has one (the
        hold), or level with the thrust cut while nearly upside down (``recovering``). Returns
        the command and the new integral."""
        cfg = self.cfg
        hover = hover_thrust_norm
        if not (math.isfinite(hover) and 0.0 < hover < 1.0):
            hover = cfg.hover_thrust_norm
        v_up = -float(est.x[2, 1]) if est.initialised[2] else 0.0
        err = climb_m_s - v_up
        thrust_i = float(np.clip(thrust_i + _KI * err * cfg.control_dt_s, -2.0, 2.0))
        a_up = float(np.clip(_KV * err + thrust_i, -_MAX_ACCEL_UP, _MAX_ACCEL_UP))
        roll, pitch, yaw = (float(a) for a in attitude_rad)
        cos_tilt = math.cos(roll) * math.cos(pitch)
        g = self._gravity(est)
        thrust = float(np.clip(hover * (1.0 + a_up / g) / max(cos_tilt, 0.5), 0.05, 0.95))
        if recovering and cos_tilt < _INVERTED_COS:
            thrust = 0.05
        a_fwd = a_right = 0.0
        if not recovering and np.all(est.initialised[:2]):
            a_n, a_e = (-_KD_HORIZONTAL * float(est.x[i, 1]) for i in (0, 1))
            c, s = math.cos(yaw), math.sin(yaw)
            a_fwd, a_right = c * a_n + s * a_e, -s * a_n + c * a_e
        roll_t = float(np.clip(math.atan2(a_right, g), -_MAX_TILT_RAD, _MAX_TILT_RAD))
        pitch_t = float(np.clip(-math.atan2(a_fwd, g), -_MAX_TILT_RAD, _MAX_TILT_RAD))
        limits = np.asarray(cfg.max_rate_rad_s, float)
        rates = np.clip(
            [_KP_ATTITUDE * (roll_t - roll), _KP_ATTITUDE * (pitch_t - pitch), 0.0],
            -limits,
            limits,
        )
        return Command(thrust_norm=thrust, rate_frd_rad_s=rates), thrust_i
