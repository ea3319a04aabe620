"""The companion's side of camera frames through shared memory (docs/reference/wire.md): a ring
written here by hand in the documented layout, served by a real TCP server; a torn or lapped
slot never reaches the consumer, a segment that cannot be mapped is a clear error."""

from __future__ import annotations

import asyncio
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.camera import CameraError, FrameSocketSource, open_camera
from companion.camera.shm import Announcement, SharedFrames

HEADER = struct.Struct("<4sBBHIQHHII")
ANNOUNCE = struct.Struct("<4sBBHIIIQI")
STRIDE, OFF, N_SLOTS = 8192, 64, 2
W, H = 64, 48


class Ring:
    """A ring file in the documented layout, written as the emulator does."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.size = 4096 + N_SLOTS * STRIDE
        self.buf = bytearray(self.size)
        struct.pack_into("<4sBBHIII", self.buf, 0, b"IBVR", 1, 0, 0, N_SLOTS, STRIDE, OFF)
        self.flush()

    def flush(self) -> None:
        self.path.write_bytes(bytes(self.buf))

    def gen(self, slot: int, value: int | None = None) -> int:
        if value is not None:
            struct.pack_into("<Q", self.buf, 4096 + slot * STRIDE, value)
            self.flush()
        return int(struct.unpack_from("<Q", self.buf, 4096 + slot * STRIDE)[0])

    def write(self, slot: int, seq: int, image: np.ndarray) -> bytes:
        base = 4096 + slot * STRIDE
        n = image.size
        self.gen(slot, self.gen(slot) + 1)
        self.buf[base + OFF:base + OFF + n] = image.tobytes()
        HEADER.pack_into(self.buf, base + 16, b"IBVF", 1, 0, 0, seq, 1000 * seq, W, H, n, 0)
        self.gen(slot, self.gen(slot) + 1)
        return HEADER.pack(b"IBVN", 1, 0, slot, seq, 1000 * seq, W, H, n, 0)

    def announcement(self, name: str | None = None) -> bytes:
        raw = (name or str(self.path)).encode()
        return ANNOUNCE.pack(b"IBVA", 1, 0, 0, N_SLOTS, STRIDE, OFF, self.size, len(raw)) + raw


def _image(seq: int) -> np.ndarray:
    return np.random.default_rng(seq).integers(0, 256, (H, W), dtype=np.uint8)


def _ann(ring: Ring) -> Announcement:
    return Announcement.unpack(ring.announcement()[:32])


def test_a_whole_slot_is_copied_a_torn_or_lapped_one_is_not(tmp_path: Path) -> None:
    ring = Ring(tmp_path / "ring")
    ring.write(0, 5, _image(5))
    frames = SharedFrames(str(ring.path), _ann(ring))
    try:
        got = frames.read(0, 5, 5000, W * H, 0)
        assert got is not None and bytes(got) == _image(5).tobytes()
        assert got.readonly
        # being written: the generation is odd
        ring.gen(0, ring.gen(0) + 1)
        assert frames.read(0, 5, 5000, W * H, 0) is None
        ring.gen(0, ring.gen(0) + 1)
        assert frames.read(0, 5, 5000, W * H, 0) is not None
        # lapped: the slot now holds frame 7, the notice named frame 5
        ring.write(0, 7, _image(7))
        assert frames.read(0, 5, 5000, W * H, 0) is None
        with pytest.raises(CameraError, match="outside the ring"):
            frames.read(N_SLOTS, 7, 7000, W * H, 0)
    finally:
        frames.close()


def test_a_missing_or_foreign_segment_is_a_clear_error(tmp_path: Path) -> None:
    ring = Ring(tmp_path / "ring")
    with pytest.raises(CameraError, match=r"cannot open .*nowhere.*transport=shm"):
        SharedFrames(str(tmp_path / "nowhere"), _ann(ring))
    (tmp_path / "other").write_bytes(bytes(ring.size))
    with pytest.raises(CameraError, match="not the announced ring"):
        SharedFrames(str(tmp_path / "other"), _ann(ring))
    (tmp_path / "short").write_bytes(b"IBVR")
    with pytest.raises(CameraError, match="has 4 bytes"):
        SharedFrames(str(tmp_path / "short"), _ann(ring))


async def _serve(records: list[bytes], requests: list[bytes],
                 later: list[bytes] | None = None) -> tuple[asyncio.Server, int]:
    """A server sending ``records`` on its first connection, ``later`` (or the same) after."""
    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        requests.append(await reader.readexactly(8))
        for r in records if len(requests) == 1 or later is None else later:
            writer.write(r)
        await writer.drain()
        try:
            await reader.read()
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    return server, server.sockets[0].getsockname()[1]


def test_the_source_asks_maps_and_drops_a_lapped_frame(tmp_path: Path) -> None:
    """Over a real socket: the request, the announcement, a whole TCP record, notices; the
    frame whose slot was overwritten before the consumer took it is counted, never
    delivered."""
    ring = Ring(tmp_path / "ring")
    n5 = ring.write(0, 5, _image(5))
    n6 = ring.write(1, 6, _image(6))
    stale = HEADER.pack(b"IBVN", 1, 0, 0, 4, 4000, W, H, W * H, 0)  # slot 0 holds frame 5
    img4 = _image(4)
    whole = HEADER.pack(b"IBVF", 1, 0, 0, 3, 3000, W, H, W * H,
                        zlib.crc32(img4.tobytes())) + img4.tobytes()
    requests: list[bytes] = []

    async def main() -> list[Any]:
        server, port = await _serve([whole, ring.announcement(), stale, n5, n6], requests)
        out = []
        async with server, open_camera(f"tcp://127.0.0.1:{port}?frames=all&transport=shm",
                                       queue_size=8) as cam:
            for _ in range(3):
                f = await asyncio.wait_for(anext(cam), 10.0)
                out.append((f.seq, f.t_us, f.image.copy()))
            stats = cam.stats
        return [out, stats]

    out, stats = asyncio.run(main())
    assert requests == [struct.pack("<4sBBH", b"IBVQ", 1, 1, 0)]
    assert [s for s, _, _ in out] == [3, 5, 6]
    assert np.array_equal(out[0][2], img4)  # the whole record before the announcement
    assert np.array_equal(out[1][2], _image(5)) and np.array_equal(out[2][2], _image(6))
    assert stats.torn_frames == 1 and stats.frames_received == 4


def test_an_unmappable_segment_fails_the_source_with_its_name(tmp_path: Path) -> None:
    ring = Ring(tmp_path / "ring")
    gone = str(tmp_path / "sim_bridge-frames-1-5700")

    async def main() -> None:
        server, port = await _serve([ring.announcement(gone), ring.write(0, 1, _image(1))], [])
        async with server, FrameSocketSource("127.0.0.1", port, shared_memory=True) as cam:
            with pytest.raises(CameraError, match="sim_bridge-frames-1-5700"):
                await asyncio.wait_for(anext(cam), 10.0)

    asyncio.run(main())


def test_a_tcp_client_takes_no_notice_and_the_url_names_the_transport() -> None:
    assert "shm" in repr(open_camera("tcp://127.0.0.1:5700?transport=shm&frames=all"))
    assert "shm" not in repr(open_camera("tcp://127.0.0.1:5700?frames=all&transport=tcp"))
    for bad in ("tcp://h:1?transport=udp", "tcp://h:1?frames=all&frames=all", "tcp://h:1?x=1"):
        with pytest.raises(CameraError, match="transport=shm"):
            open_camera(bad)


def test_a_notice_before_the_announcement_is_a_bad_record(tmp_path: Path) -> None:
    """The client resynchronises (reconnects) and takes the frames of the next connection."""
    ring = Ring(tmp_path / "ring")
    n5 = ring.write(0, 5, _image(5))

    async def main() -> tuple[int, int]:
        server, port = await _serve([n5], [], later=[ring.announcement(), n5])
        async with server, FrameSocketSource("127.0.0.1", port, shared_memory=True) as cam:
            f = await asyncio.wait_for(anext(cam), 10.0)
            assert np.array_equal(f.image, _image(5))
            return cam.stats.bad_records, cam.stats.connects

    assert asyncio.run(main()) == (1, 2)
