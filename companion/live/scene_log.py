"""The live view's picture written into a flight log: :func:`add_scene`.

A recorded flight opens in Foxglove with the same picture as a live one: the log gets the live
view's channels beside its own (``/camera/calibration``, ``/camera/annotations``, ``/scene``,
``/tf`` as foxglove-sdk's protobuf messages, ``/live/state`` as JSON, ``/log`` as
``foxglove.Log``), built from :func:`companion.live.replay.logged_frames` by the same functions
the live view publishes with (:mod:`companion.live.messages`). Each frame's messages carry its
logged image's stamp and log time, so the annotations sit on the very frame they were drawn for
in an Image panel, and ``docs/foxglove/visland.json`` shows a file as it shows a live flight.

The log's own records (metadata, schemas, channels, messages) are copied as they are; channels
that an earlier pass added are replaced, so running it twice gives the same file. A truncated
log gets the scene of its readable part. The new file is written beside the old one and renamed
over it only when complete (or written to ``out``): a failure loses nothing.
"""

from __future__ import annotations

import contextlib
import json
import os
import struct
import sys
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zstandard
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from companion.contract.records import EventKind
from companion.flightlog import FlightLogError, read_log
from companion.live.frame import LiveFrame
from companion.live.messages import (
    TRAIL,
    camera_calibration,
    image_annotations,
    scene_update,
    stamp_ns,
    state_values,
    transforms,
)
from companion.live.replay import REPLAY_TOPICS, LoggedEvent, logged_frames, policy_of

__all__ = ["SCENE_TOPICS", "SceneChannel", "SceneReport", "SceneStream", "add_scene", "add_scenes"]

SCENE_TOPICS = (
    "/camera/calibration",
    "/camera/annotations",
    "/scene",
    "/tf",
    "/live/state",
    "/log",
)
"""The channels :func:`add_scene` adds (the live view's, less the image the log has)."""

_BUILDERS = (
    ("/camera/calibration", camera_calibration),
    ("/camera/annotations", image_annotations),
    ("/tf", transforms),
)


@dataclass(frozen=True)
class SceneReport:
    file: str
    """The log written."""
    frames: int
    events: int
    messages: int
    """Messages added."""
    policy: str | None
    """The checkpoint run again for the CNN's bearing and the estimate (None: the logged one,
    if any)."""
    truncated: bool

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class SceneChannel:
    """A channel of the scene (or of a log being rewritten)."""

    topic: str
    schema: tuple[str, str, bytes] | None
    """(name, encoding, data); None: schemaless."""
    message_encoding: str


_STATE = SceneChannel("/live/state", None, "json")


def add_scene(
    path: str | Path, out: str | Path | None = None, policy: str | None = None
) -> SceneReport:
    """Write the flight log ``path`` with the live view's channels added to ``out`` (None:
    ``path`` itself, replaced when the new file is complete).

    Raises:
        FlightLogError: not a readable flight log, or it has no camera frames to draw.
        ImportError: foxglove-sdk is not installed (``pip install 'visland[live]'``).
    """
    import foxglove.messages  # noqa: F401  (ImportError before anything is written)

    path = Path(path)
    out = path if out is None else Path(out)
    log = read_log(path, topics=set(REPLAY_TOPICS))
    if not log.topic("/camera/image"):
        raise FlightLogError(f"{path}: no /camera/image frames; the scene is drawn per frame")
    policy_name = policy_of(log, policy)
    loaded = None
    if policy_name is not None:
        from companion.policy_net import load_policy

        loaded = load_policy(policy_name)
    added = _scene_messages(log, loaded)
    frames = sum(1 for _, topic, *_ in added if topic == "/scene")
    events = sum(1 for _, topic, *_ in added if topic == "/log")
    tmp = out.with_name(f".{out.name}.scene.part")
    try:
        _rewrite(path, tmp, added)
        os.replace(tmp, out)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise FlightLogError(f"{out}: cannot write the scene: {exc}") from None
    return SceneReport(
        file=str(out),
        frames=frames,
        events=events,
        messages=len(added),
        policy=policy_name,
        truncated=log.truncated,
    )


class SceneStream:
    """The live view's channels for one flight, frame by frame: what :func:`add_scene` writes
    into a log afterwards and a flying process (``log_scene``) writes as it goes — the same
    builders, the same trail, so both files show the same picture.

    Needs foxglove-sdk (its protobuf messages): constructing one raises ImportError without it.
    """

    def __init__(self) -> None:
        import foxglove.messages  # noqa: F401  (ImportError before anything is built)

        self._trail: deque[tuple[float, float, float]] = deque(maxlen=TRAIL)
        self._channels: dict[str, SceneChannel] = {"/live/state": _STATE}

    def _encoded(self, topic: str, msg: Any) -> tuple[SceneChannel, bytes]:
        chan = self._channels.get(topic)
        if chan is None:
            schema = type(msg).get_schema()
            chan = SceneChannel(
                topic, (schema.name, schema.encoding, bytes(schema.data)), "protobuf"
            )
            self._channels[topic] = chan
        return chan, msg.encode()

    def frame(self, f: LiveFrame) -> list[tuple[SceneChannel, bytes]]:
        """``f``'s messages (stamped ``f.stamp_ns``, else its time), in the order they go."""
        if f.vehicle_pos_ned_m is not None:
            self._trail.append(tuple(float(v) for v in f.vehicle_pos_ned_m))
        out = [self._encoded(topic, build(f)) for topic, build in _BUILDERS]
        out.append(self._encoded("/scene", scene_update(f, self._trail)))
        out.append((_STATE, json.dumps(state_values(f)).encode()))
        return out

    def event(self, ns: int, text: str) -> tuple[SceneChannel, bytes]:
        """A log event (``/events``' text) as ``foxglove.Log`` stamped ``ns``; a failsafe is an
        error, as the live view marks it."""
        from foxglove.messages import Log, LogLevel

        error = text.split(":", 1)[0] == EventKind.FAILSAFE.value
        level = LogLevel.Error if error else LogLevel.Info
        return self._encoded(
            "/log", Log(timestamp=stamp_ns(ns), level=level, message=text, name="visland")
        )


def add_scenes(logs: list[tuple[Path, str | None]], who: str) -> int:
    """:func:`add_scene` on each ``(log, policy)`` where it can be drawn, for a command that
    keeps logs (``visland eval --keep-logs``, ``visland fly --scene``): a log that cannot be
    drawn stays as it was and ``who`` says so on stderr; without foxglove-sdk every log stays as
    it was, said once. Returns how many logs got their scene."""
    done = 0
    for path, policy in logs:
        try:
            add_scene(path, policy=policy)
        except ImportError as exc:
            print(f"{who}: the scene needs foxglove-sdk ({exc}): logs as they are", file=sys.stderr)
            return done
        except FlightLogError as exc:
            print(f"{who}: {path} left without its scene: {exc}", file=sys.stderr)
        else:
            done += 1
    return done


def _scene_messages(log: Any, policy: Any) -> list[tuple[int, str, SceneChannel, bytes]]:
    """``(log_time_ns, topic, channel, data)`` of every message the scene adds."""
    stream = SceneStream()
    out: list[tuple[int, str, SceneChannel, bytes]] = []
    epoch_ns = None  # the file's clock: a frame's image stamp less its time

    def event(e: LoggedEvent) -> None:
        ns = epoch_ns + round(e.time_s * 1e9)
        chan, data = stream.event(ns, e.text)
        out.append((ns, chan.topic, chan, data))

    pending: list[LoggedEvent] = []
    for item in logged_frames(log, policy):
        if isinstance(item, LoggedEvent):
            if epoch_ns is None:
                pending.append(item)
            else:
                event(item)
            continue
        ns = int(item.stamp_ns)
        if epoch_ns is None:
            epoch_ns = ns - round(item.time_s * 1e9)
            for e in pending:
                event(e)
        out.extend((ns, chan.topic, chan, data) for chan, data in stream.frame(item))
    return out


def _rewrite(src: Path, dst: Path, added: list[tuple[int, str, SceneChannel, bytes]]) -> None:
    """``src``'s records (less any earlier scene) and ``added``, by log time, into ``dst``."""
    metadata: list[tuple[str, dict[str, str]]] = []
    schemas: dict[int, Schema] = {}
    chans: dict[int, SceneChannel] = {}
    messages: list[tuple[int, str, SceneChannel, bytes]] = []
    # a truncated log stops where read_log stopped: its readable prefix is what the scene is of
    cut = (McapError, struct.error, zstandard.ZstdError, ValueError, EOFError)
    with src.open("rb") as fh, contextlib.suppress(*cut):
        for record in StreamReader(fh, skip_magic=False).records:
            if isinstance(record, Metadata):
                metadata.append((record.name, dict(record.metadata)))
            elif isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                if record.topic in SCENE_TOPICS:
                    continue
                s = schemas.get(record.schema_id)
                chans[record.id] = SceneChannel(
                    record.topic,
                    None if s is None else (s.name, s.encoding, bytes(s.data)),
                    record.message_encoding,
                )
            elif isinstance(record, Message):
                chan = chans.get(record.channel_id)
                if chan is not None:
                    messages.append((record.log_time, chan.topic, chan, bytes(record.data)))
            elif isinstance(record, Footer):
                break
    merged = sorted(messages + added, key=lambda m: m[0])
    with dst.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start(profile="", library="visland")
        for name, values in metadata:
            writer.add_metadata(name, values)
        schema_ids: dict[tuple[str, str, bytes], int] = {}
        chan_ids: dict[SceneChannel, int] = {}
        seq: dict[int, int] = {}
        for log_time, _, chan, data in merged:
            cid = chan_ids.get(chan)
            if cid is None:
                sid = 0
                if chan.schema is not None:
                    sid = schema_ids.get(chan.schema, 0)
                    if not sid:
                        name, encoding, sdata = chan.schema
                        sid = writer.register_schema(name, encoding, sdata)
                        schema_ids[chan.schema] = sid
                cid = writer.register_channel(chan.topic, chan.message_encoding, sid)
                chan_ids[chan] = cid
            n = seq.get(cid, 0)
            seq[cid] = n + 1
            writer.add_message(
                channel_id=cid, log_time=log_time, publish_time=log_time, data=data, sequence=n
            )
        writer.finish()
