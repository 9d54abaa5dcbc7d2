"""MAVLink 2 over UDP for the SITL: one bound socket, per-datagram decoding, signing, counters.

Why not ``pymavlink.mavutil``: it cannot choose its source port for ``udpout`` and keeps one parse
buffer across datagrams (a truncated frame would swallow the start of the next datagram). Here a
pymavlink ``MAVLink`` object is used only as a codec (mavlink_notes.md section 14.1):

* the dialect module is ``pymavlink.dialects.v20.common`` imported directly, so the wire protocol
  is MAVLink 2 whatever ``MAVLINK20`` says (the MAVLink-1 trap of mavutil does not apply);
* every datagram is parsed by a fresh parser: a bad datagram cannot corrupt the next one;
* signatures are checked here, not by pymavlink, because pymavlink records a stream's timestamp
  *before* comparing the signature (a forged frame could then block the real stream). Allowed
  unsigned, as PX4: HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE, COLLISION;
* outgoing frames go to the configured remote plus every peer that sent a valid frame (PX4's
  SITL does the same), at most ``max_peers``; with :attr:`MavlinkEndpoint.batching` they are
  packed into one datagram until :meth:`MavlinkEndpoint.flush` (the SITL's loop flushes once
  per physics step), as routers pack frames into MTU-sized datagrams: one ``sendto`` and one
  wake-up of the receiver per step instead of one per message;
* nothing received ever raises: malformed input is counted in :class:`LinkStats` and returned
  as :class:`RxError` records for the flight log;
* with a :class:`~sitl_sim.mavlink.link_impairment.LinkImpairment` (a scenario's ``[link]``) every
  datagram sent goes through its ``mavlink_tx`` stream (sent when :meth:`release` finds it
  due) and every datagram read from the socket through ``mavlink_rx`` (decoded when due), so
  loss, delay, jitter, duplicates and reordering act on the wire, below MAVLink.
"""

from __future__ import annotations

import errno
import hashlib
import socket
import struct
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import common as mavlink

from companion.contract.datagrams import (
    MAX_DATAGRAM_BYTES,
    RCVBUF_BYTES,
    RX_DATAGRAMS_PER_POLL,
    frame_start,
)
from companion.contract.signing import UNSIGNED_ALLOWED, sign_outgoing, signing_timestamp_now
from sitl_sim.errors import SimError
from sitl_sim.mavlink.packing import pack_unsigned

if TYPE_CHECKING:
    from sitl_sim.mavlink.link_impairment import LinkImpairment

__all__ = [
    "MAX_DATAGRAM_BYTES",
    "RX_FOREIGN_PER_CALL",
    "Inbound",
    "LinkStats",
    "MavlinkEndpoint",
    "RxError",
    "SitlError",
    "SitlPortInUseError",
    "signing_timestamp_now",  # re-exported from companion.contract.signing
]


_NEW_STREAM_WINDOW = 6_000_000  # 60 s in 10 us units: how far behind a new stream may start
_RCVBUF_BYTES = RCVBUF_BYTES  # the companion's too (companion.contract.datagrams)
RX_FOREIGN_PER_CALL = 8
"""At most this many datagrams from addresses other than the link's remote (the companion, the
GCS) are decoded per :meth:`MavlinkEndpoint.receive`; the rest of them are shed unparsed
(``rx_shed``), at the cost of a ``recvfrom``. The SITL's loop receives once per 4-ms physics
step and again and again while it waits for a frame's answer: 2,000 foreign datagrams a second
per link at 250 Hz, plenty for a second client. Without it (issue 31) a flood's backlog filled
the socket buffer, which the SITL only kept pace with at ~48 us of decoding a datagram: every
lockstep answer waited behind megabytes of flood (one frame per 1.5 s of wall time), HEARTBEATs
(sim time) came 3-11 s apart, and the companion declared the link lost and failed safe."""
_BATCH_BYTES = 1472
"""A batch is sent before it would outgrow this: a 1500-byte Ethernet MTU less the IPv4 and UDP
headers (a datagram any MAVLink peer on a LAN receives unfragmented)."""


class SitlError(SimError):
    """Root of the MAVLink SITL's errors."""


class SitlPortInUseError(SitlError, OSError):
    """A UDP port the SITL must bind is taken (another SITL, PX4, or a client bound there)."""


@dataclass
class LinkStats:
    """Counters of one link (mutable; the SITL's SYS_STATUS and the log read them).

    ``errors_comm`` (SYS_STATUS) = everything dropped as malformed or not allowed:
    bad CRC/length/prefix, truncated, unsigned or badly signed, wrong target, rejected setpoint.
    """

    rx_datagrams: int = 0
    rx_bytes: int = 0
    rx_messages: int = 0
    rx_mavlink1: int = 0
    rx_bad_data: int = 0
    rx_truncated: int = 0
    rx_unknown_msgid: int = 0
    rx_unsigned_rejected: int = 0
    rx_bad_signature: int = 0
    rx_wrong_target: int = 0
    rx_rejected_setpoints: int = 0
    rx_deferred: int = 0
    """Times a receive call stopped (count/time budget) with datagrams possibly waiting."""
    rx_shed: int = 0
    """Datagrams from other addresses than the link's remote dropped unparsed beyond
    :data:`RX_FOREIGN_PER_CALL` (a flood; counted in ``errors_comm`` as dropped packets)."""
    tx_messages: int = 0
    tx_errors: int = 0

    @property
    def errors_comm(self) -> int:
        return (
            self.rx_bad_data
            + self.rx_truncated
            + self.rx_unsigned_rejected
            + self.rx_bad_signature
            + self.rx_wrong_target
            + self.rx_rejected_setpoints
            + self.rx_shed
        )

    @property
    def drop_rate_comm_centi_percent(self) -> int:
        """SYS_STATUS drop_rate_comm: errors per datagram received, in c% (0..10000)."""
        if self.rx_datagrams == 0:
            return 0
        return min(10_000, round(10_000 * self.errors_comm / self.rx_datagrams))

    def to_dict(self) -> dict[str, int]:
        d = asdict(self)
        d["errors_comm"] = self.errors_comm
        return d

    @classmethod
    def total(cls, *stats: LinkStats) -> LinkStats:
        """The field-wise sum of several links' counters (a system's SYS_STATUS)."""
        return cls(**{f.name: sum(getattr(s, f.name) for s in stats) for f in fields(cls)})


@dataclass(frozen=True)
class Inbound:
    """One accepted message and where it came from (``signed``: carried a valid signature;
    ``link``: the name of the endpoint that received it, e.g. ``offboard`` or ``gcs``)."""

    msg: Any
    addr: tuple[str, int]
    signed: bool
    link: str = "offboard"


@dataclass(frozen=True)
class RxError:
    """One dropped datagram or frame, for the log: ``kind`` names the counter it went to."""

    kind: str
    reason: str
    length: int
    addr: tuple[str, int]


class MavlinkEndpoint:
    """A bound UDP socket speaking MAVLink 2 as (sysid, compid).

    Args:
        bind: (host, port) to bind; a taken port raises :class:`SitlPortInUseError`.
        remote: (host, port) always sent to (PX4's offboard API default :14540).
        sysid / compid: our ids (1 / 1: the autopilot).
        signing_key: 32-byte MAVLink 2 secret; None = no signing (the default, as PX4).
        max_peers: how many extra peers (those that sent us valid frames) receive our traffic.
        name: the link's name (``offboard``, ``gcs``), carried by every :class:`Inbound`.
    """

    def __init__(
        self,
        bind: tuple[str, int],
        remote: tuple[str, int],
        *,
        sysid: int = 1,
        compid: int = 1,
        signing_key: bytes | None = None,
        max_peers: int = 8,
        name: str = "offboard",
    ) -> None:
        self.name = name
        if signing_key is not None and len(signing_key) != 32:
            raise SitlError(f"signing key must be 32 bytes, got {len(signing_key)}")
        self.stats = LinkStats()
        self.remote = remote
        self._max_peers = max_peers
        self._peers: OrderedDict[tuple[str, int], None] = OrderedDict()
        self._key = signing_key
        self._streams: dict[tuple[int, int, int], int] = {}
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _RCVBUF_BYTES)
            self._sock.bind(bind)
        except OSError as exc:
            self._sock.close()
            if exc.errno == errno.EADDRINUSE:
                raise SitlPortInUseError(
                    f"UDP {bind[0]}:{bind[1]} is already in use (another SITL or PX4 running?); "
                    "stop it or choose another port"
                ) from None
            raise SitlError(f"cannot bind UDP {bind[0]}:{bind[1]}: {exc}") from None
        self._sock.setblocking(False)
        self._encoder = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if signing_key is not None:
            sign_outgoing(self._encoder, signing_key, link_id=0)
        self.sysid = sysid
        self.compid = compid
        self._impairment: LinkImpairment | None = None
        self.batching = False
        """Pack outgoing frames into one datagram until :meth:`flush` (not through an impaired
        link, whose loss and delay act per frame)."""
        self._batch = bytearray()

    def set_impairment(self, impairment: LinkImpairment | None) -> None:
        """Send and receive through ``impairment``'s ``mavlink_tx`` / ``mavlink_rx`` streams
        (None: straight to the socket). The caller must call :meth:`release` often."""
        self._impairment = impairment

    def set_signing_key(self, key: bytes | None, initial_timestamp: int = 0) -> None:
        """Start, change (32-byte key) or stop (None) MAVLink 2 signing on this link; the
        incoming streams' timestamps are forgotten, our own signing time never goes back."""
        if key is not None and len(key) != 32:
            raise SitlError(f"signing key must be 32 bytes, got {len(key)}")
        self._key = key
        self._streams.clear()
        signing = self._encoder.signing
        signing.secret_key = key
        signing.sign_outgoing = key is not None
        signing.link_id = 0
        signing.timestamp = max(signing.timestamp, initial_timestamp, signing_timestamp_now())

    @property
    def signing(self) -> bool:
        """True while this link signs and checks signatures."""
        return self._key is not None

    # ------------------------------------------------------------------ properties

    @property
    def address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    @property
    def mav(self) -> Any:
        """The pymavlink codec (use its ``*_encode`` methods to build messages)."""
        return self._encoder

    def fileno(self) -> int:
        return self._sock.fileno()

    def close(self) -> None:
        self._sock.close()

    # ------------------------------------------------------------------ sending

    def send(self, msg: Any, component: int | None = None) -> bytes:
        """Pack (sign) and send to the remote and every peer; socket errors are counted.
        ``component``: another component of this system sends it (None: ours)."""
        enc = self._encoder
        if enc.signing.sign_outgoing:
            # Signing time must not lag the wall clock (receivers reject old new-streams).
            enc.signing.timestamp = max(enc.signing.timestamp, signing_timestamp_now())
            own, enc.srcComponent = enc.srcComponent, component or enc.srcComponent
            try:
                buf = msg.pack(enc)
            finally:
                enc.srcComponent = own
        else:  # pymavlink's bytes, packed in a third of its time
            buf = pack_unsigned(msg, enc.seq, enc.srcSystem, component or enc.srcComponent)
        enc.seq = (enc.seq + 1) % 256
        self.send_bytes(buf)
        return buf

    def send_bytes(self, buf: bytes) -> None:
        """Send an already packed frame (e.g. the one :meth:`send` of another link of the same
        system returned: packed and signed once, one sequence for both links)."""
        self.stats.tx_messages += 1
        imp = self._impairment
        if imp is not None:
            imp.streams["mavlink_tx"].offer(buf, imp.clock(), imp.cut)
            return
        if self.batching:
            if len(self._batch) + len(buf) > _BATCH_BYTES:
                self.flush()
            self._batch += buf
            return
        self._sendto_all(buf)

    def flush(self) -> None:
        """Send the batched frames as one datagram (no-op when none wait)."""
        if self._batch:
            buf = bytes(self._batch)
            self._batch.clear()
            self._sendto_all(buf)

    def release(self) -> None:
        """Send the impaired link's datagrams whose release time has come (no-op without one)."""
        imp = self._impairment
        if imp is not None:
            for buf in imp.streams["mavlink_tx"].due(imp.clock()):
                self._sendto_all(buf)

    def _sendto_all(self, buf: bytes) -> None:
        for addr in (self.remote, *self._peers):
            try:
                self._sock.sendto(buf, addr)
            except OSError:
                # Nobody listening (ECONNREFUSED from an earlier ICMP), buffer full: UDP is lossy.
                self.stats.tx_errors += 1

    # ------------------------------------------------------------------ receiving

    def receive(
        self,
        max_datagrams: int = RX_DATAGRAMS_PER_POLL,
        budget_s: float = 0.02,
        max_foreign: int = RX_FOREIGN_PER_CALL,
    ) -> tuple[list[Inbound], list[RxError]]:
        """Drain waiting datagrams without blocking: at most ``max_datagrams`` and about
        ``budget_s`` of decoding, so a flood delays the simulation but never stalls it (the
        rest waits in the kernel buffer, which drops the excess). Of the datagrams from other
        addresses than :attr:`remote`, ``max_foreign`` are decoded and the rest shed unparsed
        (``rx_shed``): a flood's backlog is drained at ``recvfrom`` speed and the remote's
        datagrams behind it are not kept waiting."""
        accepted: list[Inbound] = []
        errors: list[RxError] = []
        imp = self._impairment
        deadline = time.perf_counter() + budget_s
        foreign = 0
        for _ in range(max_datagrams):
            if time.perf_counter() > deadline:
                self.stats.rx_deferred += 1
                break
            try:
                data, addr = self._sock.recvfrom(65_535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                errors.append(RxError("rx_bad_data", f"recvfrom: {exc}", 0, ("", 0)))
                self.stats.rx_bad_data += 1
                break
            if addr != self.remote:
                if foreign >= max_foreign:
                    self.stats.rx_datagrams += 1
                    self.stats.rx_bytes += len(data)
                    self.stats.rx_shed += 1
                    continue
                foreign += 1
            if imp is None:
                self._decode_datagram(data, addr, accepted, errors)
            else:  # on the impaired wire: decoded when (and if) it arrives
                imp.streams["mavlink_rx"].offer((data, addr), imp.clock(), imp.cut)
        else:
            self.stats.rx_deferred += 1  # more waiting: the caller comes back next tick
        if imp is not None:
            for data, addr in imp.streams["mavlink_rx"].due(imp.clock()):
                self._decode_datagram(data, addr, accepted, errors)
        return accepted, errors

    def _decode_datagram(
        self,
        data: bytes,
        addr: tuple[str, int],
        accepted: list[Inbound],
        errors: list[RxError],
    ) -> None:
        st = self.stats
        st.rx_datagrams += 1
        st.rx_bytes += len(data)
        if not data or len(data) > MAX_DATAGRAM_BYTES:
            st.rx_bad_data += 1
            errors.append(RxError("rx_bad_data", "empty or oversize datagram", len(data), addr))
            return
        # Skip leading junk at C speed (pymavlink's robust parser scans it byte by byte).
        start = frame_start(data)
        if start > 0:
            st.rx_bad_data += 1
            errors.append(RxError("rx_bad_data", f"{start} bytes before a frame", len(data), addr))
            data = data[start:]
            if not data:
                return
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True  # bad frames come back as MAVLink_bad_data, never raise
        # Trust boundary: hostile bytes must never take the SITL down; whatever pymavlink raises
        # is counted and logged with its type, not swallowed.
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception as exc:
            st.rx_bad_data += 1
            errors.append(RxError("rx_bad_data", f"{type(exc).__name__}: {exc}", len(data), addr))
            return
        for msg in msgs:
            name = msg.get_type()
            if name == "BAD_DATA":
                st.rx_bad_data += 1
                errors.append(RxError("rx_bad_data", str(msg.reason), len(msg.data), addr))
                continue
            if name == "UNKNOWN" or name.startswith("UNKNOWN_"):
                st.rx_unknown_msgid += 1
                errors.append(RxError("rx_unknown_msgid", name, len(msg.get_msgbuf()), addr))
                continue
            buf = msg.get_msgbuf()
            if buf[0] != mavlink.PROTOCOL_MARKER_V2:
                st.rx_mavlink1 += 1
            signed = self._key is not None and self._check_signature(msg, buf, addr, errors)
            if self._key is not None and not signed:
                if msg.get_msgId() not in UNSIGNED_ALLOWED:
                    continue  # counted by _check_signature
            st.rx_messages += 1
            self._remember_peer(addr)
            accepted.append(Inbound(msg, addr, signed, self.name))
        if parser.buf_len() > 0:
            st.rx_truncated += 1
            errors.append(
                RxError(
                    "rx_truncated",
                    f"{parser.buf_len()} bytes of an incomplete frame",
                    len(data),
                    addr,
                )
            )

    def _check_signature(
        self, msg: Any, buf: bytearray, addr: tuple[str, int], errors: list[RxError]
    ) -> bool:
        """True for a valid signature with a fresh timestamp; counts and records the rest
        (unsigned frames of the allow-list are not errors)."""
        allowed = msg.get_msgId() in UNSIGNED_ALLOWED
        if buf[0] != mavlink.PROTOCOL_MARKER_V2 or not buf[2] & mavlink.MAVLINK_IFLAG_SIGNED:
            if not allowed:
                self.stats.rx_unsigned_rejected += 1
                errors.append(
                    RxError("rx_unsigned_rejected", f"unsigned {msg.get_type()}", len(buf), addr)
                )
            return False
        link_id = buf[-13]
        tlow, thigh = struct.unpack("<IH", bytes(buf[-12:-6]))
        stamp = tlow | (thigh << 32)
        expected = hashlib.sha256(self._key + bytes(buf[:-6])).digest()[:6]  # type: ignore[operator]
        reason = None
        if expected != bytes(buf[-6:]):
            reason = "signature mismatch"
        else:
            key = (link_id, msg.get_srcSystem(), msg.get_srcComponent())
            last = self._streams.get(key)
            if last is not None and stamp <= last:
                reason = "replayed or old timestamp"
            elif last is None and stamp + _NEW_STREAM_WINDOW < signing_timestamp_now():
                reason = "new stream more than 60 s in the past"
            else:
                self._streams[key] = stamp  # only after the signature verified
        if reason is None:
            return True
        if not allowed:
            self.stats.rx_bad_signature += 1
            errors.append(
                RxError("rx_bad_signature", f"{msg.get_type()}: {reason}", len(buf), addr)
            )
        return False

    def _remember_peer(self, addr: tuple[str, int]) -> None:
        if addr == self.remote:
            return
        if addr in self._peers:
            self._peers.move_to_end(addr)
            return
        self._peers[addr] = None
        while len(self._peers) > self._max_peers:
            self._peers.popitem(last=False)
