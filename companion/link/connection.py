"""The companion's MAVLink connection: the port, our HEARTBEAT, autopilot discovery, reconnect.

Any pymavlink connection string works (``udpin:0.0.0.0:14540``, ``udpout:10.0.0.1:14580``,
``tcp:127.0.0.1:5760``, ``/dev/ttyAMA0`` with ``baud``, or ``serial:/dev/ttyAMA0:921600``).
MAVLink 2 is forced (``MAVLINK20`` is set before pymavlink's ``mavutil`` is imported and the
``common`` dialect is selected explicitly, so nothing can downgrade the link to MAVLink 1).

The companion announces itself as an onboard controller (``MAV_TYPE_ONBOARD_CONTROLLER``,
``MAV_AUTOPILOT_INVALID``, component 191 = ``MAV_COMP_ID_ONBOARD_COMPUTER``) at 1 Hz,
discovers the autopilot from the first HEARTBEAT of a component whose ``autopilot`` is not
INVALID, and watches the link: no autopilot HEARTBEAT for ``link_timeout_s`` = *lost*; the next
one = *reconnected*; ``time_boot_ms`` going backwards = the autopilot *restarted*. A broken
serial/TCP port is reopened every ``reopen_period_s``.

On a lossy link datagrams may be duplicated or reordered. Telemetry carries time stamps (the
store drops late samples); a HEARTBEAT does not, and a stale one would show an old mode or
arming state (a reordered HOLD heartbeat after the switch to OFFBOARD reads as "someone else
changed the mode"). So a HEARTBEAT whose MAVLink sequence number is at most
:data:`STALE_SEQ_WINDOW` behind the newest one received from that component is dropped and
counted (``rx_stale_heartbeats``); further behind is a new stream (a restarted sender).

On a UDP server port (``udpin:``) pymavlink sends every datagram to every address that ever sent
one to the port, so a GCS, a scanner or a flood from elsewhere on the network would receive the
setpoints too (and could steer the replies of a naive "last sender" link). The connection *pins
its peer*: the address the autopilot's HEARTBEAT came from (each datagram is parsed on its own —
an incomplete message left by another datagram is dropped, as over UDP it can never complete —
so every message has a known sender). Everything is then sent to that address only. The peer
moves only when the link is lost (no autopilot HEARTBEAT for ``link_timeout_s``) and the
autopilot is heard from a new address — a restarted autopilot on another port. Unsigned MAVLink
cannot stop a spoof on a lost link: sign it (``signing_key``) or use a serial port where that
matters.

A flood must not starve the autopilot (issue 31: on a busy 2-core board, a flood of junk on the
port cost a flight its telemetry). While the link is up, a datagram from any address other than
the pinned peer is dropped before any MAVLink parse and counted (``rx_peer_mismatch``: a GCS, a
scanner, a flood, a HEARTBEAT spoofing the autopilot from elsewhere); before the peer is known
(or while the link is lost) every datagram is parsed, but an oversized one is dropped unparsed
and junk before the first frame is skipped at C speed (:mod:`companion.contract.datagrams`).
One :meth:`MavlinkConnection.poll` reads at most
:data:`~companion.contract.datagrams.RX_DATAGRAMS_PER_POLL` datagrams (``rx_deferred`` counts
the polls that stopped there), so the companion's loop gets back to its camera; the UDP socket
asks for a :data:`~companion.contract.datagrams.RCVBUF_BYTES` receive buffer.

What goes over the connection (commands, parameters, setpoints) is
:class:`companion.link.protocol.LinkProtocol`'s; what differs between autopilots is the
contract's table (:mod:`companion.contract.autopilots`).
"""

from __future__ import annotations

import errno
import logging
import math
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

os.environ["MAVLINK20"] = "1"  # before mavutil is imported: mavutil reads it at import time
os.environ.setdefault("MAVLINK_DIALECT", "common")

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from companion.contract.datagrams import (
    MAX_DATAGRAM_BYTES,
    RX_DATAGRAMS_PER_POLL,
    frame_start,
)
from companion.contract.signing import UNSIGNED_ALLOWED
from companion.link.datagrams import parse_datagram, size_receive_buffer, whole_datagrams

mavutil.set_dialect("common")  # v20.common, whatever MAVLINK_DIALECT said

__all__ = [
    "COMPANION_COMPID",
    "STALE_SEQ_WINDOW",
    "LinkCounters",
    "LinkError",
    "LinkEvent",
    "MavlinkConnection",
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

_UDP_MAX = 65_535


class LinkError(Exception):
    """The link cannot be opened or a parameter of it is invalid (names the value)."""


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
    ``restarted``, ``peer``, ``port_error``, ``port_reopened``."""

    kind: str
    text: str


@dataclass
class LinkCounters:
    """What the link has seen (reported in the flight log and at exit). The connection counts
    what it receives and its port's errors; :class:`~companion.link.protocol.LinkProtocol`
    counts the ``tx_`` messages it sends."""

    rx_messages: int = 0
    rx_bad_data: int = 0
    """Malformed input: bad CRC, bad prefix, an incomplete frame, an empty or oversized
    datagram, junk before a datagram's first frame (one per datagram)."""
    rx_other_systems: int = 0
    tx_setpoints: int = 0
    tx_landing_targets: int = 0
    tx_commands: int = 0
    reconnects: int = 0
    restarts: int = 0
    port_errors: int = 0
    rx_stale_heartbeats: int = 0
    rx_peer_mismatch: int = 0
    """Datagrams from an address other than the pinned peer while the link is up, dropped
    before any parse (udpin only): a GCS, a scanner, a flood, a spoofed autopilot."""
    rx_deferred: int = 0
    """Polls that stopped after ``RX_DATAGRAMS_PER_POLL`` datagrams with more possibly
    waiting (udpin only; the next poll reads on)."""
    tx_errors: int = 0
    """Datagrams to the pinned peer the OS would not send (too big, no route, no buffer);
    lost, as any UDP datagram (udpin only)."""
    extra: dict[str, int] = field(default_factory=dict)


class MavlinkConnection:
    """One MAVLink 2 port to one autopilot: receiving, sending, and watching the link.

    Args:
        url: pymavlink connection string (see the module doc).
        baud: serial baud rate.
        sysid: our system id; None = take the autopilot's once discovered (the convention for a
            component on the vehicle), 1 until then.
        compid: our component id (191, onboard computer).
        signing_key: 32-byte MAVLink 2 signing secret (None: unsigned).
        link_timeout_s: no autopilot HEARTBEAT for this long = link lost.
        heartbeat_period_s: our HEARTBEAT period.
        reopen_period_s: a broken port is reopened this often.
        clock: monotonic clock (injectable for tests).

    Raises:
        LinkError: a parameter is invalid or the port cannot be opened.
    """

    def __init__(
        self,
        url: str,
        *,
        baud: int = 57_600,
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
        self._fixed_sysid = sysid
        self.compid = compid
        self.signing_key = signing_key
        self.link_timeout_s = link_timeout_s
        self.heartbeat_period_s = heartbeat_period_s
        self.reopen_period_s = reopen_period_s
        self.clock = clock
        """The monotonic clock every time stamp of the link is read from."""
        self.target_system: int | None = None
        self.target_component: int = 1
        self.connected = False
        self.counters = LinkCounters()
        self.events: list[LinkEvent] = []
        self._last_hb_rx_s = -math.inf
        self._last_hb_tx_s = -math.inf
        self._last_boot_ms: int | None = None
        self._newest_seq: dict[tuple[int, int], int] = {}
        self._broken_since: float | None = None
        self.conn: Any = None
        self.last_send_call_s = 0.0
        self.peer: tuple[str, int] | None = None
        """udpin: the autopilot's address, the only one sent to once known."""
        self._datagram_from: tuple[str, int] | None = None
        self._leftover: tuple[int, int] | None = None
        self._rx_budget = RX_DATAGRAMS_PER_POLL
        """udpin: datagrams the current :meth:`poll` may still read."""
        self._rx_fed = False
        """udpin: the last ``recv`` gave the parser input (a datagram, or the rest of one)."""
        self._open()

    # ------------------------------------------------------------------ the port

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
        """Replace a udpin connection's ``recv``/``write`` (module doc: the peer, a flood):
        ``recv`` parses each datagram on its own (the messages left in the parser first; an
        incomplete one is dropped, as it can never complete over UDP), drops what the peer
        rule refuses before parsing it, and notes its sender (keeping pymavlink's ``clients``
        as it does); ``write`` goes to the peer alone once known."""
        port = conn.port
        write_plain = conn.write
        size_receive_buffer(port)

        def recv(n: int | None = None) -> bytes | str:
            mav = conn.mav
            self._rx_fed = False
            if mav.buf_len():
                mark = (len(mav.buf), mav.buf_index)
                if mark != self._leftover:
                    self._leftover = mark
                    self._rx_fed = True
                    return ""  # the parser takes the next message of this datagram first
                # no progress: an incomplete message, which over UDP never completes (a
                # datagram carries whole messages); it must not swallow the next datagram
                mav.buf, mav.buf_index = bytearray(), 0
                mav.expected_length = mavlink.HEADER_LEN_V1 + 2
                self.counters.rx_bad_data += 1
            self._leftover = None
            data = self._next_datagram(port)
            if data is None:
                return ""
            self._rx_fed = True
            addr = self._datagram_from
            conn.clients.add(addr)
            conn.clients_last_alive[addr] = time.time()
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

    def _next_datagram(self, port: socket.socket) -> bytes | None:
        """The next datagram worth parsing, its sender in ``_datagram_from``; None when none
        waits or this poll's budget is spent. Refused unparsed (counted): anything from another
        address than the pinned peer while the link is up (``rx_peer_mismatch``), an empty or
        oversized datagram, one without a frame start (``rx_bad_data``); junk before the first
        frame start is cut off (``rx_bad_data``)."""
        counters = self.counters
        while True:
            if self._rx_budget <= 0:
                counters.rx_deferred += 1
                return None
            self._rx_budget -= 1
            try:
                data, addr = port.recvfrom(_UDP_MAX)
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                    return None
                raise
            if self.peer is not None and self.connected and addr != self.peer:
                counters.rx_peer_mismatch += 1
                continue
            if not data or len(data) > MAX_DATAGRAM_BYTES:
                counters.rx_bad_data += 1
                continue
            start = frame_start(data)
            if start:
                counters.rx_bad_data += 1
                data = data[start:]
                if not data:
                    continue
            self._datagram_from = addr  # every message parsed until the next datagram
            return data

    @property
    def is_open(self) -> bool:
        """The port is open (False while a broken one waits to be reopened)."""
        return self.conn is not None

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
        now = self.clock()
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
        now = self.clock()
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
        self._rx_budget = RX_DATAGRAMS_PER_POLL
        n, whole = 0, whole_datagrams(self.conn)  # udpin, as a rule: a datagram at a time
        if whole:
            n = self._poll_datagrams(self.conn, on_message)
        while self.conn is not None and not whole:
            self._rx_fed = False
            try:
                msg = self.conn.recv_msg()
            except (OSError, mavutil.mavlink.MAVError) as exc:
                if isinstance(exc, OSError):
                    self._port_error(exc)
                    break
                self.counters.rx_bad_data += 1
                continue
            if msg is None:
                if self._rx_fed:  # udpin: input without a whole message; read on
                    continue
                break
            rx = self.clock()
            if msg.get_type() == "BAD_DATA":
                self.counters.rx_bad_data += 1
                continue
            if self._accept(msg, rx):
                self.counters.rx_messages += 1
                on_message(msg, rx)
                n += 1
        self._tick()
        return n

    def _poll_datagrams(self, conn: Any, on_message: Callable[[Any, float], None]) -> int:
        """:meth:`poll` a datagram at a time (:func:`~companion.link.datagrams.parse_datagram`:
        the messages of pymavlink's ``recv_msg`` loop, in a third of its time)."""
        counters, n = self.counters, 0
        while True:
            try:
                data = self._next_datagram(conn.port)
            except OSError as exc:
                self._port_error(exc)
                return n
            if data is None:
                return n
            conn.clients.add(self._datagram_from)  # as recv does
            conn.clients_last_alive[self._datagram_from] = time.time()
            msgs, cut = parse_datagram(conn.mav, data)
            for msg in msgs:
                conn.post_message(msg)  # as recv_msg does
                rx = self.clock()
                if msg.get_type() == "BAD_DATA":
                    counters.rx_bad_data += 1
                elif self._accept(msg, rx):
                    counters.rx_messages += 1
                    on_message(msg, rx)
                    n += 1
                    if self.conn is not conn:  # the port broke meanwhile: the rest is lost
                        return n
            if cut:  # an incomplete frame, which over UDP never completes (as recv says)
                counters.rx_bad_data += 1

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
        if self._stale(msg, (src_sys, src_comp)):
            return False
        if msg.get_type() == "HEARTBEAT" and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID:
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
        return True

    def _from_peer(self) -> bool:
        """udpin: whether the autopilot HEARTBEAT just parsed comes from the pinned peer,
        pinning (or, on a lost link, moving) it; other transports: always. While the link is
        up, datagrams from elsewhere never reach the parser (:meth:`_next_datagram`), so a
        HEARTBEAT parsed from another address is one heard while the link is lost."""
        if self.conn is None or not getattr(self.conn, "udp_server", False):
            return True
        addr = self._datagram_from
        if addr is None or addr == self.peer:
            return True
        what = "pinned" if self.peer is None else f"moved from {self.peer[0]}:{self.peer[1]}"
        self.peer = addr
        self._event("peer", f"autopilot at {addr[0]}:{addr[1]} ({what}); sending only there")
        return True

    def _tick(self) -> None:
        now = self.clock()
        if self.conn is not None and now - self._last_hb_tx_s >= self.heartbeat_period_s:
            self._last_hb_tx_s = now
            self.send(
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

    def _event(self, kind: str, text: str) -> None:
        self.events.append(LinkEvent(kind, text))
        log.info("link %s: %s", kind, text)

    def pop_events(self) -> list[LinkEvent]:
        events, self.events = self.events, []
        return events

    @property
    def heartbeat_age_s(self) -> float:
        return self.clock() - self._last_hb_rx_s

    # ------------------------------------------------------------------ sending

    def send(self, msg: Any) -> bool:
        """Pack and send ``msg``; False when not sent (no port, or the port broke)."""
        if msg is None or self.conn is None:
            return False
        try:
            self.conn.mav.send(msg)
        except OSError as exc:
            self._port_error(exc)
            return False
        return True

    def send_timed(self, msg: Any) -> float | None:
        """Send ``msg`` as :meth:`send`, with the monotonic time the packed datagram was handed
        to the OS taken just before the write (None: not sent). ``last_send_call_s`` is how
        long the write took: on a loopback link a busy machine may run the receiver inside it,
        which is not the companion's latency."""
        conn = self.conn
        if conn is None:
            return None
        mav = conn.mav
        buf = msg.pack(mav)  # as MAVLink.send, with the hand-off time taken before the write
        handed = self.clock()
        try:
            conn.write(buf)
        except OSError as exc:
            self._port_error(exc)
            return None
        self.last_send_call_s = self.clock() - handed
        mav.seq = (mav.seq + 1) % 256
        mav.total_packets_sent += 1
        mav.total_bytes_sent += len(buf)
        return handed
