"""Malformed datagrams for the fuzz tests (``test_sitl_mavlink``, ``test_fuzz_flights``).

None of them is a valid order to the receiver: random bytes, truncated frames, flipped bytes
(bad CRC), frames for other systems or with NaN fields, MAVLink 1 magic with junk, empty and
oversized datagrams; for the camera port, packets with the right magic and wrong everything
else besides junk.
"""

from __future__ import annotations

import math
import struct

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.contract.camera_packet import HEADER_SIZE, MAGIC, encode_frame

__all__ = ["camera_fuzz", "mavlink_fuzz"]


def mavlink_fuzz(rng: np.random.Generator, mav) -> list[bytes]:
    """Malformed or not-for-us datagrams of every kind (none is a valid order to us)."""
    hb = mav.heartbeat_encode(6, 8, 0, 0, 0).pack(mav)
    wrong_target_sp = mav.set_attitude_target_encode(0, 7, 1, 128, [1, 0, 0, 0], 0, 0, 0, 1.0)
    nan_sp = mav.set_attitude_target_encode(0, 1, 1, 128, [1, 0, 0, 0], math.nan, 0, 0, 0.5)
    unsupported = mav.command_long_encode(
        1, 1, 31_000 + int(rng.integers(0, 999)), 0, *([math.nan] * 7)
    )
    req = mav.command_long_encode(
        1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, float(rng.integers(0, 70_000)), 0, 0, 0, 0, 0, 0
    )
    wrong_cmd = mav.command_long_encode(42, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 4, 6, 0, 0, 0, 0)
    param = mav.param_request_read_encode(1, 1, b"\xff\xfeZZ", int(rng.integers(-5, 500)))
    valid = [m.pack(mav) for m in (wrong_target_sp, nan_sp, unsupported, req, wrong_cmd, param)]
    kind = int(rng.integers(0, 7))
    if kind == 0:  # random bytes
        return [rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes()]
    if kind == 1:  # truncated frame
        return [hb[: int(rng.integers(1, len(hb)))]]
    if kind == 2:  # bad CRC / flipped byte
        b = bytearray(valid[int(rng.integers(0, len(valid)))])
        b[int(rng.integers(1, len(b)))] ^= 0x5A
        return [bytes(b)]
    if kind == 3:  # valid but wrong target / bad values / unsupported
        return [valid[int(rng.integers(0, len(valid)))]]
    if kind == 4:  # several frames and junk glued together
        return [b"".join(valid) + b"\xfd\x09\x00" + hb[: int(rng.integers(1, 10))]]
    if kind == 5:  # MAVLink 1 magic, random rest
        return [b"\xfe" + rng.integers(0, 256, 40, dtype=np.uint8).tobytes()]
    return [b"", b"\xfd" * int(rng.integers(1, 64)), bytes(int(rng.integers(1000, 60_000)))]


def camera_fuzz(rng: np.random.Generator) -> list[bytes]:
    """Malformed camera datagrams: junk, bad magic, a real packet truncated / with flipped
    bytes / with its header fields randomised, and empty or oversized datagrams."""
    image = rng.integers(0, 256, (128, 128), dtype=np.uint8)
    (good,) = encode_frame(image, int(rng.integers(0, 2**32)), int(rng.integers(0, 2**40)))
    kind = int(rng.integers(0, 6))
    if kind == 0:  # random bytes
        return [rng.integers(0, 256, int(rng.integers(0, 400)), dtype=np.uint8).tobytes()]
    if kind == 1:  # the magic, then junk
        return [MAGIC + rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()]
    if kind == 2:  # truncated
        return [good[: int(rng.integers(1, len(good)))]]
    if kind == 3:  # a flipped pixel byte: the frame's CRC must catch it
        b = bytearray(good)
        b[int(rng.integers(HEADER_SIZE, len(b)))] ^= 0xA5
        return [bytes(b)]
    if kind == 4:  # header fields randomised after the magic
        fields = rng.integers(0, 256, HEADER_SIZE - len(MAGIC), dtype=np.uint8).tobytes()
        return [MAGIC + fields + good[HEADER_SIZE:]]
    return [b"", bytes(int(rng.integers(1000, 60_000))), struct.pack("<4sB", MAGIC, 99)]
