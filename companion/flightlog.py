"""Flight logs: MCAP files written while flying, crash-tolerant, readable after a crash.

The topics and schemas here are part of the companion's contract: the SITL, the expert's data
collection and the companion all write them, and training reads them. Conventions (DESIGN.md,
shared/reference/mcap_notes.md):

* one file per flight and process; JSON messages with a jsonschema whose ``title`` is the schema
  name (Foxglove plots them directly), generated from the contract's record of that schema
  (:mod:`companion.contract.records`; ``mavlink.NAME`` from pymavlink's fields), never guessed
  from a message; camera frames as ``foxglove.RawImage`` mono8 (lossless, base64 ``data`` in
  JSON encoding); ground truth pose also as ``foxglove.PoseInFrame``;
* log time = the file's epoch (wall time at the start) + sim time, in ns; every message also
  carries ``time_s`` (sim time);
* small zstd chunks, flushed whenever 1 s of wall time or 1 s of sim time has passed since the
  last flush, so a killed process loses at most the last second;
* a *reproducible* log (``reproducible=True``: in-process rollouts and expert labels, which are
  renamed into place only when complete) has the fixed epoch :data:`REPRODUCIBLE_EPOCH_NS`
  (2000-01-01T00:00:00Z; log time = that + sim time) and flushes on sim time only: the same
  flight gives the same bytes on any host, worker or backend;
* the effective configuration goes into MCAP metadata records at the start of the file.

Reading (:func:`read_log`) never seeks: a truncated file yields every message up to the cut and
says so (``FlightLog.truncated``); a file that is not MCAP at all raises :class:`FlightLogError`.
"""

from __future__ import annotations

import base64
import contextlib
import json
import math
import operator
import struct
import time
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from companion.contract.record_base import TIME_S, LogRecord
from companion.contract.records import (
    Pose,
    PoseInFrameRecord,
    Quaternion,
    RawImageRecord,
    Timestamp,
    Vector3,
    mavlink_schema_json,
    schema_json,
)
from companion.contract.topics import TOPIC_GROUNDTRUTH_POSE, TOPIC_IMAGE
from companion.mcap_chunks import install_chunk_compressor, message_appender

__all__ = [
    "FlightLog",
    "FlightLogError",
    "FlightLogWriter",
    "jsonable",
    "read_log",
]


_FLUSH_PERIOD_S = 1.0
_COMPACT_JSON = json.JSONEncoder(separators=(",", ":"))  # = json.dumps(separators=...), reused
_STRICT_JSON = json.JSONEncoder(separators=(",", ":"), allow_nan=False)
"""The same text where a message needs no :func:`_jsonable` (numpy arrays and non-float numpy
scalars raise TypeError, NaN/inf ValueError: those take the converting path)."""
_CHUNK_BYTES = 256 * 1024
_ZSTD_LEVEL = 1
"""The chunks' zstd level (:mod:`companion.mcap_chunks`): 3x faster than the Writer's level 3,
chunks ~20 % larger."""
_IMAGE_DATA = "\x00"
"""Stand-in for an image's base64 text while the rest of its record is encoded (JSON writes it
as the 6 characters ``"\\u0000"``, which no base64 text is): the text is then put in its
place as it is, since base64 needs no JSON escaping (encoding 22 kB of it through ``json`` cost
more than the rest of the frame's records)."""
_IMAGE_DATA_JSON = b'"data":"\\u0000"'


def _schema(name: str) -> dict[str, Any]:
    """The MCAP schema record's data for a schema name: the declared record's jsonschema
    (:mod:`companion.contract.records`), pymavlink's fields for ``mavlink.NAME``; a name
    neither declares gets an open object."""
    return schema_json(name) or mavlink_schema_json(name) or {"title": name, "type": "object"}


def _jsonable_slow(value: Any) -> Any:
    """The definition of what a message becomes in JSON (any type; see :func:`_jsonable`)."""
    if isinstance(value, np.ndarray):
        return [_jsonable_slow(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None  # JSON has no NaN: null = "not defined" (an invalid radar reading)
    if isinstance(value, Mapping):
        return {str(k): _jsonable_slow(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable_slow(v) for v in value]
    if isinstance(value, PurePath):
        return str(value)
    return value


_NUMPY_SCALARS: dict[type, type] = {
    np.float64: float,
    np.float32: float,
    np.int64: int,
    np.int32: int,
    np.uint8: int,
    np.bool_: bool,
}
"""Exact numpy scalar type -> the Python type its ``.item()`` returns (SITL values are these)."""


def _jsonable_leaf(v: Any) -> Any:
    conv = _NUMPY_SCALARS.get(type(v))
    if conv is float:
        f = float(v)
        return f if f - f == 0.0 else None
    if conv is not None:
        return conv(v)
    return _jsonable(v)


def _jsonable(value: Any) -> Any:
    """``value`` with numpy arrays/scalars as lists/Python numbers, non-finite floats as None,
    mappings as dicts with str keys, tuples as lists: exactly :func:`_jsonable_slow`, faster.

    The SITL writes a few hundred messages per simulated second; the isinstance chain (ABC
    ``Mapping`` checks included) on every leaf was a third of its logging cost. Exact types are
    dispatched here with the finite test inlined (``v - v == 0.0`` is False only for NaN and
    ±inf), common numpy scalars converted as ``.item()`` does; subclasses and every other type
    take the slow path, so the output is unchanged.
    """
    t = type(value)
    if t is dict:
        out = {}
        for k, v in value.items():
            if type(k) is not str:
                k = str(k)
            tv = type(v)
            if tv is float:
                out[k] = v if v - v == 0.0 else None
            elif tv is str or tv is int or tv is bool or v is None:
                out[k] = v
            else:
                out[k] = _jsonable_leaf(v)
        return out
    if t is float:
        return value if value - value == 0.0 else None
    if t is str or t is int or t is bool or value is None:
        return value
    if t is list or t is tuple:
        items = []
        for v in value:
            tv = type(v)
            if tv is float:
                items.append(v if v - v == 0.0 else None)
            elif tv is str or tv is int or tv is bool or v is None:
                items.append(v)
            else:
                items.append(_jsonable_leaf(v))
        return items
    if t is np.ndarray and value.ndim == 1:
        kind = value.dtype.kind
        if kind in "iub":
            return value.tolist()
        if kind == "f":
            floats = value.tolist()
            total = sum(floats)  # non-finite if any element is (or on overflow: slow path)
            return floats if total - total == 0.0 else _jsonable(floats)
    return _jsonable_slow(value)


def jsonable(value: Any) -> Any:
    """``value`` as strict JSON data — numpy as Python numbers/lists, NaN/inf as None, paths as
    strings — the conversion every flight-log record gets (reports and stage records use it
    too)."""
    return _jsonable(value)


_FIELD_GETTERS: dict[type, Any] = {}


def mavlink_fields(msg: Any) -> dict[str, Any]:
    """A pymavlink message as its ``to_dict()`` (``mavpackettype``, then every field in the
    message's order; text fields decoded as pymavlink does), read with one cached
    ``attrgetter`` per message type instead of a ``format_attr`` call per field."""
    cls = type(msg)
    getter = _FIELD_GETTERS.get(cls)
    if getter is None:
        # a dialect's message class (not BAD_DATA, UNKNOWN): its fields are class constants;
        # text (char) fields are bytes, which to_dict decodes
        names = tuple(getattr(cls, "fieldnames", ()))
        text = "char" in getattr(cls, "fieldtypes", ("char",))
        getter = (names, operator.attrgetter(*names)) if len(names) > 1 and not text else False
        _FIELD_GETTERS[cls] = getter
    if not getter:
        return msg.to_dict()
    names, values = getter
    out = {"mavpackettype": msg.get_type()}
    out.update(zip(names, values(msg)))  # noqa: B905 (attrgetter gives one per name)
    return out


REPRODUCIBLE_EPOCH_NS = 946_684_800 * 1_000_000_000
"""2000-01-01T00:00:00Z: the epoch of reproducible logs (not 0: a sensor's timestamp may precede
the episode's start by its latency, and MCAP log times are unsigned)."""


def _encode(time_s: float, msg: Mapping[str, Any]) -> bytes:
    """A message's JSON text: ``time_s`` first, then ``msg`` as :func:`_jsonable` makes it."""
    try:  # plain data (the usual message) is its JSON as it is
        text = _STRICT_JSON.encode({TIME_S: float(time_s), **msg})
    except (TypeError, ValueError):  # numpy, NaN/inf, paths: converted first
        text = _COMPACT_JSON.encode({TIME_S: float(time_s), **_jsonable(msg)})
    return text.encode()


class FlightLogError(Exception):
    """A flight log cannot be written or read (names the file and the reason)."""


class FlightLogWriter:
    """Writes one flight's MCAP file as it flies. Use as a context manager, or call close().

    Args:
        path: the file to create (parent folders are created).
        metadata: name -> JSON-serialisable dict (e.g. ``{"config": {...}, "episode": {...}}``),
            each written as one MCAP metadata record whose values are JSON strings.
        epoch_ns: the file's time origin; defaults to the wall time at creation.
        reproducible: no wall clock in the file: epoch :data:`REPRODUCIBLE_EPOCH_NS` (unless
            ``epoch_ns`` is given) and chunks flushed on sim time only, so the same messages
            give the same bytes. For logs written to a ``.part`` file and renamed when complete
            (a crash loses the whole file anyway, so flushing on wall time buys nothing).
    """

    def __init__(
        self,
        path: str | Path,
        metadata: Mapping[str, Mapping[str, Any]] | None = None,
        epoch_ns: int | None = None,
        reproducible: bool = False,
    ) -> None:
        self.path = Path(path)
        self._wall_flush = not reproducible
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._fh = self.path.open("wb")
        except OSError as exc:
            raise FlightLogError(f"{self.path}: cannot create flight log: {exc}") from None
        self._writer = Writer(self._fh, chunk_size=_CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="visland")
        install_chunk_compressor(self._writer, zstandard.ZstdCompressor(level=_ZSTD_LEVEL).compress)
        self._append = message_appender(self._writer)
        if epoch_ns is None:
            epoch_ns = REPRODUCIBLE_EPOCH_NS if reproducible else time.time_ns()
        self.epoch_ns = int(epoch_ns)
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._seq: dict[str, int] = defaultdict(int)
        self._last_flush_wall = time.monotonic()
        self._last_flush_sim = 0.0
        self._closed = False
        for name, data in (metadata or {}).items():
            self._writer.add_metadata(
                name, {str(k): json.dumps(_jsonable(v)) for k, v in data.items()}
            )
        self._writer.flush()

    # ------------------------------------------------------------------ writing

    def _channel(self, topic: str, schema_name: str) -> int:
        """The JSON channel of ``topic`` (its jsonschema ``schema_name``), registered once."""
        chan = self._channels.get(topic)
        if chan is None:
            sid = self._schemas.get(schema_name)
            if sid is None:
                schema = json.dumps(_schema(schema_name)).encode()
                sid = self._schema_id(schema_name, (schema_name, "jsonschema", schema))
            chan = self._channels[topic] = self._writer.register_channel(topic, "json", sid)
        return chan

    def _schema_id(self, key: str, schema: tuple[str, str, bytes]) -> int:
        """The id of ``schema`` ((name, encoding, data)) under ``key``, registered once."""
        sid = self._schemas.get(key)
        if sid is None:
            sid = self._schemas[key] = self._writer.register_schema(*schema)
        return sid

    def log_time_ns(self, time_s: float) -> int:
        return self.epoch_ns + round(time_s * 1e9)

    def write(self, topic: str, schema_name: str, time_s: float, msg: Mapping[str, Any]) -> None:
        """Write one JSON message stamped with sim time ``time_s``."""
        self.write_json(topic, schema_name, time_s, _encode(time_s, msg))

    def write_json(self, topic: str, schema_name: str, time_s: float, data: bytes) -> None:
        """Write one message whose JSON text (``time_s`` first, as :meth:`write` makes it)
        is ``data``, stamped with sim time ``time_s``."""
        if self._closed:
            raise FlightLogError(f"{self.path}: write after close")
        chan = self._channels.get(topic)
        if chan is None:
            chan = self._channel(topic, schema_name)
        self._add(chan, topic, time_s, data)

    def _add(self, chan: int, topic: str, time_s: float, data: bytes) -> None:
        t_ns = self.epoch_ns + round(time_s * 1e9)  # log_time_ns
        seq = self._seq[topic]
        self._seq[topic] = seq + 1
        if self._append is not None:
            self._append(chan, seq, t_ns, data)
        else:
            self._writer.add_message(
                channel_id=chan, log_time=t_ns, publish_time=t_ns, data=data, sequence=seq
            )
        self._maybe_flush(time_s)

    def write_encoded(
        self,
        topic: str,
        message_encoding: str,
        schema: tuple[str, str, bytes] | None,
        time_s: float,
        data: bytes,
    ) -> None:
        """Write one already-encoded message (e.g. foxglove-sdk protobuf: the live view's scene)
        on ``topic``, whose channel is registered with ``message_encoding`` and ``schema``
        ((name, encoding, data); None: schemaless) on its first message."""
        if self._closed:
            raise FlightLogError(f"{self.path}: write after close")
        chan = self._channels.get(topic)
        if chan is None:
            # keyed beside the JSON schemas, which go by name
            sid = 0 if schema is None else self._schema_id(f"{schema[1]}:{schema[0]}", schema)
            chan = self._channels[topic] = self._writer.register_channel(
                topic, message_encoding, sid
            )
        self._add(chan, topic, time_s, data)

    def write_mavlink(
        self,
        topic: str,
        time_s: float,
        msg: Any,
        extra: Mapping[str, Any] | None = None,
        redact: tuple[str, ...] = (),
    ) -> None:
        """A pymavlink message as :func:`mavlink_fields` gives it (then ``extra``), each field
        named in ``redact`` that it has replaced by ``"<redacted>"``; schema
        ``mavlink.<NAME>``."""
        body = mavlink_fields(msg)
        for key in redact:
            if key in body:
                body[key] = "<redacted>"
        if extra:
            body.update(extra)
        self.write(topic, "mavlink." + body["mavpackettype"], time_s, body)

    def write_record(self, topic: str, time_s: float, record: LogRecord) -> None:
        """Write a declared record (schema: its ``SCHEMA``) stamped with sim time ``time_s``."""
        self.write(topic, record.SCHEMA, time_s, record.to_dict())

    def write_image_record(self, topic: str, time_s: float, record: RawImageRecord) -> None:
        """:meth:`write_record` for a camera frame whose ``data`` is base64 text (as
        :meth:`RawImageRecord.mono8` makes it): the record without that text goes through
        the JSON encoder, the text is spliced in after (:data:`_IMAGE_DATA`); the same
        bytes, ~3x faster."""
        body = record.to_dict()
        text = body["data"]
        body["data"] = _IMAGE_DATA
        head, _, tail = _encode(time_s, body).partition(_IMAGE_DATA_JSON)
        data = b"".join((head, b'"data":"', text.encode("ascii"), b'"', tail))
        self.write_json(topic, record.SCHEMA, time_s, data)

    def write_image(self, time_s: float, image: np.ndarray, frame_id: int) -> None:
        """A mono8 frame as ``foxglove.RawImage`` on :data:`TOPIC_IMAGE`."""
        if np.ndim(image) != 2:
            raise FlightLogError(
                f"{self.path}: image must be 2-D mono8, got shape {np.shape(image)}"
            )
        record = RawImageRecord.mono8(image, frame_id, self.log_time_ns(time_s))
        self.write_image_record(TOPIC_IMAGE, time_s, record)

    def write_pose(self, time_s: float, pos_ned_m, quat_wxyz) -> None:
        """Ground-truth pose as ``foxglove.PoseInFrame`` in frame ``ned`` (pad centre origin)."""
        w, x, y, z = (float(v) for v in quat_wxyz)
        n, e, d = (float(v) for v in pos_ned_m)
        self.write_record(
            TOPIC_GROUNDTRUTH_POSE,
            time_s,
            PoseInFrameRecord(
                timestamp=Timestamp.from_ns(self.log_time_ns(time_s)),
                frame_id="ned",
                pose=Pose(
                    position=Vector3(x=n, y=e, z=d),
                    orientation=Quaternion(x=x, y=y, z=z, w=w),
                ),
            ),
        )

    def _maybe_flush(self, time_s: float) -> None:
        now = time.monotonic()
        if (
            self._wall_flush and now - self._last_flush_wall >= _FLUSH_PERIOD_S
        ) or time_s - self._last_flush_sim >= _FLUSH_PERIOD_S:
            self.flush(time_s)

    def flush(self, time_s: float | None = None) -> None:
        """Close the chunk in progress and push it to the file."""
        self._writer.flush()
        self._last_flush_wall = time.monotonic()
        if time_s is not None:
            self._last_flush_sim = time_s

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._writer.finish()
            finally:
                self._fh.close()

    def abandon(self) -> None:
        """Close the file without writing more (a write failed: a full disk): what reached it
        reads back as a truncated log."""
        if not self._closed:
            self._closed = True
            with contextlib.suppress(OSError):  # closing flushes Python's buffer: still full
                self._fh.close()

    def __enter__(self) -> FlightLogWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# --------------------------------------------------------------------------- reading


@dataclass
class FlightLog:
    """Everything readable in one flight log.

    Attributes:
        path: the file.
        metadata: metadata record name -> {key: decoded JSON value}.
        messages: topic -> list of decoded JSON messages, in file order.
        truncated: the file ended early (crash); ``messages`` holds the readable prefix.
        error: why reading stopped early, if it did.
        schemas: topic -> schema name, for every channel in the readable part (read or not,
            with or without messages).
        binary: topic -> message count of the channels that are not JSON (the live view's
            protobuf scene that :mod:`companion.live.scene_log` adds): counted, not decoded.
    """

    path: Path
    metadata: dict[str, dict[str, Any]] = field(default_factory=dict)
    messages: dict[str, list[dict[str, Any]]] = field(default_factory=lambda: defaultdict(list))
    truncated: bool = False
    error: str | None = None
    schemas: dict[str, str] = field(default_factory=dict)
    binary: dict[str, int] = field(default_factory=dict)

    def topic(self, name: str) -> list[dict[str, Any]]:
        return self.messages.get(name, [])

    def images(self) -> tuple[np.ndarray, np.ndarray]:
        """``(times_s (N,), frames (N, H, W) uint8)`` from the camera topic."""
        msgs = self.topic(TOPIC_IMAGE)
        if not msgs:
            return np.zeros(0), np.zeros((0, 0, 0), dtype=np.uint8)
        frames = np.stack(
            [
                np.frombuffer(base64.b64decode(m["data"]), dtype=np.uint8).reshape(
                    m["height"], m["width"]
                )
                for m in msgs
            ]
        )
        return np.array([m["time_s"] for m in msgs]), frames

    @property
    def duration_s(self) -> float:
        times = [m["time_s"] for msgs in self.messages.values() for m in msgs if "time_s" in m]
        return (max(times) - min(times)) if times else 0.0


def read_log(path: str | Path, topics: Iterable[str] | None = None) -> FlightLog:
    """Read a flight log without seeking; a truncated file gives its readable prefix.

    Raises:
        FlightLogError: the file does not exist or is not an MCAP file at all.
    """
    path = Path(path)
    wanted = set(topics) if topics is not None else None
    log = FlightLog(path=path)
    try:
        fh = path.open("rb")
    except OSError as exc:
        raise FlightLogError(f"{path}: cannot open: {exc}") from None
    with fh:
        magic = fh.read(8)
        if magic != b"\x89MCAP0\r\n":
            raise FlightLogError(f"{path}: not an MCAP file (bad magic {magic[:8]!r})")
        fh.seek(0)
        channels: dict[int, str] = {}
        binary: set[int] = set()
        schema_names: dict[int, str] = {}
        try:
            for record in StreamReader(fh, skip_magic=False).records:
                if isinstance(record, Metadata):
                    log.metadata[record.name] = {
                        k: json.loads(v) for k, v in record.metadata.items()
                    }
                    continue
                if isinstance(record, Schema):
                    schema_names[record.id] = record.name
                elif isinstance(record, Channel):
                    channels[record.id] = record.topic
                    log.schemas[record.topic] = schema_names.get(record.schema_id, "")
                    if record.message_encoding != "json":
                        binary.add(record.id)
                elif isinstance(record, Message):
                    topic = channels.get(record.channel_id)
                    if topic is None or (wanted is not None and topic not in wanted):
                        continue
                    if record.channel_id in binary:
                        log.binary[topic] = log.binary.get(topic, 0) + 1
                        continue
                    try:
                        msg = json.loads(record.data)
                    except ValueError as exc:
                        log.truncated = True
                        log.error = f"undecodable message on {topic}: {exc}"
                        break
                    log.messages[topic].append(msg)
                elif isinstance(record, Footer):
                    break
            else:
                log.truncated = True
                log.error = "file ends before the MCAP footer"
        except McapError as exc:
            log.truncated = True
            log.error = f"{type(exc).__name__}: {str(exc) or 'the file is cut inside a record'}"
        except (struct.error, zstandard.ZstdError, ValueError, EOFError, OSError) as exc:
            # What a file cut mid-record raises below the MCAP layer.
            log.truncated = True
            log.error = f"the file is cut inside a record ({type(exc).__name__}: {exc})"
    log.messages = dict(log.messages)
    return log
