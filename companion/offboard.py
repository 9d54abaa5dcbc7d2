"""The offboard state machine of one flight.

::

    WAITING ──(link, armed, fresh telemetry + camera, range > engage_min)──▶ PRESTREAM
    PRESTREAM ──(neutral setpoints at 20 Hz for ≥ prestream_s)──▶ ENGAGING (DO_SET_MODE OFFBOARD)
    ENGAGING ──(ACK accepted, HEARTBEAT shows OFFBOARD)──▶ FLYING (policy state reset)
    FLYING ──(one command per camera frame … touchdown: range + IMU)──▶ TOUCHDOWN
    TOUCHDOWN ──(zero thrust; disarm or hand back; HEARTBEAT disarmed)──▶ DONE
    any flying state ──(safety monitor: stale input, non-finite output, blind near ground)──▶
        FAILSAFE (LAND requested, no more setpoints) ──(disarmed / mode changed)──▶ DONE

In *shadow* mode WAITING goes straight to FLYING and nothing is ever sent: every command the
policy computes is logged as it would have been sent. It arms only when told to (``arm``, a
SITL demo); on hardware the pilot arms. Shadow waits for the vehicle to be armed and above
``engage_min_range_m``; *bench* shadow (``bench``, props off on the ground) starts on the first
fresh frame, disarmed and at any range, and logs would-be failsafes and touchdowns as events
without ending the flight.

**Which frames are flight frames.** Setpoints answering a frame carry the frame's own time
stamp (``time_boot_ms``); a SITL frame (autopilot clock) stamped at or before the moment the
OFFBOARD ACK arrived was rendered before the switch and gets the neutral setpoint, so the
policy's first step is the first frame of the flight — as in the in-process rollout.

**What it records.** The controller writes its flight log through
:class:`companion.flight.FlightRecorder` (the
few calls it makes); :class:`companion.record.CompanionLog` is the one the process gives it, so
this module does not depend on the log format and the log (and its replay) does not depend on
this module. Its states, results and failsafes are the typed ones of :mod:`companion.states`.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from companion.camera import ReceivedFrame
from companion.contract.companion_records import CompanionCommandRecord, CompanionObservationRecord
from companion.contract.records import EventKind
from companion.flight import FlightContext, FlightMachine, FlightRecorder
from companion.link import mavlink
from companion.live import live_frame
from companion.runtime import PolicyRuntime
from companion.safety import TouchdownDetector
from companion.states import Failsafe, FailsafeReason, FlightResult, FlightState, TouchdownAction
from companion.telemetry import assemble_observation

__all__ = ["FlightController"]

log = logging.getLogger("visland.companion")

_ZERO3 = np.zeros(3)
_ENGAGE_ATTEMPTS = 3
"""OFFBOARD refused or unanswered this many times = ``engage_failed``."""
_TOUCHDOWN_DISARM_WAIT_S = 5.0
_FAILSAFE_MODE_WAIT_S = 3.0
_LAND_REREQUEST_S = 1.5


def _action(failsafe: Failsafe) -> str:
    """What the companion does on ``failsafe`` (the shadow and bench log what it would)."""
    if failsafe.reason is FailsafeReason.PAD_NOT_FOUND:
        return "stop setpoints (no LAND)"
    return "request LAND"


def _frame_ms(frame: ReceivedFrame) -> int:
    return round(frame.time_s * 1e6) // 1000


class FlightController(FlightMachine):
    """One flight: fed messages, frames and ticks by the process loop (:mod:`companion.app`).

    Args:
        ctx: what the process hands every flight (settings, link, store, safety, clocks).
        runtime: the policy runtime.
        log: this flight's log (a :class:`FlightRecorder`).
        index: flight number.
    """

    def __init__(
        self, ctx: FlightContext, runtime: PolicyRuntime, log: FlightRecorder, index: int = 0
    ) -> None:
        super().__init__(ctx, log, index)
        self.runtime = runtime
        self._last_prestream_s = -math.inf
        self._last_mode_req_s = -math.inf
        self._mode_change_ap_s = math.inf
        self._land_confirmed = False
        self._touchdown = TouchdownDetector(ctx.cfg.touchdown_range_m)
        self._flight_start_rx = math.inf
        self._hover: float | None = None
        self._bench_failsafe: FailsafeReason | None = None
        """The bench's last would-be failsafe (each new reason is logged once)."""

    # ------------------------------------------------------------------ helpers

    @property
    def _needs_odometry(self) -> bool:
        return self.runtime.privileged

    def _armed(self) -> bool:
        hb = self.store.heartbeat
        return hb is not None and hb.armed

    def _mode(self) -> int | None:
        hb = self.store.heartbeat
        return None if hb is None else hb.custom_mode

    def _hover_thrust(self, now: float) -> float | None:
        if self._hover is None:
            value = self.link.param(self.link.profile.hover_param)
            if value is not None and math.isfinite(value) and 0.0 < value < 1.0:
                self._hover = float(value)
            elif now - self._created_s > self.cfg.param_timeout_s:
                self._hover = self.cfg.hover_thrust
                self._event(
                    EventKind.PARAM,
                    f"{self.link.profile.hover_param} not reported; neutral thrust "
                    f"{self.cfg.hover_thrust} from the config",
                )
        return self._hover

    def _ap_stamp_ms(self, frame: ReceivedFrame | None, now: float) -> int:
        """time_boot_ms for a setpoint: the answered SITL frame's stamp, else the autopilot's
        clock as last seen (advanced by the time since, for a companion-clock camera)."""
        if frame is not None and self.camera_clock == "autopilot":
            return _frame_ms(frame)
        att = self.store.attitude
        if att is None:
            return 0
        ahead = 0.0 if self.camera_clock == "autopilot" else max(0.0, now - att.rx_s)
        return int((self.store.latest_time_s + ahead) * 1000)

    def _send(self, thrust: float, rates: np.ndarray, stamp_ms: int) -> float | None:
        """Send (unless shadow); the hand-off time, or None when nothing was sent."""
        if self.cfg.shadow:
            return None
        t = self.perf.now()
        handed = self.link.send_setpoint(thrust, rates, stamp_ms)
        self.perf.add_inner("mavlink", t)
        return handed

    # ------------------------------------------------------------------ gates

    def _gate(self, now: float) -> str | None:
        """Why a flight cannot start yet (None: it can)."""
        link, store, profile = self.link, self.store, self.link.profile
        reason = self._link_gate()
        if reason is not None:
            return reason
        if now - self._params_requested_s > 2.0:
            self._params_requested_s = now
            link.request_param(profile.hover_param)
            if profile.thrust_param:
                link.request_param(profile.thrust_param)
        hb = store.heartbeat
        if hb is None:
            return "no HEARTBEAT"
        if not self.cfg.shadow:
            if profile.is_offboard(hb.custom_mode) or profile.is_land(hb.custom_mode):
                return f"autopilot in {profile.mode_name(hb.custom_mode)}"
            if not hb.armed:
                if self.cfg.arm and now - self._last_arm_s > 2.0 and now - self._created_s > 1.0:
                    self._last_arm_s = now
                    link.arm(True)
                    self._event(EventKind.ARM, "arming (--arm)")
                return "disarmed (the pilot arms; --arm for SITL demos)"
        elif not hb.armed and not self.cfg.bench:
            return "disarmed (shadow; --bench logs disarmed, on the ground)"
        names = ("attitude", "imu", "range") + (("odometry",) if self.runtime.privileged else ())
        reason = self._inputs_gate(now, names)
        if reason is not None:
            return reason
        if profile.thrust_param:
            value = link.param_int(profile.thrust_param)
            if value is None:
                return f"waiting for {profile.thrust_param}"
            if value & profile.thrust_param_bits != profile.thrust_param_bits:
                return (
                    f"{profile.thrust_param} = {value}: set bit {profile.thrust_param_bits} so "
                    "SET_ATTITUDE_TARGET thrust is collective thrust, not a climb rate"
                )
        if not self.cfg.shadow and self._hover_thrust(now) is None:
            return f"waiting for {profile.hover_param}"
        return None

    # ------------------------------------------------------------------ inputs

    def _on_mode_ack(self, result: int) -> None:
        if self.state is FlightState.ENGAGING and not self._mode_acked:
            if result == mavlink.MAV_RESULT_ACCEPTED:
                self._mode_acked = True
                self._mode_change_ap_s = self.store.latest_time_s
                self._event(EventKind.OFFBOARD_ACK, "OFFBOARD accepted")
            elif result != mavlink.MAV_RESULT_IN_PROGRESS:
                self._engage_attempts += 1
                self._event(EventKind.OFFBOARD_REFUSED, f"DO_SET_MODE result {result}")
                if self._engage_attempts >= _ENGAGE_ATTEMPTS:
                    self._finish(
                        FlightResult.ENGAGE_FAILED,
                        f"OFFBOARD refused {self._engage_attempts} times",
                    )
                else:
                    self._enter(FlightState.PRESTREAM, "retry after a refusal")
        elif self.state is FlightState.FAILSAFE and result == mavlink.MAV_RESULT_ACCEPTED:
            self._land_confirmed = True

    def _on_heartbeat(self) -> None:
        mode = self._mode()
        if mode is None:
            return
        profile = self.link.profile
        armed = self._armed()
        state = self.state
        if state is FlightState.ENGAGING and profile.is_offboard(mode):
            if not self._mode_acked:
                self._mode_acked = True
                self._mode_change_ap_s = self.store.latest_time_s
            self._start_flight("OFFBOARD confirmed in the HEARTBEAT")
        elif state is FlightState.FLYING and not self.cfg.shadow:
            if not armed:
                self._finish(
                    FlightResult.HANDED_BACK, "disarmed in flight by the autopilot or the pilot"
                )
            elif not profile.is_offboard(mode):
                self._finish(
                    FlightResult.HANDED_BACK,
                    f"mode changed to {profile.mode_name(mode)} (not by us)",
                )
        elif state is FlightState.FLYING and self.cfg.shadow and not armed and not self.cfg.bench:
            self._finish(FlightResult.SHADOW, "disarmed")
        elif state is FlightState.TOUCHDOWN:
            if not armed:
                self._finish(FlightResult.LANDED, "disarmed on the ground")
            elif self.cfg.on_touchdown is TouchdownAction.HAND_BACK and not profile.is_offboard(
                mode
            ):
                self._finish(FlightResult.LANDED, f"handed back in {profile.mode_name(mode)}")
        elif state is FlightState.FAILSAFE:
            if profile.is_land(mode):
                self._land_confirmed = True
            failsafe = self.outcome.failsafe
            if not armed:
                self._finish(FlightResult.FAILSAFE, f"{failsafe}; landed and disarmed")
            elif self._land_confirmed and not profile.is_land(mode):
                self._finish(
                    FlightResult.FAILSAFE, f"{failsafe}; then {profile.mode_name(mode)} (pilot?)"
                )
            elif (
                not profile.is_land(mode)
                and not profile.is_offboard(mode)
                and (self._clock() - self._entered_s > _FAILSAFE_MODE_WAIT_S)
            ):
                self._finish(
                    FlightResult.FAILSAFE,
                    f"{failsafe}; autopilot in {profile.mode_name(mode)}",
                )

    def _start_flight(self, text: str) -> None:
        self.runtime.reset()
        self._flight_start_rx = self._clock()
        self._enter(FlightState.FLYING, text)
        self.log.flight_start(self._clock(), text, shadow=self.cfg.shadow)

    # ------------------------------------------------------------------ frames

    def on_frame(self, frame: ReceivedFrame) -> None:
        """Answer one camera frame (the latency path: log writes are queued until after the
        send)."""
        self._last_frame_rx = frame.rx_s
        state = self.state
        answering = state in (FlightState.ENGAGING, FlightState.FLYING, FlightState.TOUCHDOWN)
        perf = self.perf
        perf.count("frames")
        t = perf.now()
        if not answering:
            self.log.frame(frame)
            perf.add_inner("log", t)
            return
        self.log.deferring = True
        try:
            self.log.frame(frame)  # queued: written after the answer, before its command record
            perf.add_inner("log", t)
            if state is FlightState.FLYING and self._is_flight_frame(frame):
                self._policy_step(frame)
            elif state is FlightState.TOUCHDOWN:
                self._answer(frame, 0.0, "touchdown")
            elif self._mode_acked:  # ENGAGING after the ACK, or a frame from before the switch
                self._answer(frame, self._hover or self.cfg.hover_thrust, "neutral")
        finally:
            t = perf.now()
            self.log.flush_pending()
            perf.add_inner("log", t)

    def _is_flight_frame(self, frame: ReceivedFrame) -> bool:
        if self.cfg.shadow:
            return True
        if self.camera_clock == "autopilot":
            return frame.time_s > self._mode_change_ap_s + 1e-9
        return frame.rx_s >= self._flight_start_rx

    def _answer(self, frame: ReceivedFrame, thrust: float, kind: str) -> None:
        now = self._clock()
        stamp = self._ap_stamp_ms(frame, now)
        handed = self._send(thrust, _ZERO3, stamp)
        self.outcome.neutral_setpoints += handed is not None
        self.log.command(
            now,
            CompanionCommandRecord(
                frame_id=frame.frame_id,
                policy=False,
                kind=kind,
                thrust_norm=thrust,
                rate_frd_rad_s=[0.0, 0.0, 0.0],
                sent=handed is not None,
                time_boot_ms=stamp,
                latency_ms=((handed or self._clock()) - frame.rx_s) * 1e3,
            ),
        )

    def _policy_step(self, frame: ReceivedFrame) -> None:
        t_in = self._clock()
        self._sync(frame)
        now = self._clock()
        failsafe = self.safety.check(now, self.store, frame.rx_s, self.runtime.privileged)
        if failsafe is not None:
            self._failsafe(failsafe)
            if not self.cfg.bench:  # the bench logs what the policy computes regardless
                return
        # an autopilot-clock frame (SITL) gets the readings stamped at its time, however late
        # it arrived after them (jitter); a companion-clock camera, the newest
        at = frame.time_s if self.camera_clock == "autopilot" else None
        obs = assemble_observation(frame, self.store, self._hover_thrust(now), at)
        gt = self.store.groundtruth_at(at) if self.runtime.privileged else None
        t_policy = self.perf.now()
        result = self.runtime.step(obs, gt)
        self.perf.add_inner("policy", t_policy)
        self.perf.count("policy_steps")
        if result.command is None:
            why = (
                FailsafeReason.PAD_NOT_FOUND
                if result.pad_not_found
                else FailsafeReason.POLICY_ERROR
            )
            self._failsafe(Failsafe(why, str(result.error)))
            return
        raw = result.command
        cmd, clamped = self.safety.clamp(raw)
        stamp = self._ap_stamp_ms(frame, now)
        handed = self._send(cmd.thrust_norm, cmd.rate_frd_rad_s, stamp)
        # shadow: when it would have been handed to the OS
        t_sent = handed if handed is not None else self._clock()
        self.outcome.policy_commands += 1
        self.log.observation(
            now,
            CompanionObservationRecord(
                **CompanionObservationRecord.values_of(obs),
                hover_thrust_norm=obs.hover_thrust_norm,  # NaN (not reported) is null
                groundtruth_time_s=None if gt is None else gt.time_s,
            ),
        )
        self.log.command(
            t_sent,
            CompanionCommandRecord(
                frame_id=frame.frame_id,
                policy=True,
                kind="shadow" if self.cfg.shadow else "policy",
                thrust_norm=cmd.thrust_norm,
                rate_frd_rad_s=cmd.rate_frd_rad_s,
                raw_thrust_norm=raw.thrust_norm,
                raw_rate_frd_rad_s=raw.rate_frd_rad_s,
                clamped=clamped,
                sent=handed is not None,
                time_boot_ms=stamp,
                latency_ms=(t_sent - frame.rx_s) * 1e3,
                send_call_ms=self.link.last_send_call_s * 1e3 if handed else None,
                compute_ms=result.compute_s * 1e3,
                queue_ms=(t_in - frame.rx_s) * 1e3,
                sync_ms=(now - t_in) * 1e3,
            ),
        )
        self._show(  # after the setpoint left: never before
            lambda: live_frame(
                obs,
                gt if gt is not None else self.store.groundtruth_at(at),
                self.runtime.next_state(),
                cmd,
                self.state.value,
                self.link.counters,
            ),
            frame.rx_s,
        )
        if self._touchdown.update(self.store, self._flight_start_rx) and not self.cfg.bench:
            self._on_touchdown()

    def _on_touchdown(self) -> None:
        if self.cfg.shadow:
            self._finish(FlightResult.SHADOW, "touchdown")
            return
        self._enter(FlightState.TOUCHDOWN, "touchdown (range + IMU): zero thrust")
        if self.cfg.on_touchdown is TouchdownAction.DISARM:
            self.link.arm(False)
        else:
            self.link.request_mode(self.link.profile.hold, armed=True)

    def _failsafe(self, failsafe: Failsafe) -> None:
        self.outcome.failsafe = failsafe
        if self.cfg.bench:  # logged once per reason; the bench keeps computing
            if failsafe.reason is not self._bench_failsafe:
                self._bench_failsafe = failsafe.reason
                self._event(EventKind.FAILSAFE_SHADOW, f"would {_action(failsafe)}: {failsafe}")
            return
        if self.cfg.shadow:
            self._event(EventKind.FAILSAFE_SHADOW, f"would {_action(failsafe)}: {failsafe}")
            self._finish(FlightResult.SHADOW, f"failsafe (shadow): {failsafe}")
            return
        if failsafe.reason is FailsafeReason.PAD_NOT_FOUND:  # LAND would land blind
            self._enter(
                FlightState.FAILSAFE,
                f"{failsafe}: setpoints stopped, no LAND; the autopilot's offboard-loss "
                "action applies",
            )
            return
        self._enter(FlightState.FAILSAFE, f"{failsafe}: LAND requested, setpoints stopped")
        self._request_land()

    def _request_land(self) -> None:
        self._last_mode_req_s = self._clock()
        self.link.request_mode(self.link.profile.land, armed=self._armed())

    # ------------------------------------------------------------------ time

    def on_tick(self) -> None:
        """Timers: gates, pre-stream, staleness, retries. Call often (every loop pass)."""
        now = self._clock()
        state = self.state
        if state is FlightState.WAITING:
            reason = self._gate(now)
            if reason is None:
                if self.cfg.shadow:
                    self._start_flight("shadow: telemetry and camera fresh")
                else:
                    self._enter(FlightState.PRESTREAM, "ready: pre-streaming neutral setpoints")
            elif reason != self._wait_reason:
                self._wait_reason = reason
                self._event(EventKind.WAITING, reason)
        elif state is FlightState.PRESTREAM:
            reason = self._gate(now)
            if reason is not None:
                self._enter(FlightState.WAITING, f"not ready any more: {reason}")
                return
            self._prestream(now)
            if now - self._entered_s >= self.cfg.prestream_s:
                self._mode_acked = False
                self._mode_change_ap_s = math.inf
                self._enter(FlightState.ENGAGING, "requesting OFFBOARD")
                self.link.request_mode(self.link.profile.offboard, armed=self._armed())
        elif state is FlightState.ENGAGING:
            if not self._mode_acked:
                self._prestream(now)
            if now - self._entered_s > self.cfg.engage_timeout_s:
                if self._mode_acked:
                    self._failsafe(
                        Failsafe(
                            FailsafeReason.OFFBOARD_UNCONFIRMED,
                            "ACK but no OFFBOARD in the HEARTBEAT",
                        )
                    )
                else:
                    self._engage_attempts += 1
                    if self._engage_attempts >= _ENGAGE_ATTEMPTS:
                        self._finish(
                            FlightResult.ENGAGE_FAILED, "no answer to DO_SET_MODE OFFBOARD"
                        )
                    else:
                        self._enter(FlightState.PRESTREAM, "no ACK for OFFBOARD: retry")
        elif state is FlightState.FLYING:
            failsafe = self.safety.check(
                now, self.store, self._last_frame_rx, self.runtime.privileged
            )
            if failsafe is not None:
                self._failsafe(failsafe)
        elif state is FlightState.TOUCHDOWN:
            if now - self._entered_s > _TOUCHDOWN_DISARM_WAIT_S:
                self._finish(
                    FlightResult.LANDED,
                    f"touchdown; no disarm seen within {_TOUCHDOWN_DISARM_WAIT_S:g} s",
                )
        elif state is FlightState.FAILSAFE:
            failsafe = self.outcome.failsafe
            if (
                not self._land_confirmed
                and (failsafe is None or failsafe.reason is not FailsafeReason.PAD_NOT_FOUND)
                and now - self._last_mode_req_s > _LAND_REREQUEST_S
            ):
                self._request_land()

    def _prestream(self, now: float) -> None:
        if now - self._last_prestream_s < 1.0 / self.cfg.prestream_rate_hz:
            return
        self._last_prestream_s = now
        hover = self._hover_thrust(now)
        self._send(
            hover if hover is not None else self.cfg.hover_thrust,
            _ZERO3,
            self._ap_stamp_ms(None, now),
        )

    # ------------------------------------------------------------------ exit

    def hand_back(self, mode: str, reason: str) -> None:
        """Stop flying now (SIGINT/SIGTERM, end of run): request ``land`` or ``hold`` if we
        were in control, stop sending setpoints."""
        if self.done:
            return
        in_control = (
            self.state
            in (
                FlightState.ENGAGING,
                FlightState.FLYING,
                FlightState.TOUCHDOWN,
            )
            and not self.cfg.shadow
        )
        if in_control:
            profile = self.link.profile
            target = profile.land if mode == "land" else profile.hold
            self.link.request_mode(target, armed=self._armed())
            self._event(
                EventKind.HAND_BACK, f"{reason}: {mode.upper()} requested, setpoints stopped"
            )
        self._finish(FlightResult.ABORTED, reason)
