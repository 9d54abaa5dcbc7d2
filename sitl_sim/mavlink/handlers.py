"""What the SITL subscribes to: the ``handle_<message>`` handlers and the COMMAND_LONG /
COMMAND_INT command handlers, with their dispatch tables (:data:`SUBSCRIBES`,
:data:`COMMANDS`) listed here, PX4-style; :data:`~sitl_sim.mavlink.publisher.PUBLISHES` lists
what it sends. The parameter protocol (PARAM_*) is here too: the table is the autopilot's
``params``.
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import common as mavlink

from companion.contract.records import EventKind
from sitl_sim.autopilot.params import param_table, param_value_msg, with_param, writable
from sitl_sim.autopilot.px4 import (
    FORCE_DISARM_MAGIC,
    FlightMode,
    MavResult,
    SetpointRejected,
)

if TYPE_CHECKING:
    from sitl_sim.mavlink.clock import SimClock
    from sitl_sim.mavlink.config import SitlConfig
    from sitl_sim.mavlink.endpoint import Inbound, LinkStats, MavlinkEndpoint
    from sitl_sim.mavlink.flight_log import FlightLog
    from sitl_sim.mavlink.links import Links
    from sitl_sim.mavlink.precland_loop import PreclandLoop
    from sitl_sim.mavlink.publisher import Publisher
    from sitl_sim.mavlink.state import FlightState
    from sitl_sim.simulator import Simulator

__all__ = ["COMMANDS", "SUBSCRIBES", "Handlers"]

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
    "LANDING_TARGET",
    "NAMED_VALUE_INT",
)
"""Messages this autopilot acts on (each has a ``handle_<name>`` method); others are counted."""

COMMANDS = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: "command_arm_disarm",
    mavlink.MAV_CMD_DO_SET_MODE: "command_do_set_mode",
    mavlink.MAV_CMD_NAV_LAND: "command_nav_land",
    mavlink.MAV_CMD_REQUEST_MESSAGE: "command_request_message",
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: "command_set_message_interval",
    mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: "command_get_message_interval",
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: "command_autopilot_capabilities",
    mavlink.MAV_CMD_GET_HOME_POSITION: "command_get_home_position",
}
"""Commands (COMMAND_LONG or COMMAND_INT) this autopilot runs -> their handler method; any other
is acknowledged MAV_RESULT_UNSUPPORTED."""

CommandHandler = Callable[[tuple[float, ...], list[Any]], MavResult]


def _thrust_body(msg: Any) -> tuple[float, float, float] | None:
    """SET_ATTITUDE_TARGET.thrust_body, an extension pymavlink 2.4.50 does not decode: read it
    from payload bytes 39..50 (zeros when truncated on the wire)."""
    buf = msg.get_msgbuf()
    if buf[0] != mavlink.PROTOCOL_MARKER_V2:
        return None
    payload = bytes(buf[10 : 10 + buf[1]]).ljust(51, b"\x00")
    return struct.unpack("<3f", payload[39:51])


@dataclass(eq=False, repr=False)
class Handlers:
    """The ``handle_<message>`` and ``command_<command>`` methods, and the parameter protocol.

    Args:
        config: the autopilot profile and the lockstep rules.
        links: the links (their ids, codec, signing keys).
        publisher: where answers go out, the streams SET_MESSAGE_INTERVAL changes, the
            messages MAV_CMD_REQUEST_MESSAGE builds.
        flight_log: where the handlers' events go.
        state: the flight (autopilot, lockstep wait, land detector).
        precland: LANDING_TARGET's and ``VL_FRAME``'s consumer.
        sim: the ground truth the land detector reads.
        clock: the SITL clock.
    """

    config: SitlConfig
    links: Links
    publisher: Publisher
    flight_log: FlightLog
    state: FlightState
    precland: PreclandLoop
    sim: Simulator
    clock: SimClock
    ignored_messages: Counter[str] = field(init=False, default_factory=Counter)
    """Messages received that this autopilot does not act on, by name."""
    _handlers: dict[str, Callable[[Any, Inbound], None]] = field(init=False)
    _commands: dict[int, CommandHandler] = field(init=False)
    _rx_stats: LinkStats = field(init=False)
    """The counters of the link being read (rejections are counted there)."""

    def __post_init__(self) -> None:
        self._handlers = {name: getattr(self, f"handle_{name.lower()}") for name in SUBSCRIBES}
        self._commands = {command: getattr(self, method) for command, method in COMMANDS.items()}
        self._rx_stats = self.links.offboard.stats

    def dispatch(self, inbound: Inbound, endpoint: MavlinkEndpoint) -> None:
        """Act on a message ``endpoint`` received (or count it as ignored)."""
        name = inbound.msg.get_type()
        handler = self._handlers.get(name)
        if handler is None:
            self.ignored_messages[name] += 1
            return
        self._rx_stats = endpoint.stats
        handler(inbound.msg, inbound)

    # ------------------------------------------------------------------ helpers

    def _for_us(self, target_system: int, target_component: int | None = None) -> bool:
        ep = self.links.offboard
        ok = target_system in (0, ep.sysid) and (
            target_component is None or target_component in (0, ep.compid)
        )
        if not ok:
            self._rx_stats.rx_wrong_target += 1
        return ok

    def _ack(self, command: int, result: MavResult, msg: Any) -> None:
        self.publisher.send(
            self.links.mav.command_ack_encode(
                command,
                int(result),
                0,
                0,
                msg.get_srcSystem(),  # MAVSDK drops ACKs addressed to someone else
                msg.get_srcComponent(),
            )
        )

    def _param_table(self) -> list[tuple[str, float, int]]:
        return param_table(
            self.state.autopilot.params, self.links.offboard.sysid, self.config.autopilot
        )

    def _send_param(self, index: int) -> None:
        self.publisher.send(
            param_value_msg(self.links.mav, self._param_table(), index, self.config.autopilot)
        )

    def announce_param(self, name: str) -> None:
        """Send parameter ``name``'s PARAM_VALUE unasked, as PX4 announces a changed parameter
        (a client holding the old value hears it)."""
        names = [row[0] for row in self._param_table()]
        self._send_param(names.index(name))

    # ------------------------------------------------------------------ message handlers

    def handle_heartbeat(self, msg: Any, inbound: Inbound) -> None:
        """A client's heartbeat (the endpoint already remembers the peer): the autopilot's GCS
        failsafe hears it (ArduCopter's FS_GCS_ENABLE; nothing for PX4 here)."""
        self.state.autopilot.on_heartbeat(
            msg.get_srcSystem(), msg.get_srcComponent(), self.clock.time_s
        )

    def handle_set_attitude_target(self, msg: Any, inbound: Inbound) -> None:
        """Setpoint, read by the autopilot's profile (PX4:
        :func:`~sitl_sim.autopilot.px4.setpoint_from_target`; ArduCopter: :meth:`~sitl_sim.
        ardupilot.ArduCopter.setpoint_from_message`); answers a frame in lockstep."""
        if not self._for_us(msg.target_system, msg.target_component):
            return
        try:
            sp = self.state.autopilot.setpoint_from_message(
                msg.type_mask,
                msg.q,
                (msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate),
                msg.thrust,
                _thrust_body(msg),
                self.clock.time_s,
            )
        except SetpointRejected as exc:
            self._rx_stats.rx_rejected_setpoints += 1
            self.flight_log.event(EventKind.SETPOINT_REJECTED, str(exc))
            return
        if sp is None:
            return  # ArduCopter outside GUIDED_NOGPS: ignored without a word
        self.state.autopilot.on_setpoint(sp)
        if inbound.link == self.links.offboard.name:
            self.state.offboard_paced = True  # the client answers frames (again)
        wait = self.state.wait
        # Lockstep is paced by the offboard link alone: a ground station's setpoint flies (as
        # in PX4, offboard setpoints are accepted from any link) but never answers a frame.
        if (
            wait is not None
            and inbound.link == self.links.offboard.name
            and wait.answers(msg.time_boot_ms, self.config.lockstep_require_stamp)
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
        """Legacy SET_MODE: PX4 splits custom_mode into main/sub and sends no ACK; ArduPilot
        reads it as the mode number and answers with a COMMAND_ACK for "command" 11."""
        if not self._for_us(msg.target_system):
            return
        ap = self.state.autopilot
        result = ap.request_mode(ap.mode_for_custom(msg.custom_mode), self.clock.time_s)
        self.flight_log.event(
            EventKind.SET_MODE, f"SET_MODE custom_mode {msg.custom_mode}: {result.name}"
        )
        if ap.acks_set_mode:
            self._ack(mavlink.MAVLINK_MSG_ID_SET_MODE, result, msg)
        self.publisher.announce_events()

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
        """The profile's writable parameters (:func:`sitl_sim.autopilot.params.writable`) change;
        any other
        PARAM_SET, or a value out of range, is answered with the unchanged value (the
        protocol's way of saying no)."""
        if not self._for_us(msg.target_system, msg.target_component):
            return
        names = [row[0] for row in self._param_table()]
        if msg.param_id not in names:
            return
        if msg.param_id in writable(self.config.autopilot):
            try:
                ap = self.state.autopilot
                ap.params = with_param(
                    ap.params, msg.param_id, msg.param_value, self.config.autopilot
                )
            except ValueError as exc:
                self.flight_log.event(EventKind.PARAM_REJECTED, str(exc))
        self._send_param(names.index(msg.param_id))

    def handle_landing_target(self, msg: Any, inbound: Inbound) -> None:
        """The precision land's input (:meth:`~sitl_sim.mavlink.precland_loop.PreclandLoop.
        on_landing_target`); a malformed one is counted and ignored."""
        self.precland.on_landing_target(msg, inbound)

    def handle_named_value_int(self, msg: Any, inbound: Inbound) -> None:
        """``VL_FRAME``: a landing-target companion's lockstep answer to a frame."""
        self.precland.on_frame_marker(msg, inbound)

    def handle_timesync(self, msg: Any, inbound: Inbound) -> None:
        """Answer requests (tc1 = 0) with the sim clock in ns; our own requests: none."""
        if msg.tc1 == 0:
            self.publisher.send(self.links.mav.timesync_encode(self.clock.time_us * 1000, msg.ts1))

    def handle_ping(self, msg: Any, inbound: Inbound) -> None:
        """MAVSDK pings PX4 autopilots: echo requests (targets 0/0) back to the sender."""
        if msg.target_system == 0 and msg.target_component == 0:
            self.publisher.send(
                self.links.mav.ping_encode(
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
        if self.state.autopilot.armed:
            self.publisher.statustext(4, "SETUP_SIGNING refused: armed")
            return
        key = bytes(msg.secret_key)
        new_key = None if key == bytes(32) else key
        self.links.set_signing_key(new_key, int(msg.initial_timestamp))
        # A signed reply tells the requester the key took (or, unsigned, that it is off).
        self.publisher.statustext(6, "Signing on" if new_key is not None else "Signing off")

    def handle_mission_request_list(self, msg: Any, inbound: Inbound) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        self.publisher.send(
            self.links.mav.mission_count_encode(
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
            self.publisher.send(reply)
        self.flight_log.event(EventKind.COMMAND, f"command {command} {list(params)}: {result.name}")
        self.publisher.announce_events()

    def _in_air(self) -> bool:
        return not self.state.on_ground(self.sim)

    def command_arm_disarm(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        if not math.isfinite(p[0]):
            return MavResult.DENIED
        return self.state.autopilot.request_arm(
            round(p[0]) == 1, force=p[1] == FORCE_DISARM_MAGIC, in_air=self._in_air()
        )

    def command_do_set_mode(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        if not all(math.isfinite(v) for v in p[:3]):
            return MavResult.DENIED
        if not int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return MavResult.DENIED  # PX4 and ArduPilot modes are custom modes
        ap = self.state.autopilot
        mode = ap.mode_for_command(p[1], p[2])
        if (
            mode is FlightMode.PRECLAND
            and ap.precland_needs_range
            and not math.isfinite(self.publisher.sample().range_m)
        ):
            # PX4 needs a local position and distance to the ground (mode_requirements.cpp)
            self.publisher.statustext(4, "Precision landing denied! Please land manually")
            return MavResult.TEMPORARILY_REJECTED
        return self.state.autopilot.request_mode(mode, self.clock.time_s)

    def command_nav_land(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        return self.state.autopilot.request_mode(
            self.state.autopilot.land_mode(), self.clock.time_s
        )

    def command_request_message(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        if not math.isfinite(p[0]):
            return MavResult.DENIED
        builder = self.publisher.builders.get(int(p[0]))
        if builder is None:
            return MavResult.UNSUPPORTED
        follow_up.append(builder())
        return MavResult.ACCEPTED

    def command_set_message_interval(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        if not (math.isfinite(p[0]) and math.isfinite(p[1])):
            return MavResult.DENIED
        stream = self.publisher.streams.get(int(p[0]))
        if stream is None:
            return MavResult.UNSUPPORTED
        interval = int(p[1])
        if stream.name == "ODOMETRY" and not self.config.groundtruth and interval >= 0:
            return MavResult.DENIED  # ground truth only with --groundtruth
        if interval == 0:
            interval = stream.default_interval_us
        elif interval < 0:
            interval = -1
        stream.set_interval(interval, self.clock.rate_hz)
        return MavResult.ACCEPTED

    def command_get_message_interval(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        stream = self.publisher.streams.get(int(p[0])) if math.isfinite(p[0]) else None
        if stream is None:
            return MavResult.UNSUPPORTED
        follow_up.append(self.links.mav.message_interval_encode(stream.msg_id, stream.interval_us))
        return MavResult.ACCEPTED

    def command_autopilot_capabilities(
        self, p: tuple[float, ...], follow_up: list[Any]
    ) -> MavResult:
        follow_up.append(self.publisher.build_autopilot_version())
        return MavResult.ACCEPTED

    def command_get_home_position(self, p: tuple[float, ...], follow_up: list[Any]) -> MavResult:
        follow_up.append(self.publisher.build_home_position())
        return MavResult.ACCEPTED
