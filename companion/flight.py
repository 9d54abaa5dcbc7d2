"""The types around one flight of the companion: its settings (:class:`OffboardConfig`, the
companion config's flight part), what the process hands every flight (:class:`FlightContext`),
the log it writes to (:class:`FlightRecorder`, the few calls the state machine makes), how it
ended (:class:`FlightOutcome`) and what the two state machines share (:class:`FlightMachine`).
The state machines themselves are :mod:`companion.offboard` (the policy flies) and
:mod:`companion.landing_target` (the autopilot lands on LANDING_TARGET); their states and
results are :mod:`companion.states`.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from companion.camera import ReceivedFrame
from companion.contract.companion_records import CompanionCommandRecord, CompanionObservationRecord
from companion.contract.perf import LoopPerf
from companion.contract.records import EventKind
from companion.link import mavlink
from companion.states import Failsafe, FlightResult, FlightState, TouchdownAction

if TYPE_CHECKING:
    from companion.link import MavlinkLink
    from companion.live import LiveFrame, LiveView
    from companion.safety import SafetyMonitor
    from companion.telemetry import TelemetryStore

__all__ = ["FlightContext", "FlightMachine", "FlightOutcome", "FlightRecorder", "OffboardConfig"]

log = logging.getLogger("visland.companion")


@dataclass(frozen=True)
class OffboardConfig:
    """The state machine's settings (the companion config's flight part).

    Attributes:
        shadow: compute and log, never send a setpoint or a mode change.
        bench: shadow on the bench (props off, on the ground; needs ``shadow``): the flight
            starts on the first fresh frame, disarmed and at any range, and goes on through
            touchdown-like readings and would-be failsafes (logged as events) until stopped.
        arm: arm the vehicle when it is disarmed (SITL demos only; on hardware the pilot arms).
        prestream_s: neutral setpoints streamed before OFFBOARD is requested (PX4 needs > 2 Hz
            before the switch; 1 s at 20 Hz).
        prestream_rate_hz: rate of those setpoints.
        engage_timeout_s: OFFBOARD not confirmed in the HEARTBEAT this long after the request
            = failsafe.
        engage_min_range_m: engage only above this range (never take over on the ground).
        touchdown_range_m: range at or below which (with a quiet gyro) the vehicle is down.
        on_touchdown: ``disarm`` or ``hand_back`` (switch to the hold mode) after touchdown;
            the string is taken and kept as a :class:`~companion.states.TouchdownAction`.
        hover_thrust: neutral thrust when the autopilot does not report its hover thrust.
        sync_timeout_s: wait at most this long for the telemetry stamped at a SITL frame's time.
        param_timeout_s: wait this long for the hover-thrust parameter before the fallback.
    """

    shadow: bool = False
    bench: bool = False
    arm: bool = False
    prestream_s: float = 1.0
    prestream_rate_hz: float = 20.0
    engage_timeout_s: float = 3.0
    engage_min_range_m: float = 1.0
    touchdown_range_m: float = 0.15
    on_touchdown: TouchdownAction = TouchdownAction.DISARM
    hover_thrust: float = 0.5
    sync_timeout_s: float = 0.02
    param_timeout_s: float = 3.0

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "on_touchdown", TouchdownAction(self.on_touchdown))
        except ValueError:
            raise ValueError(
                f"on_touchdown = {self.on_touchdown!r}; expected disarm or hand_back"
            ) from None
        if self.bench and not self.shadow:
            raise ValueError("bench = true needs shadow = true (the bench never sends)")
        if not self.prestream_s >= 1.0:
            raise ValueError(f"prestream_s = {self.prestream_s}; expected >= 1.0 (PX4 rule)")
        if not 2.0 < self.prestream_rate_hz <= 100.0:
            raise ValueError(f"prestream_rate_hz = {self.prestream_rate_hz}; expected (2, 100]")
        if not 0.0 <= self.hover_thrust <= 1.0:
            raise ValueError(f"hover_thrust = {self.hover_thrust}; expected in [0, 1]")


@dataclass(frozen=True)
class FlightContext:
    """What the process hands each flight's state machine, whatever its mode.

    Attributes:
        cfg: the state machine's settings.
        link: the MAVLink link (sends setpoints/commands; in shadow mode only listens).
        store: the telemetry store the process loop feeds.
        camera_clock: ``autopilot`` (SITL frames) or ``companion`` (a local camera).
        safety: the safety monitor.
        pump: ``pump(timeout_s)`` receives MAVLink for up to ``timeout_s`` (frame sync).
        clock: the companion's monotonic clock.
        perf: the process loop's counters (the flight times its policy steps, sends and log
            writes into them).
        live: the live view (``--live``; None: off): each answered frame and event goes there.
    """

    cfg: OffboardConfig
    link: MavlinkLink
    store: TelemetryStore
    camera_clock: str
    safety: SafetyMonitor
    pump: Callable[[float], None]
    clock: Callable[[], float]
    perf: LoopPerf = field(default_factory=LoopPerf)
    live: LiveView | None = None


@dataclass
class FlightOutcome:
    """How one flight of the companion ended."""

    index: int
    result: FlightResult = FlightResult.INCOMPLETE
    reason: str = ""
    policy_commands: int = 0
    neutral_setpoints: int = 0
    failsafe: Failsafe | None = None
    log_path: str | None = None
    events: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """The report and log summary: plain strings (``failsafe_reason`` is the failsafe's
        text, e.g. ``camera_stale: newest frame 309 ms old (> 300)``)."""
        return {
            "index": self.index,
            "result": self.result.value,
            "reason": self.reason,
            "policy_commands": self.policy_commands,
            "neutral_setpoints": self.neutral_setpoints,
            "failsafe_reason": None if self.failsafe is None else str(self.failsafe),
            "log_path": self.log_path,
            "events": list(self.events),
        }


class FlightRecorder(Protocol):
    """What the controller writes to its flight log (:class:`companion.record.CompanionLog`).

    While ``deferring`` is set, writes are queued and :meth:`flush_pending` writes them after
    the setpoint has left (logging never adds to the latency)."""

    path: Path
    deferring: bool

    def frame(self, frame: ReceivedFrame) -> None: ...

    def observation(self, t: float, record: CompanionObservationRecord) -> None: ...

    def command(self, t: float, record: CompanionCommandRecord) -> None: ...

    def event(self, t: float, kind: EventKind, text: str, **extra: Any) -> None: ...

    def flight_start(self, t: float, text: str, shadow: bool) -> None: ...

    scene: Any
    """Not None: the log also takes the live view's picture (:meth:`scene_frame`)."""

    def scene_frame(self, frame: LiveFrame, rx_s: float) -> None: ...

    def flush_pending(self) -> None: ...


class FlightMachine(ABC):
    """One flight's state machine, the part both modes share: the inputs it is fed by the
    process loop, its state and outcome, events into the flight log, the mode ACK / HEARTBEAT
    dispatch, the autopilot restart, and the wait for a SITL frame's telemetry.

    Subclasses handle the ACK of their DO_SET_MODE (``_on_mode_ack``) and the autopilot's
    HEARTBEAT (``_on_heartbeat``), and set ``_needs_odometry`` where they read ground truth.

    Args:
        ctx: what the process hands every flight (settings, link, store, safety, clocks).
        log: this flight's log (a :class:`FlightRecorder`).
        index: flight number.
    """

    def __init__(self, ctx: FlightContext, log: FlightRecorder, index: int = 0) -> None:
        self.cfg = ctx.cfg
        self.link = ctx.link
        self.store = ctx.store
        self.camera_clock = ctx.camera_clock
        self.safety = ctx.safety
        self.log = log
        self._pump = ctx.pump
        self._clock = clock = ctx.clock
        self.perf = ctx.perf
        self.live = ctx.live
        self.outcome = FlightOutcome(index=index, log_path=str(log.path))
        self.state = FlightState.WAITING
        self.began = False
        """The flight has begun: the autopilot was seen armed, or the flight left WAITING
        (pre-streamed, engaged, in shadow flew). One stopped before that was never a flight
        (the one opened after a simulator run's last landing): the companion drops its log.
        A vehicle armed but never engaged keeps its log: it says why (a parameter, a gate)."""
        self._entered_s = clock()
        self._created_s = clock()
        self._wait_reason = ""
        self._last_frame_rx: float | None = None
        self._last_arm_s = -math.inf
        self._params_requested_s = -math.inf
        self._engage_attempts = 0
        self._mode_acked = False
        self.await_disarm: str | None = None
        """Set (to why) when the vehicle is the pilot's and in the air — the flight before this
        one ended ``pad_not_found``, or the vehicle was armed when the companion first heard it
        (a companion restarted in the air): this flight starts only after a disarm (or an
        autopilot restart), never by taking the vehicle from the pilot."""

    @property
    def _needs_odometry(self) -> bool:
        """Whether the flight reads ODOMETRY (a privileged policy): the frame waits for it."""
        return False

    @property
    def done(self) -> bool:
        return self.state is FlightState.DONE

    def _link_gate(self) -> str | None:
        """Why the link cannot start a flight yet (None: it can)."""
        if self.link.target_system is None:
            return "no autopilot discovered yet"
        if not self.link.connected:
            return "autopilot link lost"
        if self.await_disarm is not None:
            hb = self.store.heartbeat
            if hb is None or hb.armed:
                return f"waiting for a disarm: {self.await_disarm}"
            self.await_disarm = None
        return None

    def _inputs_gate(self, now: float, names: tuple[str, ...]) -> str | None:
        """Why the inputs cannot start a flight yet (None: they can): a reading of ``names``
        older than the safety limit, no recent camera frame, or the range below
        ``engage_min_range_m`` (never take over on the ground)."""
        max_age_s = self.safety.config.max_age_s
        age, worst = self.store.max_age_s(names, now)
        if age > max_age_s:
            return f"waiting for fresh {worst}"
        if self._last_frame_rx is None or now - self._last_frame_rx > max_age_s:
            return "waiting for camera frames"
        if self.cfg.bench:  # on the ground, at any range: the radar may read nothing valid
            return None
        rng = self.store.range
        if rng is None or not rng.valid or rng.range_m < self.cfg.engage_min_range_m:
            return f"range {None if rng is None else rng.range_m} below engage_min_range_m"
        return None

    def note(self, kind: EventKind, text: str) -> None:
        """An event of the process's (a link change, a wall-clock step) in this flight's log."""
        self._event(kind, text)

    def _event(self, kind: EventKind, text: str) -> None:
        self.log.event(self._clock(), kind, text, state=self.state.value)
        if self.live is not None:
            latest = self.store.latest_time_s
            error = kind in (EventKind.FAILSAFE,)
            self.live.event(latest if math.isfinite(latest) else 0.0, f"{kind}: {text}", error)
        self.outcome.events.append(f"{kind}: {text}")
        log.info("flight %d %s: %s", self.outcome.index, kind, text)

    def _show(self, build: Callable[[], LiveFrame], rx_s: float) -> None:
        """After a frame's answer has left: its picture to the live view (if a client watches)
        and into the log (``log_scene``), built only if one of them takes it."""
        live = self.live is not None and self.live.watched
        if not (live or self.log.scene is not None):
            return
        frame = build()
        if live:
            self.live.publish(frame)
        self.log.scene_frame(frame, rx_s)

    def _enter(self, state: FlightState, text: str) -> None:
        self._event(EventKind.STATE, f"{self.state.value} -> {state.value}: {text}")
        self.began = self.began or state not in (FlightState.WAITING, FlightState.DONE)
        self.state = state
        self._entered_s = self._clock()

    def _finish(self, result: FlightResult, reason: str) -> None:
        if self.done:
            return
        self.outcome.result = result
        self.outcome.reason = reason
        self._enter(FlightState.DONE, f"{result}: {reason}")

    def on_message(self, msg: Any, rx_s: float) -> None:
        """After the store has taken ``msg``: ACKs and mode/arming changes."""
        name = msg.get_type()
        if name == "COMMAND_ACK" and msg.command == mavlink.MAV_CMD_DO_SET_MODE:
            self._on_mode_ack(int(msg.result))
        elif name == "HEARTBEAT" and msg.get_srcComponent() == self.link.target_component:
            heartbeat = self.store.heartbeat
            self.began = self.began or (heartbeat is not None and heartbeat.armed)
            self._on_heartbeat()

    @abstractmethod
    def _on_mode_ack(self, result: int) -> None:
        """The autopilot's COMMAND_ACK of our DO_SET_MODE."""

    @abstractmethod
    def _on_heartbeat(self) -> None:
        """A HEARTBEAT of the autopilot: its mode and arming state."""

    def on_link_event(self, kind: str, text: str) -> None:
        event = EventKind.of_link(kind)
        self._event(event, text)
        if event is EventKind.LINK_RESTARTED:
            self.await_disarm = None  # a rebooted autopilot (a new SITL episode) starts afresh
        if event is EventKind.LINK_RESTARTED and self.state not in (
            FlightState.WAITING,
            FlightState.DONE,
        ):
            self._finish(FlightResult.ABORTED, "the autopilot restarted during the flight")

    def _sync(self, frame: ReceivedFrame) -> None:
        """SITL frames: wait (briefly) for the telemetry stamped at the frame's time, which the
        SITL sends just before the frame."""
        if self.camera_clock != "autopilot":
            return
        t = frame.time_s - 1e-6
        deadline = self._clock() + self.cfg.sync_timeout_s
        store = self.store
        while True:
            needed = [store.attitude, store.imu, store.range]
            if self._needs_odometry:
                needed.append(store.odometry)
                if store.pad_odometry is not None:  # on a site: the pad's state too
                    needed.append(store.pad_odometry)
            if all(s is not None and s.time_s >= t for s in needed):
                return
            left = deadline - self._clock()
            if left <= 0:
                return
            self._pump(left)
