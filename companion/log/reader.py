"""Read a companion MCAP log robustly, including files cut short by a crash or power loss.

Opening indexes the file once:

* intact file: the summary (footer, chunk indexes, channels) is read with the normal seeking
  reader (``mcap.reader.SeekingReader``) and every chunk's CRC is checked;
* otherwise (no footer, unreadable summary): SALVAGE. The data section is walked record by
  record with mcap's record parsers; each complete chunk whose CRC and decompression check out
  is kept, a corrupt chunk is skipped and counted, and the walk stops at the first incomplete
  record (the truncation point). :attr:`LogReader.recovery` says what came back.

Iteration (:meth:`LogReader.messages`) yields :class:`LogMessage` in log-time order (ties in file
order), merging chunks with a heap like mcap's own reader, so memory stays bounded by the chunks
overlapping in time. JSON channels are decoded to dicts; foxglove images to numpy arrays.
"""

from __future__ import annotations

import bisect
import heapq
import io
import logging
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Schema

from companion import CompanionError
from companion.log import schemas as sch
from companion.log.chunks import MESSAGE_HEAD, RECORD_HEAD, chunk_data, message_tuples, records
from companion.log.encode import decode_json
from companion.log.images import decode_image, decode_protobuf_image, image_from_raw

__all__ = [
    "ChannelInfo", "LogMessage", "LogReadError", "LogReader", "NotMcapError", "Recovery",
    "decode_image", "decode_protobuf_image", "image_from_raw", "read_log",
]

log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = RECORD_HEAD
_MESSAGE_HEAD = MESSAGE_HEAD
#: What a damaged chunk may raise while being decompressed, CRC-checked or parsed.
_CHUNK_ERRORS = (
    McapError, ValueError, struct.error, RuntimeError, EOFError, IndexError, KeyError,
    zstandard.ZstdError,
)  # fmt: skip


class LogReadError(CompanionError):
    """A log file cannot be read at all (missing, unreadable)."""


class NotMcapError(LogReadError):
    """The file is not an MCAP file (wrong magic)."""


@dataclass(frozen=True)
class ChannelInfo:
    """One channel's content: message count and log-time range (ns)."""

    topic: str
    schema_name: str
    message_encoding: str
    count: int
    first_log_time_ns: int | None
    last_log_time_ns: int | None

    @property
    def duration_s(self) -> float:
        if self.first_log_time_ns is None or self.last_log_time_ns is None:
            return 0.0
        return (self.last_log_time_ns - self.first_log_time_ns) * 1e-9

    @property
    def rate_hz(self) -> float:
        """Mean message rate, (count - 1) / duration; 0 with fewer than 2 messages."""
        d = self.duration_s
        return (self.count - 1) / d if self.count > 1 and d > 0 else 0.0


@dataclass(frozen=True)
class Recovery:
    """What reading the file recovered.

    ``salvaged``: the summary could not be used, the data section was walked instead;
    ``truncated``: the file ends before its footer; ``messages``: messages readable;
    ``corrupt_chunks``: chunks skipped (CRC or decompression failure); ``orphan_messages``:
    messages whose channel definition was lost; ``bytes_used`` / ``bytes_total``: where the walk
    stopped; ``stop_reason``: why it stopped early ("" when the file is complete).
    """

    salvaged: bool
    truncated: bool
    messages: int
    corrupt_chunks: int
    orphan_messages: int
    first_log_time_ns: int | None
    last_log_time_ns: int | None
    bytes_used: int
    bytes_total: int
    stop_reason: str


@dataclass(frozen=True)
class LogMessage:
    """One logged message. ``data``: the decoded JSON object (for images without the base64
    ``data`` field), None for non-JSON channels; ``image``: the decoded picture of a
    foxglove.CompressedImage / RawImage (HxW or HxWx3 uint8, BGR), else None; ``raw``: the
    message bytes as stored."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    schema_name: str
    data: dict[str, Any] | None
    image: np.ndarray | None
    raw: bytes
    message_encoding: str = "json"


@dataclass(frozen=True)
class _ChunkRef:
    offset: int  # of the chunk record's opcode byte
    start_ns: int
    end_ns: int
    #: ids of the channels with messages in the chunk (its index); None: not known, read it
    channels: frozenset[int] | None = None


class LogReader:
    """``with LogReader(path) as r: r.recovery, r.channels, for m in r.messages(): ...``"""

    def __init__(self, path: str | Path, *, verify: bool = True) -> None:
        """``verify``: read every chunk once at open (CRC-checked) so that :attr:`recovery` and
        :attr:`channels` count exactly what is readable. ``verify=False`` on a file with an
        intact summary skips that pass (one read of the file instead of two): counts come
        from the summary's statistics, per-channel times are chunk bounds, and chunks are
        still CRC-checked as :meth:`messages` reads them (a damaged one is skipped and counted
        in ``recovery.corrupt_chunks`` then). A file without a usable summary is always
        walked and verified."""
        self.path = Path(path)
        self._verify = verify
        try:
            self._f: BinaryIO = open(self.path, "rb")  # noqa: SIM115 - closed by close()
        except OSError as e:
            raise LogReadError(f"cannot open log {str(self.path)!r}: {e.strerror}") from e
        try:
            self._size = self.path.stat().st_size
            if self._f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise NotMcapError(f"{str(self.path)!r} is not an MCAP file (bad magic)")
            self._schemas: dict[int, Schema] = {}
            self._channels: dict[int, Channel] = {}
            self._chunks: list[_ChunkRef] = []
            self._loose: list[Message] = []
            self._index()
        except BaseException:
            self._f.close()
            raise

    def __enter__(self) -> LogReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._f.close()

    # -- indexing -------------------------------------------------------------------------------

    def _index(self) -> None:
        counts: dict[int, list[int]] = {}  # channel id -> [count, first, last]
        self._corrupt = 0
        self._orphans = 0
        summary = None
        try:
            self._f.seek(0)
            summary = SeekingReader(self._f, validate_crcs=True).get_summary()
        except (McapError, ValueError, struct.error, OSError) as e:
            log.info("%s: summary unusable (%s): salvaging", self.path, e)
        usable = summary is not None and (
            bool(summary.chunk_indexes)
            or (summary.statistics is not None and summary.statistics.message_count == 0)
        )  # an unchunked file (messages outside chunks) is walked instead
        if summary is not None and usable:
            self._salvaged, self._truncated = False, False
            self._schemas.update(summary.schemas)
            self._channels.update(summary.channels)
            refs = [
                _ChunkRef(ci.chunk_start_offset, ci.message_start_time, ci.message_end_time,
                          frozenset(ci.message_index_offsets) or None)
                for ci in summary.chunk_indexes
            ]
            stats = summary.statistics
            if not self._verify and stats is not None:
                self._chunks = refs
                for ci in summary.chunk_indexes:
                    for cid in ci.message_index_offsets:
                        c = counts.setdefault(cid, [0, ci.message_start_time,
                                                    ci.message_end_time])
                        c[1] = min(c[1], ci.message_start_time)
                        c[2] = max(c[2], ci.message_end_time)
                for cid, n in stats.channel_message_counts.items():
                    if cid in counts:
                        counts[cid][0] = n
                    elif n > 0:
                        counts[cid] = [n, stats.message_start_time, stats.message_end_time]
                self._bytes_used, self._stop = self._size, ""
                self._counts = counts
                return
            for ref in refs:
                msgs = self._read_chunk(ref.offset, learn=False)
                if msgs is not None:
                    self._chunks.append(ref)
                    self._tally(msgs, counts)
            self._bytes_used, self._stop = self._size, ""
        else:
            self._salvaged = True
            self._walk(counts)
        self._counts = counts

    def _tally(self, msgs: Iterable[Message], counts: dict[int, list[int]]) -> None:
        for m in msgs:
            if m.channel_id not in self._channels:
                self._orphans += 1
                continue
            c = counts.get(m.channel_id)
            if c is None:
                counts[m.channel_id] = [1, m.log_time, m.log_time]
            else:
                c[0] += 1
                c[1] = min(c[1], m.log_time)
                c[2] = max(c[2], m.log_time)

    def _read_chunk(self, offset: int, learn: bool,
                    channel_ids: frozenset[int] | None = None) -> list[Message] | None:
        """Messages of the chunk record at ``offset`` (None if it is damaged). ``learn``:
        record the schemas and channels defined inside it. ``channel_ids``: only the messages
        of these channels (the others are skipped by their length, never parsed: a replay
        reading two topics of a chunk of twenty)."""
        try:
            data = chunk_data(self._f, offset)
            out: list[Message] = []
            for op, start, end in records(data):
                if op == Opcode.MESSAGE:
                    if end - start < _MESSAGE_HEAD.size:
                        raise McapError(f"message record of {end - start} bytes")
                    cid, seq, log_time, pub_time = _MESSAGE_HEAD.unpack_from(data, start)
                    if channel_ids is None or cid in channel_ids:
                        out.append(Message(channel_id=cid, sequence=seq, log_time=log_time,
                                           publish_time=pub_time,
                                           data=data[start + _MESSAGE_HEAD.size:end]))
                elif learn and op in (Opcode.SCHEMA, Opcode.CHANNEL):
                    rec = ReadDataStream(io.BytesIO(data[start:end]))
                    if op == Opcode.SCHEMA:
                        sc = Schema.read(rec)
                        self._schemas[sc.id] = sc
                    else:
                        ch = Channel.read(rec)
                        self._channels[ch.id] = ch
        except _CHUNK_ERRORS as e:
            self._damaged(offset, e)
            return None
        return out

    def _chunk_messages(self, offset: int, ids: frozenset[int]
                        ) -> list[tuple[int, int, bytes]] | None:
        """``(channel id, log time, bytes)`` of the chunk's messages of channels ``ids``, in
        file order: :meth:`_read_chunk` without a ``Message`` object per message; None when
        the chunk is damaged (counted and warned the same way)."""
        try:
            return message_tuples(chunk_data(self._f, offset), ids)
        except _CHUNK_ERRORS as e:
            self._damaged(offset, e)
            return None

    def _damaged(self, offset: int, e: BaseException) -> None:
        self._corrupt += 1
        log.warning("%s: skipping damaged chunk at byte %d: %s", self.path, offset, e)

    def _walk(self, counts: dict[int, list[int]]) -> None:
        """Salvage: walk the data section record by record."""
        pos = len(MCAP_MAGIC)
        self._truncated, self._stop = True, "end of file before the footer"
        while True:
            self._f.seek(pos)
            head = self._f.read(_RECORD_HEAD.size)
            if len(head) < _RECORD_HEAD.size:
                if head:
                    self._stop = f"incomplete record header at byte {pos}"
                break
            opcode, length = _RECORD_HEAD.unpack(head)
            end = pos + _RECORD_HEAD.size + length
            if end > self._size:
                self._stop = f"record at byte {pos} runs past the end of the file"
                break
            if opcode == Opcode.FOOTER:
                self._truncated, self._stop = False, ""
                pos = end
                break
            if opcode == Opcode.CHUNK:
                msgs = self._read_chunk(pos, learn=True)
                if msgs is not None:
                    if msgs:
                        start = min(m.log_time for m in msgs)
                        stop = max(m.log_time for m in msgs)
                        self._chunks.append(_ChunkRef(pos, start, stop,
                                                      frozenset(m.channel_id for m in msgs)))
                    self._tally(msgs, counts)
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                body = self._f.read(length)
                try:
                    stream = ReadDataStream(io.BytesIO(body))
                    if opcode == Opcode.SCHEMA:
                        s = Schema.read(stream)
                        self._schemas[s.id] = s
                    elif opcode == Opcode.CHANNEL:
                        c = Channel.read(stream)
                        self._channels[c.id] = c
                    else:
                        m = Message.read(stream, length)
                        self._loose.append(m)
                        self._tally([m], counts)
                except _CHUNK_ERRORS as e:
                    self._stop = f"damaged record at byte {pos}: {e}"
                    break
            pos = end
        self._bytes_used = pos

    # -- results --------------------------------------------------------------------------------

    @property
    def recovery(self) -> Recovery:
        n = sum(c[0] for c in self._counts.values())
        firsts = [c[1] for c in self._counts.values()]
        lasts = [c[2] for c in self._counts.values()]
        return Recovery(
            salvaged=self._salvaged,
            truncated=self._truncated,
            messages=n,
            corrupt_chunks=self._corrupt,
            orphan_messages=self._orphans,
            first_log_time_ns=min(firsts) if firsts else None,
            last_log_time_ns=max(lasts) if lasts else None,
            bytes_used=self._bytes_used,
            bytes_total=self._size,
            stop_reason=self._stop,
        )

    @property
    def channels(self) -> list[ChannelInfo]:
        """Every channel defined in the readable part, sorted by topic."""
        out = []
        for cid, ch in self._channels.items():
            c = self._counts.get(cid)
            out.append(
                ChannelInfo(
                    topic=ch.topic,
                    schema_name=self._schema_name(ch),
                    message_encoding=ch.message_encoding,
                    count=c[0] if c else 0,
                    first_log_time_ns=c[1] if c else None,
                    last_log_time_ns=c[2] if c else None,
                )
            )
        return sorted(out, key=lambda i: i.topic)

    def _schema_name(self, ch: Channel) -> str:
        s = self._schemas.get(ch.schema_id)
        return s.name if s is not None else ""

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
        decode: bool = True,
    ) -> Iterator[LogMessage]:
        """Messages in log-time order (ties: file order), optionally only ``topics`` and
        ``start_ns <= log_time < end_ns``. ``decode=False`` skips JSON and image decoding."""
        wanted = None if topics is None else set(topics)
        ids = None if wanted is None else frozenset(
            cid for cid, ch in self._channels.items() if ch.topic in wanted)
        heap: list[tuple[int, int, int, Any]] = []
        for ref in self._chunks:
            if ids is not None and ref.channels is not None and ref.channels.isdisjoint(ids):
                continue  # none of the topics in it (its index says): never decompressed
            if end_ns is not None and ref.start_ns >= end_ns:
                continue
            if start_ns is not None and ref.end_ns < start_ns:
                continue
            heapq.heappush(heap, (ref.start_ns, ref.offset, -1, ref))
        for i, m in enumerate(self._loose):
            heapq.heappush(heap, (m.log_time, -1, i, m))
        while heap:
            item = heapq.heappop(heap)[3]
            if isinstance(item, _ChunkRef):
                msgs = self._read_chunk(item.offset, learn=False, channel_ids=ids) or []
                for i, m in enumerate(msgs):
                    heapq.heappush(heap, (m.log_time, item.offset, i, m))
                continue
            m = item
            ch = self._channels.get(m.channel_id)
            if ch is None or (wanted is not None and ch.topic not in wanted):
                continue
            if (start_ns is not None and m.log_time < start_ns) or (
                end_ns is not None and m.log_time >= end_ns
            ):
                continue
            yield self._decode(ch, m, decode)

    def raw_messages(self, topics: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, log time ns, stored bytes)`` of the messages of ``topics``, in the order
        of :meth:`messages` (log time, ties in file order), without building a
        :class:`LogMessage` per message: a replay reads ~170 messages a second of flight,
        and the per-message objects and heap operations cost more than reading the chunks.

        The order is the same by construction: a chunk's index start time is its earliest
        message's, so once the next chunk (by start time, then file offset) is reached,
        every message read so far that sorts before it is final."""
        wanted = set(topics)
        names = {cid: ch.topic for cid, ch in self._channels.items() if ch.topic in wanted}
        ids = frozenset(names)
        refs = sorted((r for r in self._chunks
                       if r.channels is None or not r.channels.isdisjoint(ids)),
                      key=lambda r: (r.start_ns, r.offset))
        # (log time, chunk offset (-1: outside chunks), index, topic, bytes)
        buf: list[tuple[int, int, int, str, bytes]] = sorted(
            (m.log_time, -1, i, names[m.channel_id], m.data)
            for i, m in enumerate(self._loose) if m.channel_id in names)
        for ref in refs:
            bound = (ref.start_ns, ref.offset, -1)
            cut = bisect.bisect_left(buf, bound)
            for item in buf[:cut]:
                yield item[3], item[0], item[4]
            del buf[:cut]
            msgs = self._chunk_messages(ref.offset, ids)
            if msgs:
                off = ref.offset
                buf.extend((t, off, i, names[cid], data)
                           for i, (cid, t, data) in enumerate(msgs))
                buf.sort()
        for item in buf:
            yield item[3], item[0], item[4]

    def _decode(self, ch: Channel, m: Message, decode: bool) -> LogMessage:
        schema_name = self._schema_name(ch)
        data: dict[str, Any] | None = None
        image: np.ndarray | None = None
        if decode and ch.message_encoding == sch.PROTOBUF_ENCODING:
            if schema_name in sch.PROTOBUF_SCHEMAS:
                data, image = decode_protobuf_image(schema_name, m.data)
        elif decode and ch.message_encoding == sch.MESSAGE_ENCODING:
            try:
                data = decode_json(m.data)
            except (ValueError, UnicodeDecodeError) as e:
                log.warning(
                    "%s: undecodable JSON on %s at %d: %s", self.path, ch.topic, m.log_time, e
                )
            if isinstance(data, dict) and schema_name in (sch.COMPRESSED_IMAGE, sch.RAW_IMAGE):
                image = decode_image(schema_name, data)
                data.pop("data", None)
        return LogMessage(
            topic=ch.topic,
            log_time_ns=m.log_time,
            publish_time_ns=m.publish_time,
            schema_name=schema_name,
            data=data if isinstance(data, dict) else None,
            image=image,
            raw=bytes(m.data),
            message_encoding=ch.message_encoding,
        )



def read_log(path: str | Path, decode: bool = True) -> tuple[Recovery, list[LogMessage]]:
    """Convenience: the recovery report and every message, in log-time order."""
    with LogReader(path) as r:
        return r.recovery, list(r.messages(decode=decode))
