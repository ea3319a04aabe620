"""A minimal Foxglove WebSocket client (``foxglove.websocket.v1`` messages over the SDK's
``foxglove.sdk.v1`` subprotocol), written from the protocol spec with ``websockets``: what the
live-view tests and ``bench/live.py`` use to subscribe like Foxglove does.

Server -> client: JSON ``serverInfo``, ``advertise`` (channels: id, topic, encoding,
schemaName, schemaEncoding, schema), ``unadvertise``; binary ``MessageData`` (opcode 0x01,
uint32 LE subscription id, uint64 LE log time in ns, payload). Client -> server: JSON
``subscribe`` / ``unsubscribe``.
"""

from __future__ import annotations

import asyncio
import json
import re
import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import websockets

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
_HEAD = struct.Struct("<BIQ")
OP_MESSAGE_DATA = 0x01
_UNKNOWN = re.compile(r"Unknown channel ID: (\d+)")


@dataclass
class Capture:
    """What a client saw: advertised channels by topic, and per topic the messages as
    (log time ns, client receive time monotonic s, payload)."""

    server_info: dict[str, Any] = field(default_factory=dict)
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)
    messages: dict[str, list[tuple[int, float, bytes]]] = field(default_factory=dict)
    connected_at: float | None = None
    refused: int = 0  # subscriptions the server refused as "Unknown channel ID" (then retried)

    def count(self, topic: str) -> int:
        return len(self.messages.get(topic, ()))


async def _connect(url: str, deadline: float) -> Any:
    while True:
        try:
            return await websockets.connect(
                url,
                subprotocols=SUBPROTOCOLS,  # type: ignore[list-item]
                max_size=None,
                open_timeout=5.0,
            )
        except (OSError, websockets.InvalidHandshake, TimeoutError):
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.1)


async def capture(
    url: str,
    topics: Iterable[str] | None,
    done: Callable[[Capture], bool],
    timeout_s: float,
    connect_timeout_s: float = 120.0,
    stop: Callable[[], bool] = lambda: False,
) -> Capture:
    """Connect (retrying until ``connect_timeout_s``), subscribe to ``topics`` (all when None)
    as they are advertised, and collect until ``done(capture)``, ``stop()`` or ``timeout_s``
    after connecting."""
    cap = Capture()
    wanted = None if topics is None else set(topics)
    ws = await _connect(url, time.monotonic() + connect_timeout_s)
    cap.connected_at = time.monotonic()
    subs: dict[int, str] = {}
    sub_ch: dict[int, int] = {}  # subscription id -> channel id
    end = cap.connected_at + timeout_s
    try:
        while not done(cap) and not stop() and time.monotonic() < end:
            try:
                raw = await asyncio.wait_for(ws.recv(), timeout=0.2)
            except TimeoutError:
                continue
            except websockets.ConnectionClosed:
                break
            if isinstance(raw, str):
                msg = json.loads(raw)
                if msg.get("op") == "status" and (m := _UNKNOWN.search(msg.get("message", ""))):
                    # foxglove-sdk 0.30.3 may refuse a subscription to a channel it has just
                    # advertised (a race inside the SDK): ask again, and count it
                    cid = int(m[1])
                    cap.refused += 1
                    if cap.refused <= 1000:
                        again = [{"id": i, "channelId": c} for i, c in sub_ch.items() if c == cid]
                        await asyncio.sleep(0.02)
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": again}))
                elif msg.get("op") == "serverInfo":
                    cap.server_info = msg
                elif msg.get("op") == "advertise":
                    new = []
                    for ch in msg["channels"]:
                        cap.channels[ch["topic"]] = ch
                        if wanted is None or ch["topic"] in wanted:
                            sid = len(subs) + 1
                            subs[sid] = ch["topic"]
                            sub_ch[sid] = ch["id"]
                            new.append({"id": sid, "channelId": ch["id"]})
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                continue
            if raw[0] != OP_MESSAGE_DATA:
                continue
            _, sid, t_ns = _HEAD.unpack_from(raw)
            topic = subs.get(sid)
            if topic is not None:
                cap.messages.setdefault(topic, []).append(
                    (t_ns, time.monotonic(), bytes(raw[_HEAD.size :]))
                )
    finally:
        await ws.close()
    return cap
