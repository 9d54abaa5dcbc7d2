"""The companion's udpin link sends to the autopilot alone (issue 18: a link that is private on a
shared network). Real UDP sockets on loopback, real MAVLink 2 bytes; the link's clock is
injected, so nothing here depends on the machine's speed."""

from __future__ import annotations

import os
import select
import socket
from collections.abc import Iterator

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink

from companion.contract.datagrams import MAX_DATAGRAM_BYTES, RCVBUF_BYTES, RX_DATAGRAMS_PER_POLL
from companion.link import MavlinkLink
from training.exec.fly import free_udp_port


class _Node:
    """A UDP socket speaking MAVLink 2 as system ``sysid`` / component ``compid``."""

    def __init__(self, sysid: int, compid: int, sock: socket.socket | None = None) -> None:
        if sock is None:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(("127.0.0.1", 0))
        self.sock = sock
        self.mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True

    def send(self, msg, to: tuple[str, int]) -> None:
        self.sock.sendto(msg.pack(self.mav), to)

    def heartbeat(self, to: tuple[str, int]) -> None:
        self.send(
            self.mav.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 4
            ),
            to,
        )

    def received(self, timeout_s: float = 0.0) -> list[str]:
        """The message types waiting (after up to ``timeout_s`` for the first one)."""
        out: list[str] = []
        wait = timeout_s
        while select.select([self.sock], [], [], wait)[0]:
            data = self.sock.recv(65_535)
            for msg in self.parser.parse_buffer(data) or []:
                out.append(msg.get_type())
            wait = 0.0
        return out

    def close(self) -> None:
        self.sock.close()


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def nodes() -> Iterator[dict[str, _Node]]:
    made = {
        "autopilot": _Node(1, 1),
        "stranger": _Node(42, 190),
        "restarted": _Node(1, 1),
    }
    try:
        yield made
    finally:
        for n in made.values():
            n.close()


@pytest.fixture
def udpin() -> Iterator[tuple[MavlinkLink, tuple[str, int], _Clock]]:
    """A udpin link on a free loopback port (3 s link timeout, injected clock): the link, the
    address to send to it, its clock."""
    port = free_udp_port()
    clock = _Clock()
    link = MavlinkLink(f"udpin:127.0.0.1:{port}", clock=clock, link_timeout_s=3.0)
    try:
        yield link, ("127.0.0.1", port), clock
    finally:
        link.close()


def _poll_until(link: MavlinkLink, done, what: str) -> None:
    for _ in range(200):
        link.poll(lambda _m, _t: None)
        if done():
            return
        select.select([link.fileno()], [], [], 0.05)
    raise AssertionError(f"the link never got {what}")


def _setpoint(link: MavlinkLink) -> None:
    assert link.send_setpoint(0.5, (0.0, 0.0, 0.0), 1000) is not None


def test_udpin_link_sends_only_to_the_autopilot(nodes, udpin):
    link, to, _ = udpin
    ap, stranger = nodes["autopilot"], nodes["stranger"]
    # someone else on the network talks to the port first: garbage and a GCS's message
    stranger.sock.sendto(b"\xfd\x09garbage" * 3, to)
    stranger.send(stranger.mav.system_time_encode(0, 0), to)
    link.poll(lambda _m, _t: None)
    ap.heartbeat(to)
    _poll_until(link, lambda: link.connected, "the autopilot's HEARTBEAT")
    assert link.peer == ap.sock.getsockname()
    assert link.counters.rx_other_systems >= 1
    stranger.received()  # what it got before the autopilot was heard (our HEARTBEAT)

    _setpoint(link)
    assert "SET_ATTITUDE_TARGET" in ap.received(timeout_s=2.0)
    # loopback delivers inside sendto: had the stranger been sent to, it would be waiting
    assert stranger.received() == []

    # a HEARTBEAT spoofing the autopilot from elsewhere while the autopilot is alive
    spoof = _Node(1, 1, sock=stranger.sock)  # the stranger's socket, the autopilot's ids
    spoof.mav.seq = 50  # ahead of the autopilot's: not a stale (reordered) HEARTBEAT
    spoof.heartbeat(to)
    _poll_until(link, lambda: link.counters.rx_peer_mismatch == 1, "the spoof")
    assert link.peer == ap.sock.getsockname()
    _setpoint(link)
    assert "SET_ATTITUDE_TARGET" in ap.received(timeout_s=2.0)
    assert stranger.received() == []
    # a datagram the OS will not send (over UDP's 65,507 bytes) is lost and counted
    link.conn.write(b"\x00" * 70_000)
    assert link.counters.tx_errors == 1


def test_udpin_peer_moves_only_after_the_link_is_lost(nodes, udpin):
    link, to, clock = udpin
    ap, restarted = nodes["autopilot"], nodes["restarted"]
    ap.heartbeat(to)
    _poll_until(link, lambda: link.connected, "the autopilot's HEARTBEAT")
    # the autopilot goes silent; 3 s later the link is lost
    clock.t += 3.5
    link.poll(lambda _m, _t: None)
    assert not link.connected
    # it comes back from another port (restarted; its sequence numbers a new stream)
    restarted.mav.seq = 100
    restarted.heartbeat(to)
    _poll_until(link, lambda: link.connected, "the restarted autopilot's HEARTBEAT")
    assert link.peer == restarted.sock.getsockname()
    assert any(e.kind == "peer" and "moved" in e.text for e in link.pop_events())
    ap.received()
    _setpoint(link)
    assert "SET_ATTITUDE_TARGET" in restarted.received(timeout_s=2.0)
    assert ap.received() == []


def test_udpout_links_have_no_peer(nodes):
    ap = nodes["autopilot"]
    host, port = ap.sock.getsockname()
    link = MavlinkLink(f"udpout:{host}:{port}", clock=_Clock())
    try:
        link.poll(lambda _m, _t: None)  # our HEARTBEAT: the autopilot learns our address
        assert select.select([ap.sock], [], [], 2.0)[0]
        _, ours = ap.sock.recvfrom(65_535)
        ap.heartbeat(ours)
        _poll_until(link, lambda: link.connected, "the autopilot's HEARTBEAT")
        _setpoint(link)
        assert "SET_ATTITUDE_TARGET" in ap.received(timeout_s=2.0)
        assert link.peer is None  # udpout sends to its one address anyway
    finally:
        link.close()


# --------------------------------------------------------------------------- a flood (issue 31)


def _attitude(ap: _Node, to: tuple[str, int], time_boot_ms: int) -> None:
    ap.send(ap.mav.attitude_encode(time_boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), to)


def _poll_for(link: MavlinkLink, kind: str) -> tuple[list[str], int]:
    """Poll until a ``kind`` message is delivered: the types delivered and the polls taken."""
    seen: list[str] = []
    for polls in range(1, 201):
        link.poll(lambda m, _t: seen.append(m.get_type()))
        if kind in seen:
            return seen, polls
        select.select([link.fileno()], [], [], 0.05)
    raise AssertionError(f"the link never delivered {kind}; got {seen}")


def test_a_flood_from_another_address_is_refused_before_any_parse(nodes, udpin):
    """Once the autopilot is pinned, a stranger's datagrams cost a ``recvfrom`` each: none
    reaches the parser (no rx_bad_data, no rx_other_systems, no spoofed HEARTBEAT), each is
    counted as rx_peer_mismatch, and the autopilot's message behind them is delivered."""
    link, to, _ = udpin
    ap, stranger = nodes["autopilot"], nodes["stranger"]
    ap.heartbeat(to)
    _poll_until(link, lambda: link.connected, "the autopilot's HEARTBEAT")
    before = (link.counters.rx_bad_data, link.counters.rx_other_systems)
    # (few large ones: a machine whose rmem_max caps the buffer at 425,984 bytes keeps them all)
    junk = [bytes(30_000)] * 2 + [b"\xfd\x09garbage", b"\x00" * 100] * 29
    for datagram in junk:
        stranger.sock.sendto(datagram, to)
    stranger.send(stranger.mav.system_time_encode(0, 0), to)
    spoof = _Node(1, 1, sock=stranger.sock)  # the autopilot's ids from the stranger's address
    spoof.mav.seq = 50
    spoof.heartbeat(to)
    _attitude(ap, to, 1234)
    seen, _ = _poll_for(link, "ATTITUDE")
    assert seen.count("HEARTBEAT") == 0  # the spoof never reached the parser
    assert link.counters.rx_peer_mismatch == 62
    assert (link.counters.rx_bad_data, link.counters.rx_other_systems) == before
    assert link.peer == ap.sock.getsockname()


def test_junk_before_the_peer_is_known_is_skipped_at_c_speed(nodes, udpin):
    """Before the autopilot is heard every datagram is parsed, but an oversized one is one
    rx_bad_data (not one per byte, as pymavlink's robust parser would scan it), and junk
    before a frame is cut off: the frame behind it is still read."""
    link, to, _ = udpin
    ap, stranger = nodes["autopilot"], nodes["stranger"]
    stranger.sock.sendto(bytes(MAX_DATAGRAM_BYTES + 1), to)
    stranger.sock.sendto(b"", to)
    hb = ap.mav.heartbeat_encode(
        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 4
    ).pack(ap.mav)
    ap.sock.sendto(b"\x00\x01\x02" * 40 + hb, to)
    _poll_until(link, lambda: link.connected, "the HEARTBEAT behind the junk")
    assert link.counters.rx_bad_data == 3  # the oversized, the empty, the junk before the frame
    assert link.peer == ap.sock.getsockname()


def test_one_poll_reads_a_bounded_number_of_datagrams(nodes, udpin):
    """A poll returns after RX_DATAGRAMS_PER_POLL datagrams (rx_deferred), so the companion's
    loop gets back to its camera; the next polls read on to the autopilot's message."""
    link, to, _ = udpin
    ap, stranger = nodes["autopilot"], nodes["stranger"]
    ap.heartbeat(to)
    _poll_until(link, lambda: link.connected, "the autopilot's HEARTBEAT")
    flood = RX_DATAGRAMS_PER_POLL + 10
    for _ in range(flood):
        stranger.sock.sendto(b"\x00" * 8, to)
    _attitude(ap, to, 1234)
    _, polls = _poll_for(link, "ATTITUDE")
    assert polls == 2 and link.counters.rx_deferred == 1, (polls, link.counters)
    assert link.counters.rx_peer_mismatch == flood


def test_the_udp_socket_asks_for_a_large_receive_buffer(udpin):
    link, _, _ = udpin
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as plain:
        default = plain.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        plain.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        granted = plain.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    got = link.conn.port.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    assert got == granted, (got, granted, default)
