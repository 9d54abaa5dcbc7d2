"""What the companion says to the autopilot over its connection: commands, parameters, setpoints.

* **Commands**: COMMAND_LONG, re-sent every :data:`COMMAND_RETRY_S` (up to
  :data:`COMMAND_RETRIES` times) until its COMMAND_ACK; DO_SET_MODE to a mode of the autopilot's
  profile (:mod:`companion.contract.autopilots`), ARM_DISARM, SET_MESSAGE_INTERVAL.
* **Parameters**: PARAM_REQUEST_READ by name; the latest PARAM_VALUE of each name is kept.
* **Setpoints**: SET_ATTITUDE_TARGET (thrust + FRD body rates), LANDING_TARGET, and the SITL
  lockstep's frame marker (NAMED_VALUE_INT ``VL_FRAME``).

Everything goes out through a :class:`~companion.link.connection.MavlinkConnection`, addressed
to the autopilot it discovered; nothing is sent before that.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.contract.autopilots import AutopilotMode, AutopilotProfile
from companion.link.connection import MavlinkConnection, mavlink

__all__ = ["COMMAND_RETRIES", "COMMAND_RETRY_S", "LinkProtocol"]

COMMAND_RETRY_S = 0.5
"""An unacknowledged COMMAND_LONG is sent again after this long."""
COMMAND_RETRIES = 4
"""... at most this many times (the MAVLink command protocol's ``confirmation`` 1..4)."""


@dataclass
class _PendingCommand:
    command: int
    params: tuple[float, ...]
    sent_s: float
    attempts: int
    result: int | None = None


class LinkProtocol:
    """The command, parameter and setpoint exchange with one autopilot.

    Args:
        connection: the port the messages go through (its ``counters`` count them).
        profile: the autopilot's profile (what DO_SET_MODE asks for).
        clock: monotonic clock (the connection's).
    """

    def __init__(
        self,
        connection: MavlinkConnection,
        profile: AutopilotProfile,
        clock: Callable[[], float],
    ) -> None:
        self.connection = connection
        self.profile = profile
        self._clock = clock
        self._pending: dict[int, _PendingCommand] = {}
        self._acks: dict[int, int] = {}
        self._params: dict[str, float] = {}
        self._handlers: dict[str, Callable[[Any], None]] = {
            "COMMAND_ACK": self.handle_command_ack,
            "PARAM_VALUE": self.handle_param_value,
        }

    # ------------------------------------------------------------------ receiving

    def on_message(self, msg: Any) -> None:
        """Take what the protocol needs from an accepted autopilot message."""
        handler = self._handlers.get(msg.get_type())
        if handler is not None:
            handler(msg)

    def handle_command_ack(self, msg: Any) -> None:
        self._acks[msg.command] = msg.result
        pending = self._pending.get(msg.command)
        if pending is not None:
            pending.result = msg.result

    def handle_param_value(self, msg: Any) -> None:
        self._params[msg.param_id] = float(msg.param_value)

    def tick(self) -> None:
        """Re-send the commands still unacknowledged (call after each poll)."""
        now = self._clock()
        for pending in list(self._pending.values()):
            if (
                pending.result is None
                and now - pending.sent_s >= COMMAND_RETRY_S
                and pending.attempts < COMMAND_RETRIES
            ):
                pending.attempts += 1
                pending.sent_s = now
                self._send_command(pending.command, pending.params, confirmation=pending.attempts)

    # ------------------------------------------------------------------ commands

    def _addressed(self) -> bool:
        """An open port and a discovered autopilot to address."""
        return self.connection.is_open and self.connection.target_system is not None

    def _send_command(self, command: int, params: tuple[float, ...], confirmation: int = 0) -> None:
        if not self._addressed():
            return
        link = self.connection
        p = list(params) + [0.0] * (7 - len(params))
        link.send(
            mavlink.MAVLink_command_long_message(
                link.target_system, link.target_component, command, confirmation, *p
            )
        )
        link.counters.tx_commands += 1

    def command(self, command: int, *params: float) -> None:
        """Send COMMAND_LONG, re-sent every 0.5 s (up to 4 times) until its COMMAND_ACK."""
        now = self._clock()
        self._acks.pop(command, None)
        self._pending[command] = _PendingCommand(command, tuple(params), now, 0)
        self._send_command(command, tuple(params))

    def ack(self, command: int) -> int | None:
        """The MAV_RESULT of the latest ACK for ``command`` since it was sent (None: none)."""
        return self._acks.get(command)

    def request_mode(self, mode: AutopilotMode, armed: bool) -> None:
        """DO_SET_MODE to a profile mode (``profile.offboard``/``land``/``hold``)."""
        self.command(mavlink.MAV_CMD_DO_SET_MODE, *self.profile.set_mode_params(mode, armed))

    def arm(self, arm: bool) -> None:
        self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if arm else 0.0)

    def set_message_interval(self, msg_id: int, rate_hz: float) -> None:
        """SET_MESSAGE_INTERVAL (fire and forget; the autopilot's ACK is not awaited)."""
        self._send_command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (float(msg_id), 1e6 / rate_hz))

    # ------------------------------------------------------------------ parameters

    def request_param(self, name: str) -> None:
        if not self._addressed():
            return
        link = self.connection
        link.send(
            mavlink.MAVLink_param_request_read_message(
                link.target_system, link.target_component, name.encode(), -1
            )
        )

    def param(self, name: str) -> float | None:
        """The latest PARAM_VALUE received for ``name``."""
        return self._params.get(name)

    def param_int(self, name: str) -> int | None:
        """An INT32 parameter sent byte-wise in the float field (PX4) or as a float value."""
        value = self._params.get(name)
        if value is None:
            return None
        if value == int(value) and abs(value) < 2**24:
            return int(value)
        return struct.unpack("<i", struct.pack("<f", value))[0]

    # ------------------------------------------------------------------ setpoints

    def send_setpoint(self, thrust: float, rate_frd_rad_s, time_boot_ms: int) -> float | None:
        """SET_ATTITUDE_TARGET, type_mask 128 (attitude ignored): thrust + FRD body rates.

        Returns the monotonic time the packed datagram was handed to the OS (None: not sent);
        see :meth:`MavlinkConnection.send_timed`.
        """
        if not self._addressed():
            return None
        link = self.connection
        r = rate_frd_rad_s
        handed = link.send_timed(
            mavlink.MAVLink_set_attitude_target_message(
                int(time_boot_ms) & 0xFFFFFFFF,
                link.target_system,
                link.target_component,
                mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE,
                [1.0, 0.0, 0.0, 0.0],
                float(r[0]),
                float(r[1]),
                float(r[2]),
                float(thrust),
            )
        )
        if handed is not None:
            link.counters.tx_setpoints += 1
        return handed

    def send_landing_target(
        self,
        time_usec: int,
        angle_x_rad: float,
        angle_y_rad: float,
        distance_m: float,
        pos_frd_m: tuple[float, float, float] | None,
        target_type: int = mavlink.LANDING_TARGET_TYPE_VISION_OTHER,
        target_num: int = 0,
    ) -> float | None:
        """LANDING_TARGET (MAVLink 2, with its extensions) in MAV_FRAME_BODY_FRD: the angles
        (rad) and slant distance (m) always; ``pos_frd_m`` (the target in body FRD) with
        ``position_valid = 1`` when given. Returns the hand-off time (None: not sent)."""
        if not self._addressed():
            return None
        valid = pos_frd_m is not None
        x, y, z = pos_frd_m if pos_frd_m is not None else (0.0, 0.0, 0.0)
        msg = mavlink.MAVLink_landing_target_message(
            int(time_usec),
            int(target_num),
            mavlink.MAV_FRAME_BODY_FRD,
            float(angle_x_rad),
            float(angle_y_rad),
            float(distance_m),
            0.0,  # size_x, size_y: unknown (neither autopilot reads them)
            0.0,
            float(x),
            float(y),
            float(z),
            [1.0, 0.0, 0.0, 0.0],
            int(target_type),
            1 if valid else 0,
        )
        handed = self._clock()
        if not self.connection.send(msg):
            return None
        self.connection.counters.tx_landing_targets += 1
        return handed

    def send_statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT to the autopilot (and through it to the ground station): what the pilot
        must know now (at most 50 characters, as MAVLink carries)."""
        if not self.connection.is_open:
            return
        self.connection.send(mavlink.MAVLink_statustext_message(severity, text[:50].encode()))

    def send_frame_marker(self, time_boot_ms: int, frame_id: int) -> None:
        """NAMED_VALUE_INT ``VL_FRAME`` = frame id, stamped with the frame's time: a SITL
        frame processed without a LANDING_TARGET (the lockstep answer; an autopilot only logs
        it)."""
        if not self.connection.is_open:
            return
        self.connection.send(
            mavlink.MAVLink_named_value_int_message(
                int(time_boot_ms) & 0xFFFFFFFF, b"VL_FRAME", int(frame_id) & 0x7FFFFFFF
            )
        )
