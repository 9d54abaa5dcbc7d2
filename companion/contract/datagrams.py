"""What both ends of a visland UDP link do with a datagram before any MAVLink parse.

A flood of junk (a scanner, a broken device, the fuzz test's 2,000 datagrams a second and port)
must cost a receiver a ``recvfrom`` and a few C-speed checks per datagram, not a Python loop per
byte: pymavlink's robust parser turns 30 kB of zeros into one ``BAD_DATA`` only after a
byte-by-byte scan (~77 ms measured on the 2-core CI machine), and a receiver busy with that lets
its socket buffer overflow, where the kernel drops the autopilot's telemetry and the camera's
frames alike. The SITL (:mod:`sitl_sim.mavlink.endpoint`) and the companion
(:mod:`companion.link.connection`, :mod:`companion.camera`) share these limits.
"""

from __future__ import annotations

__all__ = ["MAX_DATAGRAM_BYTES", "RCVBUF_BYTES", "RX_DATAGRAMS_PER_POLL", "frame_start"]

MAX_DATAGRAM_BYTES = 4096
"""Larger MAVLink datagrams are dropped unparsed: a MAVLink 2 frame is at most 280 bytes and
routers pack frames into MTU-sized (1500-byte) datagrams; only junk is bigger."""

RCVBUF_BYTES = 4 * 1024 * 1024
"""``SO_RCVBUF`` asked for on every MAVLink and camera socket (Linux doubles it and caps the
request at ``net.core.rmem_max``). The default (212,992 bytes on Linux) holds seven of the
flood's 30 kB datagrams: a receiver descheduled for a few milliseconds on a busy board loses
what came next. 4 MiB holds about half a second of the fuzz test's flood on one port."""

RX_DATAGRAMS_PER_POLL = 256
"""The most datagrams one receive call reads from one socket before it returns, so that a
flood on one socket delays, but never starves, the others (the companion's camera, the
SITL's physics). What is left waits in the socket buffer for the next call."""

_START_BYTES = (b"\xfd", b"\xfe")  # MAVLink 2 and MAVLink 1 start-of-frame markers


def frame_start(data: bytes) -> int:
    """The index of the first MAVLink start byte (``0xFD`` or ``0xFE``) in ``data``;
    ``len(data)`` when there is none. Found at C speed (``bytes.find``): the junk before it is
    one error, not one per byte."""
    starts = [i for i in (data.find(m) for m in _START_BYTES) if i >= 0]
    return min(starts) if starts else len(data)
