"""Every flight-log message's fields, declared once (PX4's ``msg/`` is the model).

Each record is a frozen dataclass whose fields are the message's JSON keys in order
(:class:`~companion.contract.record_base.LogRecord`): writers build one and log
``record.to_dict()``, readers get one back with ``Record.from_dict(message)``, and the MCAP schema
record of each schema name is ``Record.json_schema()`` (:func:`schema_json`). A field defaulting
to :data:`ABSENT` is left out of messages that do not carry it, so logs written before a field
existed read as they did. Topic and schema names are :mod:`companion.contract.topics`';
``/events`` kinds are :class:`EventKind`. Vectors (``Vector``) are numpy arrays when written and
lists when read back.
"""

from __future__ import annotations

import base64
import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.contract.companion_records import COMPANION_RECORDS, ObservationKeys
from companion.contract.messages import PAD_STATE_FIELDS, Command, GroundTruth, Observation
from companion.contract.record_base import (
    ABSENT,
    RECORD,
    TIME_S,
    Absent,
    LogRecord,
    RecordError,
    Vector,
)
from companion.contract.topics import (
    SCHEMA_AUTOPILOT_COMMAND,
    SCHEMA_COMMAND,
    SCHEMA_EPISODE_RESULT,
    SCHEMA_EPISODE_SCENARIO,
    SCHEMA_EVENT,
    SCHEMA_GROUNDTRUTH,
    SCHEMA_GROUNDTRUTH_POSE,
    SCHEMA_IMAGE,
    SCHEMA_LABEL,
    SCHEMA_LINK_STATS,
    SCHEMA_OBSERVATION,
    SCHEMA_POLICY_ESTIMATE,
    SCHEMA_PRECLAND,
    SCHEMA_RX_ERROR,
)

__all__ = [
    "ABSENT",
    "RECORDS",
    "TIME_S",
    "Absent",
    "AutopilotCommandRecord",
    "CommandRecord",
    "EpisodeResultRecord",
    "EpisodeScenarioRecord",
    "EventKind",
    "EventRecord",
    "GroundTruthRecord",
    "LabelRecord",
    "LinkStatsRecord",
    "LogRecord",
    "ObservationRecord",
    "PolicyEstimateRecord",
    "Pose",
    "PoseInFrameRecord",
    "PreclandRecord",
    "Quaternion",
    "RawImageRecord",
    "RecordError",
    "RxErrorRecord",
    "Timestamp",
    "Vector",
    "Vector3",
    "mavlink_schema_json",
    "schema_json",
]


class EventKind(enum.StrEnum):
    """Every ``/events`` ``kind`` (a ``str``: the logged value is the member's value)."""

    # ---- the SITL (autopilot events, its handlers, episodes, precision land)
    STATUSTEXT = "statustext"
    MODE = "mode"
    MODE_REFUSED = "mode_refused"
    ARMED = "armed"
    DISARMED = "disarmed"
    FAILSAFE = "failsafe"
    TAKEOVER = "takeover"
    GUIDED = "guided"
    GUIDED_TIMEOUT = "guided_timeout"
    FLIGHT = "flight"
    """SITL: the take-over happened, the flight proper starts."""
    SET_MODE = "set_mode"
    COMMAND = "command"
    SETPOINT_REJECTED = "setpoint_rejected"
    PARAM_REJECTED = "param_rejected"
    LINK_OUTAGE = "link_outage"
    CAMERA_FRAME_DROPPED = "camera_frame_dropped"
    PRECLAND = "precland"
    LANDING_TARGET_REJECTED = "landing_target_rejected"
    LOCKSTEP = "lockstep"
    # ---- the companion (its flight state machine, its link)
    FLIGHT_START = "flight_start"
    """Companion: the policy takes over (its state reset; a replay resets there too)."""
    STATE = "state"
    ARM = "arm"
    PARAM = "param"
    WAITING = "waiting"
    OFFBOARD_ACK = "offboard_ack"
    OFFBOARD_REFUSED = "offboard_refused"
    PRECLAND_ACK = "precland_ack"
    PRECLAND_REFUSED = "precland_refused"
    FAILSAFE_SHADOW = "failsafe_shadow"
    GUARD = "guard"
    """Companion, landing-target mode: the landing guard held the descent (no confirmed pad
    below the floor) or let it go on (the pad confirmed)."""
    HAND_BACK = "hand_back"
    LINK_DISCOVERED = "link_discovered"
    LINK_LOST = "link_lost"
    LINK_RECONNECTED = "link_reconnected"
    LINK_RESTARTED = "link_restarted"
    CLOCK_STEP = "clock_step"
    LINK_PEER = "link_peer"
    LINK_PORT_ERROR = "link_port_error"
    LINK_PORT_REOPENED = "link_port_reopened"

    @classmethod
    def of_link(cls, link_kind: str) -> EventKind:
        """The companion's event for a link event of kind ``link_kind`` (``lost`` ->
        :attr:`LINK_LOST`)."""
        return cls("link_" + link_kind)


def _vec(rec: LogRecord, name: str, n: int) -> np.ndarray:
    value = getattr(rec, name)
    arr = np.asarray(value, dtype=float)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise RecordError(f"{name}: expected {n} finite numbers, got {value!r} ({rec.SCHEMA})")
    return arr


# ------------------------------------------------------------------ foxglove parts and records


@dataclass(**RECORD)
class Timestamp(LogRecord):
    """A foxglove time: whole seconds and nanoseconds of the log time."""

    sec: int
    nsec: int

    @classmethod
    def from_ns(cls, t_ns: int) -> Timestamp:
        return cls(sec=t_ns // 1_000_000_000, nsec=t_ns % 1_000_000_000)


@dataclass(**RECORD)
class Vector3(LogRecord):
    x: float
    y: float
    z: float


@dataclass(**RECORD)
class Quaternion(LogRecord):
    x: float
    y: float
    z: float
    w: float


@dataclass(**RECORD)
class Pose(LogRecord):
    position: Vector3
    orientation: Quaternion


@dataclass(**RECORD)
class RawImageRecord(LogRecord):
    """``/camera/image``: a mono8 frame (``foxglove.RawImage``); the companion adds the camera
    packet's ``frame_number``, its ``capture_time_s`` (camera clock) and ``rx_s``."""

    SCHEMA = SCHEMA_IMAGE
    timestamp: Timestamp
    frame_id: str
    """``camera/<frame id>``."""
    width: int
    height: int
    encoding: str
    step: int
    data: str = field(metadata={"schema": {"contentEncoding": "base64"}})
    frame_number: int | Absent = ABSENT
    capture_time_s: float | Absent = ABSENT
    rx_s: float | Absent = ABSENT

    @classmethod
    def mono8(
        cls, image: np.ndarray, frame_id: int, log_time_ns: int, **extra: Any
    ) -> RawImageRecord:
        """Frame ``frame_id``'s 2-D image as uint8 ``mono8``, stamped ``log_time_ns``
        (``extra``: the companion's ``frame_number``, ``capture_time_s``, ``rx_s``)."""
        img = np.ascontiguousarray(image, dtype=np.uint8)
        return cls(
            timestamp=Timestamp.from_ns(log_time_ns),
            frame_id=f"camera/{frame_id}",
            width=int(img.shape[1]),
            height=int(img.shape[0]),
            encoding="mono8",
            step=int(img.shape[1]),
            data=base64.b64encode(img.tobytes()).decode("ascii"),
            **extra,
        )


@dataclass(**RECORD)
class PoseInFrameRecord(LogRecord):
    """``/groundtruth/pose``: the ground-truth pose (``foxglove.PoseInFrame``, frame ``ned``,
    position x, y, z = north, east, down)."""

    SCHEMA = SCHEMA_GROUNDTRUTH_POSE
    timestamp: Timestamp
    frame_id: str
    pose: Pose


# ------------------------------------------------------------------ the training record


@dataclass(**RECORD)
class GroundTruthRecord(LogRecord):
    """``/groundtruth/state``: the privileged state at a frame; the SITL adds the flight status
    (``flight_time_s``, ``flying``, ``mode`` = the autopilot's mode label, ``armed``)."""

    SCHEMA = SCHEMA_GROUNDTRUTH
    frame_id: int
    pos_ned_m: Vector
    vel_ned_m_s: Vector
    quat_wxyz: Vector
    rate_frd_rad_s: Vector
    accel_ned_m_s2: Vector | None
    rotor_thrust_n: Vector | None
    wind_ned_m_s: Vector | Absent = ABSENT
    """Only in a world with wind (still-air logs are unchanged)."""
    pad_pos_ned_m: Vector | Absent = ABSENT
    """The pad's state (``GroundTruth``'s four pad fields): only on a site that is not flat
    and still (nominal logs are unchanged)."""
    pad_vel_ned_m_s: Vector | Absent = ABSENT
    pad_quat_wxyz: Vector | Absent = ABSENT
    pad_accel_ned_m_s2: Vector | Absent = ABSENT
    flight_time_s: float | Absent = ABSENT
    flying: bool | Absent = ABSENT
    mode: str | Absent = ABSENT
    armed: bool | Absent = ABSENT

    @classmethod
    def from_groundtruth(cls, gt: GroundTruth, frame_id: int, **status: Any) -> GroundTruthRecord:
        optional = {
            name: ABSENT if getattr(gt, name) is None else getattr(gt, name)
            for name in ("wind_ned_m_s", *PAD_STATE_FIELDS)
        }
        return cls(
            frame_id=frame_id,
            pos_ned_m=gt.pos_ned_m,
            vel_ned_m_s=gt.vel_ned_m_s,
            quat_wxyz=gt.quat_wxyz,
            rate_frd_rad_s=gt.rate_frd_rad_s,
            accel_ned_m_s2=gt.accel_ned_m_s2,
            rotor_thrust_n=gt.rotor_thrust_n,
            **optional,
            **status,
        )

    def groundtruth(self, time_s: float) -> GroundTruth:
        """The GroundTruth at ``time_s`` (the message's :data:`TIME_S`).

        Raises:
            RecordError: a vector of the wrong length or not finite.
        """
        return GroundTruth(
            time_s=float(time_s),
            pos_ned_m=_vec(self, "pos_ned_m", 3),
            vel_ned_m_s=_vec(self, "vel_ned_m_s", 3),
            quat_wxyz=_vec(self, "quat_wxyz", 4),
            rate_frd_rad_s=_vec(self, "rate_frd_rad_s", 3),
            accel_ned_m_s2=_vec(self, "accel_ned_m_s2", 3),
            rotor_thrust_n=_vec(self, "rotor_thrust_n", 4),
            wind_ned_m_s=None if self.wind_ned_m_s is ABSENT else _vec(self, "wind_ned_m_s", 3),
            **{
                name: None if getattr(self, name) is ABSENT else _vec(self, name, n)
                for name, n in zip(PAD_STATE_FIELDS, (3, 3, 4, 3), strict=True)
            },
        )


@dataclass(**RECORD)
class ObservationRecord(ObservationKeys):
    """``/observation``: an Observation's fields but the image (``/camera/image`` holds it);
    ``range_m`` null = invalid (NaN); ``hover_thrust_norm`` left out when not reported."""

    SCHEMA = SCHEMA_OBSERVATION
    hover_thrust_norm: float | Absent = ABSENT

    @classmethod
    def from_observation(cls, obs: Observation) -> ObservationRecord:
        hover = obs.hover_thrust_norm
        return cls(
            **cls.values_of(obs),
            hover_thrust_norm=hover if hover > 0 else ABSENT,  # NaN: not reported
        )

    def observation(self, image: np.ndarray) -> Observation:
        """The Observation, with ``image`` (ContractError if a field breaks the contract)."""
        hover = self.hover_thrust_norm
        return Observation(
            image=image,
            image_time_s=float(self.image_time_s),
            attitude_rad=np.asarray(self.attitude_rad, dtype=float),
            rate_frd_rad_s=np.asarray(self.rate_frd_rad_s, dtype=float),
            attitude_time_s=float(self.attitude_time_s),
            range_m=math.nan if self.range_m is None else float(self.range_m),
            range_time_s=float(self.range_time_s),
            accel_frd_m_s2=np.asarray(self.accel_frd_m_s2, dtype=float),
            imu_time_s=float(self.imu_time_s),
            frame_id=int(self.frame_id),
            hover_thrust_norm=math.nan if hover is ABSENT or hover is None else float(hover),
        )


@dataclass(**RECORD)
class CommandRecord(LogRecord):
    """``/command``: the Command flown for the period after frame ``frame_id``; ``source``:
    who flew it (the pilot's name in-process, ``offboard`` in the SITL)."""

    SCHEMA = SCHEMA_COMMAND
    frame_id: int
    thrust_norm: float
    rate_frd_rad_s: Vector
    source: str

    @classmethod
    def from_command(cls, cmd: Command, frame_id: int, source: str) -> CommandRecord:
        return cls(
            frame_id=frame_id,
            thrust_norm=cmd.thrust_norm,
            rate_frd_rad_s=cmd.rate_frd_rad_s,
            source=source,
        )


@dataclass(**RECORD)
class PolicyEstimateRecord(LogRecord):
    """``/policy/estimate``: a learned policy's belief after frame ``frame_id`` (in-process
    flights): the CNN's bearing and pad probability, and the pad estimator's vehicle position
    and velocity relative to the pad (NED) with the position's 1-sigma (null before a fix)."""

    SCHEMA = SCHEMA_POLICY_ESTIMATE
    frame_id: int
    tan_right: float | None
    tan_forward: float | None
    pad_probability: float | None
    rel_pos_ned_m: Vector | None
    rel_vel_ned_m_s: Vector | None
    sigma_ned_m: Vector | None

    @classmethod
    def from_state(cls, state: Any, frame_id: int) -> PolicyEstimateRecord | None:
        """The record of a policy state with perception or an estimator (None: neither, e.g.
        the MPC's)."""
        raw = getattr(state, "last_perception", None)
        est = getattr(state, "estimator", None)
        if raw is None and est is None:
            return None
        fixed = est is not None and bool(np.all(est.initialised))
        logit = None if raw is None else max(-50.0, min(50.0, float(raw[2])))
        return cls(
            frame_id=frame_id,
            tan_right=None if raw is None else float(raw[0]),
            tan_forward=None if raw is None else float(raw[1]),
            pad_probability=None if logit is None else 1.0 / (1.0 + math.exp(-logit)),
            rel_pos_ned_m=est.x[:, 0] if fixed else None,
            rel_vel_ned_m_s=est.x[:, 1] if fixed else None,
            sigma_ned_m=np.sqrt(np.maximum(est.cov[:, 0, 0], 0.0)) if fixed else None,
        )


@dataclass(**RECORD)
class LabelRecord(LogRecord):
    """``/label/command`` (``visland relabel``): the expert's Command for ``frame_id`` and the
    recorded one beside it (NaN / null when the log has no command for that frame)."""

    SCHEMA = SCHEMA_LABEL
    frame_id: int
    thrust_norm: float
    rate_frd_rad_s: Vector
    recorded_thrust_norm: float | None
    recorded_rate_frd_rad_s: Vector


@dataclass(**RECORD)
class EpisodeScenarioRecord(LogRecord):
    """``/episode/scenario``, first in the file: the seed, the episode (the SITL's
    ``episode``, the in-process ``episode_index``), its initial state and scenario, and what
    its world drew (``airframe``, ``visual``, ``pad``, ``site``: left out when nominal)."""

    SCHEMA = SCHEMA_EPISODE_SCENARIO
    episode: int | Absent = ABSENT
    seed: int
    episode_index: int | Absent = ABSENT
    initial_state: Mapping[str, Any]
    scenario: Mapping[str, Any]
    airframe: Mapping[str, Any] | Absent = ABSENT
    visual: Mapping[str, Any] | Absent = ABSENT
    pad: Mapping[str, Any] | Absent = ABSENT
    """The pad design drawn (``[pad] design``)."""
    site: Mapping[str, Any] | Absent = ABSENT
    """The landing site drawn (``sitl_sim.site.Site.record``: the pad's motion, terrain)."""


@dataclass(**RECORD)
class EpisodeResultRecord(LogRecord):
    """``/episode/result``, last in the file: the episode's result, the fields every message
    has (``time_s``: touchdown or timeout; ``sitl_sim.metrics.EpisodeResult`` is this record
    with the rest absent, scored), and in the SITL's log the episode, whether it was aborted,
    the link counters and the precision land's part."""

    SCHEMA = SCHEMA_EPISODE_RESULT
    episode: int | Absent = ABSENT
    aborted: bool | Absent = ABSENT
    landed: bool
    time_s: float
    landing_error_m: float
    touchdown_speed_m_s: float
    touchdown_vertical_speed_m_s: float
    tilt_deg: float
    success: bool
    touched_pad: bool | Absent = ABSENT
    """On a site (a moving pad, slope, rocks): whether the vehicle came down on the pad's own
    surface; the metrics above are then in the pad's frame. Absent on the nominal flat site."""
    tipped_over: bool | Absent = ABSENT
    """On a site: the surface it came down on was too steep to stand on (a failure)."""
    failsafe: str | Absent = ABSENT
    """The pilot ended the flight in the air: why (``pad_not_found``: the landing guard,
    ``companion.policy_net.guard``); a failure, not an unsafe one; else absent."""
    took_over: bool | Absent = ABSENT
    """False: the episode ended in the SITL's HOLD, nobody took over (``not_started``)."""
    link_stats: Mapping[str, int] | Absent = ABSENT
    gcs_link_stats: Mapping[str, int] | Absent = ABSENT
    lockstep_timeouts: int | Absent = ABSENT
    landing_target: Mapping[str, int] | Absent = ABSENT
    precland_state: str | Absent | None = ABSENT
    link_impairment: Mapping[str, Any] | Absent = ABSENT


# ------------------------------------------------------------------ SITL only


@dataclass(**RECORD)
class AutopilotCommandRecord(LogRecord):
    """``/autopilot/command``: what the autopilot flew for a control period, in any mode
    (disarmed: motors off, zero thrust and rates)."""

    SCHEMA = SCHEMA_AUTOPILOT_COMMAND
    flight_time_s: float
    mode: str
    """The autopilot's mode label (``companion.contract.autopilots``' modes' ``label``)."""
    armed: bool
    thrust_norm: float
    rate_frd_rad_s: Vector


@dataclass(**RECORD)
class RxErrorRecord(LogRecord):
    """``/mavlink/rx_errors``: a datagram an endpoint refused (``kind``: the counter it went
    to), its length, sender ``[host, port]`` and link."""

    SCHEMA = SCHEMA_RX_ERROR
    kind: str
    reason: str
    length: int
    src: Sequence[Any]
    link: str


@dataclass(**RECORD)
class LinkStatsRecord(LogRecord):
    """``/mavlink/link_stats``: each link's counters (``offboard``; ``gcs`` when open)."""

    SCHEMA = SCHEMA_LINK_STATS
    offboard: Mapping[str, int]
    gcs: Mapping[str, int] | Absent = ABSENT


@dataclass(**RECORD)
class PreclandRecord(LogRecord):
    """``/autopilot/precland`` (AUTO.PRECLAND): the precision land's state, the autopilot's
    estimate and its landing-target estimate (null: none yet) at a control period."""

    SCHEMA = SCHEMA_PRECLAND
    flight_time_s: float
    state: str
    search_count: int
    est_pos_ned_m: Vector
    est_vel_ned_m_s: Vector
    target_valid: bool
    target_age_s: float | None
    target_rel_ne_m: Vector | None
    target_rel_vel_ne_m_s: Vector | None
    target_ne_m: Vector | None
    approx_ne_m: Vector | None
    hold_altitude_m: float | None


# ------------------------------------------------------------------ every log kind


@dataclass(**RECORD)
class EventRecord(LogRecord):
    """``/events``: a state-machine transition, link event or failsafe; the companion adds
    its flight ``state`` (or, at ``flight_start``, whether it flies in ``shadow``)."""

    SCHEMA = SCHEMA_EVENT
    kind: EventKind
    text: str
    state: str | Absent = ABSENT
    shadow: bool | Absent = ABSENT


RECORDS: dict[str, type[LogRecord]] = {
    rec.SCHEMA: rec
    for rec in (
        RawImageRecord,
        PoseInFrameRecord,
        GroundTruthRecord,
        ObservationRecord,
        CommandRecord,
        PolicyEstimateRecord,
        LabelRecord,
        EpisodeScenarioRecord,
        EpisodeResultRecord,
        AutopilotCommandRecord,
        RxErrorRecord,
        LinkStatsRecord,
        PreclandRecord,
        EventRecord,
        *COMPANION_RECORDS,
    )
}
"""Schema name -> its record, for every fixed topic's schema (``mavlink.NAME``: pymavlink's)."""


def schema_json(schema_name: str) -> dict[str, Any] | None:
    """The jsonschema of a schema name's messages (None: not a declared record's)."""
    rec = RECORDS.get(schema_name)
    return None if rec is None else rec.json_schema()


_MAVLINK_TYPES: dict[str, Any] = {
    "float": ["number", "null"],  # NaN (an unknown covariance) is null
    "double": ["number", "null"],
    "char": "string",
}
_RECEIPT_FIELDS: dict[str, Any] = {
    "rx_s": {"type": "number"},
    "src_system": {"type": "integer"},
    "src_component": {"type": "integer"},
    "signed": {"type": "boolean"},
    "link": {"type": "string"},
}
"""What a logged received message adds to pymavlink's fields (the companion: ``rx_s``, its
receipt time; the SITL: the sender, whether it was signed and the link)."""


def mavlink_schema_json(schema_name: str) -> dict[str, Any] | None:
    """The jsonschema of a logged MAVLink message (schema ``mavlink.NAME``): pymavlink's
    ``to_dict()`` (``mavpackettype`` + the common dialect's fields; char arrays as strings,
    other arrays as arrays) and what a receiver adds. None: not a common-dialect message."""
    from pymavlink.dialects.v20 import common as mavlink

    name = schema_name.removeprefix("mavlink.")
    cls = getattr(mavlink, f"MAVLink_{name.lower()}_message", None)
    if cls is None or not hasattr(cls, "fieldnames"):
        return None
    props: dict[str, Any] = {TIME_S: {"type": "number"}, "mavpackettype": {"type": "string"}}
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))  # wire order
    for fname, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        item = {"type": _MAVLINK_TYPES.get(ftype, "integer")}
        array = lengths[fname] and ftype != "char"
        props[fname] = {"type": "array", "items": item} if array else item
    return {
        "title": schema_name,
        "type": "object",
        "properties": {**props, **_RECEIPT_FIELDS},
        "required": [TIME_S, "mavpackettype", *cls.fieldnames],
    }
