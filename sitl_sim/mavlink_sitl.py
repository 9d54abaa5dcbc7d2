"""``visland sitl``: the simulator behind a PX4-like MAVLink 2 autopilot endpoint over real UDP.

One process, one thread, one clock. The loop advances the SITL clock one physics step (4 ms at
250 Hz) at a time; everything the outside world sees is stamped with that sim clock
(``time_boot_ms``/``time_usec`` = time since SITL start, monotonic across episodes; TIMESYNC
answers in sim ns). Per physics step:

1. physics (:class:`~sitl_sim.simulator.Simulator`) with the autopilot's command — or nothing
   while the vehicle is frozen (HOLD: before the take-over, and whenever HOLD is selected);
2. every stream whose interval is due (ATTITUDE, HIGHRES_IMU, ... at SET_MESSAGE_INTERVAL rates);
3. at each control period (10 Hz): offboard/land checks, episode end, the camera frame (UDP
   packet of :mod:`companion.camera_packet`), the ground-truth log record; in lockstep and
   OFFBOARD, then wait for the companion's answer.

The flight log is a training record: for each control step the companion flies (in flight,
before touchdown, armed in OFFBOARD) it also holds ``/observation`` (the attitude, IMU and range
readings last streamed) and ``/command`` (the setpoint flown for the period after the frame),
keyed by frame id like the in-process log, so ``visland relabel`` labels SITL flights (DAgger
rollouts through the real processes).

**Lockstep** (default): in OFFBOARD the clock stops after each camera frame until a
SET_ATTITUDE_TARGET arrives that was received after the frame was sent and is stamped
(``time_boot_ms``) at or after the frame's time (``lockstep_require_stamp``; turn it off for
clients that stamp with their own clock, e.g. MAVSDK), or until ``lockstep_timeout_s`` of wall
time passes (counted; the last setpoint holds, so a dead client meets COM_OF_LOSS_T after 10
frames). Outside OFFBOARD nobody paces the loop: LAND and the wait for disarm run as fast as the
machine allows, and the frozen HOLD phase runs at wall-clock speed (the companion's hand-shake
happens in wall time). **Real time** (``lockstep=False``): the clock follows the wall clock ×
``speed`` throughout; the last setpoint holds between messages.

**Episodes**: episode ``i`` starts at ``InitialStateSampler(scenario, seed).sample(i)`` in HOLD,
armed, frozen; the flight starts at the first control period after the vehicle is armed in a mode
other than HOLD (the simulator is re-seeded then, so a flight does not depend on how long HOLD
lasted); it ends at touchdown + disarm (auto after COM_DISARM_LAND), at ``episode_timeout_s`` of
flight, or after ``hold_timeout_s`` without a take-over. One MCAP flight log per episode;
``first_episode`` lets parallel SITLs fly disjoint parts of one seed.

The message handlers are the ``handle_<message>`` methods; :data:`SUBSCRIBES` and
:data:`PUBLISHES` list what this endpoint reads and writes.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import json
import logging
import math
import select
import signal
import socket
import string
import struct
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.contract import Command, GroundTruth
from companion.contract.camera_packet import encode_frame
from companion.contract.topics import (
    TOPIC_COMMAND,
    TOPIC_EVENTS,
    TOPIC_GROUNDTRUTH,
    TOPIC_OBSERVATION,
    TOPIC_RESULT,
    TOPIC_SCENARIO,
)
from companion.flightlog import FlightLogWriter
from sitl_sim.autopilot import (
    FORCE_DISARM_MAGIC,
    Autopilot,
    AutopilotParams,
    FlightMode,
    LandController,
    MavResult,
    SetpointRejected,
    base_mode,
    custom_mode,
    mode_from_custom,
    setpoint_from_target,
)
from sitl_sim.config import SimConfig, VehicleConfig, load_sim, load_vehicle
from sitl_sim.dynamics import quat_from_euler, quat_to_rotation
from sitl_sim.errors import SimError
from sitl_sim.flight_record import command_msg, groundtruth_msg
from sitl_sim.land_controller import CascadeLandController
from sitl_sim.mavlink_endpoint import (
    Inbound,
    LinkStats,
    MavlinkEndpoint,
    RxError,
    SitlError,
    SitlPortInUseError,
)
from sitl_sim.metrics import EpisodeResult, summarize
from sitl_sim.scenario import InitialState, InitialStateSampler, Scenario, load_scenario
from sitl_sim.simulator import Simulator

__all__ = [
    "PUBLISHES",
    "SUBSCRIBES",
    "MavlinkSitl",
    "SitlConfig",
    "SitlError",
    "SitlPortInUseError",
    "add_sitl_arguments",
    "main",
    "run_sitl",
    "signing_key_bytes",
    "sitl_config_from_args",
]

log = logging.getLogger("visland.sitl")

SUBSCRIBES = (
    "HEARTBEAT",
    "SET_ATTITUDE_TARGET",
    "COMMAND_LONG",
    "COMMAND_INT",
    "SET_MODE",
    "PARAM_REQUEST_LIST",
    "PARAM_REQUEST_READ",
    "PARAM_SET",
    "TIMESYNC",
    "PING",
    "MISSION_REQUEST_LIST",
    "SETUP_SIGNING",
)
"""Messages this autopilot acts on (each has a ``handle_<name>`` method); others are counted."""

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

TOPIC_MAVLINK_IN = "/mavlink/in/"
TOPIC_MAVLINK_OUT = "/mavlink/out/"
TOPIC_RX_ERRORS = "/mavlink/rx_errors"
TOPIC_LINK_STATS = "/mavlink/link_stats"
TOPIC_AUTOPILOT_COMMAND = "/autopilot/command"

_MAV_TYPE_QUADROTOR = mavlink.MAV_TYPE_QUADROTOR
_MAV_AUTOPILOT_PX4 = mavlink.MAV_AUTOPILOT_PX4
_UINT16_MAX = 65_535
_ON_GROUND_DOWN_M = -0.01  # within 1 cm of the ground plane counts as on the ground
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


# --------------------------------------------------------------------------- configuration


def _opt(default: Any, help: str, arg_type: type | None = None) -> Any:
    return field(default=default, metadata={"help": help, "arg_type": arg_type})


@dataclass(frozen=True)
class SitlConfig:
    """Everything ``visland sitl`` takes; each field is a ``--flag`` (underscores -> dashes).

    Saved (key redacted) in every flight log's metadata.
    """

    host: str = _opt("127.0.0.1", "address to bind the MAVLink port on (loopback by default)")
    mavlink_port: int = _opt(14580, "local UDP port of the offboard link (PX4 SITL: 14580)")
    remote_host: str = _opt("127.0.0.1", "where the offboard API listens")
    remote_port: int = _opt(14540, "UDP port the offboard API listens on (PX4 SITL: 14540)")
    gcs: bool = _opt(
        True, "ground-station link (QGroundControl, MAVProxy) beside the offboard link"
    )
    gcs_port: int = _opt(18570, "local UDP port of the ground-station link (PX4 SITL: 18570)")
    gcs_remote_host: str = _opt("127.0.0.1", "where the ground station listens")
    gcs_remote_port: int = _opt(14550, "UDP port the ground station listens on (QGC: 14550)")
    camera_host: str = _opt("127.0.0.1", "where camera frames are sent")
    camera_port: int = _opt(5600, "UDP port camera frames are sent to")
    lockstep: bool = _opt(True, "lockstep (sim waits for the companion) vs real time")
    lockstep_timeout_s: float = _opt(
        0.5, "wall seconds to wait for the answer to one frame before going on without it"
    )
    lockstep_require_stamp: bool = _opt(
        True, "an answer must be stamped (time_boot_ms) at or after the frame's time"
    )
    speed: float = _opt(1.0, "sim seconds per wall second when paced (real time, HOLD)")
    episodes: int = _opt(1, "consecutive episodes to fly, then exit")
    first_episode: int = _opt(
        0, "index of the first episode (parallel SITLs split one seed's episodes)"
    )
    seed: int = _opt(0, "episode i starts at InitialStateSampler(scenario, seed).sample(i)")
    scenario: str | None = _opt(None, "scenario TOML (default configs/scenario.toml)", str)
    sim_config: str | None = _opt(None, "simulation TOML (default configs/sim.toml)", str)
    vehicle_config: str | None = _opt(None, "vehicle TOML (default configs/vehicle.toml)", str)
    episode_timeout_s: float | None = _opt(
        None, "flight time after which an episode ends as a timeout (default: sim.toml)", float
    )
    hold_timeout_s: float = _opt(
        120.0, "sim seconds in HOLD without a take-over before the episode is abandoned"
    )
    groundtruth: bool = _opt(False, "publish ground truth as ODOMETRY (privileged clients)")
    signing_key: str | None = _opt(
        None, "MAVLink 2 signing: 64 hex digits, or a passphrase (key = SHA-256 of it)", str
    )
    log_dir: str | None = _opt(
        "runs/sitl/flights", "folder for one MCAP flight log per episode (empty: no logs)", str
    )
    render: bool = _opt(True, "render the pybullet camera (off: black frames, faster)")
    noiseless: bool = _opt(False, "turn every sensor noise off")
    start_armed: bool = _opt(True, "episodes start armed (the vehicle is flying)")
    attitude_rate_hz: float = _opt(50.0, "ATTITUDE and ATTITUDE_QUATERNION rate")
    imu_rate_hz: float = _opt(50.0, "HIGHRES_IMU rate")
    distance_rate_hz: float = _opt(10.0, "DISTANCE_SENSOR rate")
    groundtruth_rate_hz: float = _opt(50.0, "ODOMETRY rate with --groundtruth")
    max_wall_s: float | None = _opt(None, "stop after this many wall seconds (safety net)", float)

    def __post_init__(self) -> None:
        for name in ("mavlink_port", "remote_port", "camera_port", "gcs_port", "gcs_remote_port"):
            port = getattr(self, name)
            if not 0 <= port <= 65535:
                raise SitlError(f"{name} = {port}; expected a UDP port in [0, 65535]")
        positive = (
            "lockstep_timeout_s",
            "speed",
            "hold_timeout_s",
            "attitude_rate_hz",
            "imu_rate_hz",
            "distance_rate_hz",
            "groundtruth_rate_hz",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SitlError(f"{name} = {value}; expected a finite number > 0")
        if self.episodes < 1:
            raise SitlError(f"episodes = {self.episodes}; expected >= 1")
        if self.first_episode < 0:
            raise SitlError(f"first_episode = {self.first_episode}; expected >= 0")
        if self.episode_timeout_s is not None and not self.episode_timeout_s > 0:
            raise SitlError(f"episode_timeout_s = {self.episode_timeout_s}; expected > 0")
        if self.signing_key is not None:
            signing_key_bytes(self.signing_key)  # validates

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, with the signing key redacted."""
        d = dataclasses.asdict(self)
        if d["signing_key"] is not None:
            d["signing_key"] = "<set>"
        return d


def signing_key_bytes(key: str) -> bytes:
    """The 32-byte secret of ``--signing-key``: 64 hex digits as is, else SHA-256 of the text
    (MAVProxy's ``signing key <passphrase>`` convention)."""
    text = key.strip()
    if not text:
        raise SitlError("signing key is empty")
    if len(text) == 64 and all(c in string.hexdigits for c in text):
        return bytes.fromhex(text)
    return hashlib.sha256(text.encode()).digest()


# --------------------------------------------------------------------------- internals


@dataclass
class _Stream:
    """A periodic message: sent when ``(tick - phase) % period_ticks == 0``."""

    name: str
    msg_id: int
    default_interval_us: int  # -1 = off by default
    interval_us: int = -1
    period_ticks: int = 0


@dataclass
class _FrameWait:
    """Lockstep: the frame the companion must answer before the clock moves on."""

    frame_id: int
    frame_time_ms: int
    deadline_wall_s: float
    answered: bool = False


@dataclass
class _Episode:
    index: int
    initial: InitialState
    seed_key: tuple[int, int]  # (config seed, episode index): a fresh SeedSequence per reset
    start_tick: int
    writer: FlightLogWriter | None


class _Sample:
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
        return self._sim.radar.read(gt.pos_ned_m, gt.quat_wxyz)


def _jsonable_msg(msg: Any) -> dict[str, Any]:
    d = msg.to_dict()
    for key, value in d.items():
        if isinstance(value, bytes | bytearray):
            d[key] = value.decode("utf-8", errors="replace")
    if "secret_key" in d:  # SETUP_SIGNING: a secret never goes into a log
        d["secret_key"] = "<redacted>"
    return d


def _float_bits_of_int(value: int) -> float:
    """PX4 sends INT32 parameters byte-wise inside the float field (PARAM_ENCODE_BYTEWISE)."""
    return struct.unpack("<f", struct.pack("<i", int(value)))[0]


def _int_of_float_bits(value: float) -> int:
    return struct.unpack("<i", struct.pack("<f", value))[0]


def _thrust_body(msg: Any) -> tuple[float, float, float] | None:
    """SET_ATTITUDE_TARGET.thrust_body, an extension pymavlink 2.4.50 does not decode: read it
    from payload bytes 39..50 (zeros when truncated on the wire)."""
    buf = msg.get_msgbuf()
    if buf[0] != mavlink.PROTOCOL_MARKER_V2:
        return None
    payload = bytes(buf[10 : 10 + buf[1]]).ljust(51, b"\x00")
    return struct.unpack("<3f", payload[39:51])


# --------------------------------------------------------------------------- the SITL


class MavlinkSitl:
    """The MAVLink SITL: build it (binds the ports), then :meth:`run` (blocking) or
    :meth:`stop` from another thread. Use as a context manager to release the ports.

    Args:
        config: the SitlConfig.
        land_controller_factory: builds the AUTO.LAND controller from (vehicle, planet); the
            default is the privileged
            :class:`~sitl_sim.land_controller.CascadeLandController` (ground truth in).

    Raises:
        SitlPortInUseError: the MAVLink port is taken.
        ConfigError: a TOML file is missing or invalid.
    """

    def __init__(
        self,
        config: SitlConfig,
        land_controller_factory: Callable[[VehicleConfig, Any], LandController] | None = None,
    ) -> None:
        self.config = config
        self.vehicle = load_vehicle(config.vehicle_config)
        self.scenario: Scenario = load_scenario(config.scenario)
        sim_cfg: SimConfig = load_sim(config.sim_config).with_planet(self.scenario.world)
        if config.noiseless:
            sim_cfg = sim_cfg.noiseless()
        self.sim_cfg = sim_cfg
        self.episode_timeout_s = config.episode_timeout_s or sim_cfg.episode_timeout_s
        self._dt = sim_cfg.physics_dt_s
        self._rate_hz = sim_cfg.physics_rate_hz
        self._substeps = sim_cfg.substeps
        factory = land_controller_factory or _default_land_controller
        self.land_controller = factory(self.vehicle, sim_cfg.planet)
        self.params = AutopilotParams(mpc_thr_hover=self.vehicle.hover_thrust_norm(sim_cfg.planet))
        self.autopilot = Autopilot(self.params, armed=config.start_armed)
        self.sampler = InitialStateSampler(self.scenario, config.seed)
        self.results: list[EpisodeResult] = []
        self.lockstep_timeouts = 0
        self.pacing_overruns = 0
        self.ignored_messages: Counter[str] = Counter()
        key = signing_key_bytes(config.signing_key) if config.signing_key else None
        self.sim = Simulator(self.vehicle, sim_cfg, render=config.render)
        try:
            self.endpoint = MavlinkEndpoint(
                (config.host, config.mavlink_port),
                (config.remote_host, config.remote_port),
                signing_key=key,
            )
        except SitlError:
            self.sim.close()  # the pybullet client must not outlive a failed start
            raise
        self.gcs_endpoint: MavlinkEndpoint | None = None
        """The ground-station link (None: ``gcs`` off, or its port was taken)."""
        if config.gcs:
            try:
                self.gcs_endpoint = MavlinkEndpoint(
                    (config.host, config.gcs_port),
                    (config.gcs_remote_host, config.gcs_remote_port),
                    signing_key=key,
                    name="gcs",
                )
            except SitlError as exc:
                # The offboard link is the one a flight needs; a second SITL (or a PX4) holding
                # 18570 must not stop this one. Said once, loudly; --gcs-port / --no-gcs fix it.
                log.warning("ground-station link off: %s (use --gcs-port or --no-gcs)", exc)
        self._endpoints = [self.endpoint] + (
            [self.gcs_endpoint] if self.gcs_endpoint is not None else []
        )
        self._rx_endpoint = self.endpoint
        self._camera_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._camera_addr = (config.camera_host, config.camera_port)
        self.camera_tx_errors = 0
        self._handlers = {name: getattr(self, f"handle_{name.lower()}") for name in SUBSCRIBES}
        self._commands: dict[int, Callable[[tuple[float, ...], Any], MavResult]] = {
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM: self._command_arm_disarm,
            mavlink.MAV_CMD_DO_SET_MODE: self._command_do_set_mode,
            mavlink.MAV_CMD_NAV_LAND: self._command_nav_land,
            mavlink.MAV_CMD_REQUEST_MESSAGE: self._command_request_message,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: self._command_set_message_interval,
            mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: self._command_get_message_interval,
            mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._command_autopilot_capabilities,
            mavlink.MAV_CMD_GET_HOME_POSITION: self._command_get_home_position,
        }
        self._streams = self._make_streams()
        self._builders: dict[int, Callable[[], Any]] = {
            s.msg_id: getattr(self, f"_build_{s.name.lower()}") for s in self._streams.values()
        }
        self._builders[mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION] = self._build_autopilot_version
        self._builders[mavlink.MAVLINK_MSG_ID_HOME_POSITION] = self._build_home_position
        self._stop = threading.Event()
        self._tick = 0
        self._phase_tick = 0
        self._frame_id = 0
        self._flying = False
        self._land_cmd: Command | None = None
        self._wait: _FrameWait | None = None
        self._sample: _Sample | None = None
        self._sample_tick = -1
        self._streamed: dict[str, tuple[float, Any]] = {}
        """The latest attitude / IMU / range reading sent (flight time, reading): the
        observation a client has at the next frame, logged as ``/observation``."""
        self._episode: _Episode | None = None
        self._done = False
        self._closed = False
        self._last_stats_log_wall = 0.0
        self._last_errors_logged = 0

    # ------------------------------------------------------------------ public

    @property
    def time_s(self) -> float:
        """The SITL clock: sim seconds since start (MAVLink time_boot_ms / 1000)."""
        return self._tick * self._dt

    @property
    def time_us(self) -> int:
        return self._tick * 1_000_000 // self._rate_hz

    @property
    def stats(self) -> LinkStats:
        """The offboard link's counters (read-only from other threads)."""
        return self.endpoint.stats

    @property
    def gcs_stats(self) -> LinkStats | None:
        """The ground-station link's counters (None without that link)."""
        return self.gcs_endpoint.stats if self.gcs_endpoint is not None else None

    def stop(self) -> None:
        """Ask :meth:`run` to return (thread-safe); the current episode is logged as aborted."""
        self._stop.set()

    def run(self) -> list[EpisodeResult]:
        """Fly ``config.episodes`` episodes (or until :meth:`stop`); returns their results."""
        cfg = self.config
        wall0 = time.monotonic()
        pace_origin = (wall0, self._tick)
        last_regime = None
        try:
            self._start_episode(cfg.first_episode)
            while not self._stop.is_set() and not self._done:
                now = time.monotonic()
                if cfg.max_wall_s is not None and now - wall0 > cfg.max_wall_s:
                    log.warning("max_wall_s = %.1f s reached: stopping", cfg.max_wall_s)
                    break
                self._poll()
                wait = self._wait
                if wait is not None:
                    if not wait.answered and now < wait.deadline_wall_s:
                        self._sleep(min(wait.deadline_wall_s - now, 0.05))
                        continue
                    if not wait.answered:
                        self.lockstep_timeouts += 1
                    self._wait = None
                regime = "paced" if (not self._physics_running() or not cfg.lockstep) else "free"
                if regime != last_regime:
                    pace_origin, last_regime = (now, self._tick), regime
                if regime == "paced":
                    target = pace_origin[0] + (self._tick + 1 - pace_origin[1]) * self._dt / (
                        cfg.speed
                    )
                    if target > now:
                        self._sleep(min(target - now, 0.05))
                        continue
                    if now - target > 0.5:  # fell behind (machine busy): re-anchor, no burst
                        self.pacing_overruns += 1
                        pace_origin = (now, self._tick)
                self._tick_once()
        finally:
            self._finish_episode(aborted=not self._done)
            self.close()
        return list(self.results)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for endpoint in self._endpoints:
            endpoint.close()
        self._camera_sock.close()
        self.sim.close()

    def __enter__(self) -> MavlinkSitl:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ loop pieces

    def _physics_running(self) -> bool:
        return self._flying and self.autopilot.physics_running

    def _sleep(self, timeout_s: float) -> None:
        """Wait for a datagram (on any link) or the timeout."""
        if timeout_s > 0:
            select.select([e.fileno() for e in self._endpoints], [], [], timeout_s)

    def _poll(self) -> None:
        for endpoint in self._endpoints:
            self._rx_endpoint = endpoint  # whose counters the handlers' rejections go to
            accepted, errors = endpoint.receive()
            for err in errors:
                self._log_rx_error(err, endpoint.name)
            for inbound in accepted:
                msg = inbound.msg
                name = msg.get_type()
                self._log(
                    TOPIC_MAVLINK_IN + name,
                    "mavlink." + name,
                    {
                        **_jsonable_msg(msg),
                        "src_system": msg.get_srcSystem(),
                        "src_component": msg.get_srcComponent(),
                        "signed": inbound.signed,
                        "link": inbound.link,
                    },
                )
                handler = self._handlers.get(name)
                if handler is None:
                    self.ignored_messages[name] += 1
                    continue
                handler(msg, inbound)
        self._rx_endpoint = self.endpoint
        self._announce_events()
        self._maybe_log_stats()

    def _tick_once(self) -> None:
        running = self._physics_running()
        if running:
            cmd = self._current_command()
            if (self._tick - self._phase_tick) % self._substeps == 0:
                self._log_command(cmd)
                if cmd is not None and self._control_step():
                    # the command flown for the period after the latest frame: in lockstep its
                    # answer (the training record's /command, keyed like the in-process log)
                    self._log(
                        TOPIC_COMMAND,
                        "visland.Command",
                        command_msg(cmd, self._frame_id - 1, "offboard"),
                    )
            self.sim.step_physics(cmd)
        self._tick += 1
        boundary = (self._tick - self._phase_tick) % self._substeps == 0
        if boundary and not self._control_period():
            return  # the episode ended here; the next one starts at the next tick
        self._emit_streams()
        if boundary:
            self._send_frame()
            ap = self.autopilot
            if (
                self.config.lockstep
                and self._physics_running()
                and ap.mode is FlightMode.OFFBOARD
                and ap.armed
            ):
                self._wait = _FrameWait(
                    frame_id=self._frame_id - 1,
                    frame_time_ms=self.time_us // 1000,
                    deadline_wall_s=time.monotonic() + self.config.lockstep_timeout_s,
                )

    def _sample_now(self) -> _Sample:
        if self._sample is None or self._sample_tick != self._tick:
            self._sample = _Sample(self.sim, self.sim_cfg.planet.gravity_m_s2)
            self._sample_tick = self._tick
        return self._sample

    def _current_command(self) -> Command | None:
        ap = self.autopilot
        if not ap.armed:
            return None  # disarmed: motors off
        if ap.mode is FlightMode.OFFBOARD and ap.setpoint is not None:
            sp = ap.setpoint
            quat = self.sim.ground_truth().quat_wxyz if sp.attitude_quat_wxyz is not None else None
            return sp.command(quat)
        if self._land_cmd is None:  # LAND (or OFFBOARD without setpoint, impossible by rule)
            gt = self.sim.ground_truth()
            self._land_cmd = self.land_controller.command(
                gt.pos_ned_m, gt.vel_ned_m_s, gt.quat_wxyz
            )
        return self._land_cmd

    def _control_step(self) -> bool:
        """The companion flies this control period: in flight, before touchdown, armed in
        OFFBOARD. Only these steps are the training record's control steps."""
        ap = self.autopilot
        return (
            self._flying
            and self.sim.contact is None
            and ap.armed
            and ap.mode is FlightMode.OFFBOARD
        )

    def _on_ground(self, truth: GroundTruth) -> bool:
        return self._flying and float(truth.pos_ned_m[2]) > _ON_GROUND_DOWN_M

    def _control_period(self) -> bool:
        """10 Hz checks. Returns False when the episode ended (nothing more this tick)."""
        ep = self._episode
        assert ep is not None
        ap = self.autopilot
        truth = self.sim.ground_truth()
        ap.update(self.time_s, on_ground=self._on_ground(truth))
        self._announce_events()
        if not self._flying and ap.taken_over:
            # The flight starts now, from the initial state, re-seeded: HOLD's length and the
            # sensor readings taken while frozen cannot change the flight.
            self.sim.reset(ep.initial, np.random.SeedSequence(ep.seed_key))
            self._sample = None
            self._streamed.clear()
            self._flying = True
            self._phase_tick = self._tick
            self._event("flight", f"flight starts at t = {self.time_s:.3f} s in {ap.mode.label}")
        self._land_cmd = None
        sim_t = self.sim.time_s
        if self._flying and self.sim.contact is not None and not ap.armed:
            self._finish_episode()
            return self._next_episode()
        if self._flying and sim_t >= self.episode_timeout_s - 1e-9:
            self._finish_episode()
            return self._next_episode()
        if not self._flying and (self._tick - ep.start_tick) * self._dt >= (
            self.config.hold_timeout_s
        ):
            self._finish_episode()
            return self._next_episode()
        return True

    # ------------------------------------------------------------------ episodes

    def _start_episode(self, index: int) -> None:
        initial = self.sampler.sample(index)
        seed_key = (self.config.seed, index)
        self.sim.reset(initial, np.random.SeedSequence(seed_key))
        self._sample = None
        self._streamed.clear()
        self.autopilot = Autopilot(self.params, armed=self.config.start_armed)
        self._flying = False
        self._land_cmd = None
        self._wait = None
        self._phase_tick = self._tick
        writer = None
        if self.config.log_dir:
            path = Path(self.config.log_dir) / f"sitl_seed{self.config.seed}_ep{index:04d}.mcap"
            writer = FlightLogWriter(
                path,
                metadata={
                    "config": {
                        "sitl": self.config.to_dict(),
                        "sim": self.sim_cfg.to_dict(),
                        "vehicle": self.vehicle.to_dict(),
                        "params": dataclasses.asdict(self.params),
                    },
                    "episode": {"index": index, "seed": self.config.seed},
                },
            )
        self._episode = _Episode(index, initial, seed_key, self._tick, writer)
        self._log(
            TOPIC_SCENARIO,
            "visland.EpisodeScenario",
            {
                "episode": index,
                "seed": self.config.seed,
                "initial_state": initial.to_dict(),
                "scenario": self.scenario.to_dict(),
            },
        )
        self._statustext(6, f"Episode {index} ready: HOLD")
        self._send_heartbeat()
        log.info("episode %d: initial state %s", index, initial.to_dict())

    def _finish_episode(self, aborted: bool = False) -> None:
        ep = self._episode
        if ep is None:
            return
        self._episode = None
        if self.sim.contact is not None and self._flying:
            result = EpisodeResult.from_contact(self.sim.contact)
        else:
            gt = self.sim.ground_truth()
            result = EpisodeResult.timeout(self.sim.time_s, gt.pos_ned_m, gt.vel_ned_m_s)
        if not aborted:
            self.results.append(result)
        record = {"episode": ep.index, "aborted": aborted, **result.to_dict()}
        record["link_stats"] = self.stats.to_dict()
        if self.gcs_endpoint is not None:
            record["gcs_link_stats"] = self.gcs_endpoint.stats.to_dict()
        record["lockstep_timeouts"] = self.lockstep_timeouts
        if ep.writer is not None:
            ep.writer.write(TOPIC_RESULT, "visland.EpisodeResult", self.time_s, record)
            ep.writer.close()
        log.info("episode %d %s: %s", ep.index, "aborted" if aborted else "ended", record)
        if not aborted:
            what = "landed" if result.landed else "timeout"
            self._statustext(6, f"Episode {ep.index} {what}: err {result.landing_error_m:.2f} m")

    def _next_episode(self) -> bool:
        flown = len(self.results)
        if flown >= self.config.episodes:
            self._done = True
        else:
            self._start_episode(self.config.first_episode + flown)
        return False

    # ------------------------------------------------------------------ output

    def _send(self, msg: Any) -> None:
        # Packed (and signed) once; the ground station gets the same frame, as every PX4 link
        # sees the system's one message sequence.
        buf = self.endpoint.send(msg)
        if self.gcs_endpoint is not None:
            self.gcs_endpoint.send_bytes(buf)
        name = msg.get_type()
        if self._episode is not None and self._episode.writer is not None:
            self._log(TOPIC_MAVLINK_OUT + name, "mavlink." + name, _jsonable_msg(msg))

    def _log(self, topic: str, schema: str, body: dict[str, Any]) -> None:
        ep = self._episode
        if ep is not None and ep.writer is not None:
            ep.writer.write(topic, schema, self.time_s, body)

    def _event(self, kind: str, text: str) -> None:
        self._log(TOPIC_EVENTS, "visland.Event", {"kind": kind, "text": text})

    def _log_rx_error(self, err: RxError, link: str) -> None:
        self._log(
            TOPIC_RX_ERRORS,
            "visland.RxError",
            {
                "kind": err.kind,
                "reason": err.reason,
                "length": err.length,
                "src": list(err.addr),
                "link": link,
            },
        )

    def _maybe_log_stats(self) -> None:
        now = time.monotonic()
        if now - self._last_stats_log_wall < 1.0:
            return
        self._last_stats_log_wall = now
        total = self._total_stats()
        errors = total.errors_comm + total.rx_unknown_msgid
        if errors != self._last_errors_logged:
            self._last_errors_logged = errors
            stats = {e.name: e.stats.to_dict() for e in self._endpoints}
            log.warning("MAVLink link errors so far: %s", stats)
            self._log(TOPIC_LINK_STATS, "visland.LinkStats", stats)

    def _log_command(self, cmd: Command | None) -> None:
        self._log(
            TOPIC_AUTOPILOT_COMMAND,
            "visland.AutopilotCommand",
            {
                "flight_time_s": self.sim.time_s,
                "mode": self.autopilot.mode.label,
                "armed": cmd is not None,
                "thrust_norm": cmd.thrust_norm if cmd is not None else 0.0,
                "rate_frd_rad_s": cmd.rate_frd_rad_s if cmd is not None else [0.0, 0.0, 0.0],
            },
        )

    def _statustext(self, severity: int, text: str) -> None:
        self._send(self.endpoint.mav.statustext_encode(severity, text[:50].encode()))
        self._event("statustext", text)

    def _announce_events(self) -> None:
        events = self.autopilot.pop_events()
        if not events:
            return
        for ev in events:
            self._event(ev.kind, ev.text)
            if ev.kind != "takeover":
                self._statustext(ev.severity, ev.text)
            log.info("autopilot: %s", ev.text)
        # PX4 shows a mode/arming change in the next heartbeat; MAVSDK waits for it: send now.
        self._send_heartbeat()

    def _send_heartbeat(self) -> None:
        self._send(self._build_heartbeat())

    def _send_frame(self) -> None:
        sample = self._sample_now()
        gt = sample.truth
        cam = self.sim.camera
        if cam is not None:
            image = cam.capture(gt.pos_ned_m, gt.quat_wxyz)
        else:
            c = self.sim_cfg.camera
            image = np.zeros((c.height_px, c.width_px), dtype=np.uint8)
        frame_id = self._frame_id
        self._frame_id += 1
        time_us = self.time_us
        for datagram in encode_frame(image, frame_id % 2**32, time_us):
            try:
                self._camera_sock.sendto(datagram, self._camera_addr)
            except OSError:
                self.camera_tx_errors += 1
        ep = self._episode
        if ep is not None and ep.writer is not None:
            ep.writer.write_image(self.time_s, image, frame_id)
            ep.writer.write_pose(self.time_s, gt.pos_ned_m, gt.quat_wxyz)
            ap = self.autopilot
            self._log(
                TOPIC_GROUNDTRUTH,
                "visland.GroundTruth",
                {
                    **groundtruth_msg(gt, frame_id),  # the same record as the in-process path
                    "flight_time_s": gt.time_s,
                    "flying": self._flying,
                    "mode": ap.mode.label,
                    "armed": ap.armed,
                },
            )
            obs = self._streamed_observation(frame_id, gt.time_s)
            if obs is not None and self._control_step():
                self._log(TOPIC_OBSERVATION, "visland.Observation", obs)

    def _streamed_observation(self, frame_id: int, image_time_s: float) -> dict[str, Any] | None:
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
        return {
            "frame_id": frame_id,
            "image_time_s": image_time_s,
            "attitude_rad": att.attitude_rad,
            "rate_frd_rad_s": att.rate_frd_rad_s,
            "attitude_time_s": att_t,
            "range_m": rng if math.isfinite(rng) else None,
            "range_time_s": rng_t,
            "accel_frd_m_s2": imu.accel_frd_m_s2,
            "imu_time_s": imu_t,
        }

    # ------------------------------------------------------------------ streams

    def _make_streams(self) -> dict[int, _Stream]:
        cfg = self.config

        def us(hz: float) -> int:
            return round(1e6 / hz)

        table = [
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
        streams = {}
        for name, default in table:
            msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
            stream = _Stream(name, msg_id, default)
            self._set_interval(stream, default)
            streams[msg_id] = stream
        return streams

    def _set_interval(self, stream: _Stream, interval_us: int) -> None:
        stream.interval_us = interval_us
        # Rounded to whole physics steps (4 ms at 250 Hz): the loop's time quantum.
        stream.period_ticks = (
            0 if interval_us < 0 else max(1, round(interval_us * 1e-6 * self._rate_hz))
        )

    def _emit_streams(self) -> None:
        phase = self._tick - self._phase_tick
        for stream in self._streams.values():
            if stream.period_ticks and phase % stream.period_ticks == 0:
                self._send(self._builders[stream.msg_id]())

    def _time_boot_ms(self) -> int:
        return (self.time_us // 1000) & 0xFFFFFFFF

    def _build_heartbeat(self) -> Any:
        ap = self.autopilot
        return self.endpoint.mav.heartbeat_encode(
            _MAV_TYPE_QUADROTOR,
            _MAV_AUTOPILOT_PX4,
            base_mode(ap.mode, ap.armed),
            custom_mode(ap.mode),
            mavlink.MAV_STATE_ACTIVE if ap.armed else mavlink.MAV_STATE_STANDBY,
        )

    def _total_stats(self) -> LinkStats:
        return LinkStats.total(*(e.stats for e in self._endpoints))

    def _build_sys_status(self) -> Any:
        st = self._total_stats()  # the system's counters: every link
        return self.endpoint.mav.sys_status_encode(
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
            min(self.lockstep_timeouts, _UINT16_MAX),  # errors_count3
            min(st.rx_unknown_msgid, _UINT16_MAX),  # errors_count4
        )

    def _build_system_time(self) -> Any:
        # time_unix_usec 0 = unknown: there is no wall-clock date in a simulation.
        return self.endpoint.mav.system_time_encode(0, self._time_boot_ms())

    def _landed_state(self) -> int:
        if self._on_ground(self._sample_now().truth):
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.autopilot.mode is FlightMode.LAND:
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def _build_extended_sys_state(self) -> Any:
        return self.endpoint.mav.extended_sys_state_encode(
            mavlink.MAV_VTOL_STATE_UNDEFINED, self._landed_state()
        )

    def _streamed_reading(self, kind: str) -> Any:
        sample = self._sample_now()
        reading = getattr(sample, kind)
        self._streamed[kind] = (sample.truth.time_s, reading)
        return reading

    def _build_attitude(self) -> Any:
        att = self._streamed_reading("attitude")
        r = att.attitude_rad
        w = att.rate_frd_rad_s
        return self.endpoint.mav.attitude_encode(
            self._time_boot_ms(), r[0], r[1], r[2], w[0], w[1], w[2]
        )

    def _build_attitude_quaternion(self) -> Any:
        att = self._streamed_reading("attitude")
        q = quat_from_euler(*att.attitude_rad)
        w = att.rate_frd_rad_s
        return self.endpoint.mav.attitude_quaternion_encode(
            self._time_boot_ms(), q[0], q[1], q[2], q[3], w[0], w[1], w[2]
        )

    def _build_highres_imu(self) -> Any:
        imu = self._streamed_reading("imu")
        a, g = imu.accel_frd_m_s2, imu.gyro_frd_rad_s
        return self.endpoint.mav.highres_imu_encode(
            self.time_us,
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

    def _build_distance_sensor(self) -> Any:
        rng = self._streamed_reading("range_m")
        max_cm = round(self.sim_cfg.radar.max_range_m * 100)
        if math.isfinite(rng):
            current, quality = min(round(rng * 100), _UINT16_MAX - 1), 100
        else:
            current, quality = _UINT16_MAX, 1  # no return: UINT16_MAX and quality 1 = invalid
        return self.endpoint.mav.distance_sensor_encode(
            self._time_boot_ms(),
            0,
            min(max_cm, _UINT16_MAX - 1),
            current,
            mavlink.MAV_DISTANCE_SENSOR_RADAR,
            0,
            mavlink.MAV_SENSOR_ROTATION_PITCH_270,
            255,  # covariance unknown
            signal_quality=quality,
        )

    def _build_odometry(self) -> Any:
        """Ground truth: pose in LOCAL_NED (pad centre origin); velocity and rates in BODY_FRD
        (ODOMETRY's velocity is in ``child_frame_id``)."""
        gt = self._sample_now().truth
        vel_body = quat_to_rotation(gt.quat_wxyz).T @ gt.vel_ned_m_s
        p, q, w = gt.pos_ned_m, gt.quat_wxyz, gt.rate_frd_rad_s
        nan21 = [math.nan] + [0.0] * 20  # covariance unknown (first element NaN, per spec)
        return self.endpoint.mav.odometry_encode(
            self.time_us,
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

    def _build_attitude_target(self) -> Any:
        sp = self.autopilot.setpoint
        if sp is None:
            q, rates, thrust, mask = [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0, 128
        else:
            q = [1.0, 0.0, 0.0, 0.0] if sp.attitude_quat_wxyz is None else sp.attitude_quat_wxyz
            rates, thrust, mask = sp.rate_frd_rad_s, sp.thrust_norm, sp.type_mask
        return self.endpoint.mav.attitude_target_encode(
            self._time_boot_ms(), mask, [float(v) for v in q], rates[0], rates[1], rates[2], thrust
        )

    def _build_autopilot_version(self) -> Any:
        return self.endpoint.mav.autopilot_version_encode(
            _CAPABILITIES, 0, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0
        )

    def _build_home_position(self) -> Any:
        # Home = the pad centre, the local origin; there is no GPS, so lat/lon/alt are 0.
        return self.endpoint.mav.home_position_encode(
            0, 0, 0, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, self.time_us
        )

    # ------------------------------------------------------------------ helpers for handlers

    def _for_us(self, target_system: int, target_component: int | None = None) -> bool:
        ep = self.endpoint
        ok = target_system in (0, ep.sysid) and (
            target_component is None or target_component in (0, ep.compid)
        )
        if not ok:
            self._rx_endpoint.stats.rx_wrong_target += 1
        return ok

    def _ack(self, command: int, result: MavResult, msg: Any) -> None:
        self._send(
            self.endpoint.mav.command_ack_encode(
                command,
                int(result),
                0,
                0,
                msg.get_srcSystem(),  # MAVSDK drops ACKs addressed to someone else
                msg.get_srcComponent(),
            )
        )

    def _param_table(self) -> list[tuple[str, float, int]]:
        p = self.params
        return [
            ("COM_OF_LOSS_T", p.com_of_loss_t_s, mavlink.MAV_PARAM_TYPE_REAL32),
            ("COM_OBL_RC_ACT", p.com_obl_rc_act, mavlink.MAV_PARAM_TYPE_INT32),
            ("COM_DISARM_LAND", p.com_disarm_land_s, mavlink.MAV_PARAM_TYPE_REAL32),
            ("MPC_THR_HOVER", p.mpc_thr_hover, mavlink.MAV_PARAM_TYPE_REAL32),
            ("MAV_SYS_ID", self.endpoint.sysid, mavlink.MAV_PARAM_TYPE_INT32),
        ]

    def _send_param(self, index: int) -> None:
        table = self._param_table()
        name, value, ptype = table[index]
        wire = _float_bits_of_int(int(value)) if ptype == mavlink.MAV_PARAM_TYPE_INT32 else value
        self._send(
            self.endpoint.mav.param_value_encode(name.encode(), wire, ptype, len(table), index)
        )

    # ------------------------------------------------------------------ message handlers

    def handle_heartbeat(self, msg: Any, inbound: Inbound) -> None:
        """A client's heartbeat: nothing to do (the endpoint already remembers the peer)."""

    def handle_set_attitude_target(self, msg: Any, inbound: Inbound) -> None:
        """Setpoint (see :func:`~sitl_sim.autopilot.setpoint_from_target`); answers a frame in
        lockstep."""
        if not self._for_us(msg.target_system, msg.target_component):
            return
        prev = self.autopilot.setpoint
        try:
            sp = setpoint_from_target(
                msg.type_mask,
                msg.q,
                (msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate),
                msg.thrust,
                _thrust_body(msg),
                self.time_s,
                prev.thrust_norm if prev is not None else None,
            )
        except SetpointRejected as exc:
            self._rx_endpoint.stats.rx_rejected_setpoints += 1
            self._event("setpoint_rejected", str(exc))
            return
        self.autopilot.on_setpoint(sp)
        wait = self._wait
        # Lockstep is paced by the offboard link alone: a ground station's setpoint flies (as
        # in PX4, offboard setpoints are accepted from any link) but never answers a frame.
        if (
            wait is not None
            and inbound.link == self.endpoint.name
            and (not self.config.lockstep_require_stamp or msg.time_boot_ms >= wait.frame_time_ms)
        ):
            wait.answered = True

    def handle_command_long(self, msg: Any, inbound: Inbound) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        params = (
            msg.param1,
            msg.param2,
            msg.param3,
            msg.param4,
            msg.param5,
            msg.param6,
            msg.param7,
        )
        self._run_command(msg.command, params, msg)

    def handle_command_int(self, msg: Any, inbound: Inbound) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._run_command(msg.command, params, msg)

    def handle_set_mode(self, msg: Any, inbound: Inbound) -> None:
        """Legacy SET_MODE (no ACK, as PX4): custom_mode split into main/sub."""
        if not self._for_us(msg.target_system):
            return
        main, sub = (msg.custom_mode >> 16) & 0xFF, (msg.custom_mode >> 24) & 0xFF
        result = self.autopilot.request_mode(mode_from_custom(main, sub), self.time_s)
        self._event("set_mode", f"SET_MODE main {main} sub {sub}: {result.name}")

    def handle_param_request_list(self, msg: Any, inbound: Inbound) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        for index in range(len(self._param_table())):
            self._send_param(index)

    def handle_param_request_read(self, msg: Any, inbound: Inbound) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        table = self._param_table()
        if 0 <= msg.param_index < len(table):
            self._send_param(msg.param_index)
            return
        names = [row[0] for row in table]
        if msg.param_id in names:
            self._send_param(names.index(msg.param_id))
        # unknown parameter: PX4 stays silent (the client times out)

    def handle_param_set(self, msg: Any, inbound: Inbound) -> None:
        """COM_OF_LOSS_T and COM_DISARM_LAND are writable; any other PARAM_SET is answered with
        the unchanged value (the protocol's way of saying no)."""
        if not self._for_us(msg.target_system, msg.target_component):
            return
        names = [row[0] for row in self._param_table()]
        if msg.param_id not in names:
            return
        writable = {"COM_OF_LOSS_T": "com_of_loss_t_s", "COM_DISARM_LAND": "com_disarm_land_s"}
        attr = writable.get(msg.param_id)
        if attr is not None:
            try:
                self.params = replace(self.params, **{attr: float(msg.param_value)})
                self.autopilot.params = self.params
            except ValueError as exc:
                self._event("param_rejected", str(exc))
        self._send_param(names.index(msg.param_id))

    def handle_timesync(self, msg: Any, inbound: Inbound) -> None:
        """Answer requests (tc1 = 0) with the sim clock in ns; our own requests: none."""
        if msg.tc1 == 0:
            self._send(self.endpoint.mav.timesync_encode(self.time_us * 1000, msg.ts1))

    def handle_ping(self, msg: Any, inbound: Inbound) -> None:
        """MAVSDK pings PX4 autopilots: echo requests (targets 0/0) back to the sender."""
        if msg.target_system == 0 and msg.target_component == 0:
            self._send(
                self.endpoint.mav.ping_encode(
                    msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )

    def handle_setup_signing(self, msg: Any, inbound: Inbound) -> None:
        """MAVLink 2 signing key (PX4 v1.17 rules, mavlink_notes.md section 12): accepted on any
        link while no key is set; once signing is on, only a *signed* SETUP_SIGNING (the
        endpoint drops unsigned ones) changes the key, and an all-zero key turns signing off;
        refused while armed. Applies to every link at once. The protocol has no reply: the
        outcome is a STATUSTEXT (and an event in the flight log; the key never is)."""
        if not self._for_us(msg.target_system, msg.target_component):
            return
        if self.autopilot.armed:
            self._statustext(4, "SETUP_SIGNING refused: armed")
            return
        key = bytes(msg.secret_key)
        new_key = None if key == bytes(32) else key
        for endpoint in self._endpoints:
            endpoint.set_signing_key(new_key, int(msg.initial_timestamp))
        # A signed reply tells the requester the key took (or, unsigned, that it is off).
        self._statustext(6, "Signing on" if new_key is not None else "Signing off")

    def handle_mission_request_list(self, msg: Any, inbound: Inbound) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        self._send(
            self.endpoint.mav.mission_count_encode(
                msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type
            )
        )

    # ------------------------------------------------------------------ commands

    def _run_command(self, command: int, params: tuple[float, ...], msg: Any) -> None:
        handler = self._commands.get(command)
        follow_up: list[Any] = []
        if handler is None:
            result = MavResult.UNSUPPORTED
        else:
            result = handler(params, follow_up)
        self._ack(command, result, msg)
        for reply in follow_up:
            self._send(reply)
        self._event("command", f"command {command} {list(params)}: {result.name}")
        self._announce_events()

    def _in_air(self) -> bool:
        return not self._on_ground(self.sim.ground_truth())

    def _command_arm_disarm(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        if not math.isfinite(p[0]):
            return MavResult.DENIED
        return self.autopilot.request_arm(
            round(p[0]) == 1, force=p[1] == FORCE_DISARM_MAGIC, in_air=self._in_air()
        )

    def _command_do_set_mode(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        if not all(math.isfinite(v) for v in p[:3]):
            return MavResult.DENIED
        if not int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return MavResult.DENIED  # PX4 modes are custom modes
        return self.autopilot.request_mode(mode_from_custom(int(p[1]), int(p[2])), self.time_s)

    def _command_nav_land(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        return self.autopilot.request_mode(FlightMode.LAND, self.time_s)

    def _command_request_message(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        if not math.isfinite(p[0]):
            return MavResult.DENIED
        builder = self._builders.get(int(p[0]))
        if builder is None:
            return MavResult.UNSUPPORTED
        follow_up.append(builder())
        return MavResult.ACCEPTED

    def _command_set_message_interval(
        self, p: tuple[float, ...], follow_up: list[Any]
    ) -> MavResult:
        if not (math.isfinite(p[0]) and math.isfinite(p[1])):
            return MavResult.DENIED
        stream = self._streams.get(int(p[0]))
        if stream is None:
            return MavResult.UNSUPPORTED
        interval = int(p[1])
        if stream.name == "ODOMETRY" and not self.config.groundtruth and interval >= 0:
            return MavResult.DENIED  # ground truth only with --groundtruth
        if interval == 0:
            interval = stream.default_interval_us
        elif interval < 0:
            interval = -1
        self._set_interval(stream, interval)
        return MavResult.ACCEPTED

    def _command_get_message_interval(
        self, p: tuple[float, ...], follow_up: list[Any]
    ) -> MavResult:
        stream = self._streams.get(int(p[0])) if math.isfinite(p[0]) else None
        if stream is None:
            return MavResult.UNSUPPORTED
        follow_up.append(
            self.endpoint.mav.message_interval_encode(stream.msg_id, stream.interval_us)
        )
        return MavResult.ACCEPTED

    def _command_autopilot_capabilities(
        self, p: tuple[float, ...], follow_up: list[Any]
    ) -> MavResult:
        follow_up.append(self._build_autopilot_version())
        return MavResult.ACCEPTED

    def _command_get_home_position(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        follow_up.append(self._build_home_position())
        return MavResult.ACCEPTED


def _default_land_controller(vehicle: VehicleConfig, planet: Any) -> LandController:
    # AUTO.LAND flies the SITL's own cascade lander on ground truth (the law that
    # expert.cascade.CascadeLander wraps as a Policy); pass land_controller_factory to replace it.
    return CascadeLandController(vehicle, planet)


# --------------------------------------------------------------------------- entry points


def run_sitl(
    config: SitlConfig,
    land_controller_factory: Callable[[VehicleConfig, Any], LandController] | None = None,
) -> int:
    """Run the SITL until its episodes are flown; 0 when all were, 1 when stopped early
    (SIGINT/SIGTERM, ``max_wall_s``).

    SIGINT/SIGTERM stop it cleanly (flight logs closed) when called from the main thread.

    Raises:
        SitlPortInUseError: the MAVLink port is taken.
        SimError: any configuration error.
    """
    sitl = MavlinkSitl(config, land_controller_factory)
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: sitl.stop())
    try:
        log.info(
            "SITL on udp %s:%d -> %s:%d, camera -> %s:%d, %s",
            config.host,
            sitl.endpoint.address[1],
            config.remote_host,
            config.remote_port,
            config.camera_host,
            config.camera_port,
            "lockstep" if config.lockstep else f"real time x{config.speed}",
        )
        if sitl.gcs_endpoint is not None:
            log.info(
                "ground-station link on udp %s:%d -> %s:%d",
                config.host,
                sitl.gcs_endpoint.address[1],
                config.gcs_remote_host,
                config.gcs_remote_port,
            )
        results = sitl.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    log.info("summary: %s", json.dumps(summarize(results)))
    return 0 if len(results) == config.episodes else 1


def add_sitl_arguments(parser: argparse.ArgumentParser) -> None:
    """One ``--flag`` per :class:`SitlConfig` field, its help from the field's doc."""
    for f in dataclasses.fields(SitlConfig):
        flag = "--" + f.name.replace("_", "-")
        help_text = f"{f.metadata['help']} (default: {f.default})"
        if isinstance(f.default, bool):
            parser.add_argument(
                flag, action=argparse.BooleanOptionalAction, default=f.default, help=help_text
            )
        else:
            arg_type = f.metadata.get("arg_type") or type(f.default)
            parser.add_argument(flag, type=arg_type, default=f.default, help=help_text)


def sitl_config_from_args(args: argparse.Namespace) -> SitlConfig:
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(SitlConfig)}
    if values["log_dir"] == "":
        values["log_dir"] = None
    return SitlConfig(**values)


def main(argv: list[str] | None = None) -> int:
    """``python -m sitl_sim.mavlink_sitl`` (the CLI wires the same flags as ``visland sitl``)."""
    parser = argparse.ArgumentParser(prog="visland sitl", description=__doc__.split("\n")[0])
    add_sitl_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        return run_sitl(sitl_config_from_args(args))
    except SimError as exc:  # config, port in use, ...: one clear line, no traceback
        print(f"visland sitl: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
