"""LogReader.raw_messages (the replay's lean read) gives what messages(decode=False) gives:
the same messages, order and bytes, on chunks overlapping in time, salvaged, unchunked and
damaged files."""

from __future__ import annotations

import io
import itertools
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from companion.log import schemas as sch
from companion.log.reader import LogReader
from companion.log.writer import McapLogger

N = 2000


@pytest.fixture(scope="module")
def jittered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three topics, 4 KiB chunks, log times out of order by up to ~30 messages (ties too):
    chunks overlap in time, so the order comes from merging them."""
    path = tmp_path_factory.mktemp("raw") / "jitter.mcap"
    rng = np.random.default_rng(11)
    with McapLogger(path, chunk_size=4096, flush_interval_s=10.0, queue_size=N + 10) as lg:
        for i in range(N):
            t = max(0, 1000 * i + int(rng.integers(-30_000, 30_000)) // 1000 * 1000)
            lg.log(("/a", "/b", "/c")[i % 3], t,
                   {"i": i, "noise": rng.integers(0, 1 << 30, 6).tolist()}, schema=sch.JSON)
    return path


Row = tuple[str, int, bytes]


def _both(r: LogReader, topics: list[str]) -> tuple[list[Row], list[Row]]:
    old = [(m.topic, m.log_time_ns, m.raw) for m in r.messages(topics=topics, decode=False)]
    return old, list(r.raw_messages(topics))


def test_raw_messages_match_messages(jittered: Path, tmp_path: Path) -> None:
    with LogReader(jittered, verify=False) as r:
        times = [t for _, t, _ in r.raw_messages(["/a", "/b", "/c"])]
        refs = sorted((c.start_ns, c.end_ns) for c in r._chunks)
    assert times == sorted(times) and len(times) == N
    assert any(b[0] <= a[1] for a, b in itertools.pairwise(refs))  # chunks overlap
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(jittered.read_bytes()[: jittered.stat().st_size * 2 // 3])
    for path in (jittered, cut):
        with LogReader(path, verify=False) as r:
            for topics in (["/a"], ["/a", "/c"], ["/a", "/b", "/c"], ["/nope"]):
                old, new = _both(r, topics)
                assert new == old
                assert len(new) > 0 or topics == ["/nope"]


def test_raw_messages_of_an_unchunked_file(tmp_path: Path) -> None:
    buf = io.BytesIO()
    w = Writer(buf, use_chunking=False)
    w.start()
    sid = w.register_schema(sch.JSON, "jsonschema", sch.schema_bytes(sch.JSON))
    cid = w.register_channel("/x", "json", sid)
    for i in range(10):
        w.add_message(cid, log_time=10 - i, data=b'{"i": %d}' % i, publish_time=0)
    w.finish()
    path = tmp_path / "plain.mcap"
    path.write_bytes(buf.getvalue())
    with LogReader(path, verify=False) as r:
        old, new = _both(r, ["/x"])
    assert new == old and new[0][2] == b'{"i": 9}'


def test_raw_messages_skip_and_count_a_damaged_chunk(jittered: Path, tmp_path: Path) -> None:
    data = bytearray(jittered.read_bytes())
    with LogReader(jittered, verify=False) as r:
        offsets = sorted(c.offset for c in r._chunks)
    k = len(offsets) // 2
    data[(offsets[k] + offsets[k + 1]) // 2] ^= 0x40  # inside chunk k's compressed data
    path = tmp_path / "flip.mcap"
    path.write_bytes(bytes(data))
    with LogReader(path, verify=False) as r:
        new = list(r.raw_messages(["/a", "/b", "/c"]))
        assert r.recovery.corrupt_chunks == 1
    with LogReader(path, verify=False) as r:
        old = [(m.topic, m.log_time_ns, m.raw) for m in r.messages(decode=False)]
    assert new == old and 0 < len(new) < N
