"""The companion's MAVLink link: connection, own HEARTBEAT, autopilot discovery, reconnect.

Any pymavlink connection string works (``udpin:0.0.0.0:14540``, ``udpout:10.0.0.1:14580``,
``tcp:127.0.0.1:5760``, ``/dev/ttyAMA0`` with ``baud``, or ``serial:/dev/ttyAMA0:921600``).
MAVLink 2 is forced (``MAVLINK20`` is set before pymavlink's ``mavutil`` is imported and the
``common`` dialect is selected explicitly, so nothing can downgrade the link to MAVLink 1).

The companion announces itself as an onboard controller (``MAV_TYPE_ONBOARD_CONTROLLER``,
``MAV_AUTOPILOT_INVALID``, component 191 = ``MAV_COMP_ID_ONBOARD_COMPUTER``) at 1 Hz,
discovers the autopilot from the first HEARTBEAT of a component whose ``autopilot`` is not
INVALID, and watches the link: no autopilot HEARTBEAT for ``link_timeout_s`` = *lost*; the next
one = *reconnected* (streams re-requested); ``time_boot_ms`` going backwards = the autopilot
*restarted*. A broken serial/TCP port is reopened every ``reopen_period_s``.

On a lossy link datagrams may be duplicated or reordered. Telemetry carries time stamps (the
store drops late samples); a HEARTBEAT does not, and a stale one would show an old mode or
arming state (a reordered HOLD heartbeat after the switch to OFFBOARD reads as "someone else
changed the mode"). So a HEARTBEAT whose MAVLink sequence number is at most
:data:`STALE_SEQ_WINDOW` behind the newest one received from that component is dropped and
counted (``rx_stale_heartbeats``); further behind is a new stream (a restarted sender).

On a UDP server port (``udpin:``) pymavlink sends every datagram to every address that ever sent
one to the port, so a GCS, a scanner or a flood from elsewhere on the network would receive the
setpoints too (and could steer the replies of a naive "last sender" link). The link *pins its
peer*: the address the autopilot's HEARTBEAT came from (each datagram is parsed on its own — an
incomplete message left by another datagram is dropped, as over UDP it can never complete — so
every message has a known sender). Everything is then sent to that address only. The peer moves
only when the link is lost (no autopilot HEARTBEAT for ``link_timeout_s``) and the autopilot is
heard from a new address — a restarted autopilot on another port; a HEARTBEAT spoofing the
autopilot's ids from elsewhere while it is alive is counted (``rx_peer_mismatch``) and moves
nothing. Unsigned MAVLink cannot stop a spoof on a lost link: sign it (``signing_key``) or use a
serial port where that matters.

Autopilot *profiles* hold what differs between PX4 and ArduPilot: mode numbers, the
hover-thrust parameter and the meaning of SET_ATTITUDE_TARGET's ``thrust``.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

os.environ["MAVLINK20"] = "1"  # before mavutil is imported: mavutil reads it at import time
os.environ.setdefault("MAVLINK_DIALECT", "common")

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from companion.contract.signing import UNSIGNED_ALLOWED

mavutil.set_dialect("common")  # v20.common, whatever MAVLINK_DIALECT said

__all__ = [
    "ARDUPILOT",
    "PROFILES",
    "PX4",
    "AutopilotProfile",
    "LinkError",
    "LinkEvent",
    "MavlinkLink",
    "mavlink",
    "parse_connection",
]

log = logging.getLogger("visland.companion.link")

COMPANION_COMPID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191

STALE_SEQ_WINDOW = 64
"""A HEARTBEAT 0..64 sequence numbers behind the newest message of its sender is stale (a
duplicate or a reordered datagram). An autopilot streams ~170 messages/s here, so 64 is ~0.4 s
of traffic: far more than a reordered datagram is overtaken by (delay + jitter ~0.1 s), far
less than the 256 at which the u8 sequence wraps."""


class LinkError(Exception):
    """The link cannot be opened or a parameter of it is invalid (names the value)."""


# --------------------------------------------------------------------------- profiles


@dataclass(frozen=True)
class AutopilotProfile:
    """What differs between autopilots for an offboard rate controller.

    Attributes:
        name: ``px4`` or ``ardupilot``.
        offboard: DO_SET_MODE (param2, param3) of the mode that takes SET_ATTITUDE_TARGET
            (PX4 OFFBOARD = main 6; ArduPilot GUIDED_NOGPS = 20).
        land: DO_SET_MODE params of the landing mode (PX4 AUTO.LAND 4/6; ArduPilot LAND 9).
        hold: DO_SET_MODE params of the hand-back hold mode (PX4 AUTO.LOITER 4/3; ArduPilot
            ALT_HOLD 2: LOITER needs a position estimate, which a GPS-less vehicle lacks).
        hover_param: the parameter holding the hover thrust (PX4 MPC_THR_HOVER, ArduPilot
            MOT_THST_HOVER).
        thrust_param: a parameter that must have ``thrust_param_bits`` set for ``thrust`` to be
            collective thrust, or None when it always is (PX4). ArduPilot reads ``thrust`` as a
            climb-rate demand (0.5 = hold altitude) unless GUID_OPTIONS bit 3 (8) is set.
        precland: DO_SET_MODE params of the mode that lands on LANDING_TARGET (PX4
            AUTO.PRECLAND 4/9; ArduPilot LAND 9, which uses the target when PLND_ENABLED = 1).
        landing_target_position: send LANDING_TARGET's x, y, z with ``position_valid = 1`` in
            MAV_FRAME_BODY_FRD (ArduPilot reads them, divided by ``distance``); PX4 drops a
            body-frame position outright ("coordinate frame 12 unsupported"), so for PX4 the
            angle form alone is sent.
        precland_param: a parameter that must be 1 for the precision land to use the target
            (ArduPilot PLND_ENABLED), or None (PX4: AUTO.PRECLAND always does).
    """

    name: str
    offboard: tuple[int, int]
    land: tuple[int, int]
    hold: tuple[int, int]
    hover_param: str
    thrust_param: str | None = None
    thrust_param_bits: int = 0
    precland: tuple[int, int] = (4, 9)
    landing_target_position: bool = False
    precland_param: str | None = None

    @staticmethod
    def _main_sub(custom_mode: int) -> tuple[int, int]:
        return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF

    def _matches(self, custom_mode: int, mode: tuple[int, int]) -> bool:
        if self.name == "px4":
            main, sub = self._main_sub(custom_mode)
            return main == mode[0] and (mode[0] == 6 or sub == mode[1])
        return custom_mode == mode[0]

    def is_offboard(self, custom_mode: int) -> bool:
        return self._matches(custom_mode, self.offboard)

    def is_land(self, custom_mode: int) -> bool:
        if self.name == "px4":
            main, sub = self._main_sub(custom_mode)
            return main == 4 and sub in (6, 9)  # AUTO.LAND or AUTO.PRECLAND
        return self._matches(custom_mode, self.land)

    def is_precland(self, custom_mode: int) -> bool:
        return self._matches(custom_mode, self.precland)

    def is_hold(self, custom_mode: int) -> bool:
        return self._matches(custom_mode, self.hold)

    def mode_name(self, custom_mode: int) -> str:
        if self.name == "px4":
            main, sub = self._main_sub(custom_mode)
            names = {
                (6, 0): "OFFBOARD",
                (4, 3): "AUTO.LOITER",
                (4, 6): "AUTO.LAND",
                (4, 9): "AUTO.PRECLAND",
                (4, 5): "AUTO.RTL",
                (3, 0): "POSCTL",
                (2, 0): "ALTCTL",
                (1, 0): "MANUAL",
                (7, 0): "STABILIZED",
            }
            return names.get((main, sub), f"PX4 {main}/{sub}")
        names = {
            0: "STABILIZE",
            2: "ALT_HOLD",
            4: "GUIDED",
            5: "LOITER",
            9: "LAND",
            20: "GUIDED_NOGPS",
        }
        return names.get(custom_mode, f"ArduPilot {custom_mode}")

    def set_mode_params(self, mode: tuple[int, int], armed: bool) -> tuple[float, float, float]:
        """DO_SET_MODE param1..3 (param1 = CUSTOM_MODE_ENABLED, + SAFETY_ARMED when armed)."""
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (
            mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0
        )
        return float(base), float(mode[0]), float(mode[1])


PX4 = AutopilotProfile(
    name="px4", offboard=(6, 0), land=(4, 6), hold=(4, 3), hover_param="MPC_THR_HOVER"
)
ARDUPILOT = AutopilotProfile(
    name="ardupilot",
    offboard=(20, 0),
    land=(9, 0),
    hold=(2, 0),
    hover_param="MOT_THST_HOVER",
    thrust_param="GUID_OPTIONS",
    thrust_param_bits=8,
    precland=(9, 0),
    landing_target_position=True,
    precland_param="PLND_ENABLED",
)
PROFILES = {"px4": PX4, "ardupilot": ARDUPILOT}


# --------------------------------------------------------------------------- helpers


def parse_connection(url: str, baud: int) -> tuple[str, int]:
    """A pymavlink device string and baud rate; ``serial:PATH[:BAUD]`` is accepted too."""
    text = url.strip()
    if not text:
        raise LinkError("connection string is empty; e.g. udpin:0.0.0.0:14540 or /dev/ttyAMA0")
    if text.startswith("serial:"):
        rest = text[len("serial:") :]
        path, _, rate = rest.partition(":")
        if rate:
            try:
                baud = int(rate)
            except ValueError:
                raise LinkError(f"connection {url!r}: baud {rate!r} is not an integer") from None
        text = path
    if baud <= 0:
        raise LinkError(f"baud = {baud}; expected > 0")
    if text.startswith(("udpin:", "udpout:", "udp:", "tcp:", "tcpin:", "udpbcast:")):
        host_port = text.split(":", 1)[1]
        host, _, port = host_port.rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise LinkError(f"connection {url!r}: expected {text.split(':')[0]}:HOST:PORT")
    return text, baud


@dataclass(frozen=True)
class LinkEvent:
    """Something that happened to the link: ``discovered``, ``lost``, ``reconnected``,
    ``restarted``, ``port_error``, ``port_reopened``."""

    kind: str
    text: str


@dataclass
class _PendingCommand:
    command: int
    params: tuple[float, ...]
    sent_s: float
    attempts: int
    result: int | None = None


@dataclass
class LinkCounters:
    """What the link has seen (reported in the flight log and at exit)."""

    rx_messages: int = 0
    rx_bad_data: int = 0
    rx_other_systems: int = 0
    tx_setpoints: int = 0
    tx_landing_targets: int = 0
    tx_commands: int = 0
    reconnects: int = 0
    restarts: int = 0
    port_errors: int = 0
    rx_stale_heartbeats: int = 0
    rx_peer_mismatch: int = 0
    """Autopilot HEARTBEATs from an address other than the pinned peer (udpin only)."""
    tx_errors: int = 0
    """Datagrams to the pinned peer the OS would not send (too big, no route, no buffer);
    lost, as any UDP datagram (udpin only)."""
    extra: dict[str, int] = field(default_factory=dict)


# --------------------------------------------------------------------------- the link

_UDP_MAX = 65_535


class MavlinkLink:
    """One MAVLink 2 connection to one autopilot.

    Args:
        url: pymavlink connection string (see the module doc).
        baud: serial baud rate.
        profile: the autopilot profile.
        sysid: our system id; None = take the autopilot's once discovered (the convention for a
            component on the vehicle), 1 until then.
        compid: our component id (191, onboard computer).
        signing_key: 32-byte MAVLink 2 signing secret (None: unsigned).
        link_timeout_s: no autopilot HEARTBEAT for this long = link lost.
        heartbeat_period_s: our HEARTBEAT period.
        clock: monotonic clock (injectable for tests).
    """

    def __init__(
        self,
        url: str,
        *,
        baud: int = 57_600,
        profile: AutopilotProfile = PX4,
        sysid: int | None = None,
        compid: int = COMPANION_COMPID,
        signing_key: bytes | None = None,
        link_timeout_s: float = 3.0,
        heartbeat_period_s: float = 1.0,
        reopen_period_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.device, self.baud = parse_connection(url, baud)
        if not (math.isfinite(link_timeout_s) and link_timeout_s > 0):
            raise LinkError(f"link_timeout_s = {link_timeout_s}; expected > 0")
        if signing_key is not None and len(signing_key) != 32:
            raise LinkError(f"signing key of {len(signing_key)} bytes; expected 32")
        self.url = url
        self.profile = profile
        self._fixed_sysid = sysid
        self.compid = compid
        self.signing_key = signing_key
        self.link_timeout_s = link_timeout_s
        self.heartbeat_period_s = heartbeat_period_s
        self.reopen_period_s = reopen_period_s
        self._clock = clock
        self.target_system: int | None = None
        self.target_component: int = 1
        self.connected = False
        self.counters = LinkCounters()
        self.events: list[LinkEvent] = []
        self._last_hb_rx_s = -math.inf
        self._last_hb_tx_s = -math.inf
        self._last_boot_ms: int | None = None
        self._newest_seq: dict[tuple[int, int], int] = {}
        self._pending: dict[int, _PendingCommand] = {}
        self._acks: dict[int, int] = {}
        self._params: dict[str, float] = {}
        self._broken_since: float | None = None
        self.conn: Any = None
        self.last_send_call_s = 0.0
        self.peer: tuple[str, int] | None = None
        """udpin: the autopilot's address, the only one sent to once known."""
        self._datagram_from: tuple[str, int] | None = None
        self._leftover: tuple[int, int] | None = None
        self._open()

    # ------------------------------------------------------------------ connection

    def _open(self) -> None:
        try:
            self.conn = mavutil.mavlink_connection(
                self.device,
                baud=self.baud,
                source_system=self._fixed_sysid or 1,
                source_component=self.compid,
                autoreconnect=True,
                dialect="common",
            )
        except (OSError, ValueError) as exc:
            raise LinkError(f"{self.url}: cannot open the MAVLink connection: {exc}") from None
        codec = type(self.conn.mav).__module__
        if codec != "pymavlink.dialects.v20.common":  # pragma: no cover - forced above
            self.close()
            raise LinkError(f"{self.url}: pymavlink chose {codec}, expected MAVLink 2 common")
        self.conn.mav.robust_parsing = True
        if getattr(self.conn, "udp_server", False):
            self._pin_udp_peer(self.conn)
        if self.signing_key is not None:
            self.conn.setup_signing(
                self.signing_key,
                sign_outgoing=True,
                allow_unsigned_callback=lambda _mav, msg_id: msg_id in UNSIGNED_ALLOWED,
            )

    def _pin_udp_peer(self, conn: Any) -> None:
        """Replace a udpin connection's ``recv``/``write`` (module doc: the peer): ``recv``
        parses each datagram on its own (the messages left in the parser first; an incomplete
        one is dropped, as it can never complete over UDP) and notes its sender (keeping
        pymavlink's ``clients`` as it does); ``write`` goes to the peer alone once known."""
        port = conn.port
        write_plain = conn.write

        def recv(n: int | None = None) -> bytes | str:
            mav = conn.mav
            if mav.buf_len():
                mark = (len(mav.buf), mav.buf_index)
                if mark != self._leftover:
                    self._leftover = mark
                    return ""  # the parser takes the next message of this datagram first
                # no progress: an incomplete message, which over UDP never completes (a
                # datagram carries whole messages); it must not swallow the next datagram
                mav.buf, mav.buf_index = bytearray(), 0
                mav.expected_length = mavlink.HEADER_LEN_V1 + 2
                self.counters.rx_bad_data += 1
            self._leftover = None
            try:
                data, addr = port.recvfrom(_UDP_MAX)
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                    return ""
                raise
            conn.clients.add(addr)
            conn.clients_last_alive[addr] = time.time()
            self._datagram_from = addr  # every message parsed until the next datagram
            return data

        def write(buf: bytes) -> None:
            if self.peer is None:
                write_plain(buf)  # before the autopilot is heard: pymavlink's (every sender)
                return
            try:
                port.sendto(buf, self.peer)
            except OSError:  # as pymavlink: a datagram the OS refuses is lost, but counted
                self.counters.tx_errors += 1

        conn.recv = recv
        conn.write = write

    def fileno(self) -> int | None:
        """The file descriptor to ``select`` on (None while the port is being reopened)."""
        if self.conn is None:
            return None
        try:
            return int(self.conn.fd) if self.conn.fd is not None else None
        except (AttributeError, TypeError, ValueError):
            return None

    def close(self) -> None:
        if self.conn is not None:
            try:
                self.conn.close()
            except OSError:
                pass
            self.conn = None

    def _port_error(self, exc: BaseException) -> None:
        now = self._clock()
        self.counters.port_errors += 1
        if self._broken_since is None:
            self._broken_since = now
            self._event(
                "port_error", f"{self.url}: {exc}; reopening every {self.reopen_period_s} s"
            )
        self.close()

    def _maybe_reopen(self) -> None:
        if self.conn is not None or self._broken_since is None:
            return
        now = self._clock()
        if now - self._broken_since < self.reopen_period_s:
            return
        try:
            self._open()
        except LinkError:
            self._broken_since = now
            return
        self._broken_since = None
        self._event("port_reopened", f"{self.url}: reopened")

    # ------------------------------------------------------------------ receiving

    def poll(self, on_message: Callable[[Any, float], None]) -> int:
        """Receive everything waiting; each autopilot message goes to ``on_message(msg,
        rx_monotonic_s)``. Also sends our HEARTBEAT when due and watches the link. Returns the
        number of messages delivered."""
        self._maybe_reopen()
        n = 0
        while self.conn is not None:
            try:
                msg = self.conn.recv_msg()
            except (OSError, mavutil.mavlink.MAVError) as exc:
                if isinstance(exc, OSError):
                    self._port_error(exc)
                    break
                self.counters.rx_bad_data += 1
                continue
            if msg is None:
                break
            rx = self._clock()
            if msg.get_type() == "BAD_DATA":
                self.counters.rx_bad_data += 1
                continue
            if self._accept(msg, rx):
                self.counters.rx_messages += 1
                on_message(msg, rx)
                n += 1
        self._tick()
        return n

    def _stale(self, msg: Any, key: tuple[int, int]) -> bool:
        """Whether ``msg`` is a stale HEARTBEAT (see :data:`STALE_SEQ_WINDOW`); keeps the newest
        sequence number of each sender."""
        seq = msg.get_seq()
        newest = self._newest_seq.get(key)
        if newest is None or (newest - seq) % 256 > STALE_SEQ_WINDOW:  # ahead, or a new stream
            self._newest_seq[key] = seq
            return False
        if msg.get_type() != "HEARTBEAT":
            return False
        self.counters.rx_stale_heartbeats += 1
        return True

    def _accept(self, msg: Any, rx: float) -> bool:
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        name = msg.get_type()
        if self._stale(msg, (src_sys, src_comp)):
            return False
        if name == "HEARTBEAT" and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID:
            if self.target_system is None:
                self.target_system, self.target_component = src_sys, src_comp
                if self._fixed_sysid is None:
                    self.conn.mav.srcSystem = src_sys
                self._event(
                    "discovered",
                    f"autopilot {src_sys}/{src_comp} (type {msg.type}, autopilot {msg.autopilot})"
                    f" on {self.url}",
                )
            if (src_sys, src_comp) == (self.target_system, self.target_component):
                if not self._from_peer():
                    return False
                if not self.connected and self._last_hb_rx_s > -math.inf:
                    self.counters.reconnects += 1
                    self._event("reconnected", f"autopilot {src_sys}/{src_comp} is back")
                self.connected = True
                self._last_hb_rx_s = rx
        if self.target_system is None or src_sys != self.target_system:
            self.counters.rx_other_systems += 1
            return False
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None:
            if self._last_boot_ms is not None and boot_ms + 1000 < self._last_boot_ms:
                self.counters.restarts += 1
                self._newest_seq.clear()
                self._event(
                    "restarted",
                    f"autopilot clock went back from {self._last_boot_ms} to {boot_ms} ms",
                )
            self._last_boot_ms = boot_ms
        if name == "COMMAND_ACK":
            self._acks[msg.command] = msg.result
            pending = self._pending.get(msg.command)
            if pending is not None:
                pending.result = msg.result
        elif name == "PARAM_VALUE":
            self._params[msg.param_id] = float(msg.param_value)
        return True

    def _from_peer(self) -> bool:
        """udpin: whether the autopilot HEARTBEAT just parsed comes from the pinned peer,
        pinning (or, on a lost link, moving) it; other transports: always."""
        if self.conn is None or not getattr(self.conn, "udp_server", False):
            return True
        addr = self._datagram_from
        if addr is None or addr == self.peer:
            return True
        if self.peer is not None and self.connected:
            self.counters.rx_peer_mismatch += 1
            return False
        what = "pinned" if self.peer is None else f"moved from {self.peer[0]}:{self.peer[1]}"
        self.peer = addr
        self._event("peer", f"autopilot at {addr[0]}:{addr[1]} ({what}); sending only there")
        return True

    def _tick(self) -> None:
        now = self._clock()
        if self.conn is not None and now - self._last_hb_tx_s >= self.heartbeat_period_s:
            self._last_hb_tx_s = now
            self._send(
                self.conn.mav.heartbeat_encode(
                    mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                    mavlink.MAV_AUTOPILOT_INVALID,
                    0,
                    0,
                    mavlink.MAV_STATE_ACTIVE,
                )
            )
        if self.connected and now - self._last_hb_rx_s > self.link_timeout_s:
            self.connected = False
            self._event(
                "lost", f"no HEARTBEAT from the autopilot for {now - self._last_hb_rx_s:.1f} s"
            )
        for pending in list(self._pending.values()):
            if pending.result is None and now - pending.sent_s >= 0.5 and pending.attempts < 4:
                pending.attempts += 1
                pending.sent_s = now
                self._send_command(pending.command, pending.params, confirmation=pending.attempts)

    def _event(self, kind: str, text: str) -> None:
        self.events.append(LinkEvent(kind, text))
        log.info("link %s: %s", kind, text)

    def pop_events(self) -> list[LinkEvent]:
        events, self.events = self.events, []
        return events

    @property
    def heartbeat_age_s(self) -> float:
        return self._clock() - self._last_hb_rx_s

    # ------------------------------------------------------------------ sending

    def _send(self, msg: Any) -> bool:
        if msg is None or self.conn is None:
            return False
        try:
            self.conn.mav.send(msg)
        except OSError as exc:
            self._port_error(exc)
            return False
        return True

    def send_setpoint(self, thrust: float, rate_frd_rad_s, time_boot_ms: int) -> float | None:
        """SET_ATTITUDE_TARGET, type_mask 128 (attitude ignored): thrust + FRD body rates.

        Returns the monotonic time the packed datagram was handed to the OS (None: not sent).
        ``last_send_call_s`` is how long the send call took: on a loopback link a busy machine
        may run the receiver inside it, which is not the companion's latency.
        """
        conn = self.conn
        if conn is None or self.target_system is None:
            return None
        r = rate_frd_rad_s
        msg = conn.mav.set_attitude_target_encode(
            int(time_boot_ms) & 0xFFFFFFFF,
            self.target_system,
            self.target_component,
            mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE,
            [1.0, 0.0, 0.0, 0.0],
            float(r[0]),
            float(r[1]),
            float(r[2]),
            float(thrust),
        )
        mav = conn.mav
        buf = msg.pack(mav)  # as MAVLink.send, with the hand-off time taken before the write
        handed = self._clock()
        try:
            conn.write(buf)
        except OSError as exc:
            self._port_error(exc)
            return None
        self.last_send_call_s = self._clock() - handed
        mav.seq = (mav.seq + 1) % 256
        mav.total_packets_sent += 1
        mav.total_bytes_sent += len(buf)
        self.counters.tx_setpoints += 1
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
        conn = self.conn
        if conn is None or self.target_system is None:
            return None
        valid = pos_frd_m is not None
        x, y, z = pos_frd_m if pos_frd_m is not None else (0.0, 0.0, 0.0)
        msg = conn.mav.landing_target_encode(
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
        if not self._send(msg):
            return None
        self.counters.tx_landing_targets += 1
        return handed

    def send_frame_marker(self, time_boot_ms: int, frame_id: int) -> None:
        """NAMED_VALUE_INT ``VL_FRAME`` = frame id, stamped with the frame's time: a SITL
        frame processed without a LANDING_TARGET (the lockstep answer; an autopilot only logs
        it)."""
        if self.conn is None:
            return
        self._send(
            self.conn.mav.named_value_int_encode(
                int(time_boot_ms) & 0xFFFFFFFF, b"VL_FRAME", int(frame_id) & 0x7FFFFFFF
            )
        )

    def _send_command(self, command: int, params: tuple[float, ...], confirmation: int = 0) -> None:
        if self.conn is None or self.target_system is None:
            return
        p = list(params) + [0.0] * (7 - len(params))
        self._send(
            self.conn.mav.command_long_encode(
                self.target_system, self.target_component, command, confirmation, *p
            )
        )
        self.counters.tx_commands += 1

    def command(self, command: int, *params: float) -> None:
        """Send COMMAND_LONG, re-sent every 0.5 s (up to 4 times) until its COMMAND_ACK."""
        now = self._clock()
        self._acks.pop(command, None)
        self._pending[command] = _PendingCommand(command, tuple(params), now, 0)
        self._send_command(command, tuple(params))

    def ack(self, command: int) -> int | None:
        """The MAV_RESULT of the latest ACK for ``command`` since it was sent (None: none)."""
        return self._acks.get(command)

    def request_mode(self, mode: tuple[int, int], armed: bool) -> None:
        """DO_SET_MODE to a profile mode (``profile.offboard``/``land``/``hold``)."""
        self.command(mavlink.MAV_CMD_DO_SET_MODE, *self.profile.set_mode_params(mode, armed))

    def arm(self, arm: bool) -> None:
        self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if arm else 0.0)

    def set_message_interval(self, msg_id: int, rate_hz: float) -> None:
        """SET_MESSAGE_INTERVAL (fire and forget; the autopilot's ACK is not awaited)."""
        self._send_command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (float(msg_id), 1e6 / rate_hz))

    def request_param(self, name: str) -> None:
        if self.conn is None or self.target_system is None:
            return
        self._send(
            self.conn.mav.param_request_read_encode(
                self.target_system, self.target_component, name.encode(), -1
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
        import struct

        return struct.unpack("<i", struct.pack("<f", value))[0]
