"""Always-on MCAP flight log, written by a background thread so the control loop never blocks.

``log*`` calls only validate cheap things and put an item on a bounded queue; JSON encoding,
JPEG/PNG encoding (cv2) and ``mcap.writer.Writer`` calls all happen in the writer thread. When
the queue is full the item is dropped and counted (a warning at most once per second).

Durability: the current chunk is closed and the file flushed every ``flush_interval_s`` (a
chunk also closes when it reaches ``chunk_size`` bytes), so a process killed at any time leaves
a file that :mod:`companion.log.reader` salvages up to the last closed chunk. ``fsync`` policy:
"interval" (default) also ``os.fsync``-s at every timed flush, so a power loss costs at most
``flush_interval_s``; "close" only at the end; "never" leaves it to the OS. The fsyncs run in the
writer thread (``fsync_count``, ``fsync_time_s``), never in the caller's.

Times: ``log_time_ns`` comes from the caller's clock; the logger never reads a clock for data
(only to pace flushes and warnings). Every channel is JSON with a JSON schema
(:mod:`companion.log.schemas`), so the file opens in Foxglove as is. Payload dicts and image arrays
are NOT copied: do not mutate them after handing them over.
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from mcap.writer import CompressionType

from companion.log import McapLogError
from companion.log import schemas as sch
from companion.log.encode import (
    IMAGE_ENCODINGS,
    stamp,
    xyz,
    xyzw,
)
from companion.log.writer_thread import STOP, Sink, WriterThread

log = logging.getLogger(__name__)

_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
_FSYNC_POLICIES = ("interval", "close", "never")


class LogObserver(Protocol):
    """Sees exactly what the MCAP writer writes, in the writer thread, after each write
    (:class:`companion.log.live.LiveServer`). Both calls must return at once (never block)."""

    def add_channel(self, topic: str, schema_name: str, schema_encoding: str,
                    schema_data: bytes, message_encoding: str) -> None: ...

    def message(self, topic: str, log_time_ns: int, data: bytes) -> None: ...


@dataclass(frozen=True)
class LoggerStats:
    """Counters: ``enqueued`` accepted by ``log*``, ``written`` handed to the MCAP writer,
    ``flushed`` written and fsync-ed, ``dropped`` (queue full or logger failed/closed),
    ``errors`` (an item that could not be encoded)."""

    enqueued: int
    written: int
    flushed: int
    dropped: int
    errors: int


class McapLogger(WriterThread):
    """``with McapLogger(path, chunk_size, flush_interval_s, queue_size) as lg: lg.log(...)``.

    Topics are registered lazily: the first ``log`` on a topic fixes its schema name (or call
    :meth:`register`). Logging methods return False when the item was dropped. Thread-safe.
    """

    def __init__(
        self,
        path: str | Path,
        chunk_size: int = 1 << 20,
        flush_interval_s: float = 1.0,
        queue_size: int = 4096,
        max_pending_image_bytes: int = 64 << 20,
        *,
        block_on_backlog: bool = False,
        compression: str = "zstd",
        fsync: str = "interval",
        jpeg_quality: int = 90,
        extra_schemas: Mapping[str, Mapping[str, Any]] | None = None,
    ) -> None:
        if chunk_size < 1:
            raise McapLogError("chunk_size must be >= 1 byte")
        if not flush_interval_s > 0:
            raise McapLogError("flush_interval_s must be > 0")
        if queue_size < 1:
            raise McapLogError("queue_size must be >= 1")
        if compression not in _COMPRESSION:
            raise McapLogError(f"compression {compression!r} not in {sorted(_COMPRESSION)}")
        if fsync not in _FSYNC_POLICIES:
            raise McapLogError(f"fsync policy {fsync!r} not in {_FSYNC_POLICIES}")
        if not 1 <= jpeg_quality <= 100:
            raise McapLogError("jpeg_quality must be in 1..100")
        self.path = Path(path)
        self.chunk_size = chunk_size
        self.flush_interval_s = float(flush_interval_s)
        self.queue_size = queue_size
        self.max_pending_image_bytes = max_pending_image_bytes
        self.block_on_backlog = block_on_backlog
        # cleared while the control step runs: the writer thread then waits between messages
        # (at most MAX_HOLD_S) instead of taking the GIL from the step (hold / release)
        self._may_write = threading.Event()
        self._may_write.set()
        self._pending_image_bytes = 0
        self._images_dropped = 0
        self._last_image_warn = 0.0
        self._compression = _COMPRESSION[compression]
        self.fsync_policy = fsync
        self.fsync_count = 0  # os.fsync calls made by the writer thread
        self.fsync_time_s = 0.0  # wall time spent in them (writer thread, never the loop)
        self._jpeg_quality = jpeg_quality
        self._extra = {k: dict(v) for k, v in (extra_schemas or {}).items()}
        # a plain deque, not queue.Queue: an append wakes no one (the writer thread polls it
        # every POLL_S and drains it in one go), so a record costs its caller ~1 us, not a
        # lock, a notify and a thread switch (see WriterThread)
        self._q: collections.deque[Any] = collections.deque()
        self._wake = threading.Event()  # close, or a queue half full: drain now
        self._lock = threading.Lock()
        self._space = threading.Condition(self._lock)  # image backlog below the byte budget
        self._topics: dict[str, str] = {}
        self._mav_topics: dict[tuple[str, str], str] = {}  # (direction, name) -> registered topic
        self._enqueued = self._written = self._flushed = self._dropped = self._errors = 0
        self._last_warn = -math.inf
        self._last_err_warn = -math.inf
        self._failure: BaseException | None = None
        self._thread: threading.Thread | None = None
        self._sink: Sink | None = None
        self._open = False
        self._closed = False
        #: Set before :meth:`open` to see every channel; a failing observer is dropped, never
        #: the log.
        self.observer: LogObserver | None = None

    @classmethod
    def from_config(cls, logging_cfg: Any, path: str | Path) -> McapLogger:
        """From :class:`companion.config.LoggingConfig` (chunk size, flush interval, queue size);
        the caller picks ``path`` (e.g. under ``logging_cfg.dir``) and passes
        ``logging_cfg.image_encoding`` to :meth:`log_image`."""
        return cls(
            path,
            chunk_size=logging_cfg.chunk_size_bytes,
            flush_interval_s=logging_cfg.flush_interval_s,
            queue_size=logging_cfg.queue_size,
            max_pending_image_bytes=int(getattr(logging_cfg, "max_pending_image_mb", 64)) << 20,
            block_on_backlog=bool(getattr(logging_cfg, "block_on_backlog", False)),
            compression=str(getattr(logging_cfg, "compression", "lz4")),
            fsync=str(getattr(logging_cfg, "fsync", "interval")),
        )

    # -- lifecycle ------------------------------------------------------------------------------

    def __enter__(self) -> McapLogger:
        self.open()
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close(raise_on_failure=exc_type is None)

    def open(self) -> None:
        """Open the file (errors raised here) and start the writer thread."""
        if self._open:
            raise McapLogError("logger already open")
        try:
            f = open(self.path, "wb")  # noqa: SIM115 - owned by the writer thread, closed there
        except OSError as e:
            raise McapLogError(f"cannot open log file {str(self.path)!r}: {e.strerror}") from e
        self._sink = Sink(f)
        self._open = True
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._thread.start()
        log.info("MCAP log: %s", self.path)

    def close(self, raise_on_failure: bool = True) -> None:
        """Drain the queue, write the summary and footer, close the file. Raises
        :class:`McapLogError` if the writer thread failed (unless ``raise_on_failure`` is False)."""
        if not self._open or self._closed:
            return
        with self._space:
            self._closed = True
            self._space.notify_all()
        assert self._thread is not None
        self._q.append(STOP)
        self._wake.set()
        self._thread.join()
        if self._failure is not None and raise_on_failure:
            raise McapLogError(f"MCAP writer failed: {self._failure!r}") from self._failure

    # -- counters -------------------------------------------------------------------------------

    @property
    def images_dropped(self) -> int:
        """Frames dropped because the image backlog exceeded ``max_pending_image_bytes``."""
        with self._lock:
            return self._images_dropped

    @property
    def stats(self) -> LoggerStats:
        with self._lock:
            return LoggerStats(
                self._enqueued, self._written, self._flushed, self._dropped, self._errors
            )

    @property
    def written(self) -> int:
        return self._written

    @property
    def dropped(self) -> int:
        return self._dropped

    @property
    def failure(self) -> BaseException | None:
        """The exception that stopped the writer thread, if any."""
        return self._failure

    # -- logging API (any thread) ---------------------------------------------------------------

    def register(self, topic: str, schema_name: str) -> None:
        """Fix ``topic``'s schema. Re-registering with another schema is an error."""
        if not topic:
            raise McapLogError("empty topic")
        if schema_name not in self._extra and not sch.known(schema_name):
            raise McapLogError(f"unknown schema {schema_name!r} for topic {topic!r}")
        with self._lock:
            old = self._topics.setdefault(topic, schema_name)
        if old != schema_name:
            raise McapLogError(f"topic {topic!r} already uses schema {old!r}, not {schema_name!r}")

    def log(
        self,
        topic: str,
        log_time_ns: int,
        payload: Mapping[str, Any] | bytes,
        schema: str | None = None,
        publish_time_ns: int | None = None,
    ) -> bool:
        """Log a JSON object (dict: encoded in the writer thread) or pre-encoded JSON bytes.
        ``schema`` is required the first time a topic is used (unless registered)."""
        self._ensure_topic(topic, schema)
        kind = "bytes" if isinstance(payload, bytes | bytearray) else "json"
        pub = None if publish_time_ns is None else int(publish_time_ns)
        return self._put((kind, topic, int(log_time_ns), pub, payload))

    def log_image(
        self,
        topic: str,
        log_time_ns: int,
        image: np.ndarray,
        encoding: str = "jpeg",
        frame_id: str = "camera",
        stamp_ns: int | None = None,
        *,
        scale: float = 1.0,
        jpeg_quality: int | None = None,
    ) -> bool:
        """Log a uint8 mono (HxW) or BGR (HxWx3) image as foxglove.CompressedImage ("jpeg",
        "png": encoded with cv2 in the writer thread) or foxglove.RawImage ("raw").
        ``scale`` (0, 1]: downscale first (area interpolation, in the writer thread);
        ``jpeg_quality``: this image's, instead of the logger's."""
        if encoding not in IMAGE_ENCODINGS:
            raise McapLogError(f"image encoding {encoding!r} not in {IMAGE_ENCODINGS}")
        if not 0.0 < scale <= 1.0:
            raise McapLogError(f"image scale {scale!r} not in (0, 1]")
        quality = self._jpeg_quality if jpeg_quality is None else int(jpeg_quality)
        if not 1 <= quality <= 100:
            raise McapLogError("jpeg_quality must be in 1..100")
        self._ensure_topic(topic, sch.RAW_IMAGE if encoding == "raw" else sch.COMPRESSED_IMAGE)
        t = int(log_time_ns)
        item = (
            "image",
            topic,
            t,
            None,
            (image, encoding, frame_id, t if stamp_ns is None else stamp_ns, scale, quality),
        )
        nbytes = int(image.nbytes)
        with self._space:
            if self.block_on_backlog:
                # lockstep: no wall-clock deadline, so wait for the writer rather than drop;
                # a writer held (hold) would then wait for us: let it work
                if self._pending_image_bytes + nbytes > self.max_pending_image_bytes:
                    self._may_write.set()
                self._space.wait_for(
                    lambda: self._pending_image_bytes + nbytes <= self.max_pending_image_bytes
                    or self._failure is not None or self._closed,
                    timeout=10.0,
                )
            over = self._pending_image_bytes + nbytes > self.max_pending_image_bytes
            if not over:
                self._pending_image_bytes += nbytes
        if over:
            # The writer is behind on images (encoding is the costly part): drop this frame
            # rather than let the backlog grow without bound in memory.
            self._drop_image()
            return False
        if not self._put(item):
            with self._space:
                self._pending_image_bytes -= nbytes
                self._space.notify_all()
            return False
        return True

    def _drop_image(self) -> None:
        now = time.monotonic()
        with self._lock:
            self._dropped += 1
            self._images_dropped += 1
            warn = now - self._last_image_warn >= 1.0
            if warn:
                self._last_image_warn = now
            n = self._images_dropped
        if warn:
            log.warning("MCAP log: image backlog over %d MB, %d frames dropped so far",
                        self.max_pending_image_bytes >> 20, n)

    def log_text(
        self, topic: str, log_time_ns: int, message: str, level: str = "INFO", name: str = ""
    ) -> bool:
        """foxglove.Log text (level: DEBUG, INFO, WARNING, ERROR, FATAL)."""
        if level not in sch.LOG_LEVELS:
            raise McapLogError(f"log level {level!r} not in {sorted(sch.LOG_LEVELS)}")
        msg = {
            "timestamp": stamp(log_time_ns), "level": sch.LOG_LEVELS[level], "message": message,
            "name": name, "file": "", "line": 0,
        }  # fmt: skip
        return self.log(topic, log_time_ns, msg, schema=sch.LOG)

    def log_pose(
        self,
        topic: str,
        log_time_ns: int,
        frame_id: str,
        position_m: Sequence[float],
        q_wxyz: Sequence[float],
    ) -> bool:
        """foxglove.PoseInFrame (quaternion given w,x,y,z; written as Foxglove's x,y,z,w)."""
        msg = {
            "timestamp": stamp(log_time_ns),
            "frame_id": frame_id,
            "pose": {"position": xyz(position_m), "orientation": xyzw(q_wxyz)},
        }
        return self.log(topic, log_time_ns, msg, schema=sch.POSE_IN_FRAME)

    def log_transform(
        self,
        topic: str,
        log_time_ns: int,
        parent_frame_id: str,
        child_frame_id: str,
        translation_m: Sequence[float],
        q_wxyz: Sequence[float],
    ) -> bool:
        """foxglove.FrameTransform: the child frame's pose in the parent (q w,x,y,z)."""
        msg = {
            "timestamp": stamp(log_time_ns), "parent_frame_id": parent_frame_id,
            "child_frame_id": child_frame_id, "translation": xyz(translation_m),
            "rotation": xyzw(q_wxyz),
        }  # fmt: skip
        return self.log(topic, log_time_ns, msg, schema=sch.FRAME_TRANSFORM)

    def log_mavlink(self, direction: str, item: Any, log_time_ns: int | None = None) -> bool:
        """Log a :class:`companion.link.Received` (``direction`` "in") or ``Sent``
        ("out") on ``/mavlink/<direction>/<NAME>``; log time defaults to its link timestamp."""
        if direction not in ("in", "out"):
            raise McapLogError(f"direction {direction!r} is not 'in' or 'out'")
        t_link = item.t_rx_ns if direction == "in" else item.t_tx_ns
        topic = self._mav_topics.get((direction, item.name))
        if topic is None:
            topic = f"/mavlink/{direction}/{item.name}"
            self._ensure_topic(topic, sch.MAVLINK_PREFIX + item.name)
            self._mav_topics[(direction, item.name)] = topic
        t = int(t_link if log_time_ns is None else log_time_ns)
        return self._put(("mavlink", topic, t, None, (direction, item)))

    def log_rejected(self, reason: str, raw: bytes, t_rx_ns: int,
                     log_time_ns: int | None = None) -> bool:
        """A frame the MAVLink link rejected (its ``on_reject`` callback) on
        ``/mavlink/rejected``: reason, bytes (base64), link receive time. ``log_time_ns``: the
        log's time base when it is not the receipt clock (default ``t_rx_ns``)."""
        payload = {"reason": reason, "raw_b64": raw, "t_rx_ns": int(t_rx_ns)}
        t = int(t_rx_ns) if log_time_ns is None else int(log_time_ns)
        return self.log("/mavlink/rejected", t, payload, schema=sch.MAVLINK_REJECTED)

    def log_config(
        self, log_time_ns: int, toml_text: str, parsed: Mapping[str, Any], source: str = ""
    ) -> bool:
        """The configuration of this run on ``/config`` (TOML text + parsed dict), once at start."""
        payload = {"source": source, "toml": toml_text, "config": parsed}
        return self.log("/config", log_time_ns, payload, schema=sch.CONFIG)

    # -- internals ------------------------------------------------------------------------------

    def _ensure_topic(self, topic: str, schema: str | None) -> None:
        cur = self._topics.get(topic)
        if cur is not None and (schema is None or schema == cur):
            return
        if schema is None:
            raise McapLogError(f"topic {topic!r} is new: give its schema name")
        self.register(topic, schema)

    def hold(self) -> None:
        """Keep the writer thread off the GIL until :meth:`release` (at most ``MAX_HOLD_S``
        per message): the control step holds it while it computes. The writer serialises
        messages in Python; a step that wants the GIL back from it can wait up to the switch
        interval. Logging itself is unchanged (nothing is dropped; a message waits in the
        queue), only when the writer works; a hold ends early when the holder's own logging
        would wait for the writer (an image backlog) or the queue is half full."""
        self._may_write.clear()

    def release(self) -> None:
        """Let the writer thread work again (see :meth:`hold`)."""
        self._may_write.set()

    def _put(self, item: tuple[Any, ...]) -> bool:
        if not isinstance(item[2], int) or item[2] < 0 or (item[3] is not None and item[3] < 0):
            raise McapLogError(f"log time must be a non-negative int (ns), got {item[2]!r}")
        if not self._open or self._closed or self._failure is not None:
            with self._lock:
                self._dropped += 1
            return False
        q = self._q
        if len(q) >= self.queue_size:
            now = time.monotonic()
            with self._lock:
                self._dropped += 1
                warn = now - self._last_warn >= 1.0
                if warn:
                    self._last_warn = now
                dropped = self._dropped
            if warn:
                log.warning(
                    "MCAP log queue full (%d): %d items dropped so far", self.queue_size, dropped
                )
            return False
        q.append(item)
        if len(q) * 2 >= self.queue_size:  # drain now, held or not: a full queue drops
            self._may_write.set()
            self._wake.set()
        with self._lock:
            self._enqueued += 1
        return True
