"""What the SITL publishes: the MAVLink message builders (HEARTBEAT, SYS_STATUS, ... ODOMETRY),
the stream table and its SET_MESSAGE_INTERVAL schedule, the once-per-tick sensor sample the
streams read from, and the way out for everything the SITL sends (each message sent is also
logged).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import common as mavlink

from companion.contract import PAD_ODOMETRY_COMPONENT, GroundTruth
from companion.contract.records import EventKind, ObservationRecord
from sitl_sim.autopilot.px4 import FlightMode
from sitl_sim.physics.dynamics import quat_from_euler, quat_to_rotation
from sitl_sim.simulator import Simulator

if TYPE_CHECKING:
    from sitl_sim.config import SimConfig
    from sitl_sim.mavlink.clock import SimClock
    from sitl_sim.mavlink.config import SitlConfig
    from sitl_sim.mavlink.flight_log import FlightLog
    from sitl_sim.mavlink.links import Links
    from sitl_sim.mavlink.state import FlightState

__all__ = ["ON_REQUEST", "PUBLISHES", "Publisher", "Stream", "TickSample"]

log = logging.getLogger("visland.sitl")

PUBLISHES = (
    "HEARTBEAT",
    "SYS_STATUS",
    "SYSTEM_TIME",
    "EXTENDED_SYS_STATE",
    "ATTITUDE",
    "ATTITUDE_QUATERNION",
    "HIGHRES_IMU",
    "DISTANCE_SENSOR",
    "ODOMETRY",
    "ATTITUDE_TARGET",
    "COMMAND_ACK",
    "PARAM_VALUE",
    "STATUSTEXT",
    "TIMESYNC",
    "PING",
    "AUTOPILOT_VERSION",
    "HOME_POSITION",
    "MESSAGE_INTERVAL",
    "MISSION_COUNT",
)
"""Messages this autopilot sends (streams at :class:`SitlConfig` rates, or on request)."""

ON_REQUEST = ("AUTOPILOT_VERSION", "HOME_POSITION")
"""Messages built only on request (MAV_CMD_REQUEST_MESSAGE), beside every stream's."""

_MAV_TYPE_QUADROTOR = mavlink.MAV_TYPE_QUADROTOR
_UINT16_MAX = 65_535
_CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
_SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_LASER_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_GEOFENCE  # MAVProxy reports "fence breach" without it
)


@dataclass
class Stream:
    """A periodic message: sent when ``(tick - phase) % period_ticks == 0``."""

    name: str
    msg_id: int
    default_interval_us: int  # -1 = off by default
    interval_us: int = -1
    period_ticks: int = 0

    def set_interval(self, interval_us: int, rate_hz: int) -> None:
        self.interval_us = interval_us
        # Rounded to whole physics steps (4 ms at 250 Hz): the loop's time quantum.
        self.period_ticks = 0 if interval_us < 0 else max(1, round(interval_us * 1e-6 * rate_hz))


def _stream_table(cfg: SitlConfig) -> list[tuple[str, int]]:
    """Every stream and its default interval in µs (-1: off until SET_MESSAGE_INTERVAL)."""

    def us(hz: float) -> int:
        return round(1e6 / hz)

    return [
        ("HEARTBEAT", us(1.0)),
        ("SYS_STATUS", us(1.0)),
        ("SYSTEM_TIME", us(1.0)),
        ("EXTENDED_SYS_STATE", us(5.0)),
        ("ATTITUDE", us(cfg.attitude_rate_hz)),
        ("ATTITUDE_QUATERNION", us(cfg.attitude_rate_hz)),
        ("HIGHRES_IMU", us(cfg.imu_rate_hz)),
        ("DISTANCE_SENSOR", us(cfg.distance_rate_hz)),
        ("ODOMETRY", us(cfg.groundtruth_rate_hz) if cfg.groundtruth else -1),
        ("ATTITUDE_TARGET", -1),
    ]


class TickSample:
    """Sensor readings of one tick, each sensor read at most once (their RNG streams then do
    not depend on which streams happen to be due together)."""

    def __init__(self, sim: Simulator, planet_g: float) -> None:
        self._sim = sim
        self._g = planet_g

    @functools.cached_property
    def truth(self) -> GroundTruth:
        return self._sim.ground_truth()

    @functools.cached_property
    def attitude(self):  # AttitudeReading
        gt = self.truth
        return self._sim.attitude_sensor.read(gt.time_s, gt.quat_wxyz, gt.rate_frd_rad_s)

    @functools.cached_property
    def imu(self):  # ImuReading
        gt = self.truth
        return self._sim.imu.read(
            gt.time_s, gt.quat_wxyz, gt.accel_ned_m_s2, gt.rate_frd_rad_s, self._g
        )

    @functools.cached_property
    def range_m(self) -> float:
        gt = self.truth
        return self._sim.radar.read(gt.pos_ned_m, gt.quat_wxyz, gt.time_s)


@dataclass(eq=False, repr=False)
class Publisher:
    """Builds and sends the SITL's messages.

    Args:
        config: the stream rates, ``groundtruth``, the autopilot profile.
        links: where messages go.
        flight_log: where each message sent is logged.
        state: the flight's autopilot and land detector.
        sim: the simulator the sensor readings come from.
        sim_cfg: the planet (gravity) and the radar's range.
        clock: the SITL clock (message stamps, the stream schedule).
    """

    config: SitlConfig
    links: Links
    flight_log: FlightLog
    state: FlightState
    sim: Simulator
    sim_cfg: SimConfig
    clock: SimClock
    streams: dict[int, Stream] = field(init=False, default_factory=dict)
    """The periodic messages by message id, at their current SET_MESSAGE_INTERVAL."""
    builders: dict[int, Callable[[], Any]] = field(init=False)
    """What MAV_CMD_REQUEST_MESSAGE can ask for, by message id."""
    _sample: TickSample | None = field(init=False, default=None)
    _sample_tick: int = field(init=False, default=-1)
    _streamed: dict[str, tuple[float, Any]] = field(init=False, default_factory=dict)
    """The latest attitude / IMU / range reading sent (flight time, reading): the
    observation a client has at the next frame, logged as ``/observation``."""

    def __post_init__(self) -> None:
        for name, default in _stream_table(self.config):
            msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
            stream = Stream(name, msg_id, default)
            stream.set_interval(default, self.clock.rate_hz)
            self.streams[msg_id] = stream
        names = [s.name for s in self.streams.values()] + list(ON_REQUEST)
        self.builders = {
            getattr(mavlink, f"MAVLINK_MSG_ID_{name}"): getattr(self, f"build_{name.lower()}")
            for name in names
        }

    # ------------------------------------------------------------------ sending

    def send(self, msg: Any, component: int | None = None) -> None:
        self.links.send(msg, component)
        self.flight_log.outbound(msg)

    def statustext(self, severity: int, text: str) -> None:
        self.send(self.links.mav.statustext_encode(severity, text[:50].encode()))
        self.flight_log.event(EventKind.STATUSTEXT, text)

    def heartbeat(self) -> None:
        self.send(self.build_heartbeat())

    def announce_events(self) -> None:
        """The autopilot's events: logged, said in a STATUSTEXT, then a HEARTBEAT (PX4 shows a
        mode/arming change in the next heartbeat; MAVSDK waits for it: send now)."""
        events = self.state.autopilot.pop_events()
        if not events:
            return
        for ev in events:
            self.flight_log.event(ev.kind, ev.text)
            if ev.kind != EventKind.TAKEOVER and ev.statustext:
                self.statustext(ev.severity, ev.text)
            log.info("autopilot: %s", ev.text)
        self.heartbeat()

    def emit_streams(self) -> None:
        """Every stream due at this tick."""
        phase = self.clock.phase
        for stream in self.streams.values():
            if stream.period_ticks and phase % stream.period_ticks == 0:
                self.send(self.builders[stream.msg_id]())
                if stream.msg_id == mavlink.MAVLINK_MSG_ID_ODOMETRY and self.sim.site is not None:
                    self.send(self.build_pad_odometry(), PAD_ODOMETRY_COMPONENT)

    # ------------------------------------------------------------------ the tick's readings

    def reset_samples(self) -> None:
        """The simulator was reset: nothing sampled or streamed since."""
        self._sample = None
        self._streamed.clear()

    def sample(self) -> TickSample:
        """This tick's sensor readings (each sensor read at most once per tick)."""
        tick = self.clock.tick
        if self._sample is None or self._sample_tick != tick:
            self._sample = TickSample(self.sim, self.sim_cfg.planet.gravity_m_s2)
            self._sample_tick = tick
        return self._sample

    def _streamed_reading(self, kind: str) -> Any:
        sample = self.sample()
        reading = getattr(sample, kind)
        self._streamed[kind] = (sample.truth.time_s, reading)
        return reading

    def streamed_observation(self, frame_id: int, image_time_s: float) -> ObservationRecord | None:
        """What a client holds at this frame: the latest attitude, IMU and range readings this
        SITL sent (before MAVLink's float32 / centimetre encoding), with their own times, in the
        in-process log's ``/observation`` record. None until each has been sent since the
        simulator was last reset."""
        parts = self._streamed
        if any(k not in parts for k in ("attitude", "imu", "range_m")):
            return None
        (att_t, att), (imu_t, imu), (rng_t, rng) = (
            parts["attitude"],
            parts["imu"],
            parts["range_m"],
        )
        return ObservationRecord(
            frame_id=frame_id,
            image_time_s=image_time_s,
            attitude_rad=att.attitude_rad,
            rate_frd_rad_s=att.rate_frd_rad_s,
            attitude_time_s=att_t,
            range_m=rng if math.isfinite(rng) else None,
            range_time_s=rng_t,
            accel_frd_m_s2=imu.accel_frd_m_s2,
            imu_time_s=imu_t,
        )

    # ------------------------------------------------------------------ builders

    def build_heartbeat(self) -> Any:
        # autopilot id, base_mode, custom_mode and state as the profile's autopilot sets them
        return self.links.mav.heartbeat_encode(
            _MAV_TYPE_QUADROTOR, *self.state.autopilot.heartbeat()
        )

    def build_sys_status(self) -> Any:
        st = self.links.total_stats()  # the system's counters: every link
        return self.links.mav.sys_status_encode(
            _SENSORS,
            _SENSORS,
            _SENSORS,
            0,
            _UINT16_MAX,  # no battery model
            -1,
            -1,
            st.drop_rate_comm_centi_percent,
            min(st.errors_comm, _UINT16_MAX),
            min(st.rx_unsigned_rejected + st.rx_bad_signature, _UINT16_MAX),  # errors_count1
            min(st.rx_wrong_target, _UINT16_MAX),  # errors_count2
            min(self.state.lockstep_timeouts, _UINT16_MAX),  # errors_count3
            min(st.rx_unknown_msgid, _UINT16_MAX),  # errors_count4
        )

    def build_system_time(self) -> Any:
        # time_unix_usec 0 = unknown: there is no wall-clock date in a simulation.
        return self.links.mav.system_time_encode(0, self.clock.time_boot_ms)

    def _landed_state(self) -> int:
        if self.state.on_ground(self.sim):
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.state.autopilot.mode is FlightMode.LAND:
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def build_extended_sys_state(self) -> Any:
        return self.links.mav.extended_sys_state_encode(
            mavlink.MAV_VTOL_STATE_UNDEFINED, self._landed_state()
        )

    def build_attitude(self) -> Any:
        att = self._streamed_reading("attitude")
        r = att.attitude_rad
        w = att.rate_frd_rad_s
        return self.links.mav.attitude_encode(
            self.clock.time_boot_ms, r[0], r[1], r[2], w[0], w[1], w[2]
        )

    def build_attitude_quaternion(self) -> Any:
        att = self._streamed_reading("attitude")
        q = quat_from_euler(*att.attitude_rad)
        w = att.rate_frd_rad_s
        return self.links.mav.attitude_quaternion_encode(
            self.clock.time_boot_ms, q[0], q[1], q[2], q[3], w[0], w[1], w[2]
        )

    def build_highres_imu(self) -> Any:
        imu = self._streamed_reading("imu")
        a, g = imu.accel_frd_m_s2, imu.gyro_frd_rad_s
        return self.links.mav.highres_imu_encode(
            self.clock.time_us,
            a[0],
            a[1],
            a[2],
            g[0],
            g[1],
            g[2],
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            0b111111,  # fields_updated: accel x/y/z, gyro x/y/z
        )

    def build_distance_sensor(self) -> Any:
        rng = self._streamed_reading("range_m")
        max_cm = round(self.sim_cfg.radar.max_range_m * 100)
        if math.isfinite(rng):
            current, quality = min(round(rng * 100), _UINT16_MAX - 1), 100
        else:
            current, quality = _UINT16_MAX, 1  # no return: UINT16_MAX and quality 1 = invalid
        return self.links.mav.distance_sensor_encode(
            self.clock.time_boot_ms,
            0,
            min(max_cm, _UINT16_MAX - 1),
            current,
            mavlink.MAV_DISTANCE_SENSOR_RADAR,
            0,
            mavlink.MAV_SENSOR_ROTATION_PITCH_270,
            255,  # covariance unknown
            signal_quality=quality,
        )

    def build_odometry(self) -> Any:
        """Ground truth: pose in LOCAL_NED (pad centre origin); velocity and rates in BODY_FRD
        (ODOMETRY's velocity is in ``child_frame_id``)."""
        gt = self.sample().truth
        vel_body = quat_to_rotation(gt.quat_wxyz).T @ gt.vel_ned_m_s
        p, q, w = gt.pos_ned_m, gt.quat_wxyz, gt.rate_frd_rad_s
        nan21 = [math.nan] + [0.0] * 20  # covariance unknown (first element NaN, per spec)
        return self.links.mav.odometry_encode(
            self.clock.time_us,
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_FRAME_BODY_FRD,
            p[0],
            p[1],
            p[2],
            [float(v) for v in q],
            vel_body[0],
            vel_body[1],
            vel_body[2],
            w[0],
            w[1],
            w[2],
            nan21,
            nan21,
            0,
            mavlink.MAV_ESTIMATOR_TYPE_MOCAP,
            100,
        )

    def build_pad_odometry(self) -> Any:
        """The pad's ground truth on a site (:data:`companion.contract.PAD_ODOMETRY_COMPONENT`
        sends it): pose and velocity in LOCAL_NED, the pad frame's angular rates."""
        gt = self.sample().truth
        assert gt.pad_pos_ned_m is not None and gt.pad_vel_ned_m_s is not None
        assert gt.pad_quat_wxyz is not None
        p, v, q = gt.pad_pos_ned_m, gt.pad_vel_ned_m_s, gt.pad_quat_wxyz
        nan21 = [math.nan] + [0.0] * 20
        return self.links.mav.odometry_encode(
            self.clock.time_us,
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_FRAME_LOCAL_NED,
            p[0],
            p[1],
            p[2],
            [float(x) for x in q],
            v[0],
            v[1],
            v[2],
            0.0,
            0.0,
            0.0,
            nan21,
            nan21,
            0,
            mavlink.MAV_ESTIMATOR_TYPE_MOCAP,
            100,
        )

    def build_attitude_target(self) -> Any:
        sp = self.state.autopilot.setpoint
        if sp is None:
            q, rates, thrust, mask = [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0, 128
        else:
            q = [1.0, 0.0, 0.0, 0.0] if sp.attitude_quat_wxyz is None else sp.attitude_quat_wxyz
            rates, thrust, mask = sp.rate_frd_rad_s, sp.thrust_norm, sp.type_mask
        return self.links.mav.attitude_target_encode(
            self.clock.time_boot_ms,
            mask,
            [float(v) for v in q],
            rates[0],
            rates[1],
            rates[2],
            thrust,
        )

    def build_autopilot_version(self) -> Any:
        caps = _CAPABILITIES
        if self.config.autopilot == "ardupilot":  # ArduPilot sends parameter values as floats
            caps = (caps & ~mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE) | (
                mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
            )
        return self.links.mav.autopilot_version_encode(
            caps, 0, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0
        )

    def build_home_position(self) -> Any:
        # Home = the pad centre, the local origin; there is no GPS, so lat/lon/alt are 0.
        return self.links.mav.home_position_encode(
            0, 0, 0, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, self.clock.time_us
        )
