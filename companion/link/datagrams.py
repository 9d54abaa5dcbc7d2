"""One UDP datagram's MAVLink messages, parsed in one call.

pymavlink's connection reads a datagram through ``recv_msg``: one ``parse_char`` state-machine
step per message, each behind a ``recv`` call (~20 us a message; the companion receives ~170
a simulated second from a SITL). :func:`parse_datagram` walks the datagram's frames itself and
hands each whole frame to the codec's ``decode`` — what ``parse_char`` does with a frame once it
has all of it — so the messages, their fields and the codec's counters are those of the
``parse_char`` loop (with ``robust_parsing``: junk, bad flags and frames ``decode`` refuses come
back as ``BAD_DATA`` messages; a frame cut short by the datagram's end is reported, as a
``parse_char`` loop leaves it in the buffer). The test parses random datagrams both ways.
:func:`size_receive_buffer` asks for the UDP socket's receive buffer.
"""

from __future__ import annotations

import logging
import socket
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.contract.datagrams import RCVBUF_BYTES

__all__ = ["parse_datagram", "size_receive_buffer", "whole_datagrams"]

_V1, _V2 = mavlink.PROTOCOL_MARKER_V1, mavlink.PROTOCOL_MARKER_V2
_SIGNED = mavlink.MAVLINK_IFLAG_SIGNED
_SIGNATURE = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN

log = logging.getLogger("visland.companion.link")


def parse_datagram(mav: Any, data: bytes) -> tuple[list[Any], bool]:
    """``(messages, cut)``: what a ``robust_parsing`` codec ``mav`` with an empty buffer gives
    for ``data`` through ``parse_char(data)`` and then ``parse_char(b"")`` until it returns
    None, with the same codec counters (bytes, packets, errors); ``cut``: bytes were left over
    (an incomplete frame). The codec's buffer is left empty. Its ``callback`` is not called
    (the caller checks there is none)."""
    mav.total_bytes_received += len(data)
    out: list[Any] = []
    i, end = 0, len(data)
    while i < end:
        magic = data[i]
        if magic != _V1 and magic != _V2:
            j = i + 1
            while j < end and data[j] != _V1 and data[j] != _V2:
                j += 1
            out.append(mavlink.MAVLink_bad_data(bytearray(data[i:j]), "Bad prefix"))
            mav.total_receive_errors += 1
            i = j
            continue
        if end - i < 3:
            return _counted(mav, out), True
        flags = data[i + 2]
        header = mavlink.HEADER_LEN_V2 if magic == _V2 else mavlink.HEADER_LEN_V1
        length = data[i + 1] + header + 2
        if magic == _V2 and flags & _SIGNED:
            length += _SIGNATURE
        if end - i < length:
            return _counted(mav, out), True
        frame = bytearray(data[i : i + length])
        i += length
        try:
            if magic == _V2 and flags & ~_SIGNED:  # pymavlink's words (its length is reset)
                raise mavlink.MAVError(
                    f"invalid incompat_flags 0x{flags:x} 0x{magic:x} {header + 2}"
                )
            out.append(mav.decode(frame))
        except mavlink.MAVError as reason:
            out.append(mavlink.MAVLink_bad_data(frame, reason.message))
            mav.total_receive_errors += 1
    return _counted(mav, out), False


def _counted(mav: Any, messages: list[Any]) -> list[Any]:
    mav.total_packets_received += len(messages)
    return messages


def whole_datagrams(conn: Any) -> bool:
    """Whether a pymavlink connection may be read a datagram at a time: udpin, its codec's
    buffer empty, nothing that needs its ``recv_msg`` (the first byte's version check, raw
    logs, a codec callback, strict parsing)."""
    return (
        getattr(conn, "udp_server", False)
        and not conn.first_byte
        and conn.logfile is None
        and conn.logfile_raw is None
        and conn.mav.robust_parsing
        and conn.mav.callback is None
        and not conn.mav.buf_len()
    )


def size_receive_buffer(sock: socket.socket) -> None:
    """Ask for :data:`RCVBUF_BYTES` of receive buffer; say once when the OS gives less (Linux
    caps the request at ``net.core.rmem_max``: ``sysctl -w net.core.rmem_max=4194304``)."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        got = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    except OSError as exc:
        log.warning("MAVLink socket: SO_RCVBUF not set (%s)", exc)
        return
    if got < RCVBUF_BYTES:  # Linux reports twice what it grants (its bookkeeping overhead)
        log.warning(
            "MAVLink socket: receive buffer %d bytes, asked for %d (net.core.rmem_max caps it;"
            " a flood on the port then costs telemetry sooner)",
            got,
            RCVBUF_BYTES,
        )
