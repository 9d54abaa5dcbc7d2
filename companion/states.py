"""The companion's typed states: the offboard state machine's states, why it failed safe, how a
flight ended, and what it does after touchdown.

The string enums (:class:`enum.StrEnum`) are their own wire text: a member compares equal to,
formats as and serialises (JSON, MCAP, ``--json``) as its value, so logs and reports read
exactly as plain strings did. Code tests identity (``result is FlightResult.LANDED``), never
prefixes.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

__all__ = [
    "Failsafe",
    "FailsafeReason",
    "FlightResult",
    "FlightState",
    "TouchdownAction",
]


class FlightState(enum.Enum):
    """The states of one flight's offboard state machine (:mod:`companion.offboard`)."""

    WAITING = "waiting"
    PRESTREAM = "prestream"
    ENGAGING = "engaging"
    FLYING = "flying"
    TOUCHDOWN = "touchdown"
    FAILSAFE = "failsafe"
    DONE = "done"


class FailsafeReason(enum.StrEnum):
    """Why the companion stopped flying the policy (and, but for ``PAD_NOT_FOUND``,
    requested LAND)."""

    CAMERA_STALE = "camera_stale"
    """The newest camera frame was received more than ``max_age_s`` ago."""
    TELEMETRY_STALE = "telemetry_stale"
    """ATTITUDE, HIGHRES_IMU, DISTANCE_SENSOR (or ODOMETRY) older than ``max_age_s``."""
    RANGE_INVALID = "range_invalid"
    """Near the ground, no valid range for ``max_age_s``: the policy would descend blind."""
    POLICY_ERROR = "policy_error"
    """The policy raised or produced a non-finite command."""
    OFFBOARD_UNCONFIRMED = "offboard_unconfirmed"
    """OFFBOARD was acknowledged but never shown in the HEARTBEAT."""
    PAD_NOT_FOUND = "pad_not_found"
    """The landing guard held below its floor without a confirmed pad for its whole timeout
    (``companion.policy_net.guard``): the companion stops its setpoints and requests nothing —
    the autopilot's offboard-loss action applies (never LAND: that would land blind)."""


@dataclass(frozen=True)
class Failsafe:
    """A failsafe: its reason and the measured detail; ``str()`` is ``"<reason>: <detail>"``,
    the text of the logs and reports (e.g. ``camera_stale: newest frame 309 ms old (> 300)``)."""

    reason: FailsafeReason
    detail: str

    def __str__(self) -> str:
        return f"{self.reason}: {self.detail}"


class FlightResult(enum.StrEnum):
    """How one flight of the companion ended (``FlightOutcome.result``)."""

    LANDED = "landed"
    FAILSAFE = "failsafe"
    HANDED_BACK = "handed_back"
    """The autopilot or the pilot took control back (mode change, disarm) in flight."""
    ENGAGE_FAILED = "engage_failed"
    """OFFBOARD refused or unanswered three times."""
    ABORTED = "aborted"
    """Stopped by us: signal, end of run, autopilot restart."""
    SHADOW = "shadow"
    """A shadow flight ended (touchdown, disarm or a failsafe it would have requested)."""
    INCOMPLETE = "incomplete"
    """Not ended yet."""


class TouchdownAction(enum.StrEnum):
    """What the companion does once the vehicle is down (``on_touchdown``)."""

    DISARM = "disarm"
    HAND_BACK = "hand_back"
    """Switch to the autopilot's hold mode and let it disarm."""
