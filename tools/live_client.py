"""A client of the Foxglove WebSocket protocol (what the Foxglove app speaks), for the live
view's tests and ``visland bench companion --live``: connect, read the advertised channels,
subscribe to all of them and decode the messages of each (protobuf from the schema the server
advertises, JSON as JSON)."""

from __future__ import annotations

import asyncio
import base64
import json
import time
from dataclasses import dataclass, field
from typing import Any

import websockets

from companion.live.messages import protobuf_decoder

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
_MESSAGE_DATA = 0x01


@dataclass
class Seen:
    """What a client saw: the server's info, the channels by topic, and per topic the decoded
    messages (protobuf messages or JSON objects), oldest first."""

    server: dict[str, Any] = field(default_factory=dict)
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)
    messages: dict[str, list[Any]] = field(default_factory=dict)


def _decoder(channel: dict[str, Any]):
    if channel["encoding"] == "json":
        return lambda data: json.loads(bytes(data))
    return protobuf_decoder(channel["schemaName"], base64.b64decode(channel["schema"]))


async def _watch(url: str, topics: set[str], per_topic: int, timeout_s: float, until) -> Seen:
    seen = Seen()
    async with websockets.connect(url, subprotocols=SUBPROTOCOLS, max_size=None) as ws:
        deadline = time.monotonic() + timeout_s
        by_id: dict[int, dict[str, Any]] = {}
        while not by_id or not topics <= {c["topic"] for c in by_id.values()}:
            raw = await asyncio.wait_for(ws.recv(), max(0.1, deadline - time.monotonic()))
            if isinstance(raw, str):
                msg = json.loads(raw)
                if msg["op"] == "serverInfo":
                    seen.server = msg
                elif msg["op"] == "advertise":
                    for ch in msg["channels"]:
                        by_id[ch["id"]] = ch
        subs = {}
        for sub_id, (_, ch) in enumerate(sorted(by_id.items())):
            subs[sub_id] = (ch["topic"], _decoder(ch))
            seen.channels[ch["topic"]] = ch
        await ws.send(
            json.dumps(
                {
                    "op": "subscribe",
                    "subscriptions": [
                        {"id": s, "channelId": c} for s, (c, _) in enumerate(sorted(by_id.items()))
                    ],
                }
            )
        )
        while time.monotonic() < deadline and not (until is not None and until()):
            if all(len(seen.messages.get(t, [])) >= per_topic for t in topics):
                break
            try:
                raw = await asyncio.wait_for(ws.recv(), max(0.1, deadline - time.monotonic()))
            except (TimeoutError, websockets.exceptions.ConnectionClosed):
                break  # the server went away (the flight is over): what came is what is seen
            if isinstance(raw, bytes) and raw[0] == _MESSAGE_DATA:
                sub_id = int.from_bytes(raw[1:5], "little")
                topic, decode = subs[sub_id]
                seen.messages.setdefault(topic, []).append(decode(raw[13:]))
    return seen


def watch(
    port: int,
    topics: set[str],
    per_topic: int = 1,
    timeout_s: float = 30.0,
    host: str = "127.0.0.1",
    until=None,
) -> Seen:
    """Subscribe to every channel of the server on ``port`` until each of ``topics`` has
    delivered ``per_topic`` messages, ``until()`` is true, or ``timeout_s``; connects as soon
    as the server listens (and keeps trying until then)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return asyncio.run(
                _watch(f"ws://{host}:{port}", topics, per_topic, deadline - time.monotonic(), until)
            )
        except (OSError, websockets.exceptions.InvalidMessage):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
