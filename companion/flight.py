"""The types around one flight of the companion: its settings (:class:`OffboardConfig`, the
companion config's flight part), the log it writes to (:class:`FlightRecorder`, the few calls
the state machine makes) and how it ended (:class:`FlightOutcome`). The state machine itself is
:mod:`companion.offboard`; its states and results are :mod:`companion.states`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from companion.camera import ReceivedFrame
from companion.states import Failsafe, FlightResult, TouchdownAction

__all__ = ["FlightOutcome", "FlightRecorder", "OffboardConfig"]


@dataclass(frozen=True)
class OffboardConfig:
    """The state machine's settings (the companion config's flight part).

    Attributes:
        shadow: compute and log, never send a setpoint or a mode change.
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
        if not self.prestream_s >= 1.0:
            raise ValueError(f"prestream_s = {self.prestream_s}; expected >= 1.0 (PX4 rule)")
        if not 2.0 < self.prestream_rate_hz <= 100.0:
            raise ValueError(f"prestream_rate_hz = {self.prestream_rate_hz}; expected (2, 100]")
        if not 0.0 <= self.hover_thrust <= 1.0:
            raise ValueError(f"hover_thrust = {self.hover_thrust}; expected in [0, 1]")


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

    def observation(self, t: float, body: dict[str, Any]) -> None: ...

    def command(self, t: float, body: dict[str, Any]) -> None: ...

    def event(self, t: float, kind: str, text: str, **extra: Any) -> None: ...

    def flight_start(self, t: float, text: str, shadow: bool) -> None: ...

    def flush_pending(self) -> None: ...
