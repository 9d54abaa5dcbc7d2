"""The telemetry store: the latest ATTITUDE, HIGHRES_IMU, DISTANCE_SENSOR, HEARTBEAT (mode,
armed), EXTENDED_SYS_STATE and — for privileged policies in simulation only — ODOMETRY, each with
the autopilot's time stamp and the companion's receive time, so every reader can ask how stale it
is.

One ``handle_<message>`` method per message (``SUBSCRIBES`` lists them); anything else is
ignored. Malformed values (non-finite attitude, a range outside the sensor's limits) never raise:
the sample is marked invalid or dropped and counted. A sample stamped before the one held (a
reordered datagram of a lossy link) is dropped and counted as ``<NAME> late``: the newest
reading never goes back in time. One stamped more than a second before it is a restarted
autopilot, and is taken (:data:`companion.camera.RESTART_WINDOW_S`, the link's rule).

:func:`assemble_observation` makes the policy's :class:`~companion.contract.Observation` from a
camera frame and the newest samples: in flight (:mod:`companion.offboard`) and in a log's replay
(:mod:`companion.record`) alike.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from companion.camera import RESTART_WINDOW_S, ReceivedFrame
from companion.contract import PAD_ODOMETRY_COMPONENT, GroundTruth, Observation
from companion.contract.messages import quat_to_rotation

__all__ = [
    "SUBSCRIBES",
    "AttitudeSample",
    "HeartbeatSample",
    "ImuSample",
    "LandedSample",
    "OdometrySample",
    "RangeSample",
    "TelemetryStore",
    "assemble_observation",
    "odometry_from_msg",
]

SUBSCRIBES = (
    "HEARTBEAT",
    "ATTITUDE",
    "HIGHRES_IMU",
    "DISTANCE_SENSOR",
    "EXTENDED_SYS_STATE",
    "ODOMETRY",
)

HISTORY_SAMPLES = 16
"""Samples kept per timed message for :meth:`TelemetryStore.at`: 0.32 s of 50 Hz ATTITUDE,
HIGHRES_IMU or ODOMETRY, 1.6 s of 10 Hz DISTANCE_SENSOR — beyond any jitter worth flying."""
_TIMED = ("attitude", "imu", "range", "odometry", "pad_odometry")

_MAV_SENSOR_ROTATION_PITCH_270 = 25  # downward-facing
_MAV_MODE_FLAG_SAFETY_ARMED = 128
_MAV_FRAME_LOCAL_NED = 1
_MAV_FRAME_BODY_FRD = 12
_MAV_FRAME_BODY_NED = 8  # legacy name some autopilots use for the body frame


@dataclass(frozen=True)
class AttitudeSample:
    """ATTITUDE: roll/pitch/yaw (rad) and FRD body rates (rad/s)."""

    attitude_rad: np.ndarray
    rate_frd_rad_s: np.ndarray
    time_s: float
    rx_s: float


@dataclass(frozen=True)
class ImuSample:
    """HIGHRES_IMU: specific force (m/s², FRD; about (0, 0, -g) at rest) and gyro (rad/s)."""

    accel_frd_m_s2: np.ndarray
    gyro_frd_rad_s: np.ndarray
    time_s: float
    rx_s: float


@dataclass(frozen=True)
class RangeSample:
    """DISTANCE_SENSOR (downward): range (m), NaN when the sensor reports no valid return."""

    range_m: float
    time_s: float
    rx_s: float

    @property
    def valid(self) -> bool:
        return math.isfinite(self.range_m)


@dataclass(frozen=True)
class HeartbeatSample:
    """The autopilot's HEARTBEAT: custom mode, armed flag, system status."""

    custom_mode: int
    base_mode: int
    system_status: int
    autopilot: int
    rx_s: float

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & _MAV_MODE_FLAG_SAFETY_ARMED)


@dataclass(frozen=True)
class LandedSample:
    """EXTENDED_SYS_STATE's landed state (MAV_LANDED_STATE: 1 on ground, 2 in air, ...)."""

    landed_state: int
    rx_s: float


@dataclass(frozen=True)
class OdometrySample(GroundTruth):
    """ODOMETRY as ground truth (the SITL publishes it only with ``--groundtruth``): a
    :class:`companion.contract.GroundTruth` (NED position, NED velocity, attitude quaternion
    body FRD -> NED, FRD body rates, time; no acceleration or rotor thrusts) that also knows when
    it was received, for the staleness check."""

    rx_s: float = 0.0


def odometry_from_msg(msg: Any, rx_s: float = 0.0) -> OdometrySample | None:
    """ODOMETRY (pose in LOCAL_NED; velocity in BODY_FRD or LOCAL_NED) -> NED sample, or None
    for frames this companion does not understand or non-finite values."""
    if msg.frame_id != _MAV_FRAME_LOCAL_NED:
        return None
    q = np.array(msg.q, dtype=float)
    pos = np.array([msg.x, msg.y, msg.z], dtype=float)
    vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
    rates = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
    if not all(np.all(np.isfinite(a)) for a in (q, pos, vel, rates)):
        return None
    norm = float(np.linalg.norm(q))
    if not 0.9 < norm < 1.1:
        return None
    q = q / norm
    if msg.child_frame_id in (_MAV_FRAME_BODY_FRD, _MAV_FRAME_BODY_NED):
        vel = quat_to_rotation(q) @ vel
    elif msg.child_frame_id != _MAV_FRAME_LOCAL_NED:
        return None
    return OdometrySample(
        time_s=msg.time_usec * 1e-6,
        pos_ned_m=pos,
        vel_ned_m_s=vel,
        quat_wxyz=q,
        rate_frd_rad_s=rates,
        rx_s=rx_s,
    )


@dataclass
class TelemetryStore:
    """Latest sample of each subscribed message. ``update(msg, rx_s)`` feeds it."""

    attitude: AttitudeSample | None = None
    """ATTITUDE: Euler angles and body rates."""
    imu: ImuSample | None = None
    """HIGHRES_IMU: specific force and gyro."""
    range: RangeSample | None = None
    """DISTANCE_SENSOR, valid or not (NaN: no return)."""
    last_valid_range: RangeSample | None = None
    heartbeat: HeartbeatSample | None = None
    """The autopilot's HEARTBEAT: mode and armed state."""
    landed: LandedSample | None = None
    """EXTENDED_SYS_STATE's landed state."""
    odometry: OdometrySample | None = None
    """ODOMETRY: ground truth, only from a SITL run with ``--groundtruth``."""
    pad_odometry: OdometrySample | None = None
    """On a SITL link flying a landing site: the pad's state (ODOMETRY from
    :data:`companion.contract.PAD_ODOMETRY_COMPONENT`)."""
    latest_time_s: float = -math.inf
    """The newest autopilot time stamp seen (s since autopilot boot)."""
    rejected: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._handlers = {name: getattr(self, f"handle_{name.lower()}") for name in SUBSCRIBES}
        self._history: dict[str, deque[Any]] = {
            name: deque(maxlen=HISTORY_SAMPLES) for name in _TIMED
        }

    def __setattr__(self, name: str, value: Any) -> None:
        # every new timed sample (set by a handler) also goes into its short history
        super().__setattr__(name, value)
        if name in _TIMED and value is not None and "_history" in self.__dict__:
            self._history[name].append(value)

    def at(self, name: str, time_s: float | None) -> Any:
        """The ``name`` sample (attitude, imu, range, odometry) stamped at ``time_s``: the newest
        one stamped at or before it, of the last :data:`HISTORY_SAMPLES`; the oldest held if
        all are newer; the newest when ``time_s`` is None. None when there is none.

        On a jittery link a frame can arrive after telemetry stamped later than it; the
        observation must still hold the readings at the frame's time, as in lockstep."""
        newest = getattr(self, name)
        if time_s is None or newest is None or newest.time_s <= time_s + 1e-6:
            return newest
        older = [s for s in self._history[name] if s.time_s <= time_s + 1e-6]
        return older[-1] if older else self._history[name][0]

    def update(self, msg: Any, rx_s: float) -> bool:
        """Feed one message; True when it was one of :data:`SUBSCRIBES` and valid."""
        handler = self._handlers.get(msg.get_type())
        if handler is None:
            return False
        return bool(handler(msg, rx_s))

    def _reject(self, name: str) -> bool:
        self.rejected[name] = self.rejected.get(name, 0) + 1
        return False

    def _late(self, held: Any, time_s: float, name: str) -> bool:
        """Whether a sample stamped ``time_s`` is older than ``held`` (and not a restart);
        counted as ``<name> late``."""
        if held is None or not held.time_s - RESTART_WINDOW_S <= time_s < held.time_s:
            return False
        self._reject(f"{name} late")
        return True

    def _keep(self, name: str, sample: Any, msg_name: str) -> bool:
        """Hold ``sample`` as the newest ``name`` reading unless it is late (see :meth:`_late`);
        whether it was kept."""
        if self._late(getattr(self, name), sample.time_s, msg_name):
            return False
        setattr(self, name, sample)
        if sample.time_s > self.latest_time_s:
            self.latest_time_s = sample.time_s
        return True

    def reset_clock(self) -> None:
        """The autopilot restarted: its clock starts again, forget the old newest stamp."""
        self.latest_time_s = -math.inf

    # ------------------------------------------------------------------ handlers

    def handle_heartbeat(self, msg: Any, rx_s: float) -> bool:
        self.heartbeat = HeartbeatSample(
            int(msg.custom_mode), int(msg.base_mode), int(msg.system_status), msg.autopilot, rx_s
        )
        return True

    def handle_attitude(self, msg: Any, rx_s: float) -> bool:
        att = np.array([msg.roll, msg.pitch, msg.yaw], dtype=float)
        rates = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
        if not (np.all(np.isfinite(att)) and np.all(np.isfinite(rates))):
            return self._reject("ATTITUDE")
        sample = AttitudeSample(att, rates, msg.time_boot_ms * 1e-3, rx_s)
        return self._keep("attitude", sample, "ATTITUDE")

    def handle_highres_imu(self, msg: Any, rx_s: float) -> bool:
        acc = np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float)
        gyro = np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float)
        if msg.fields_updated & 0b111 != 0b111 or not np.all(np.isfinite(acc)):
            return self._reject("HIGHRES_IMU")
        return self._keep("imu", ImuSample(acc, gyro, msg.time_usec * 1e-6, rx_s), "HIGHRES_IMU")

    def handle_distance_sensor(self, msg: Any, rx_s: float) -> bool:
        if msg.orientation != _MAV_SENSOR_ROTATION_PITCH_270:
            return self._reject("DISTANCE_SENSOR")  # not the downward altimeter
        invalid = (
            msg.current_distance < msg.min_distance
            or msg.current_distance > msg.max_distance
            or getattr(msg, "signal_quality", 0) == 1
        )
        t = msg.time_boot_ms * 1e-3
        sample = RangeSample(math.nan if invalid else msg.current_distance * 0.01, t, rx_s)
        if not self._keep("range", sample, "DISTANCE_SENSOR"):
            return False
        if sample.valid:
            self.last_valid_range = sample
        return True

    def handle_extended_sys_state(self, msg: Any, rx_s: float) -> bool:
        self.landed = LandedSample(int(msg.landed_state), rx_s)
        return True

    def handle_odometry(self, msg: Any, rx_s: float) -> bool:
        sample = odometry_from_msg(msg, rx_s)
        if sample is None:
            return self._reject("ODOMETRY")
        if msg.get_srcComponent() == PAD_ODOMETRY_COMPONENT:
            return self._keep("pad_odometry", sample, "ODOMETRY (pad)")
        return self._keep("odometry", sample, "ODOMETRY")

    def groundtruth_at(self, time_s: float | None) -> GroundTruth | None:
        """The privileged state at ``time_s`` (:meth:`at` of ODOMETRY) with, on a site, the
        pad's: position, velocity and attitude of its ODOMETRY then, and its acceleration from
        the two samples before (zero with one)."""
        gt = self.at("odometry", time_s)
        pad = self.at("pad_odometry", time_s)
        if gt is None or pad is None:
            return gt
        earlier = [s for s in self._history["pad_odometry"] if s.time_s < pad.time_s - 1e-6]
        accel = np.zeros(3)
        if earlier:
            prev = earlier[-1]
            accel = (pad.vel_ned_m_s - prev.vel_ned_m_s) / (pad.time_s - prev.time_s)
        return replace(
            gt,
            pad_pos_ned_m=pad.pos_ned_m,
            pad_vel_ned_m_s=pad.vel_ned_m_s,
            pad_quat_wxyz=pad.quat_wxyz,
            pad_accel_ned_m_s2=accel,
        )

    # ------------------------------------------------------------------ queries

    def age_s(self, name: str, now_s: float) -> float:
        """Seconds since ``name`` (attitude, imu, range, heartbeat, odometry) was received;
        infinity when never."""
        sample = getattr(self, name)
        return math.inf if sample is None else now_s - sample.rx_s

    def max_age_s(self, names: tuple[str, ...], now_s: float) -> tuple[float, str]:
        """The stalest of ``names`` and its age."""
        worst = max(names, key=lambda n: self.age_s(n, now_s))
        return self.age_s(worst, now_s), worst


def assemble_observation(
    frame: ReceivedFrame,
    store: TelemetryStore,
    hover_thrust_norm: float | None = None,
    at_time_s: float | dict[str, float | None] | None = None,
) -> Observation:
    """The policy's Observation: this frame + the ATTITUDE, DISTANCE_SENSOR, HIGHRES_IMU samples
    at ``at_time_s`` (:meth:`TelemetryStore.at`: the frame's time for an autopilot-clock
    camera; None: the newest; a mapping: per sample, as a replay re-selects the recorded ones),
    and the autopilot's hover thrust as read at connect time (None: not reported, NaN).

    Raises:
        ValueError: a sample is missing (the safety monitor runs first, so this is a bug).
    """

    def when(name: str) -> float | None:
        return at_time_s.get(name) if isinstance(at_time_s, dict) else at_time_s

    att, imu, rng = (store.at(n, when(n)) for n in ("attitude", "imu", "range"))
    if att is None or imu is None or rng is None:
        raise ValueError("observation: attitude, IMU and range samples are all needed")
    return Observation(
        image=frame.image,
        image_time_s=frame.time_s,
        attitude_rad=att.attitude_rad,
        rate_frd_rad_s=att.rate_frd_rad_s,
        attitude_time_s=att.time_s,
        range_m=rng.range_m,
        range_time_s=rng.time_s,
        accel_frd_m_s2=imu.accel_frd_m_s2,
        imu_time_s=imu.time_s,
        frame_id=frame.frame_id,
        hover_thrust_norm=math.nan if hover_thrust_norm is None else hover_thrust_norm,
    )
