"""The companion's MAVLink link to its autopilot, in three parts, each with one job:

=======================  ==============================================================
part                     what it owns
=======================  ==============================================================
``connection``           :class:`MavlinkConnection`: the port (udpin/udpout, TCP,
                         serial), our HEARTBEAT, autopilot discovery, the pinned udpin
                         peer, lost / reconnected / restarted, reopening a broken port,
                         the stale-HEARTBEAT filter, :class:`LinkCounters`
the autopilot profile    :class:`~companion.contract.autopilots.AutopilotProfile`
                         (:data:`PX4`, :data:`ARDUPILOT`): mode numbers, parameters and
                         arming rules, one table in the contract that the SITL's
                         autopilots read too
``protocol``             :class:`LinkProtocol`: COMMAND_LONG / COMMAND_ACK with retries,
                         DO_SET_MODE to a profile mode, PARAM_* exchange, setpoints,
                         LANDING_TARGET
=======================  ==============================================================

:class:`MavlinkLink` puts them together for the companion process and its state machines;
each part is built with what it needs passed in (the protocol is given the connection, the
profile and the clock).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from companion.contract.autopilots import ARDUPILOT, PROFILES, PX4, AutopilotProfile
from companion.link.connection import (
    LinkCounters,
    LinkError,
    LinkEvent,
    MavlinkConnection,
    mavlink,
    parse_connection,
)
from companion.link.protocol import LinkProtocol

__all__ = [
    "ARDUPILOT",
    "PROFILES",
    "PX4",
    "AutopilotProfile",
    "LinkCounters",
    "LinkError",
    "LinkEvent",
    "LinkProtocol",
    "MavlinkConnection",
    "MavlinkLink",
    "mavlink",
    "parse_connection",
]


class MavlinkLink:
    """One MAVLink 2 link to one autopilot: a :class:`MavlinkConnection`, the autopilot's
    :class:`AutopilotProfile` and a :class:`LinkProtocol` over them.

    Args:
        url: pymavlink connection string (see :mod:`companion.link.connection`).
        profile: the autopilot profile.
        **connection_options: :class:`MavlinkConnection`'s keyword arguments (``baud``,
            ``sysid``, ``compid``, ``signing_key``, ``link_timeout_s``, ``heartbeat_period_s``,
            ``reopen_period_s``, ``clock``).

    Raises:
        LinkError: a parameter is invalid or the port cannot be opened.
    """

    def __init__(
        self, url: str, *, profile: AutopilotProfile = PX4, **connection_options: Any
    ) -> None:
        self.profile = profile
        self.connection = MavlinkConnection(url, **connection_options)
        self.protocol = LinkProtocol(self.connection, profile, self.connection.clock)
        # the calls the companion's state machines make, straight to the part that owns them
        self.send_setpoint = self.protocol.send_setpoint
        self.send_landing_target = self.protocol.send_landing_target
        self.send_frame_marker = self.protocol.send_frame_marker
        self.command = self.protocol.command
        self.ack = self.protocol.ack
        self.request_mode = self.protocol.request_mode
        self.arm = self.protocol.arm
        self.set_message_interval = self.protocol.set_message_interval
        self.request_param = self.protocol.request_param
        self.param = self.protocol.param
        self.param_int = self.protocol.param_int
        self.fileno = self.connection.fileno
        self.close = self.connection.close
        self.pop_events = self.connection.pop_events

    def poll(self, on_message: Callable[[Any, float], None]) -> int:
        """Receive everything waiting; each autopilot message goes to the protocol (ACKs,
        parameter values), then to ``on_message(msg, rx_monotonic_s)``. Also sends our
        HEARTBEAT when due, watches the link and re-sends unacknowledged commands. Returns the
        number of messages delivered."""
        protocol = self.protocol

        def deliver(msg: Any, rx_s: float) -> None:
            protocol.on_message(msg)
            on_message(msg, rx_s)

        n = self.connection.poll(deliver)
        protocol.tick()
        return n

    # ------------------------------------------------------------------ the connection's state

    @property
    def url(self) -> str:
        return self.connection.url

    @property
    def conn(self) -> Any:
        """pymavlink's connection (None while the port is being reopened)."""
        return self.connection.conn

    @property
    def target_system(self) -> int | None:
        """The autopilot's system id (None: not discovered yet)."""
        return self.connection.target_system

    @property
    def target_component(self) -> int:
        return self.connection.target_component

    @property
    def connected(self) -> bool:
        """An autopilot HEARTBEAT came within ``link_timeout_s``."""
        return self.connection.connected

    @property
    def peer(self) -> tuple[str, int] | None:
        """udpin: the autopilot's address, the only one sent to once known."""
        return self.connection.peer

    @property
    def counters(self) -> LinkCounters:
        return self.connection.counters

    @property
    def heartbeat_age_s(self) -> float:
        return self.connection.heartbeat_age_s

    @property
    def last_send_call_s(self) -> float:
        """How long the last setpoint's write call took (see
        :meth:`MavlinkConnection.send_timed`)."""
        return self.connection.last_send_call_s
