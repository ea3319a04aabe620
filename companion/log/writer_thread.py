"""The MCAP log's writer thread (:class:`companion.log.writer.McapLogger` runs it): takes the
queued items, encodes them (JSON, images, MAVLink frames), hands them to ``mcap.writer.Writer``,
closes a chunk and flushes (and fsyncs, by policy) every ``flush_interval_s``, and feeds the
log's observer. A failure (disk full, broken pipe) stops logging, never the flight: the queue is
drained and counted as dropped.

The logger's state it works on (queue, counters, locks) is declared in :class:`WriterThread`
and set up by ``McapLogger.__init__``.
"""

from __future__ import annotations

import collections
import errno
import logging
import os
import threading
import time
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.writer import CompressionType, Writer

from companion import __version__
from companion.log import McapLogError
from companion.log import schemas as sch
from companion.log.encode import encode_image, encode_json, mavlink_payload
from companion.log.mcap_lean import LeanWriter

log = logging.getLogger("companion.log.writer")

STOP = object()  # the queue's end marker (close)
MAX_HOLD_S = 0.05  # the longest a hold (McapLogger.hold) delays the writer per message
#: The writer thread drains its queue every POLL_S (sooner on close or a half-full queue):
#: one wake-up for ~5-10 records at a flight's rates instead of one per record. Not longer: a
#: 100 ms drain saves wake-ups (50-100 us each on a loaded machine) but holds the GIL for a
#: longer batch, and a frame arriving meanwhile waits for it (the latency's decode stage
#: 0.32-0.34 -> 0.42 ms median, p95 0.62-0.65 -> 1.29 ms, docs/reference/logging.md).
POLL_S = 0.02
POLL_LIVE_S = 0.02


def downscale(image: np.ndarray, scale: float) -> np.ndarray:
    import cv2

    h, w = image.shape[:2]
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA))


class Sink:
    """File wrapper counting bytes so ``tell()`` works on pipes too (the MCAP writer needs it)."""

    def __init__(self, f: IO[bytes]) -> None:
        self._f = f
        self._n = 0
        self.fsync_ok = True

    def write(self, data: bytes) -> int:
        self._f.write(data)
        self._n += len(data)
        return len(data)

    def tell(self) -> int:
        return self._n

    def flush(self) -> None:
        self._f.flush()

    def fsync(self) -> None:
        if not self.fsync_ok:
            return
        try:
            os.fsync(self._f.fileno())
        except OSError as e:
            if e.errno in (errno.EINVAL, errno.EROFS, errno.ENOTSUP, errno.ESPIPE):
                self.fsync_ok = False  # a pipe or special file: nothing to sync
                log.debug("fsync not supported on this log output: %s", e)
            else:
                raise

    def close(self) -> None:
        self._f.close()


class WriterThread:
    """The writer thread's half of :class:`companion.log.writer.McapLogger`."""

    path: Path
    chunk_size: int
    flush_interval_s: float
    fsync_policy: str
    fsync_count: int
    fsync_time_s: float
    observer: Any
    _compression: CompressionType
    _extra: dict[str, dict[str, Any]]
    _q: collections.deque[Any]
    _wake: threading.Event
    _lock: threading.Lock
    _space: threading.Condition
    _may_write: threading.Event
    _topics: dict[str, str]
    _written: int
    _flushed: int
    _dropped: int
    _errors: int
    _last_err_warn: float
    _pending_image_bytes: int
    _failure: BaseException | None
    _sink: Sink | None
    _closed: bool

    def _schema_text(self, name: str) -> bytes:
        if name in self._extra:
            return encode_json(self._extra[name])
        if name in sch.PROTOBUF_SCHEMAS:
            return sch.protobuf_schema_bytes(name)
        return sch.schema_bytes(name)

    def _run(self) -> None:
        assert self._sink is not None
        sink = self._sink
        channels: dict[str, int] = {}
        schema_ids: dict[str, int] = {}
        writer: Writer | None = None
        next_flush = time.monotonic() + self.flush_interval_s
        try:
            writer = LeanWriter(sink, chunk_size=self.chunk_size, compression=self._compression)
            writer.start(profile="", library=f"companion-{__version__}")
            self._flush(writer, sink)
            while self._drain(writer, channels, schema_ids):
                if time.monotonic() >= next_flush:
                    self._flush(writer, sink)
                    next_flush = time.monotonic() + self.flush_interval_s
                poll = POLL_S if self.observer is None else POLL_LIVE_S
                self._wake.wait(min(poll, max(0.0, next_flush - time.monotonic())))
                self._wake.clear()
            writer.finish()  # type: ignore[no-untyped-call]
            sink.flush()
            if self.fsync_policy != "never":
                self._fsync(sink)
            with self._lock:
                self._flushed = self._written
        except BaseException as e:  # disk full, broken pipe...: stop logging, never the flight
            with self._space:
                self._failure = e
                self._space.notify_all()
            log.error("MCAP writer stopped: %r (%d items written)", e, self._written)
            self._drain_after_failure()
        finally:
            try:
                sink.close()
            except OSError as e:
                log.error("closing %s: %s", self.path, e)

    def _drain(self, writer: Writer, channels: dict[str, int],
               schema_ids: dict[str, int]) -> bool:
        """Write what is queued; False once the end marker was reached."""
        q, may_write = self._q, self._may_write
        while q:
            item = q.popleft()
            if item is STOP:
                return False
            if not may_write.is_set():
                may_write.wait(MAX_HOLD_S)
            self._write(writer, item, channels, schema_ids)
        return True

    def _drain_after_failure(self) -> None:
        while True:
            while self._q:
                if self._q.popleft() is STOP:
                    return
                with self._lock:
                    self._dropped += 1
            if self._closed and not self._q:
                return
            self._wake.wait(0.05)
            self._wake.clear()

    def _flush(self, writer: Writer, sink: Sink) -> None:
        n = self._written
        writer.flush()  # type: ignore[no-untyped-call]  # closes the chunk, flushes the stream
        if self.fsync_policy == "interval":
            self._fsync(sink)
        with self._lock:
            self._flushed = n

    def _fsync(self, sink: Sink) -> None:
        t0 = time.perf_counter()
        sink.fsync()
        self.fsync_time_s += time.perf_counter() - t0
        self.fsync_count += 1

    def _write(
        self,
        writer: Writer,
        item: tuple[Any, ...],
        channels: dict[str, int],
        schema_ids: dict[str, int],
    ) -> None:
        kind, topic, t, pub, payload = item
        try:
            if kind == "mavlink":  # the most frequent: ~12 a step
                schema_name, data = self._topics[topic], encode_json(mavlink_payload(*payload))
            elif kind == "json":
                schema_name, data = self._topics[topic], encode_json(payload)
            elif kind == "bytes":
                schema_name, data = self._topics[topic], bytes(payload)
            elif kind == "image":
                image, enc, frame_id, stamp_ns, scale, quality = payload
                try:
                    small = downscale(image, scale) if scale != 1.0 else image
                    schema_name, data = encode_image(small, enc, stamp_ns, frame_id, quality)
                finally:
                    with self._space:
                        self._pending_image_bytes -= int(image.nbytes)
                        self._space.notify_all()
            else:
                raise McapLogError(f"unknown log item kind {kind!r}")
        except (McapLogError, TypeError, ValueError, AttributeError) as e:
            now = time.monotonic()
            with self._lock:
                self._errors += 1
                warn = now - self._last_err_warn >= 1.0
                if warn:
                    self._last_err_warn = now
            if warn:
                log.warning("MCAP: cannot encode an item for %s: %s", topic, e)
            return
        cid = channels.get(topic)
        if cid is None:
            sid = schema_ids.get(schema_name)
            if sid is None:
                sid = writer.register_schema(
                    schema_name, sch.encodings(schema_name)[0], self._schema_text(schema_name)
                )
                schema_ids[schema_name] = sid
            cid = writer.register_channel(topic, sch.encodings(schema_name)[1], sid)
            channels[topic] = cid
            enc_s, enc_m = sch.encodings(schema_name)
            self._observe("add_channel", topic, schema_name, enc_s,
                          self._schema_text(schema_name), enc_m)
        writer.add_message(cid, t, data, t if pub is None else int(pub))
        # only this thread writes the count (a reader's lock still sees it whole)
        self._written += 1
        if self.observer is not None:
            self._observe("message", topic, t, data)

    def _observe(self, what: str, *args: Any) -> None:
        if self.observer is None:
            return
        try:
            getattr(self.observer, what)(*args)
        except Exception as e:  # the live view is optional: stop feeding it, keep logging
            log.error("log observer failed, detached: %r", e)
            self.observer = None
