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
from operator import attrgetter
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


def _reads_through(**parts: tuple[str, ...]) -> Callable[[type], type]:
    """Class decorator: each ``name`` listed under ``part`` becomes a read-only attribute
    ``obj.name`` that is ``obj.part.name`` (a method comes bound to the part)."""

    def decorate(cls: type) -> type:
        for part, names in parts.items():
            for name in names:
                setattr(cls, name, property(attrgetter(f"{part}.{name}")))
        return cls

    return decorate


# the calls and state the companion's state machines use, straight from the part that owns them
@_reads_through(
    protocol=(
        "send_setpoint",
        "send_landing_target",
        "send_frame_marker",
        "send_statustext",
        "command",
        "ack",
        "request_mode",
        "arm",
        "set_message_interval",
        "request_param",
        "param",
        "param_int",
    ),
    connection=(
        "fileno",
        "close",
        "pop_events",
        "url",
        "conn",
        "target_system",
        "target_component",
        "connected",
        "peer",
        "counters",
        "heartbeat_age_s",
        "last_send_call_s",
    ),
)
class MavlinkLink:
    """One MAVLink 2 link to one autopilot: a :class:`MavlinkConnection`, the autopilot's
    :class:`AutopilotProfile` and a :class:`LinkProtocol` over them. What the state machines
    call and read (``send_setpoint``, ``request_mode``, ``connected``, ``counters``, ...) is
    the owning part's own (``link.send_setpoint`` is ``link.protocol.send_setpoint``,
    ``link.connected`` is ``link.connection.connected``), listed above the class.

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
