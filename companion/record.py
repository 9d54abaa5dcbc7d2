"""The companion flight log (MCAP, one file per flight) and its replay.

Topics (JSON, log time = the file's wall-clock epoch + companion monotonic seconds since the
file was opened; every record also has ``time_s`` on that clock):

* ``/mavlink/in/<NAME>`` — every message from the autopilot as received (pymavlink fields,
  plus ``rx_s``);
* ``/camera/image`` — every frame as received (``foxglove.RawImage`` mono8, plus
  ``capture_time_s`` on the camera's clock, ``rx_s`` and ``frame_number``);
* ``/companion/observation`` — the observation the policy saw (image excluded: see the frame);
* ``/companion/command`` — every command computed: the policy's raw output, what was (or in
  shadow mode would have been) sent after the clamps, ``sent``, and the latency from frame
  receipt to the setpoint leaving the socket (``latency_ms``) and the policy's share of it;
* ``/events`` — state-machine transitions, link events, failsafes; ``flight_start`` marks where
  the policy's state was reset (:meth:`CompanionLog.flight_start`; the replay resets there too);
* ``/companion/summary`` — the flight's counters, last.

Every message's fields are a record of the contract (:mod:`companion.contract.companion_records`,
:mod:`companion.contract.records`): written from one, read back with its ``from_dict``.

Writes are queued while a frame is being answered and written after the setpoint is sent
(:meth:`CompanionLog.flush_pending`), so logging never adds to the latency; the queue keeps
receipt order, which is what makes a log replayable (:func:`replay_log`).

:class:`CompanionLog` is what the flight controller writes through
(:class:`companion.flight.FlightRecorder`); this module does not import the controller.
"""

from __future__ import annotations

import base64
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.camera import ReceivedFrame
from companion.contract import PAD_ODOMETRY_COMPONENT
from companion.contract.companion_records import (
    CompanionCommandRecord,
    CompanionLandingTargetRecord,
    CompanionObservationRecord,
    CompanionSummaryRecord,
)
from companion.contract.record_base import ABSENT, TIME_S, LogRecord
from companion.contract.records import EventKind, EventRecord, RawImageRecord
from companion.contract.topics import (
    TOPIC_COMPANION_COMMAND,
    TOPIC_COMPANION_LANDING_TARGET,
    TOPIC_COMPANION_OBSERVATION,
    TOPIC_COMPANION_SUMMARY,
    TOPIC_EVENTS,
    TOPIC_IMAGE,
    TOPIC_MAVLINK_IN,
)
from companion.flightlog import FlightLogWriter, read_log
from companion.telemetry import TelemetryStore, assemble_observation

if TYPE_CHECKING:
    from companion.live.frame import LiveFrame
    from companion.live.scene_log import SceneStream

__all__ = [
    "CompanionLog",
    "ReplayReport",
    "latency_stats",
    "replay_log",
]


class CompanionLog:
    """One flight's companion log.

    A write that fails (a full SD card, a file-size limit, an I/O error) never stops the flight:
    logging stops, the file keeps what reached it (a truncated log that reads back), and
    ``on_failure`` is told once (:attr:`failed` says why).

    Args:
        path: the MCAP file.
        metadata: MCAP metadata records (``config``, ``flight``, ``policy``...).
        clock: the companion's monotonic clock.
        on_failure: called once with the reason when logging stops.
        scene: also write the live view's picture as the flight goes (``log_scene``): a
            :class:`companion.live.scene_log.SceneStream` (None: not; ``visland log scene``
            adds it afterwards).
    """

    def __init__(
        self,
        path: str | Path,
        metadata: dict[str, dict[str, Any]],
        clock: Callable[[], float] = time.monotonic,
        on_failure: Callable[[str], None] | None = None,
        scene: SceneStream | None = None,
    ) -> None:
        self.path = Path(path)
        self.scene = scene
        self._clock = clock
        self.t0 = clock()
        self._pending: list[tuple[Callable[..., None], tuple[Any, ...]]] = []
        self.deferring = False
        self.failed: str | None = None
        self._on_failure = on_failure
        self.writer: FlightLogWriter | None = None
        try:
            self.writer = FlightLogWriter(path, metadata)
        except OSError as exc:
            self._fail(exc)

    def _fail(self, exc: OSError) -> None:
        self.failed = f"{exc.strerror or type(exc).__name__} ({self.path})"
        self._pending.clear()
        if self.writer is not None:
            self.writer.abandon()
        if self._on_failure is not None:
            self._on_failure(f"flight log stopped: {self.failed}")

    def _write(self, write: Callable[..., None], args: tuple[Any, ...]) -> None:
        if self.failed is not None:
            return
        try:
            write(*args)
        except OSError as exc:
            self._fail(exc)

    def rel(self, monotonic_s: float) -> float:
        return monotonic_s - self.t0

    def _put(self, write: Callable[..., None], *args: Any) -> None:
        """``write(*args)`` (a writer method, its log time first after the topic) now, or
        queued while :attr:`deferring`."""
        if self.failed is not None:
            return
        if self.deferring:
            self._pending.append((write, args))
        else:
            self._write(write, args)

    def flush_pending(self) -> None:
        """Write what was queued while answering a frame (receipt order kept)."""
        self.deferring = False
        pending, self._pending = self._pending, []
        for write, args in pending:
            self._write(write, args)

    def _put_record(self, topic: str, t: float, record: LogRecord) -> None:
        if self.writer is None or self.failed is not None:
            return
        self._put(self.writer.write_record, topic, max(0.0, self.rel(t)), record)

    def message(self, msg: Any, rx_s: float) -> None:
        """A message from the autopilot as received (its fields are read when the write runs:
        a received message is never changed), with ``rx_s``; the pad's ODOMETRY on a SITL
        link also with its ``src_component`` (the replay tells the two streams apart by it)."""
        if self.writer is None or self.failed is not None:
            return
        extra: dict[str, Any] = {"rx_s": rx_s}
        if msg.get_srcComponent() == PAD_ODOMETRY_COMPONENT:
            extra["src_component"] = PAD_ODOMETRY_COMPONENT
        self._put(
            self.writer.write_mavlink,
            TOPIC_MAVLINK_IN + msg.get_type(),
            max(0.0, self.rel(rx_s)),
            msg,
            extra,
        )

    def frame(self, frame: ReceivedFrame) -> None:
        """A camera frame as received (encoded when the write runs: a received image is never
        changed)."""
        self._put(self._write_frame, frame)

    def _write_frame(self, frame: ReceivedFrame) -> None:
        assert self.writer is not None  # queued only while writing
        t = max(0.0, self.rel(frame.rx_s))
        record = RawImageRecord.mono8(
            frame.image,
            frame.frame_id,
            self.writer.log_time_ns(t),
            frame_number=frame.frame_id,
            capture_time_s=frame.time_s,
            rx_s=frame.rx_s,
        )
        self.writer.write_image_record(TOPIC_IMAGE, t, record)

    def scene_frame(self, frame: LiveFrame, rx_s: float) -> None:
        """The live view's picture of the frame received at ``rx_s`` (built and encoded when
        the write runs, after the answer), stamped as its logged image so the annotations sit
        on it; nothing without :attr:`scene`."""
        if self.scene is not None:
            self._put(self._write_scene, frame, rx_s)

    def _write_scene(self, frame: LiveFrame, rx_s: float) -> None:
        assert self.writer is not None and self.scene is not None  # queued only while writing
        t = max(0.0, self.rel(rx_s))
        frame.stamp_ns = self.writer.log_time_ns(t)
        for chan, data in self.scene.frame(frame):
            self.writer.write_encoded(chan.topic, chan.message_encoding, chan.schema, t, data)

    def _write_scene_event(self, t: float, text: str) -> None:
        assert self.writer is not None and self.scene is not None
        chan, data = self.scene.event(self.writer.log_time_ns(t), text)
        self.writer.write_encoded(chan.topic, chan.message_encoding, chan.schema, t, data)

    def observation(self, t: float, record: CompanionObservationRecord) -> None:
        self._put_record(TOPIC_COMPANION_OBSERVATION, t, record)

    def command(self, t: float, record: CompanionCommandRecord) -> None:
        self._put_record(TOPIC_COMPANION_COMMAND, t, record)

    def landing_target(self, t: float, record: CompanionLandingTargetRecord) -> None:
        """Landing-target mode: a frame's pad estimate and what was sent."""
        self._put_record(TOPIC_COMPANION_LANDING_TARGET, t, record)

    def event(self, t: float, kind: EventKind, text: str, **extra: Any) -> None:
        """An ``/events`` record (``extra``: the companion's ``state`` or ``shadow``), and with
        :attr:`scene` the same on ``/log`` as ``foxglove.Log``."""
        self._put_record(TOPIC_EVENTS, t, EventRecord(kind=kind, text=text, **extra))
        if self.scene is not None and self.writer is not None and self.failed is None:
            self._put(self._write_scene_event, max(0.0, self.rel(t)), f"{kind}: {text}")

    def flight_start(self, t: float, text: str, shadow: bool) -> None:
        """The policy takes over (state reset): where :func:`replay_log` resets it too."""
        self.event(t, EventKind.FLIGHT_START, text, shadow=shadow)

    def close(self, summary: CompanionSummaryRecord | None = None) -> None:
        self.flush_pending()
        if self.failed is not None or self.writer is None:
            return
        if summary is not None:
            t = self.rel(self._clock())
            self._write(self.writer.write_record, (TOPIC_COMPANION_SUMMARY, t, summary))
        if self.failed is None:
            self._write(self.writer.close, ())


# --------------------------------------------------------------------------- reading back


def latency_stats(paths: list[str | Path]) -> dict[str, Any]:
    """Frame receipt -> setpoint sent latency (ms) over the *sent* policy commands of logs."""
    lat: list[float] = []
    compute: list[float] = []
    for path in paths:
        log = read_log(path, topics=[TOPIC_COMPANION_COMMAND])
        for m in log.topic(TOPIC_COMPANION_COMMAND):
            rec = CompanionCommandRecord.from_dict(m)
            if rec.policy and rec.sent and rec.latency_ms is not None:
                lat.append(float(rec.latency_ms))
                compute.append(
                    float(rec.compute_ms or 0.0) if rec.compute_ms is not ABSENT else 0.0
                )
    if not lat:
        return {"commands": 0}
    arr = np.asarray(lat)
    return {
        "commands": len(lat),
        "median_ms": float(np.median(arr)),
        "p90_ms": float(np.percentile(arr, 90)),
        "p99_ms": float(np.percentile(arr, 99)),
        "max_ms": float(arr.max()),
        "mean_ms": float(arr.mean()),
        "policy_median_ms": float(np.median(compute)),
        "policy_p99_ms": float(np.percentile(compute, 99)),
    }


class _Recorded:
    """A logged MAVLink message read back: attribute access and ``get_type()``."""

    def __init__(self, name: str, fields: dict[str, Any]) -> None:
        self._name = name
        self.__dict__.update(fields)

    def get_type(self) -> str:
        return self._name

    def get_srcComponent(self) -> int:  # pymavlink's name
        """The sender's component: logged only for the pad's ODOMETRY, else the autopilot's."""
        return int(self.__dict__.get("src_component", 1))


@dataclass
class ReplayReport:
    """How a shadow replay of a companion log compared with what was recorded."""

    log: str
    commands: int = 0
    max_abs_diff: float = 0.0
    errors: list[str] = field(default_factory=list)
    worst_frame: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "log": self.log,
            "commands": self.commands,
            "max_abs_diff": self.max_abs_diff,
            "worst_frame": self.worst_frame,
            "errors": self.errors,
        }


def _raw_records(path: Path):
    """(topic, message) of the JSON channels in file order — the receipt order (the scene's
    protobuf channels are the live view's picture, not inputs)."""
    import json

    from mcap.exceptions import McapError
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    channels: dict[int, str] = {}
    with path.open("rb") as fh:
        try:
            for record in StreamReader(fh, skip_magic=False).records:
                if isinstance(record, Channel):
                    if record.message_encoding == "json":
                        channels[record.id] = record.topic
                elif isinstance(record, Message):
                    topic = channels.get(record.channel_id)
                    if topic is not None:
                        yield topic, json.loads(record.data)
        except (McapError, ValueError, EOFError):
            return  # a truncated log replays up to its cut


def replay_log(path: str | Path, runtime: Any) -> ReplayReport:
    """Replay a companion log in shadow mode: feed the recorded telemetry and frames, in the
    order they were received, through the same observation assembly and ``runtime``
    (a :class:`~companion.runtime.PolicyRuntime`), and compare each policy command with the one
    recorded (raw policy output, before the clamps).
    """
    path = Path(path)
    report = ReplayReport(log=str(path))
    store = TelemetryStore()
    frames: dict[int, ReceivedFrame] = {}
    hovers: dict[int, float] = {}  # the hover thrust the policy was given, per frame
    times: dict[int, dict[str, float | None]] = {}  # the sample times it was given
    for topic, msg in _raw_records(path):
        if topic.startswith(TOPIC_MAVLINK_IN):
            fields = {k: v for k, v in msg.items() if k not in (TIME_S, "mavpackettype")}
            for key in ("x", "y", "z"):  # JSON null = NaN (never in fields we read, but safe)
                if key in fields and fields[key] is None:
                    fields[key] = float("nan")
            store.update(_Recorded(topic[len(TOPIC_MAVLINK_IN) :], fields), float(fields["rx_s"]))
        elif topic == TOPIC_IMAGE:
            image = RawImageRecord.from_dict(msg)
            img = np.frombuffer(base64.b64decode(image.data), dtype=np.uint8).reshape(
                image.height, image.width
            )
            fid = int(image.frame_number)
            frames = {fid: ReceivedFrame(fid, float(image.capture_time_s), img, image.rx_s)}
        elif topic == TOPIC_COMPANION_OBSERVATION:
            obs_rec = CompanionObservationRecord.from_dict(msg)
            fid = int(obs_rec.frame_id)
            if obs_rec.hover_thrust_norm is not None:
                hovers = {fid: float(obs_rec.hover_thrust_norm)}
            # the samples the flight used (on a jittery link not always the newest)
            times = {
                fid: {
                    "attitude": obs_rec.attitude_time_s,
                    "imu": obs_rec.imu_time_s,
                    "range": obs_rec.range_time_s,
                    "odometry": obs_rec.groundtruth_time_s,
                }
            }
        elif topic == TOPIC_EVENTS and EventRecord.from_dict(msg).kind == EventKind.FLIGHT_START:
            runtime.reset()
        elif (
            topic == TOPIC_COMPANION_COMMAND
            and (rec := CompanionCommandRecord.from_dict(msg)).policy
        ):
            fid = int(rec.frame_id)
            frame = frames.get(fid)
            if frame is None:
                report.errors.append(f"frame {fid}: not in the log before its command")
                continue
            at = times.get(fid)
            obs = assemble_observation(frame, store, hovers.get(fid), at)
            gt = store.groundtruth_at(at and at["odometry"]) if runtime.privileged else None
            result = runtime.step(obs, gt)
            if result.command is None:
                report.errors.append(f"frame {fid}: {result.error}")
                continue
            ours = np.concatenate(([result.command.thrust_norm], result.command.rate_frd_rad_s))
            theirs = np.asarray([rec.raw_thrust_norm, *rec.raw_rate_frd_rad_s], float)
            diff = float(np.max(np.abs(ours - theirs)))
            report.commands += 1
            if report.worst_frame is None or diff > report.max_abs_diff:
                report.max_abs_diff = diff
                report.worst_frame = fid
    return report
