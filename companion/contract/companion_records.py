"""The records only the companion's log holds (``/companion/*``), declared once like the rest of
:mod:`companion.contract.records` (which re-exports nothing from here: import these from here),
and :class:`ObservationKeys`, the keys ``/companion/observation`` shares with ``/observation``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

from companion.contract.record_base import ABSENT, RECORD, Absent, LogRecord, Vector
from companion.contract.topics import (
    SCHEMA_COMPANION_COMMAND,
    SCHEMA_COMPANION_LANDING_TARGET,
    SCHEMA_COMPANION_OBSERVATION,
    SCHEMA_COMPANION_SUMMARY,
)

if TYPE_CHECKING:
    from companion.contract.messages import Observation

__all__ = [
    "COMPANION_RECORDS",
    "CompanionCommandRecord",
    "CompanionLandingTargetRecord",
    "CompanionObservationRecord",
    "CompanionSummaryRecord",
    "ObservationKeys",
]


@dataclass(**RECORD)
class ObservationKeys(LogRecord):
    """The keys ``/observation`` (:class:`companion.contract.records.ObservationRecord`) and
    ``/companion/observation`` share, first in both: an Observation's fields but the image and
    the hover thrust, with each sample's time."""

    frame_id: int
    image_time_s: float
    attitude_rad: Vector
    rate_frd_rad_s: Vector
    attitude_time_s: float
    range_m: float | None
    range_time_s: float
    accel_frd_m_s2: Vector
    imu_time_s: float

    @staticmethod
    def values_of(obs: Observation) -> dict[str, Any]:
        """These keys' values in ``obs`` (``range_m`` NaN, invalid, is written as null)."""
        return {f.name: getattr(obs, f.name) for f in fields(ObservationKeys)}


@dataclass(**RECORD)
class CompanionObservationRecord(ObservationKeys):
    """``/companion/observation``: the observation the policy saw (image excluded), with the
    sample times it was assembled from (``groundtruth_time_s``: the ODOMETRY a privileged
    policy was given; null for a deployable one). ``hover_thrust_norm`` null: not reported."""

    SCHEMA = SCHEMA_COMPANION_OBSERVATION
    hover_thrust_norm: float | None
    groundtruth_time_s: float | None


@dataclass(**RECORD)
class CompanionCommandRecord(LogRecord):
    """``/companion/command``: every command computed for a frame. ``policy``: the policy's
    (``kind`` ``policy`` or ``shadow``) or a neutral answer (``neutral``, ``touchdown``);
    ``sent``: it left the socket; ``latency_ms``: frame receipt -> sent. A policy command also
    has the raw output before the clamps and where its time went (``send_call_ms`` null when
    nothing was sent)."""

    SCHEMA = SCHEMA_COMPANION_COMMAND
    frame_id: int
    policy: bool
    kind: str
    thrust_norm: float
    rate_frd_rad_s: Vector
    raw_thrust_norm: float | Absent = ABSENT
    raw_rate_frd_rad_s: Vector | Absent = ABSENT
    clamped: bool | Absent = ABSENT
    sent: bool
    time_boot_ms: int
    latency_ms: float
    send_call_ms: float | Absent | None = ABSENT
    compute_ms: float | Absent = ABSENT
    queue_ms: float | Absent = ABSENT
    sync_ms: float | Absent = ABSENT


@dataclass(**RECORD)
class CompanionLandingTargetRecord(LogRecord):
    """``/companion/landing_target`` (landing-target mode): a frame's pad estimate and the
    LANDING_TARGET sent, or ``why_not`` (stale inputs). The target fields are there when the
    tracker has a horizontal estimate."""

    SCHEMA = SCHEMA_COMPANION_LANDING_TARGET
    frame_id: int
    image_time_s: float
    why_not: str | Absent = ABSENT
    visibility: float | Absent = ABSENT
    seen: bool | Absent = ABSENT
    error: str | Absent | None = ABSENT
    target_rel_ned_m: Vector | Absent = ABSENT
    angle_x_rad: float | Absent = ABSENT
    angle_y_rad: float | Absent = ABSENT
    distance_m: float | Absent = ABSENT
    pos_frd_m: Vector | Absent = ABSENT
    sent: bool
    latency_ms: float


@dataclass(**RECORD)
class CompanionSummaryRecord(LogRecord):
    """``/companion/summary``, last: the flight's outcome (``companion.flight.FlightOutcome``)
    and counters (the link's, the clamps', the camera's, telemetry refused per reason)."""

    SCHEMA = SCHEMA_COMPANION_SUMMARY
    index: int
    result: str
    reason: str
    policy_commands: int
    neutral_setpoints: int
    failsafe_reason: str | None
    log_path: str | None
    events: list[str]
    link: Mapping[str, int] | Absent = ABSENT
    clamped: int | Absent = ABSENT
    camera: Mapping[str, int] | Absent = ABSENT
    telemetry_rejected: Mapping[str, Any] | Absent = ABSENT


COMPANION_RECORDS: tuple[type[LogRecord], ...] = (
    CompanionObservationRecord,
    CompanionCommandRecord,
    CompanionLandingTargetRecord,
    CompanionSummaryRecord,
)
"""Every companion record (:data:`companion.contract.records.RECORDS` holds them too)."""
