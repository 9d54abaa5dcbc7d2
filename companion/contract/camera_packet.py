"""The UDP camera packet: how a camera frame travels from the SITL (or a camera bridge) to the
companion. Part of the companion contract, so it depends on numpy and the standard library only.

One frame is one or more datagrams. Each datagram is a fixed 40-byte little-endian header and a
chunk of the image bytes::

    offset size type  field
         0    4 char  magic         b"VLCM"
         4    1 u8    version       1
         5    1 u8    encoding      1 = mono8 (row-major, row 0 = image top)
         6    2 u16   header_size   40 (bytes before the chunk; lets a later version grow)
         8    4 u32   frame_id      increases by one per rendered frame
        12    8 u64   time_us       capture time, autopilot boot time = sim time (us), the
                                    same clock as MAVLink time_boot_ms / time_usec
        20    2 u16   width         px
        22    2 u16   height        px
        24    4 u32   image_size    bytes of the whole image (width * height for mono8)
        28    4 u32   chunk_offset  where this chunk starts in the image
        32    2 u16   chunk_index   0-based
        34    2 u16   chunk_count   >= 1
        36    4 u32   crc32         zlib.crc32 of the whole image
        40    n bytes chunk

A 128 x 128 mono8 frame (16 KiB) fits one datagram (the UDP maximum is 65,507 bytes on IPv4), so
the SITL sends one datagram per frame; :func:`encode_frame` splits larger frames and
:class:`FrameAssembler` joins them (chunks in any order), dropping incomplete frames when newer ones
complete.
Malformed datagrams raise a :class:`CameraPacketError` subclass naming what was wrong.
"""

from __future__ import annotations

import struct
import zlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

__all__ = [
    "ENCODING_MONO8",
    "HEADER_SIZE",
    "MAGIC",
    "MAX_DATAGRAM_BYTES",
    "VERSION",
    "BadMagicError",
    "CameraFrame",
    "CameraPacket",
    "CameraPacketError",
    "CorruptFrameError",
    "FrameAssembler",
    "InconsistentPacketError",
    "TruncatedPacketError",
    "UnsupportedPacketError",
    "decode_frame",
    "decode_packet",
    "encode_frame",
]

MAGIC = b"VLCM"
VERSION = 1
ENCODING_MONO8 = 1
_HEADER = struct.Struct("<4sBBHIQHHIIHHI")
HEADER_SIZE = _HEADER.size  # 40
MAX_DATAGRAM_BYTES = 65_507
"""Largest UDP payload over IPv4; :func:`encode_frame` never exceeds it."""
_BYTES_PER_PIXEL = {ENCODING_MONO8: 1}


class CameraPacketError(ValueError):
    """Root of every camera-packet error: the datagram is not a valid packet of this format."""


class TruncatedPacketError(CameraPacketError):
    """Fewer bytes than the header, or than the header says the chunk has."""


class BadMagicError(CameraPacketError):
    """The datagram does not start with :data:`MAGIC` (not a camera packet at all)."""


class UnsupportedPacketError(CameraPacketError):
    """A version or encoding this code does not know."""


class InconsistentPacketError(CameraPacketError):
    """Header fields contradict each other (sizes, chunk index/offset)."""


class CorruptFrameError(CameraPacketError):
    """A reassembled image whose CRC-32 differs from the header's."""


@dataclass(frozen=True)
class CameraPacket:
    """One decoded datagram: header fields and this chunk's bytes."""

    frame_id: int
    time_us: int
    width: int
    height: int
    encoding: int
    image_size: int
    chunk_offset: int
    chunk_index: int
    chunk_count: int
    crc32: int
    chunk: bytes


@dataclass(frozen=True)
class CameraFrame:
    """A complete frame.

    Attributes:
        frame_id: the sender's frame counter.
        time_us: capture time on the autopilot's boot clock (sim time), us.
        image: (height, width) uint8 mono8, row 0 = top = body forward.
    """

    frame_id: int
    time_us: int
    image: np.ndarray

    @property
    def time_s(self) -> float:
        return self.time_us * 1e-6


def encode_frame(
    image: np.ndarray,
    frame_id: int,
    time_us: int,
    max_datagram_bytes: int = MAX_DATAGRAM_BYTES,
) -> list[bytes]:
    """Datagrams carrying one mono8 frame (one datagram when it fits).

    Args:
        image: (height, width) uint8.
        frame_id: 0 .. 2**32 - 1.
        time_us: capture time, us, 0 .. 2**64 - 1.
        max_datagram_bytes: datagram size limit, header included (> HEADER_SIZE).
    """
    img = np.ascontiguousarray(image)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"image: expected a 2-D uint8 mono8 array, got {img.shape} {img.dtype}")
    height, width = img.shape
    if not (0 < width < 65536 and 0 < height < 65536):
        raise ValueError(f"image: {width}x{height} does not fit the u16 width/height fields")
    if not 0 <= frame_id < 2**32 or not 0 <= time_us < 2**64:
        raise ValueError(f"frame_id {frame_id} / time_us {time_us} out of the u32 / u64 range")
    if max_datagram_bytes <= HEADER_SIZE or max_datagram_bytes > MAX_DATAGRAM_BYTES:
        raise ValueError(
            f"max_datagram_bytes = {max_datagram_bytes}; expected ({HEADER_SIZE}, "
            f"{MAX_DATAGRAM_BYTES}]"
        )
    data = img.tobytes()
    crc = zlib.crc32(data)
    per_chunk = max_datagram_bytes - HEADER_SIZE
    count = max(1, -(-len(data) // per_chunk))
    if count >= 65536:
        raise ValueError(f"image of {len(data)} bytes needs {count} chunks; at most 65535")
    out = []
    for index in range(count):
        offset = index * per_chunk
        chunk = data[offset : offset + per_chunk]
        header = _HEADER.pack(
            MAGIC,
            VERSION,
            ENCODING_MONO8,
            HEADER_SIZE,
            frame_id,
            time_us,
            width,
            height,
            len(data),
            offset,
            index,
            count,
            crc,
        )
        out.append(header + chunk)
    return out


def decode_packet(datagram: bytes) -> CameraPacket:
    """Parse and validate one datagram.

    Raises:
        TruncatedPacketError, BadMagicError, UnsupportedPacketError, InconsistentPacketError.
    """
    if len(datagram) < HEADER_SIZE:
        if len(datagram) >= 4 and datagram[:4] != MAGIC:
            raise BadMagicError(f"magic {bytes(datagram[:4])!r}; expected {MAGIC!r}")
        raise TruncatedPacketError(
            f"datagram of {len(datagram)} bytes; the header alone is {HEADER_SIZE}"
        )
    (
        magic,
        version,
        encoding,
        header_size,
        frame_id,
        time_us,
        width,
        height,
        image_size,
        offset,
        index,
        count,
        crc,
    ) = _HEADER.unpack_from(datagram)
    if magic != MAGIC:
        raise BadMagicError(f"magic {magic!r}; expected {MAGIC!r}")
    if version != VERSION:
        raise UnsupportedPacketError(f"version {version}; this decoder reads version {VERSION}")
    bpp = _BYTES_PER_PIXEL.get(encoding)
    if bpp is None:
        raise UnsupportedPacketError(f"encoding {encoding}; known: 1 (mono8)")
    if header_size < HEADER_SIZE or header_size > len(datagram):
        raise InconsistentPacketError(
            f"header_size {header_size}; expected >= {HEADER_SIZE} and <= the datagram "
            f"({len(datagram)} bytes)"
        )
    if width == 0 or height == 0 or image_size != width * height * bpp:
        raise InconsistentPacketError(
            f"image_size {image_size} != width {width} x height {height} x {bpp} byte(s)"
        )
    if count == 0 or index >= count:
        raise InconsistentPacketError(f"chunk_index {index} / chunk_count {count}")
    chunk = bytes(datagram[header_size:])
    if offset + len(chunk) > image_size:
        raise InconsistentPacketError(
            f"chunk at offset {offset} of {len(chunk)} bytes overruns the {image_size}-byte image"
        )
    if count == 1 and (offset != 0 or len(chunk) != image_size):
        raise TruncatedPacketError(
            f"single-chunk frame carries {len(chunk)} bytes at offset {offset}; expected "
            f"{image_size} at 0"
        )
    return CameraPacket(
        frame_id=frame_id,
        time_us=time_us,
        width=width,
        height=height,
        encoding=encoding,
        image_size=image_size,
        chunk_offset=offset,
        chunk_index=index,
        chunk_count=count,
        crc32=crc,
        chunk=chunk,
    )


def _to_frame(packet: CameraPacket, data: bytes) -> CameraFrame:
    if zlib.crc32(data) != packet.crc32:
        raise CorruptFrameError(
            f"frame {packet.frame_id}: CRC-32 {zlib.crc32(data):#010x} != header "
            f"{packet.crc32:#010x}"
        )
    image = np.frombuffer(data, dtype=np.uint8).reshape(packet.height, packet.width)
    return CameraFrame(frame_id=packet.frame_id, time_us=packet.time_us, image=image)


def decode_frame(datagram: bytes) -> CameraFrame:
    """A whole frame from a single-datagram packet (what the SITL sends for 128 x 128).

    Raises:
        CameraPacketError: malformed, or a chunk of a multi-datagram frame (use
            :class:`FrameAssembler` for those).
    """
    packet = decode_packet(datagram)
    if packet.chunk_count != 1:
        raise InconsistentPacketError(
            f"frame {packet.frame_id} spans {packet.chunk_count} datagrams; use FrameAssembler"
        )
    return _to_frame(packet, packet.chunk)


class FrameAssembler:
    """Joins chunks into frames; keeps at most ``max_pending`` incomplete frames (oldest dropped).

    Chunks may arrive in any order. ``add`` returns the completed frame, or None while chunks
    are missing. When a frame completes, every incomplete frame older than it (by ``frame_id``,
    modulo 2**32) is dropped: on a lossy link its missing chunk may never come, and a newer
    picture makes it useless anyway. ``dropped`` counts incomplete frames dropped, ``corrupt``
    frames whose CRC failed.
    """

    def __init__(self, max_pending: int = 4) -> None:
        if max_pending < 1:
            raise ValueError(f"max_pending = {max_pending}; expected >= 1")
        self._max_pending = max_pending
        self._pending: OrderedDict[int, tuple[CameraPacket, dict[int, bytes]]] = OrderedDict()
        self.dropped = 0
        self.corrupt = 0

    def add(self, datagram: bytes) -> CameraFrame | None:
        """Feed one datagram. Raises CameraPacketError for a malformed one."""
        packet = decode_packet(datagram)
        if packet.chunk_count == 1:
            self._drop_older_than(packet.frame_id)
            return self._finish(packet, packet.chunk)
        entry = self._pending.get(packet.frame_id)
        if entry is None:
            entry = (packet, {})
            self._pending[packet.frame_id] = entry
            while len(self._pending) > self._max_pending:
                self._pending.popitem(last=False)
                self.dropped += 1
        first, chunks = entry
        if (first.image_size, first.chunk_count, first.crc32) != (
            packet.image_size,
            packet.chunk_count,
            packet.crc32,
        ):
            del self._pending[packet.frame_id]
            raise InconsistentPacketError(
                f"frame {packet.frame_id}: chunk {packet.chunk_index} disagrees with chunk "
                f"{first.chunk_index} on size/count/crc"
            )
        chunks[packet.chunk_offset] = packet.chunk
        if len(chunks) < packet.chunk_count:
            return None
        del self._pending[packet.frame_id]
        self._drop_older_than(packet.frame_id)
        data = b"".join(chunks[k] for k in sorted(chunks))
        if len(data) != packet.image_size:
            raise InconsistentPacketError(
                f"frame {packet.frame_id}: chunks give {len(data)} bytes, expected "
                f"{packet.image_size}"
            )
        return self._finish(packet, data)

    def _drop_older_than(self, frame_id: int) -> None:
        for pending_id in list(self._pending):
            if 0 < (frame_id - pending_id) % 2**32 < 2**31:  # serial arithmetic (RFC 1982)
                del self._pending[pending_id]
                self.dropped += 1

    def _finish(self, packet: CameraPacket, data: bytes) -> CameraFrame:
        try:
            return _to_frame(packet, data)
        except CorruptFrameError:
            self.corrupt += 1
            raise
