"""The companion's one-call datagram parser gives what pymavlink's parse_char loop gives."""

from __future__ import annotations

import random

from pymavlink.dialects.v10 import common as mavlink1
from pymavlink.dialects.v20 import common as mavlink

from companion.link.datagrams import parse_datagram


def _frames(rng: random.Random) -> bytes:
    """A datagram: MAVLink 2 frames (some signed), a MAVLink 1 frame, junk, a bad CRC, bad
    incompat flags, an unknown message id, a frame cut short."""
    mav = mavlink.MAVLink(None, srcSystem=rng.randrange(1, 255), srcComponent=1)
    if rng.random() < 0.2:
        mav.signing.secret_key = bytes(range(32))
        mav.signing.sign_outgoing = True
    parts = []
    for _ in range(rng.randint(0, 6)):
        kind = rng.random()
        if kind < 0.55:
            msg = rng.choice(
                [
                    mav.attitude_encode(rng.randrange(10**6), 0.1, -0.2, rng.random(), 0, 0, 0),
                    mav.statustext_encode(6, b"mode OFFBOARD"[: rng.randint(0, 13)]),
                    mav.heartbeat_encode(2, 12, 29, 393216, 3),
                    mav.highres_imu_encode(5, *[0.0] * 13, 63),
                ]
            )
            frame = bytearray(msg.pack(mav))
            if rng.random() < 0.1:
                frame[-3 if not mav.signing.sign_outgoing else -16] ^= 0x55  # CRC no longer holds
            if rng.random() < 0.05:
                frame[2] |= 0x02  # an incompat flag nobody knows
            if rng.random() < 0.05:
                frame[7] = 0xEE  # a message id the dialect does not have
            parts.append(bytes(frame))
        elif kind < 0.65:
            v1 = mavlink1.MAVLink(None, srcSystem=3, srcComponent=1)
            parts.append(v1.heartbeat_encode(2, 12, 29, 0, 3).pack(v1))
        elif kind < 0.8:
            parts.append(bytes(rng.randrange(256) for _ in range(rng.randint(1, 9))))
        else:
            whole = mav.attitude_encode(7, 0.1, 0.2, 0.3, 0, 0, 0).pack(mav)
            parts.append(whole[: rng.randint(1, len(whole) - 1)])
    return b"".join(parts)


def _reference(data: bytes):
    mav = mavlink.MAVLink(None)
    mav.robust_parsing = True
    out = []
    msg = mav.parse_char(data)
    while msg is not None:
        out.append(msg)
        msg = mav.parse_char(b"")
    return mav, out, mav.buf_len() > 0


def _seen(msg) -> tuple:
    return (
        msg.get_type(),
        msg.to_dict(),
        bytes(msg.get_msgbuf()),
        getattr(msg, "_signed", None),
        vars(msg.get_header()) if msg.get_type() != "BAD_DATA" else msg.reason,
    )


def test_datagrams_parse_as_parse_char_loops_do():
    rng = random.Random(11)
    for _ in range(3000):
        data = _frames(rng)
        ref_mav, ref, ref_cut = _reference(data)
        mav = mavlink.MAVLink(None)
        mav.robust_parsing = True
        msgs, cut = parse_datagram(mav, data)
        assert [_seen(m) for m in msgs] == [_seen(m) for m in ref], data.hex()
        assert cut == ref_cut
        for counter in ("total_bytes_received", "total_packets_received", "total_receive_errors"):
            assert getattr(mav, counter) == getattr(ref_mav, counter), counter
