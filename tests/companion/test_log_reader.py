"""log_reader on intact, truncated, bit-flipped, killed-mid-write and non-MCAP files."""

from __future__ import annotations

import io
import os
import random
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer

from companion import CompanionError
from companion.log import schemas as sch
from companion.log.reader import LogReader, LogReadError, NotMcapError, read_log
from companion.log.writer import McapLogger

ROOT = Path(__file__).resolve().parents[2]
N = 3000


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """N messages on two topics, 4 KiB chunks, written by McapLogger and closed properly."""
    path = tmp_path_factory.mktemp("ref") / "ref.mcap"
    rng = np.random.default_rng(3)
    with McapLogger(path, chunk_size=4096, flush_interval_s=10.0, queue_size=N + 10) as lg:
        for i in range(N):
            topic = "/a" if i % 3 else "/b"
            noise = rng.integers(0, 1 << 30, size=8).tolist()  # keeps chunks from compressing away
            lg.log(topic, 1_000_000 * i, {"i": i, "noise": noise}, schema=sch.JSON)
    assert lg.stats.written == N
    return path


def _chunk_table(path: Path) -> list[tuple[int, int]]:
    """(end byte, message count) of every chunk, from the intact file's summary."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None
        out = []
        for ci in summary.chunk_indexes:
            f.seek(ci.chunk_start_offset + 9)
            from mcap.data_stream import ReadDataStream
            from mcap.records import Chunk

            chunk = Chunk.read(ReadDataStream(f))
            n = sum(isinstance(r, Message) for r in breakup_chunk(chunk, validate_crc=True))
            out.append((ci.chunk_start_offset + ci.chunk_length, n))
    return out


def test_intact_file(reference: Path) -> None:
    with LogReader(reference) as r:
        rec = r.recovery
        chans = {c.topic: c for c in r.channels}
        msgs = list(r.messages())
    assert (rec.salvaged, rec.truncated, rec.messages, rec.corrupt_chunks) == (False, False, N, 0)
    assert (rec.first_log_time_ns, rec.last_log_time_ns) == (0, (N - 1) * 1_000_000)
    assert [m.data["i"] for m in msgs if m.data] == list(range(N))
    b = chans["/b"]
    assert b.count == N // 3 and b.schema_name == sch.JSON
    assert (b.first_log_time_ns, b.last_log_time_ns) == (0, (N - 3) * 1_000_000)
    assert b.rate_hz == pytest.approx(1000.0 / 3.0)  # one every 3 ms
    assert chans["/a"].rate_hz == pytest.approx((N - N // 3 - 1) / ((N - 2) * 1e-3))
    # filters
    with LogReader(reference) as r:
        sel = [
            m.data["i"]
            for m in r.messages(topics=["/b"], start_ns=30_000_000, end_ns=60_000_000)
            if m.data
        ]
    assert sel == list(range(30, 60, 3))
    # one pass: same counts and messages from the summary alone; times to chunk bounds
    with LogReader(reference, verify=False) as r:
        lazy = {c.topic: c for c in r.channels}
        assert r.recovery.messages == N
        assert [m.data["i"] for m in r.messages() if m.data] == list(range(N))
    assert {t: c.count for t, c in lazy.items()} == {t: c.count for t, c in chans.items()}
    assert lazy["/b"].first_log_time_ns <= 0 and lazy["/b"].last_log_time_ns >= (N - 3) * 1e6


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_truncated_file_salvages_every_complete_chunk(
    reference: Path, tmp_path: Path, fraction: float
) -> None:
    data = reference.read_bytes()
    cut = int(len(data) * fraction)
    path = tmp_path / f"cut{int(fraction * 100)}.mcap"
    path.write_bytes(data[:cut])
    expected = sum(n for end, n in _chunk_table(reference) if end <= cut)
    assert expected > 0
    with LogReader(path) as r:
        rec = r.recovery
        got = [m.data["i"] for m in r.messages() if m.data]
    assert rec.salvaged and rec.truncated and rec.corrupt_chunks == 0
    assert rec.messages == expected and got == list(range(expected))
    assert rec.last_log_time_ns == (expected - 1) * 1_000_000
    assert rec.bytes_total == cut and rec.bytes_used <= cut and rec.stop_reason
    # mcap's seeking reader gets nothing out of the same file (the pitfall this module fixes)
    with open(path, "rb") as f, pytest.raises(Exception):  # noqa: B017
        list(make_reader(f, validate_crcs=True).iter_messages())


def test_flipped_byte_costs_only_its_chunk(reference: Path, tmp_path: Path) -> None:
    data = bytearray(reference.read_bytes())
    table = _chunk_table(reference)
    k = len(table) // 2
    start, end = table[k - 1][0], table[k][0]
    data[(start + end) // 2] ^= 0x40  # inside chunk k's compressed data
    path = tmp_path / "flip.mcap"
    path.write_bytes(bytes(data))
    with LogReader(path) as r:
        rec = r.recovery
        got = [m.data["i"] for m in r.messages() if m.data]
    lost = table[k][1]
    first_lost = sum(n for _, n in table[:k])
    assert not rec.salvaged and not rec.truncated  # the summary was intact
    assert rec.corrupt_chunks == 1 and rec.messages == N - lost
    assert got == list(range(first_lost)) + list(range(first_lost + lost, N))

    # one pass (verify=False, as replay reads): the summary's counts up front, the damaged
    # chunk found, skipped and counted while reading, the same messages out
    with LogReader(path, verify=False) as r:
        before = r.recovery
        lazy = [m.data["i"] for m in r.messages() if m.data]
        after = r.recovery
    assert before.messages == N and before.corrupt_chunks == 0
    assert lazy == got and after.corrupt_chunks == 1

    # the same damage in a truncated file: salvage skips the chunk and keeps walking
    cut = tmp_path / "flip_cut.mcap"
    cut.write_bytes(bytes(data[: table[-2][0]]))
    with LogReader(cut) as r:
        rec = r.recovery
    assert rec.salvaged and rec.corrupt_chunks == 1
    assert rec.messages == sum(n for _, n in table[:-1]) - lost


_CHILD = """
import sys, time
from companion.log.writer import McapLogger
lg = McapLogger(sys.argv[1], chunk_size=1 << 20, flush_interval_s=0.05, queue_size=100000)
lg.open()
i = 0
while True:
    lg.log("/seq", i, {"i": i, "pad": "x" * 64}, schema="companion.Json")
    i += 1
    if i % 100 == 0:
        print(lg.stats.flushed, flush=True)
        time.sleep(0.002)
"""


def test_sigkill_mid_write_keeps_everything_flushed(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    flushed = 0
    with subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path)], stdout=subprocess.PIPE, env=env, text=True
    ) as proc:
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                flushed = int(line)
                if flushed >= 3000:
                    break
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    assert flushed >= 3000
    rec, msgs = read_log(path)
    assert rec.truncated and rec.salvaged and rec.corrupt_chunks == 0
    got = [m.data["i"] for m in msgs if m.data]
    assert len(got) >= flushed  # nothing that was reported flushed is lost
    assert got == list(range(len(got)))


def test_unchunked_file_from_another_writer(tmp_path: Path) -> None:
    buf = io.BytesIO()
    w = Writer(buf, use_chunking=False)
    w.start()
    sid = w.register_schema(sch.JSON, "jsonschema", sch.schema_bytes(sch.JSON))
    cid = w.register_channel("/x", "json", sid)
    for i in range(10):
        w.add_message(cid, log_time=10 - i, data=b'{"i": %d}' % i, publish_time=0)
    w.finish()
    whole = tmp_path / "plain.mcap"
    whole.write_bytes(buf.getvalue())
    cut = tmp_path / "plain_cut.mcap"
    cut.write_bytes(buf.getvalue()[:-40])  # no footer
    for path, truncated in ((whole, False), (cut, True)):
        rec, msgs = read_log(path)
        assert rec.salvaged and rec.truncated == truncated and rec.messages == 10
        assert [m.data["i"] for m in msgs if m.data] == list(range(9, -1, -1))  # log-time order


def test_frames_in_every_stored_form_decode(tmp_path: Path) -> None:
    """Protobuf frames (what the companion writes) and the JSON/base64 frames of older logs,
    PNG and raw, mono and colour: the reader gives back the same pixels."""
    import base64
    import json

    import cv2

    from companion.log.encode import encode_image

    rng = np.random.default_rng(3)
    mono = rng.integers(0, 255, (24, 32), dtype=np.uint8)
    bgr = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    buf = io.BytesIO()
    w = Writer(buf)
    w.start()
    expect = []
    for enc in ("png", "raw"):
        for img in (mono, bgr):
            name, data = encode_image(img, enc, 5, "cam", 90)
            sid = w.register_schema(name, "protobuf", sch.protobuf_schema_bytes(name))
            cid = w.register_channel(f"/pb/{enc}/{img.ndim}", "protobuf", sid)
            w.add_message(cid, log_time=len(expect), data=data, publish_time=0)
            expect.append(img)
    ok, png = cv2.imencode(".png", bgr)
    assert ok
    legacy = [
        (sch.COMPRESSED_IMAGE, {"format": "png", "data": base64.b64encode(png.tobytes()).decode()}),
        (sch.RAW_IMAGE, {"width": 32, "height": 24, "encoding": "mono8", "step": 32,
                         "data": base64.b64encode(mono.tobytes()).decode()}),
    ]  # fmt: skip
    for i, (name, msg) in enumerate(legacy):
        sid = w.register_schema(name, "jsonschema", sch.schema_bytes(name))
        cid = w.register_channel(f"/json/{i}", "json", sid)
        w.add_message(cid, log_time=len(expect), data=json.dumps(msg).encode(), publish_time=0)
        expect.append(bgr if i == 0 else mono)
    w.finish()
    path = tmp_path / "frames.mcap"
    path.write_bytes(buf.getvalue())
    _, msgs = read_log(path)
    assert len(msgs) == len(expect)
    for m, img in zip(msgs, expect, strict=True):
        assert m.image is not None and np.array_equal(m.image, img), m.topic
        assert m.data is not None and "data" not in m.data
    assert msgs[0].data == {"timestamp": {"sec": 0, "nsec": 5}, "frame_id": "cam",
                            "format": "png"}
    # a damaged protobuf frame is a warning and no picture, never an exception
    bad = io.BytesIO()
    w = Writer(bad)
    w.start()
    sid = w.register_schema(sch.RAW_IMAGE, "protobuf", sch.protobuf_schema_bytes(sch.RAW_IMAGE))
    cid = w.register_channel("/bad", "protobuf", sid)
    w.add_message(cid, log_time=0, data=b"\xff\xff\xff", publish_time=0)
    w.finish()
    (tmp_path / "bad.mcap").write_bytes(bad.getvalue())
    _, msgs = read_log(tmp_path / "bad.mcap")
    assert len(msgs) == 1 and msgs[0].image is None


def test_not_an_mcap_file(tmp_path: Path) -> None:
    rnd = tmp_path / "random.mcap"
    rnd.write_bytes(random.Random(1).randbytes(10_000))
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    for p in (rnd, empty):
        with pytest.raises(NotMcapError, match="not an MCAP file") as ei:
            LogReader(p)
        assert isinstance(ei.value, CompanionError)
    with pytest.raises(LogReadError, match="cannot open"):
        LogReader(tmp_path / "missing.mcap")


def test_magic_only_file_is_empty_not_an_error(tmp_path: Path) -> None:
    p = tmp_path / "magic.mcap"
    p.write_bytes(b"\x89MCAP0\r\n")
    rec, msgs = read_log(p)
    assert rec.truncated and rec.messages == 0 and msgs == []


def test_reading_some_topics_gives_the_same_messages_as_filtering_all(
    reference: Path, tmp_path: Path
) -> None:
    """A topic filter skips the other channels' records unparsed: the messages, their order
    and payloads are those of the whole stream filtered afterwards; so on a salvaged file."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(reference.read_bytes()[: reference.stat().st_size * 2 // 3])
    for path in (reference, cut):
        with LogReader(path) as r:
            everything = [(m.topic, m.log_time_ns, m.raw) for m in r.messages(decode=False)]
            for topics in (["/a"], ["/b"], ["/a", "/b"], ["/nope"]):
                some = [(m.topic, m.log_time_ns, m.raw)
                        for m in r.messages(topics=topics, decode=False)]
                assert some == [m for m in everything if m[0] in topics]
        assert {t for t, _, _ in everything} == {"/a", "/b"}


def test_a_topic_reads_only_the_chunks_holding_it(tmp_path: Path) -> None:
    """A topic logged once at the start (``/config``) is read from its chunk alone: a damaged
    chunk without it is never decompressed (no corrupt chunk counted), while reading every
    topic finds the damage; so in a salvaged (summary-less) file."""
    path = tmp_path / "once.mcap"
    rng = np.random.default_rng(5)
    with McapLogger(path, chunk_size=4096, flush_interval_s=10.0, queue_size=N + 10) as lg:
        lg.log("/once", 0, {"first": True}, schema=sch.JSON)
        for i in range(1, N):
            lg.log("/a", 1_000_000 * i, {"i": i, "noise": rng.integers(0, 1 << 30, 8).tolist()},
                   schema=sch.JSON)
    table = _chunk_table(path)
    assert len(table) > 4
    data = bytearray(path.read_bytes())
    k = len(table) // 2
    data[(table[k - 1][0] + table[k][0]) // 2] ^= 0x40  # inside chunk k, which has no /once
    flipped = tmp_path / "flipped.mcap"
    flipped.write_bytes(bytes(data))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(bytes(data[: table[-2][0]]))
    for p, salvaged in ((flipped, False), (cut, True)):
        with LogReader(p, verify=False) as r:
            assert [m.data for m in r.messages(topics=["/once"])] == [{"first": True}]
            assert r.recovery.salvaged == salvaged
            if not salvaged:  # a salvage pass has read (and counted) every chunk already
                assert r.recovery.corrupt_chunks == 0
            kept = table[:-1] if salvaged else table
            assert len(list(r.messages(topics=["/a"]))) == sum(n for _, n in kept) - 1 - table[k][1]
            assert r.recovery.corrupt_chunks == 1
