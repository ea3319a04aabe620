"""The records inside one MCAP chunk, for :mod:`companion.log.reader`: the chunk's bytes
decompressed and CRC-checked, walked record by record, and its messages of some channels as
plain tuples (a replay reads ~170 messages a second of flight: building an ``mcap`` ``Message``
object for each cost more than decompressing the chunk)."""

from __future__ import annotations

import io
import struct
from collections.abc import Iterator
from typing import BinaryIO

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Chunk
from mcap.stream_reader import get_chunk_data_stream

RECORD_HEAD = struct.Struct("<BQ")  # opcode, body length
MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


def chunk_data(f: BinaryIO, offset: int) -> bytes:
    """The decompressed, CRC-checked records of the chunk record at ``offset`` of ``f``
    (``McapError``, ``ValueError``... when it is not a whole, intact chunk)."""
    f.seek(offset)
    opcode, length = RECORD_HEAD.unpack(f.read(RECORD_HEAD.size))
    if opcode != Opcode.CHUNK:
        raise McapError(f"no chunk at offset {offset}")
    body = f.read(length)
    if len(body) != length:
        raise McapError("chunk cut short")
    chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
    stream, n = get_chunk_data_stream(chunk, validate_crc=True)
    data: bytes = stream.read(n)
    return data


def records(data: bytes) -> Iterator[tuple[int, int, int]]:
    """``(opcode, body start, body end)`` of the records of a chunk's decompressed data."""
    n, pos, head = len(data), 0, RECORD_HEAD
    while pos < n:
        op, rlen = head.unpack_from(data, pos)
        start = pos + head.size
        pos = start + rlen
        if pos > n:
            raise McapError(f"record at byte {start} of a chunk runs past its end")
        yield op, start, pos


def message_tuples(data: bytes, ids: frozenset[int]) -> list[tuple[int, int, bytes]]:
    """``(channel id, log time, message bytes)`` of the messages of channels ``ids`` in a
    chunk's decompressed data, in file order (the others skipped by their length)."""
    out: list[tuple[int, int, bytes]] = []
    head = MESSAGE_HEAD
    for op, start, end in records(data):
        if op == Opcode.MESSAGE:
            if end - start < head.size:
                raise McapError(f"message record of {end - start} bytes")
            cid, _, log_time, _ = head.unpack_from(data, start)
            if cid in ids:
                out.append((cid, log_time, data[start + head.size:end]))
    return out
