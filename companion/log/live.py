"""Live view: the running companion's log channels served over the Foxglove WebSocket protocol.

The server is fed by the MCAP writer (:class:`companion.log.writer.McapLogger` calls
:meth:`LiveServer.add_channel` and :meth:`LiveServer.message` from its writer thread, after
each write), so a live client gets exactly the bytes, schema names and encodings the file gets:
the layout in ``foxglove/layout.json`` works on both. Nothing is encoded twice.

Never in the control loop's way:

- the control loop never calls this module; the writer thread does, and :meth:`message` only
  checks whether any client subscribes to the topic (a call into the SDK) and appends to a
  bounded deque: no client, no work beyond that check;
- a publisher thread drains the deque into ``foxglove`` channels. When it falls behind, the
  deque drops the OLDEST message and counts it (``dropped``), with a warning at most once per
  10 s;
- inside the SDK every client has its own queue of ``client_backlog`` messages; a slow client
  loses its oldest messages there (the SDK does not report that count).

The server binds ``host:port`` when :meth:`LiveServer.start` runs and raises
:class:`LiveViewError` (a :class:`companion.CompanionError`) if the port is taken, before the
flight starts. ``foxglove-sdk`` is an optional dependency (``pip install -e '.[live]'``).

Protocol note (measured with foxglove-sdk 0.30.3): the server accepts only the WebSocket
subprotocol ``foxglove.sdk.v1`` (a client offering only ``foxglove.websocket.v1`` gets HTTP
400); the messages are those of the ``foxglove.websocket.v1`` spec.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, cast

from companion import CompanionError
from companion.log import schemas as sch

log = logging.getLogger(__name__)

#: The WebSocket subprotocol the SDK's server speaks.
SUBPROTOCOL = "foxglove.sdk.v1"


class LiveViewError(CompanionError):
    """The live view cannot start (SDK missing, port taken, bad address)."""


@dataclass(frozen=True)
class LiveStats:
    """Counters since start: ``offered`` messages the writer handed over, ``unsubscribed`` of
    them skipped because no client subscribed to the topic, ``queued`` accepted, ``published``
    handed to the SDK, ``dropped`` (oldest dropped from a full queue), ``errors`` (the SDK
    refused a message), ``subscriptions`` now active (all clients)."""

    offered: int
    unsubscribed: int
    queued: int
    published: int
    dropped: int
    errors: int
    subscriptions: int


class _Listener:
    """foxglove ServerListener: counts subscriptions (SDK threads call it)."""

    def __init__(self, owner: LiveServer) -> None:
        self._owner = owner

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self._owner._subscribed(channel.topic, +1)

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        self._owner._subscribed(channel.topic, -1)


class LiveServer:
    """``server = LiveServer(host, port); server.start(); logger.observer = server; ...;
    server.close()``. Also a context manager. ``port`` 0 picks a free port (see :attr:`port`)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8765,
        *,
        queue_size: int = 512,
        client_backlog: int = 256,
        name: str = "companion",
    ) -> None:
        if queue_size < 1 or client_backlog < 1:
            raise LiveViewError("live view: queue_size and client_backlog must be >= 1")
        self.host = host
        self.requested_port = port
        self.queue_size = queue_size
        self.client_backlog = client_backlog
        self.name = name
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._q: collections.deque[tuple[str, Any, int, bytes]] = collections.deque()
        self._channels: dict[str, Any] = {}
        self._subs: dict[str, int] = {}
        self._schema_names: dict[str, str] = {}
        self._last: dict[str, tuple[Any, int, bytes]] = {}  # per topic: the newest message
        self._offered = self._unsub = self._queued = 0
        self._published = self._dropped = self._errors = 0
        self._last_warn = -1e9
        self._server: Any = None
        self._context: Any = None
        self._thread: threading.Thread | None = None
        self._closing = False

    @classmethod
    def from_config(cls, live_cfg: Any) -> LiveServer:
        """From :class:`companion.config.LiveConfig` (host, port, queue_size, client_backlog)."""
        return cls(
            live_cfg.host,
            live_cfg.port,
            queue_size=live_cfg.queue_size,
            client_backlog=live_cfg.client_backlog,
        )

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> LiveServer:
        """Bind and serve; raises :class:`LiveViewError` when that is impossible."""
        try:
            import foxglove
        except ImportError as e:
            raise LiveViewError(
                "live view: foxglove-sdk is not installed (pip install -e '.[live]')"
            ) from e
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name=self.name,
                host=self.host,
                port=self.requested_port,
                context=self._context,
                server_listener=cast(Any, _Listener(self)),  # implements 2 of its hooks
                message_backlog_size=self.client_backlog,
            )
        except (RuntimeError, ValueError, OSError) as e:  # the SDK raises RuntimeError
            taken = "in use" in str(e)
            hint = (
                "the port is taken: stop the other process or set live.port"
                if taken
                else "check live.host / live.port"
            )
            raise LiveViewError(
                f"live view: cannot serve on {self.host}:{self.requested_port}: {e} ({hint})"
            ) from None
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()
        log.info(
            "live view: ws://%s:%d (Foxglove: open a connection, Foxglove WebSocket)",
            self.host,
            self.port,
        )
        return self

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def port(self) -> int:
        """The TCP port served (the one picked when 0 was asked for)."""
        if self._server is None:
            return self.requested_port
        return int(self._server.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def close(self) -> None:
        """Stop the publisher thread (what is queued is dropped) and the server."""
        with self._wake:
            self._closing = True
            self._wake.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._server is not None:
            self._server.stop()
            self._server = None
            s = self.stats
            log.info(
                "live view closed: %d messages published, %d dropped (queue full), "
                "%d not subscribed, %d errors",
                s.published,
                s.dropped,
                s.unsubscribed,
                s.errors,
            )

    @property
    def stats(self) -> LiveStats:
        with self._lock:
            return LiveStats(
                self._offered,
                self._unsub,
                self._queued,
                self._published,
                self._dropped,
                self._errors,
                sum(self._subs.values()),
            )

    # -- the writer thread's side (companion.log.writer.LogObserver) ---------------------------

    def add_channel(
        self,
        topic: str,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
        message_encoding: str,
    ) -> None:
        """Advertise ``topic`` with the schema the MCAP file has for it (a topic advertised
        ahead with another schema is advertised again with this one)."""
        if self._context is None:
            return
        old = self._channels.get(topic)
        if old is not None:
            if self._schema_names.get(topic) == schema_name:
                return
            log.warning(
                "live view: %s advertised as %s, written as %s: re-advertised",
                topic,
                self._schema_names.get(topic),
                schema_name,
            )
            old.close()
        import foxglove

        schema = foxglove.Schema(name=schema_name, encoding=schema_encoding, data=schema_data)
        ch = foxglove.Channel(
            topic, schema=schema, message_encoding=message_encoding, context=self._context
        )
        self._schema_names[topic] = schema_name
        self._channels[topic] = ch

    def advertise(self, topics: Mapping[str, str]) -> None:
        """Advertise ``{topic: schema name}`` now, before their first message.

        Call it right after :meth:`start`: a channel created while a client is connected can
        race with that client's subscription in foxglove-sdk 0.30.3 (measured: 14 of 300
        subscriptions to just-advertised channels were refused as "Unknown channel ID"), so
        the layout's topics are advertised before any client can connect."""
        for topic, name in topics.items():
            enc_s, enc_m = sch.encodings(name)
            data = (
                sch.protobuf_schema_bytes(name)
                if name in sch.PROTOBUF_SCHEMAS
                else sch.schema_bytes(name)
            )
            self.add_channel(topic, name, enc_s, data, enc_m)

    def message(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Queue one message for the clients subscribed to ``topic``; never blocks."""
        ch = self._channels.get(topic)
        if ch is None:
            return
        with self._wake:
            self._offered += 1
            self._last[topic] = (ch, log_time_ns, data)
            if self._closing or not self._subs.get(topic):
                self._unsub += 1
                return
            warn = self._enqueue_locked(topic, ch, log_time_ns, data)
        if warn:
            log.warning(
                "live view: the publisher is behind, %d messages dropped so far", self._dropped
            )

    # -- internals ------------------------------------------------------------------------------

    def _enqueue_locked(self, topic: str, ch: Any, log_time_ns: int, data: bytes) -> bool:
        warn = False
        if len(self._q) >= self.queue_size:
            self._q.popleft()
            self._dropped += 1
            warn = time.monotonic() - self._last_warn >= 10.0
            if warn:
                self._last_warn = time.monotonic()
        self._q.append((topic, ch, log_time_ns, data))
        self._queued += 1
        self._wake.notify()
        return warn

    def _subscribed(self, topic: str, delta: int) -> None:
        with self._wake:
            self._subs[topic] = max(0, self._subs.get(topic, 0) + delta)
            last = self._last.get(topic) if delta > 0 else None
            if last is not None and not self._closing:
                # latched: a client joining late still sees the topic's newest message (the
                # initial safety state, the config); other subscribers get it once more
                self._enqueue_locked(topic, *last)
        log.debug("live view: %s %s", "subscribe" if delta > 0 else "unsubscribe", topic)

    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._q and not self._closing:
                    self._wake.wait()
                if self._closing:
                    return
                batch = list(self._q)
                self._q.clear()
            n_ok = n_err = 0
            for topic, ch, t, data in batch:
                try:
                    ch.log(data, log_time=t)
                    n_ok += 1
                except Exception as e:  # a bad message must not stop the others
                    n_err += 1
                    log.debug("live view: %s: %r", topic, e)
            with self._lock:
                self._published += n_ok
                self._errors += n_err


def layout_topics(image_encoding: str) -> dict[str, str]:
    """The topics the shipped layout (``foxglove/layout.json``) shows, with the schemas the
    companion writes them with (``logging.image_encoding`` decides the image's)."""
    return {
        "/camera/image": sch.RAW_IMAGE if image_encoding == "raw" else sch.COMPRESSED_IMAGE,
        "/control/step": sch.CONTROLLER_STEP,
        "/control/safety": sch.LOG,
        "/vehicle/pose": sch.POSE_IN_FRAME,
        "/target/pose": sch.POSE_IN_FRAME,
        "/mavlink/out/SET_ATTITUDE_TARGET": sch.MAVLINK_PREFIX + "SET_ATTITUDE_TARGET",
    }


def start_live(live_cfg: Any, image_encoding: str = "png") -> LiveServer | None:
    """The started server, the layout's topics advertised, when ``live_cfg.enabled``; else
    None. Raises :class:`LiveViewError` when it cannot serve."""
    if not live_cfg.enabled:
        return None
    server = LiveServer.from_config(live_cfg).start()
    server.advertise(layout_topics(image_encoding))
    return server
