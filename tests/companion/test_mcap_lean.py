"""LeanWriter writes byte for byte what mcap's Writer writes, and the reader reads it back."""

from __future__ import annotations

import io
import random

import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from companion.log.mcap_lean import LeanWriter


def _write(cls: type[Writer], chunk_size: int, compression: CompressionType) -> bytes:
    rng = random.Random(7)
    buf = io.BytesIO()
    w = cls(buf, chunk_size=chunk_size, compression=compression)
    w.start(profile="", library="test")
    sid = w.register_schema("s", "jsonschema", b"{}")
    chans = [w.register_channel(f"/t{i}", "json", sid) for i in range(3)]
    t = 1_000_000_000
    for k in range(3000):
        t += rng.randint(-2_000_000, 5_000_000)  # log times out of order now and then
        data = bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 300)))
        w.add_message(chans[k % 3], log_time=max(t, 0), data=data,
                      publish_time=max(t, 0) + 7, sequence=k % 5)
        if k == 1500:
            w.flush()
    w.finish()
    return buf.getvalue()


@pytest.mark.parametrize("compression", [CompressionType.LZ4, CompressionType.NONE])
@pytest.mark.parametrize("chunk_size", [1 << 20, 4096])
def test_same_bytes_as_mcap_writer(chunk_size: int, compression: CompressionType) -> None:
    lean = _write(LeanWriter, chunk_size, compression)
    assert lean == _write(Writer, chunk_size, compression)
    msgs = list(make_reader(io.BytesIO(lean)).iter_messages())
    assert len(msgs) == 3000
    assert [m.sequence for _, _, m in msgs[:5]] != []


def test_lean_path_is_taken() -> None:
    w = LeanWriter(io.BytesIO(), chunk_size=1 << 20, compression=CompressionType.LZ4)
    assert w._lean  # the pinned mcap's internals are there: not the fallback
