"""The two hot paths of an MCAP flight log's writer, written out against mcap 1.6.0's
:class:`~mcap.writer.Writer` (``pyproject.toml`` pins it): a message appended to the open chunk,
and a full chunk compressed and written.

Both write what the Writer itself writes (its statistics, the chunk's message index and time
range, the Chunk, MessageIndex and chunk-index records: tests/test_flightlog.py compares the
files byte for byte), but:

* :func:`message_appender` without the Writer's per-call Message object and field-by-field
  record builder (a third of the time of ``add_message``);
* :func:`install_chunk_compressor` with the zstd compressor given, where the Writer calls
  ``zstandard.compress`` at its default level 3: the SITL and the companion each compress ~30
  kB of JSON a frame (mostly base64 images), and level 1 does it 3x faster for chunks ~20 %
  larger. The chunk is still a standard ``zstd`` chunk any reader opens.

Each returns None (nothing installed) where the Writer is not laid out as expected; the
caller then uses the Writer's own methods.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable

from mcap.records import Chunk, ChunkIndex, MessageIndex
from mcap.writer import CompressionType, IndexType, Writer

__all__ = ["install_chunk_compressor", "message_appender"]

_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
"""An MCAP Message record's head: opcode 0x05, record length, channel id, sequence, log time,
publish time (the data follows)."""


def message_appender(writer: Writer) -> Callable[[int, int, int, bytes], None] | None:
    """``append(channel_id, sequence, log_time_ns, data)``: ``writer.add_message`` of a
    chunked writer (publish time = log time), or None (see the module docstring)."""
    try:
        stats = writer._Writer__statistics  # type: ignore[attr-defined]
        chunk = writer._Writer__chunk_builder  # type: ignore[attr-defined]
        chunk_size = writer._Writer__chunk_size  # type: ignore[attr-defined]
        records = chunk.record_writer
        counts, indices = stats.channel_message_counts, chunk.message_indices
        records._buffer.tell()
    except AttributeError:
        return None
    head = _MESSAGE_HEAD.pack

    def append(channel_id: int, sequence: int, log_time: int, data: bytes) -> None:
        if stats.message_count == 0:
            stats.message_start_time = log_time
        else:
            stats.message_start_time = min(log_time, stats.message_start_time)
        stats.message_end_time = max(log_time, stats.message_end_time)
        counts[channel_id] += 1
        stats.message_count += 1
        if chunk.num_messages == 0:
            chunk.message_start_time = log_time
        else:
            chunk.message_start_time = min(chunk.message_start_time, log_time)
        chunk.message_end_time = max(chunk.message_end_time, log_time)
        buffer = records._buffer  # replaced whenever a chunk ends
        index = indices.get(channel_id)
        if index is None:
            index = indices[channel_id] = MessageIndex(channel_id=channel_id, records=[])
        index.records.append((log_time, buffer.tell()))
        chunk.num_messages += 1
        buffer.write(head(0x05, 22 + len(data), channel_id, sequence, log_time, log_time))
        buffer.write(data)
        if buffer.tell() > chunk_size:
            writer._Writer__finalize_chunk()  # type: ignore[attr-defined]

    return append


def install_chunk_compressor(writer: Writer, compress: Callable[[bytes], bytes]) -> bool:
    """Make a zstd-chunked ``writer`` compress its chunks with ``compress`` (the Writer's chunk
    finalisation, which ``flush`` and ``finish`` call, shadowed on this instance); False where
    nothing was installed (see the module docstring)."""
    try:
        chunk_builder = writer._Writer__chunk_builder  # type: ignore[attr-defined]
        stats = writer._Writer__statistics  # type: ignore[attr-defined]
        stream = writer._Writer__stream  # type: ignore[attr-defined]
        records = writer._Writer__record_builder  # type: ignore[attr-defined]
        flush = writer._Writer__flush  # type: ignore[attr-defined]
        chunk_indices = writer._Writer__chunk_indices  # type: ignore[attr-defined]
        crcs = writer._Writer__enable_crcs  # type: ignore[attr-defined]
        index_types = writer._Writer__index_types  # type: ignore[attr-defined]
        zstd = writer._Writer__compression == CompressionType.ZSTD  # type: ignore[attr-defined]
        writer._Writer__finalize_chunk  # type: ignore[attr-defined]  # noqa: B018
    except AttributeError:
        return False
    if chunk_builder is None or not zstd:
        return False

    def finalize_chunk() -> None:
        if chunk_builder.num_messages == 0:
            return
        stats.chunk_count += 1
        chunk_data = chunk_builder.end()
        compressed = compress(chunk_data)
        chunk = Chunk(
            compression="zstd",
            data=compressed,
            message_start_time=chunk_builder.message_start_time,
            message_end_time=chunk_builder.message_end_time,
            uncompressed_crc=zlib.crc32(chunk_data) if crcs else 0,
            uncompressed_size=len(chunk_data),
        )
        flush()
        chunk_start_offset = stream.tell()
        chunk.write(records)
        chunk_index = ChunkIndex(
            message_start_time=chunk.message_start_time,
            message_end_time=chunk.message_end_time,
            chunk_start_offset=chunk_start_offset,
            chunk_length=records.count,
            message_index_offsets={},
            message_index_length=0,
            compression=chunk.compression,
            compressed_size=len(compressed),
            uncompressed_size=chunk.uncompressed_size,
        )
        flush()
        message_index_start_offset = stream.tell()
        if index_types & IndexType.MESSAGE:
            for channel_id, index in chunk_builder.message_indices.items():
                chunk_index.message_index_offsets[channel_id] = (
                    message_index_start_offset + records.count
                )
                index.write(records)
        chunk_index.message_index_length = records.count
        flush()
        chunk_indices.append(chunk_index)
        chunk_builder.reset()

    writer._Writer__finalize_chunk = finalize_chunk  # type: ignore[attr-defined]
    return True
