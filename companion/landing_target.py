"""Landing-target mode (``--mode landing-target``): the companion sees, the autopilot lands.

Only perception and the pad estimator run (the learned policy's CNN and
:class:`~companion.policy_net.PadEstimator`, through ``LearnedPolicy.features``; the control
LSTM never does, no setpoint is sent). Each camera frame gives the pad's position relative to
the vehicle; while the pad is tracked it goes to the autopilot as MAVLink LANDING_TARGET, at the
camera rate, and the autopilot's own precision land flies to it (PX4 AUTO.PRECLAND, ArduPilot
LAND with PLND_ENABLED).

**LANDING_TARGET as sent** (MAV_FRAME_BODY_FRD, MAVLink 2 with extensions), and who reads
what (``shared/reference/precland_notes.md`` 1.3, 2.1, 3.2):

* ``time_usec``: the frame's exposure time (µs; the autopilot clock for SITL frames). PX4's
  angle path ignores it (receive time); ArduPilot uses it, jitter-corrected.
* ``target_num`` 0 (PX4: the irlock signature; ArduPilot: unused). ``type`` 3 VISION_OTHER,
  ``q`` identity, ``size_x/y`` 0: read by neither.
* ``frame`` 12 BODY_FRD: ArduPilot requires 12 (or 20); PX4's angle path ignores it.
* ``angle_x`` = atan(right / down), ``angle_y`` = atan(−forward / down) of the target, rad:
  image x = body right, image y = body backward (image top = nose). ArduPilot takes tan() of
  them: LOS = (−tan angle_y, tan angle_x, 1). PX4 uses them **as tangents** (irlock pos_x/y,
  LTEST_SENS_ROT yaw 90° gives the same axes).
* ``distance`` = |target − vehicle|, m: ArduPilot's slant range; PX4 uses its range finder.
* ``x, y, z`` = the target in body FRD, m, with ``position_valid = 1`` — ArduPilot profile only
  (LOS = (x, y, z) / distance). PX4 drops a position in any frame but LOCAL_NED ("coordinate
  frame 12 unsupported"), so the PX4 profile sends ``position_valid = 0`` (the angle form).

PX4 copies angle_x/angle_y into ``irlock_report`` as tangents; sending angles understates an
offset by (tan θ − θ)/tan θ (1 % at 0.17 rad), a gain error that vanishes as the vehicle centres.

**When it is sent**: the estimator has a horizontal estimate and the pad was seen within
``target_timeout_s`` of frame time: the CNN's pad probability at or above
``visibility_threshold``, or a bearing the estimator took as a horizontal fix by the rule it flies
by in offboard mode (at ``acquire_threshold`` while it has no position; an unsure bearing its
innovation gate accepts). What is sent is always the estimate. Otherwise nothing (no stale
detection is re-sent, so the autopilot's PLD_BTOUT works). (Waiting for ``visibility_threshold``
alone, a flight over a carried pad often never started: at 75-100 m a CNN's probability for a
pad on a rover sits between the two thresholds, while it places it within a metre.)
With a SITL camera (autopilot clock) a frame without a LANDING_TARGET is answered with
NAMED_VALUE_INT ``VL_FRAME`` (the SITL's lockstep; an autopilot only logs it).

**States** (:class:`~companion.states.FlightState`): WAITING (link, armed, fresh telemetry and
camera, range ≥ ``engage_min_range_m``; ArduPilot: PLND_ENABLED = 1) → PRESTREAM (targets
streaming; the pad tracked for ``prestream_s``) → ENGAGING (DO_SET_MODE precision land,
3 tries) → FLYING (the HEARTBEAT shows it; targets keep streaming) → DONE: ``landed`` when
disarmed, ``handed_back`` on another mode. Losing the companion (stale input, killed) only stops
the stream, and the autopilot's target timeout falls back.

**Never land blind** (the landing guard of offboard mode, :mod:`companion.policy_net.guard`,
with the same settings: the checkpoint's, or ``--estimator``): the autopilot's precision land
falls back to a normal landing where it is when it loses the target, so below
``land_floor_m`` (the estimator's altitude) the companion lets it descend only with a
**confirmed** pad (``confirm_fixes`` fixes). Without one it requests the profile's hold mode
(PX4 AUTO.LOITER, ArduPilot ALT_HOLD: the descent stops); the moment the pad is confirmed it
requests precision land again. After ``pad_timeout_s`` held in all, the flight ends with the
failsafe ``pad_not_found``: the LANDING_TARGET stream stops and the vehicle stays in hold for
the pilot (never LAND: that would land blind).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from companion.camera import ReceivedFrame
from companion.contract import Observation
from companion.contract.companion_records import CompanionLandingTargetRecord
from companion.contract.records import EventKind
from companion.flight import FlightContext, FlightMachine, FlightRecorder
from companion.link import mavlink
from companion.live import live_frame
from companion.policy_net.geometry import rotation_zyx
from companion.policy_net.guard import LandingGuard
from companion.states import Failsafe, FailsafeReason, FlightResult, FlightState
from companion.telemetry import assemble_observation

__all__ = [
    "LandingTargetController",
    "LandingTargetError",
    "LandingTargetFields",
    "PadTracker",
    "TrackResult",
    "landing_target_fields",
]

log = logging.getLogger("visland.companion")

_ENGAGE_ATTEMPTS = 3
_HOLD_REREQUEST_S = 1.5
"""The guard asks for hold again this often until the HEARTBEAT shows it."""


class LandingTargetError(ValueError):
    """Landing-target mode cannot run with this policy (names what it needs)."""


@dataclass(frozen=True)
class LandingTargetFields:
    """LANDING_TARGET's geometry in MAV_FRAME_BODY_FRD.

    Attributes:
        angle_x_rad: ``atan(right / down)``: image x = body right.
        angle_y_rad: ``atan(-forward / down)``: image y = body backward.
        distance_m: slant range ``|pos_frd_m|``.
        pos_frd_m: (3,) the target in body FRD (forward, right, down), m.
    """

    angle_x_rad: float
    angle_y_rad: float
    distance_m: float
    pos_frd_m: np.ndarray


def landing_target_fields(
    target_rel_ned_m: np.ndarray, attitude_rad: np.ndarray
) -> LandingTargetFields | None:
    """The target (target − vehicle, NED) as LANDING_TARGET sees it from a vehicle at
    ``attitude_rad`` (roll, pitch, yaw); None when it is not below the vehicle or not finite."""
    rel = np.asarray(target_rel_ned_m, dtype=float).reshape(3)
    att = np.asarray(attitude_rad, dtype=float).reshape(3)
    if not (np.all(np.isfinite(rel)) and np.all(np.isfinite(att))):
        return None
    frd = rotation_zyx(*(float(a) for a in att)).T @ rel
    if frd[2] <= 1e-3:
        return None
    return LandingTargetFields(
        angle_x_rad=math.atan2(frd[1], frd[2]),
        angle_y_rad=math.atan2(-frd[0], frd[2]),
        distance_m=float(np.linalg.norm(frd)),
        pos_frd_m=frd,
    )


@dataclass(frozen=True)
class TrackResult:
    """One frame through perception + the pad estimator.

    Attributes:
        target_rel_ned_m: (3,) pad − vehicle (NED, m) while tracked, else None.
        visibility: the CNN's pad visibility (0..1).
        seen: visibility ≥ the policy's threshold, or the estimator took this frame's bearing
            as a horizontal fix (module docstring: when it is sent).
        error: why the step failed (None: it did not).
        confirmed: the estimator holds a confirmed pad (the landing guard's test).
        altitude_m: the estimator's altitude above the ground (None: no radar fix yet).
    """

    target_rel_ned_m: np.ndarray | None
    visibility: float
    seen: bool
    error: str | None = None
    confirmed: bool = False
    altitude_m: float | None = None


class _VisionPolicy(Protocol):
    config: Any

    def initial_state(self) -> Any: ...

    def features(self, observation: Observation, groundtruth: Any, state: Any) -> Any: ...


class PadTracker:
    """A vision policy's perception and pad estimator, without its controller.

    Args:
        policy: a vision :class:`~companion.policy_net.LearnedPolicy` (torch or ONNX backend).
        target_timeout_s: the pad counts as tracked this long (frame time) after it was last
            seen (:class:`TrackResult`); the estimator coasts on the IMU meanwhile (and below its
            ``min_fix_altitude_m``, where the view is a piece of the pad).

    Raises:
        LandingTargetError: a privileged policy (no camera), or no ``features``.
    """

    def __init__(self, policy: Any, target_timeout_s: float = 1.0) -> None:
        if getattr(policy, "privileged", True) or not callable(getattr(policy, "features", None)):
            raise LandingTargetError(
                "landing-target mode needs a vision policy checkpoint (its CNN and pad "
                "estimator); expert, cascade and privileged networks read ground truth"
            )
        if not (math.isfinite(target_timeout_s) and target_timeout_s > 0):
            raise LandingTargetError(f"target_timeout_s = {target_timeout_s}; expected > 0")
        self.policy: _VisionPolicy = policy
        self.target_timeout_s = target_timeout_s
        self.threshold = float(policy.config.visibility_threshold)
        self.guard = LandingGuard(policy.config)
        self.reset()

    def reset(self) -> None:
        self._state = self.policy.initial_state()
        self._last_seen_s = -math.inf

    @property
    def state(self) -> Any:
        """The policy state of the last step (its CNN output and estimator: the live view's)."""
        return self._state

    def next_state(self) -> Any:
        """The state the next :meth:`step` starts from: a region-of-interest camera
        (:meth:`companion.roi.RoiCameraSource.follow`) cuts the next frame with its window."""
        return self._state

    def step(self, observation: Observation) -> TrackResult:
        """Never raises: a failing step is reported (and nothing is tracked)."""
        try:
            _, state = self.policy.features(observation, None, self._state)
        except Exception as exc:  # a policy failure must not stop the process: no target
            return TrackResult(None, 0.0, False, f"{type(exc).__name__}: {exc}")
        self._state = state
        raw = state.last_perception
        vis = 1.0 / (1.0 + math.exp(-float(np.clip(raw[2], -30, 30))))
        est = state.estimator
        seen = vis >= self.threshold or bool(est.took_horizontal)
        t = float(observation.image_time_s)
        if seen:
            self._last_seen_s = t
        tracked = bool(np.all(est.initialised[:2])) and t - self._last_seen_s <= (
            self.target_timeout_s
        )
        rel = -np.asarray(est.x[:, 0], dtype=float)
        guard = {
            "confirmed": self.guard.confirmed(est, state.fixes),
            "altitude_m": -float(est.x[2, 0]) if est.initialised[2] else None,
        }
        if not tracked or not np.all(np.isfinite(rel)):
            return TrackResult(None, vis, seen, **guard)
        return TrackResult(rel, vis, seen, **guard)


class LandingTargetRecorder(FlightRecorder, Protocol):
    def landing_target(self, t: float, record: CompanionLandingTargetRecord) -> None: ...


class LandingTargetController(FlightMachine):
    """One flight in landing-target mode; the same calls as
    :class:`~companion.offboard.FlightController` (``on_message``, ``on_frame``, ``on_tick``,
    ``hand_back``, ``done``, ``outcome``), fed by the same process loop.

    Args:
        ctx: what the process hands every flight (settings, link, store, safety, clocks).
        tracker: the vision policy's perception and pad estimator.
        log: this flight's log (with its LANDING_TARGET topic).
        index: flight number.
    """

    def __init__(
        self, ctx: FlightContext, tracker: PadTracker, log: LandingTargetRecorder, index: int = 0
    ) -> None:
        super().__init__(ctx, log, index)
        self.log: LandingTargetRecorder = log
        self.tracker = tracker
        self._tracked_since: float | None = None
        self._hold_since: float | None = None
        """When the landing guard requested hold (None: it does not hold)."""
        self._held_s = 0.0
        """Time held by the guard in earlier holds of this flight."""
        self._resumed_s = -math.inf
        """When the guard last asked for precision land again."""
        self._hold_requested_s = -math.inf
        tracker.reset()

    # ------------------------------------------------------------------ helpers

    def _gate(self, now: float) -> str | None:
        """Why the landing cannot be handed to the autopilot yet (None: it can)."""
        link, store, profile = self.link, self.store, self.link.profile
        reason = self._link_gate()
        if reason is not None:
            return reason
        hb = store.heartbeat
        if hb is None:
            return "no HEARTBEAT"
        if not hb.armed:
            if self.cfg.arm and not self.cfg.shadow and now - self._last_arm_s > 2.0:
                if now - self._created_s > 1.0:
                    self._last_arm_s = now
                    link.arm(True)
                    self._event(EventKind.ARM, "arming (--arm)")
            return "disarmed (the pilot arms; --arm for SITL demos)"
        if not self.cfg.shadow and (
            profile.is_land(hb.custom_mode) or profile.is_offboard(hb.custom_mode)
        ):
            return f"autopilot in {profile.mode_name(hb.custom_mode)}"
        reason = self._inputs_gate(now, ("attitude", "imu", "range"))
        if reason is not None:
            return reason
        if profile.precland_param:
            if now - self._params_requested_s > 2.0:
                self._params_requested_s = now
                link.request_param(profile.precland_param)
            value = link.param_int(profile.precland_param)
            if value != 1:
                return f"{profile.precland_param} = {value}: set it to 1 (precision landing)"
        return None

    # ------------------------------------------------------------------ inputs

    def _on_mode_ack(self, result: int) -> None:
        if self.state is not FlightState.ENGAGING or self._mode_acked:
            return
        if result == mavlink.MAV_RESULT_ACCEPTED:
            self._mode_acked = True
            self._event(EventKind.PRECLAND_ACK, "precision land accepted")
        elif result != mavlink.MAV_RESULT_IN_PROGRESS:
            self._refused(f"DO_SET_MODE result {result}")

    def _refused(self, why: str) -> None:
        self._engage_attempts += 1
        self._event(EventKind.PRECLAND_REFUSED, why)
        if self._engage_attempts >= _ENGAGE_ATTEMPTS:
            self._finish(
                FlightResult.ENGAGE_FAILED, f"precision land refused {self._engage_attempts} times"
            )
        else:
            self._enter(FlightState.PRESTREAM, "retry after a refusal")

    def _on_heartbeat(self) -> None:
        hb = self.store.heartbeat
        if hb is None:
            return
        profile, mode = self.link.profile, hb.custom_mode
        if self.state is FlightState.ENGAGING and profile.is_precland(mode):
            self._enter(FlightState.FLYING, f"{profile.mode_name(mode)} confirmed in the HEARTBEAT")
            self.log.flight_start(
                self._clock(), "the autopilot lands on our target", self.cfg.shadow
            )
        elif self.state is FlightState.FLYING and not self.cfg.shadow:
            if not hb.armed:
                self._finish(FlightResult.LANDED, "disarmed: the autopilot landed")
            elif not (profile.is_precland(mode) or self._guard_hold(mode)):
                self._finish(FlightResult.HANDED_BACK, f"mode changed to {profile.mode_name(mode)}")
        elif self.state is FlightState.FLYING and not hb.armed:
            self._finish(FlightResult.SHADOW, "disarmed")

    def on_frame(self, frame: ReceivedFrame) -> None:
        self._last_frame_rx = frame.rx_s
        self.log.deferring = True
        try:
            self.log.frame(frame)
            if not self.done:
                self._track(frame)
        finally:
            self.log.flush_pending()

    def _track(self, frame: ReceivedFrame) -> None:
        self._sync(frame)
        now = self._clock()
        stamp_ms = round(frame.time_s * 1e6) // 1000
        store = self.store
        age, worst = store.max_age_s(("attitude", "imu", "range"), now)
        body: dict[str, Any] = {}  # the record's optional fields, by keyword
        fields = None
        if age > self.safety.config.max_age_s:
            body.update(why_not=f"{worst} {age * 1e3:.0f} ms old")
            self.tracker.reset()  # an estimate built on stale inputs is not one
            result = None
        else:
            obs = assemble_observation(frame, store, None)
            result = self.tracker.step(obs)
            body.update(visibility=result.visibility, seen=result.seen, error=result.error)
            if result.target_rel_ned_m is not None:
                fields = landing_target_fields(result.target_rel_ned_m, store.attitude.attitude_rad)
            if result.error is not None:
                self.outcome.events.append(f"tracker_error: {result.error}")
            if self.state is FlightState.FLYING:
                self._guard(now, result)
                if self.done:  # pad not found: nothing more is sent
                    fields = None
        sent = None
        if fields is not None:
            body.update(
                target_rel_ned_m=result.target_rel_ned_m,
                angle_x_rad=fields.angle_x_rad,
                angle_y_rad=fields.angle_y_rad,
                distance_m=fields.distance_m,
                pos_frd_m=fields.pos_frd_m,
            )
            if not self.cfg.shadow and self.state is not FlightState.DONE:
                pos = tuple(fields.pos_frd_m) if self.link.profile.landing_target_position else None
                sent = self.link.send_landing_target(
                    round(frame.time_s * 1e6),
                    fields.angle_x_rad,
                    fields.angle_y_rad,
                    fields.distance_m,
                    pos,
                )
            self._tracked_since = self._tracked_since if self._tracked_since is not None else now
        else:
            self._tracked_since = None
            if not self.cfg.shadow and self.camera_clock == "autopilot":
                self.link.send_frame_marker(stamp_ms, frame.frame_id)
        self.outcome.policy_commands += sent is not None
        record = CompanionLandingTargetRecord(
            frame_id=frame.frame_id,
            image_time_s=frame.time_s,
            **body,
            sent=sent is not None,
            latency_ms=((sent or self._clock()) - frame.rx_s) * 1e3,
        )
        self.log.landing_target(now, record)
        if result is not None:  # after the send
            self._show(
                lambda: live_frame(
                    obs,
                    store.groundtruth_at(frame.time_s),
                    self.tracker.state,
                    None,
                    self.state.value,
                    self.link.counters,
                ),
                frame.rx_s,
            )

    # ------------------------------------------------------------------ the landing guard

    def _guard_hold(self, mode: int) -> bool:
        """``mode`` is the hold the guard asked for (or has just asked to leave)."""
        if not self.link.profile.is_hold(mode):
            return False
        return self._hold_since is not None or (
            self._clock() - self._resumed_s < self.cfg.engage_timeout_s
        )

    def _guard(self, now: float, result: TrackResult) -> None:
        """Below the floor, the precision land goes on only with a confirmed pad."""
        net = self.tracker.policy.config
        floor, profile = net.land_floor_m, self.link.profile
        if floor is None or result.altitude_m is None:
            return
        holding = self._hold_since is not None
        if not holding and (result.altitude_m >= floor or result.confirmed):
            return
        act = not self.cfg.shadow
        since = self._hold_since
        if result.confirmed and since is not None:  # the pad came into view while holding
            self._held_s += now - since
            self._hold_since, self._resumed_s = None, now
            self._event(EventKind.GUARD, f"pad confirmed: {profile.precland.label} again")
            if act:
                self.link.request_mode(profile.precland, armed=True)
            return
        if not holding:
            self._hold_since = self._hold_requested_s = now
            fixes = self.tracker.state.fixes
            self._event(
                EventKind.GUARD,
                f"{result.altitude_m:.1f} m, below the {floor:g} m floor without a confirmed pad "
                f"({fixes} of {net.confirm_fixes} fixes): {profile.hold.label}"
                + ("" if act else " (shadow: not requested)"),
            )
            if act:
                self.link.request_mode(profile.hold, armed=True)
            return
        held = self._held_s + now - since
        if held >= net.pad_timeout_s:
            self.outcome.failsafe = Failsafe(
                FailsafeReason.PAD_NOT_FOUND,
                f"pad not found: no confirmed pad ({self.tracker.state.fixes} of "
                f"{net.confirm_fixes} fixes) after {held:.1f} s held below the {floor:g} m "
                f"floor; LANDING_TARGET stopped, left in {profile.hold.label} (no LAND)",
            )
            if act:
                self._finish(FlightResult.FAILSAFE, str(self.outcome.failsafe))
            else:
                self._event(EventKind.FAILSAFE_SHADOW, f"would stop: {self.outcome.failsafe}")
                self._finish(FlightResult.SHADOW, f"failsafe (shadow): {self.outcome.failsafe}")

    # ------------------------------------------------------------------ time

    def on_tick(self) -> None:
        now = self._clock()
        state = self.state
        if state in (FlightState.WAITING, FlightState.PRESTREAM):
            reason = self._gate(now)
            if reason is not None:
                if state is FlightState.PRESTREAM:
                    self._enter(FlightState.WAITING, f"not ready any more: {reason}")
                elif reason != self._wait_reason:
                    self._wait_reason = reason
                    self._event(EventKind.WAITING, reason)
                return
            if state is FlightState.WAITING:
                if self.cfg.shadow:
                    self._enter(FlightState.FLYING, "shadow: telemetry and camera fresh")
                    self.log.flight_start(now, "shadow", True)
                else:
                    self._enter(FlightState.PRESTREAM, "ready: streaming LANDING_TARGET")
                return
            since = self._tracked_since
            if since is not None and now - since >= self.cfg.prestream_s:
                self._mode_acked = False
                profile = self.link.profile
                self._enter(
                    FlightState.ENGAGING, f"pad tracked: requesting {profile.precland.label}"
                )
                self.link.request_mode(profile.precland, armed=True)
        elif state is FlightState.ENGAGING and now - self._entered_s > self.cfg.engage_timeout_s:
            self._refused("precision land not confirmed in the HEARTBEAT")
        elif state is FlightState.FLYING and self._hold_since is not None and not self.cfg.shadow:
            hb, profile = self.store.heartbeat, self.link.profile
            # the hold refused or not yet shown: ask again (precision land would go on down)
            if hb is not None and not profile.is_hold(hb.custom_mode):
                if now - self._hold_requested_s > _HOLD_REREQUEST_S:
                    self._hold_requested_s = now
                    self.link.request_mode(profile.hold, armed=True)

    def hand_back(self, mode: str, reason: str) -> None:
        """Stop (SIGINT/SIGTERM, end of run): the LANDING_TARGET stream ends; a landing in
        progress stays the autopilot's (its target timeout falls back to a normal landing)."""
        if self.done:
            return
        if self.state is FlightState.FLYING and not self.cfg.shadow:
            self._event(
                EventKind.HAND_BACK, f"{reason}: LANDING_TARGET stream stops; the autopilot lands"
            )
        self._finish(FlightResult.ABORTED, reason)
