"""The SITL's MCAP flight log of the episode being flown: every record the SITL writes goes
through :class:`FlightLog`, stamped with the sim clock.

The log is a training record: for each control step the companion flies it also holds
``/observation`` (the attitude, IMU and range readings last streamed) and ``/command`` (the
setpoint flown for the period after the frame), keyed by frame id like the in-process log, so
``visland relabel`` labels SITL flights.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.contract.records import (
    AutopilotCommandRecord,
    CommandRecord,
    EpisodeResultRecord,
    EventKind,
    EventRecord,
    GroundTruthRecord,
    LinkStatsRecord,
    LogRecord,
    ObservationRecord,
    RxErrorRecord,
)
from companion.contract.topics import (
    TOPIC_AUTOPILOT_COMMAND,
    TOPIC_COMMAND,
    TOPIC_EVENTS,
    TOPIC_GROUNDTRUTH,
    TOPIC_LINK_STATS,
    TOPIC_MAVLINK_IN,
    TOPIC_MAVLINK_OUT,
    TOPIC_OBSERVATION,
    TOPIC_RESULT,
    TOPIC_RX_ERRORS,
)
from companion.flightlog import FlightLogWriter

if TYPE_CHECKING:
    from companion.contract import Command, GroundTruth
    from sitl_sim.mavlink.clock import SimClock
    from sitl_sim.mavlink.endpoint import Inbound, RxError
    from sitl_sim.simulator import CameraFrame

__all__ = ["FlightLog"]


_SECRETS = ("secret_key",)
"""Fields whose value never goes into a log (SETUP_SIGNING's key): written as ``<redacted>``."""


@dataclass(eq=False, repr=False)
class FlightLog:
    """The open episode's flight log (nothing is written while none is open).

    Args:
        clock: the SITL clock every record is stamped with.
        open_writer: ``open_writer(path, metadata=...)`` opens an episode's writer (the SITL
            passes :meth:`sitl_sim.mavlink.log_queue.LogQueue.open_writer`: writes queued
            until the loop waits).
    """

    clock: SimClock
    open_writer: Callable[..., FlightLogWriter] = FlightLogWriter
    _writer: FlightLogWriter | None = field(init=False, default=None)

    @property
    def active(self) -> bool:
        return self._writer is not None

    def open(self, path: Path, metadata: dict[str, Any]) -> None:
        """Start the episode's log (closes none: :meth:`close_with_result` ends the last)."""
        self._writer = self.open_writer(path, metadata=metadata)

    def close_with_result(self, record: EpisodeResultRecord) -> None:
        """Write the episode's result and close its log (no-op without one)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.write_record(TOPIC_RESULT, self.clock.time_s, record)
            writer.close()

    def write(self, topic: str, schema: str, body: dict[str, Any]) -> None:
        if self._writer is not None:
            self._writer.write(topic, schema, self.clock.time_s, body)

    def write_record(self, topic: str, record: LogRecord) -> None:
        if self._writer is not None:
            self._writer.write_record(topic, self.clock.time_s, record)

    def event(self, kind: EventKind, text: str) -> None:
        if self._writer is not None:
            self.write_record(TOPIC_EVENTS, EventRecord(kind=kind, text=text))

    def rx_error(self, err: RxError, link: str) -> None:
        if self._writer is not None:
            self.write_record(
                TOPIC_RX_ERRORS,
                RxErrorRecord(
                    kind=err.kind,
                    reason=err.reason,
                    length=err.length,
                    src=list(err.addr),
                    link=link,
                ),
            )

    def link_stats(self, stats: dict[str, dict[str, int]]) -> None:
        if self._writer is not None:
            self.write_record(TOPIC_LINK_STATS, LinkStatsRecord(**stats))

    def inbound(self, inbound: Inbound) -> None:
        """A message received, with its sender and link (its fields read when the write runs:
        a received message is never changed)."""
        if self._writer is None:
            return
        msg = inbound.msg
        self._writer.write_mavlink(
            TOPIC_MAVLINK_IN + msg.get_type(),
            self.clock.time_s,
            msg,
            {
                "src_system": msg.get_srcSystem(),
                "src_component": msg.get_srcComponent(),
                "signed": inbound.signed,
                "link": inbound.link,
            },
            _SECRETS,
        )

    def outbound(self, msg: Any) -> None:
        """A message sent (its fields read when the write runs: a sent message is never
        changed)."""
        if self._writer is not None:
            self._writer.write_mavlink(
                TOPIC_MAVLINK_OUT + msg.get_type(), self.clock.time_s, msg, None, _SECRETS
            )

    def commands(
        self,
        flight_time_s: float,
        mode_label: str,
        cmd: Command | None,
        frame_id: int | None,
    ) -> None:
        """At a control period: what the autopilot flies, and with the ``frame_id`` of a
        control step (the companion flies it) the training record's ``/command``: the command
        flown for the period after that frame (in lockstep its answer)."""
        if self._writer is None:
            return
        self.write_record(
            TOPIC_AUTOPILOT_COMMAND,
            AutopilotCommandRecord(
                flight_time_s=flight_time_s,
                mode=mode_label,
                armed=cmd is not None,
                thrust_norm=cmd.thrust_norm if cmd is not None else 0.0,
                rate_frd_rad_s=cmd.rate_frd_rad_s if cmd is not None else [0.0, 0.0, 0.0],
            ),
        )
        if cmd is not None and frame_id is not None:
            self.write_record(TOPIC_COMMAND, CommandRecord.from_command(cmd, frame_id, "offboard"))

    def frame(
        self,
        frame_id: int,
        frame: CameraFrame,
        gt: GroundTruth,
        status: dict[str, Any],
        observation: ObservationRecord | None,
    ) -> None:
        """The camera frame just sent, its pose, the ground truth with the flight ``status``
        (``flying``, ``mode``, ``armed``) and, in a control step, the training record's
        ``/observation``. A lost frame (``frame_drop_prob``) is logged as what the client still
        holds — the last delivered image and its exposure time —, as the in-process record
        does, so the training record stays one entry per control step."""
        writer = self._writer
        if writer is None:
            return
        now = self.clock.time_s
        writer.write_image(now, frame.image, frame_id)
        writer.write_pose(now, gt.pos_ned_m, gt.quat_wxyz)
        self.write_record(  # the in-process path's record, with the flight status
            TOPIC_GROUNDTRUTH,
            GroundTruthRecord.from_groundtruth(gt, frame_id, flight_time_s=gt.time_s, **status),
        )
        if observation is not None:
            self.write_record(TOPIC_OBSERVATION, observation)
