"""``mcap.writer.Writer`` with a leaner ``add_message``: the same bytes, a third of the CPU.

mcap 1.6's ``add_message`` builds a ``Message`` dataclass and writes its record field by field
(seven ``struct.pack`` and ``BytesIO.write`` calls, a seek back to patch the length): ~10 us a
message here, most of the writer thread's cost for a MAVLink record. :class:`LeanWriter` writes
the record's 31-byte head in one ``struct.pack`` and does the same bookkeeping (file
statistics, the chunk's time range and message index), so the file is byte for byte what
``Writer`` writes (tests/companion/test_mcap_lean.py); a chunk's message index is packed in
one call too. It reaches into the pinned mcap
version's private state; when that is not there (another mcap) it is plain ``Writer``.
"""

from __future__ import annotations

import struct
from typing import Any

from mcap.opcode import Opcode
from mcap.records import MessageIndex
from mcap.writer import Writer

# opcode, record length, channel id, sequence, log time, publish time
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_FIXED = 2 + 4 + 8 + 8
_INDEX_HEAD = struct.Struct("<HI")  # channel id, bytes of (log time, offset) pairs


class _LeanIndex(MessageIndex):
    """A chunk's message index written in one ``struct.pack`` (mcap writes 2 per message)."""

    def write(self, stream: Any) -> None:
        stream.start_record(Opcode.MESSAGE_INDEX)
        n = len(self.records)
        stream.write(_INDEX_HEAD.pack(self.channel_id, n * 16))
        if n:
            flat = [v for rec in self.records for v in rec]
            stream.write(struct.pack(f"<{2 * n}Q", *flat))
        stream.finish_record()


class LeanWriter(Writer):
    """:class:`mcap.writer.Writer` with :meth:`add_message` writing a chunked message in one
    go and its chunk's message index in one ``struct.pack`` (see the module docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        cb: Any = getattr(self, "_Writer__chunk_builder", None)
        self._stats: Any = getattr(self, "_Writer__statistics", None)
        self._chunk: Any = cb
        self._finalize: Any = getattr(self, "_Writer__maybe_finalize_chunk", None)
        self._chunk_size: Any = getattr(self, "_Writer__chunk_size", None)
        self._lean = (
            cb is not None and self._stats is not None and callable(self._finalize)
            and all(hasattr(cb, a) for a in ("message_indices", "record_writer", "num_messages",
                                              "message_start_time", "message_end_time"))
            and hasattr(cb.record_writer, "_buffer") and isinstance(self._chunk_size, int)
        )

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int,
                    sequence: int = 0) -> None:
        if not self._lean:
            super().add_message(channel_id, log_time, data, publish_time, sequence)
            return
        st = self._stats
        if st.message_count == 0 or log_time < st.message_start_time:
            st.message_start_time = log_time
        if log_time > st.message_end_time:
            st.message_end_time = log_time
        st.channel_message_counts[channel_id] += 1
        st.message_count += 1
        cb = self._chunk
        if cb.num_messages == 0 or log_time < cb.message_start_time:
            cb.message_start_time = log_time
        if log_time > cb.message_end_time:
            cb.message_end_time = log_time
        idx = cb.message_indices.get(channel_id)
        if idx is None:
            idx = cb.message_indices[channel_id] = _LeanIndex(channel_id=channel_id,
                                                              records=[])
        buf = cb.record_writer._buffer
        idx.records.append((log_time, buf.tell()))
        cb.num_messages += 1
        buf.write(_MESSAGE_HEAD.pack(Opcode.MESSAGE, _MESSAGE_FIXED + len(data), channel_id,
                                     sequence, log_time, publish_time))
        buf.write(data)
        if buf.tell() > self._chunk_size:  # Writer's own test, without its two calls a message
            self._finalize()
