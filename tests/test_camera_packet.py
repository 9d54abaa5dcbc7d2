"""The UDP camera packet (companion contract): round trips and every malformed-input error."""

from __future__ import annotations

import contextlib
import struct

import numpy as np
import pytest

from companion.contract.camera_packet import (
    HEADER_SIZE,
    MAX_DATAGRAM_BYTES,
    BadMagicError,
    CorruptFrameError,
    FrameAssembler,
    InconsistentPacketError,
    TruncatedPacketError,
    UnsupportedPacketError,
    decode_frame,
    decode_packet,
    encode_frame,
)


@pytest.fixture
def image() -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (128, 128), dtype=np.uint8)


def test_one_datagram_per_128px_frame_round_trips(image):
    datagrams = encode_frame(image, frame_id=7, time_us=1_234_567)
    assert len(datagrams) == 1 and len(datagrams[0]) == HEADER_SIZE + 128 * 128
    assert len(datagrams[0]) <= MAX_DATAGRAM_BYTES
    frame = decode_frame(datagrams[0])
    assert frame.frame_id == 7 and frame.time_us == 1_234_567 and frame.time_s == 1.234567
    np.testing.assert_array_equal(frame.image, image)


def test_large_frame_splits_and_reassembles_in_any_order():
    big = np.random.default_rng(1).integers(0, 256, (480, 640), dtype=np.uint8)
    datagrams = encode_frame(big, 3, 10, max_datagram_bytes=10_000)
    assert len(datagrams) == -(-big.size // (10_000 - HEADER_SIZE))
    asm = FrameAssembler()
    out = [asm.add(d) for d in reversed(datagrams)]
    assert all(o is None for o in out[:-1])
    np.testing.assert_array_equal(out[-1].image, big)
    with pytest.raises(InconsistentPacketError, match="FrameAssembler"):
        decode_frame(datagrams[0])


def test_assembler_drops_incomplete_frames_beyond_its_window(image):
    asm = FrameAssembler(max_pending=2)
    for fid in range(4):
        asm.add(encode_frame(image, fid, 0, max_datagram_bytes=5000)[0])  # first chunk only
    assert asm.dropped == 2


@pytest.mark.parametrize(
    ("mutate", "error", "match"),
    [
        (lambda d: d[:10], TruncatedPacketError, "header alone"),
        (lambda d: b"XXXX" + d[4:], BadMagicError, "magic"),
        (lambda d: d[:4] + b"\x09" + d[5:], UnsupportedPacketError, "version"),
        (lambda d: d[:5] + b"\x07" + d[6:], UnsupportedPacketError, "encoding"),
        (lambda d: d[:-100], TruncatedPacketError, "single-chunk"),
        (lambda d: d[:20] + struct.pack("<H", 64) + d[22:], InconsistentPacketError, "image_size"),
        (lambda d: d[:32] + struct.pack("<HH", 2, 2) + d[36:], InconsistentPacketError, "chunk"),
        (lambda d: d[:6] + struct.pack("<H", 10) + d[8:], InconsistentPacketError, "header_size"),
    ],
)
def test_malformed_packets_raise_typed_errors(image, mutate, error, match):
    datagram = encode_frame(image, 1, 2)[0]
    with pytest.raises(error, match=match):
        decode_packet(mutate(datagram))


def test_corrupted_pixels_fail_the_crc(image):
    datagram = bytearray(encode_frame(image, 1, 2)[0])
    datagram[HEADER_SIZE + 5] ^= 0xFF
    with pytest.raises(CorruptFrameError, match="CRC"):
        decode_frame(bytes(datagram))


def test_random_bytes_never_escape_as_other_errors():
    rng = np.random.default_rng(2)
    for _ in range(2000):
        data = rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
        if rng.random() < 0.5:
            data = b"VLCM\x01\x01" + data
        with contextlib.suppress(  # only these typed errors may escape; anything else fails
            TruncatedPacketError,
            BadMagicError,
            UnsupportedPacketError,
            InconsistentPacketError,
            CorruptFrameError,
        ):
            decode_frame(data)


def test_encode_rejects_what_the_format_cannot_carry(image):
    with pytest.raises(ValueError, match="mono8"):
        encode_frame(image.astype(np.float32), 0, 0)
    with pytest.raises(ValueError, match="u32"):
        encode_frame(image, 2**32, 0)
