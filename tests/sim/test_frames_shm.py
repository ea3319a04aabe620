"""Camera frames through shared memory, the emulator's side (docs/reference/wire.md, "Camera
frames through shared memory"): a real TCP client that sends the request, reads the
announcement and the notices, maps the segment and reads the slots as the page documents."""

from __future__ import annotations

import asyncio
import mmap
import os
import socket
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim_bridge import LinkError
from sim_bridge.camera.frames import HEADER, FrameServer, encode_frame
from sim_bridge.camera.shm import FrameRing

REQUEST = struct.pack("<4sBBH", b"IBVQ", 1, 1, 0)
ANNOUNCE = struct.Struct("<4sBBHIIIQI")


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        part = sock.recv(n - len(out))
        assert part, "connection closed"
        out += part
    return out


def _image(seq: int) -> np.ndarray:
    return np.random.default_rng(seq).integers(0, 256, (48, 64), dtype=np.uint8)


def _read_slot(mm: mmap.mmap, stride: int, off: int, notice: tuple[object, ...]) -> bytes:
    """The documented reader: generation even and unchanged, the slot's header names the
    notice's frame."""
    slot, seq, n = notice[3], notice[4], notice[8]
    assert isinstance(slot, int) and isinstance(n, int)
    base = 4096 + slot * stride
    (g1,) = struct.unpack_from("<Q", mm, base)
    head = HEADER.unpack_from(mm, base + 16)
    payload = bytes(mm[base + off:base + off + n])
    (g2,) = struct.unpack_from("<Q", mm, base)
    assert g1 % 2 == 0 and g1 == g2 and head[0] == b"IBVF" and head[4] == seq
    return payload


def test_a_client_that_asks_gets_the_segment_and_notices_and_the_same_frames() -> None:
    """Two clients, one over TCP and one through shared memory: the same frames (header
    fields and pixels); the segment is gone once the server closes."""

    async def body() -> Path:
        loop = asyncio.get_running_loop()
        async with FrameServer("127.0.0.1", 0) as srv:
            plain = socket.create_connection(("127.0.0.1", srv.port))
            shm = socket.create_connection(("127.0.0.1", srv.port))
            shm.sendall(REQUEST)
            while srv.n_clients < 2:
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.1)  # the request is read
            for seq in range(3):
                await srv.publish(seq, 1000 * seq, _image(seq))
                await asyncio.sleep(0.05)
            ann = ANNOUNCE.unpack(await loop.run_in_executor(None, _recv_exact, shm, 32))
            magic, version, flags, _, n_slots, stride, off, size, name_len = ann
            assert (magic, version, n_slots) == (b"IBVA", 1, 4)
            path = Path((await loop.run_in_executor(None, _recv_exact, shm, name_len)).decode())
            assert path.stat().st_size == size
            with open(path, "rb") as f:
                mm = mmap.mmap(f.fileno(), size, prot=mmap.PROT_READ)
            for seq in range(3):
                notice = HEADER.unpack(await loop.run_in_executor(None, _recv_exact, shm, 32))
                assert notice[0] == b"IBVN" and notice[4] == seq and notice[5] == 1000 * seq
                assert notice[9] == 0 or flags & 1  # no CRC unless the flag says so
                payload = _read_slot(mm, stride, off, notice)
                raw = await loop.run_in_executor(None, _recv_exact, plain, 32 + 48 * 64)
                assert payload == raw[32:] == _image(seq).tobytes()
                assert notice[1:3] + notice[4:9] == HEADER.unpack(raw[:32])[1:3] \
                    + HEADER.unpack(raw[:32])[4:9]
            mm.close()
            plain.close()
            shm.close()
        return path

    path = asyncio.run(asyncio.wait_for(body(), 20.0))
    assert not path.exists(), "the segment outlived the server"


def test_a_slot_is_marked_while_written_and_lapped_slots_name_the_newer_frame(
        tmp_path: Path) -> None:
    ring = FrameRing(16, tag="t", n_slots=2, directory=tmp_path, crc=True)
    try:
        notices = [HEADER.unpack(ring.write(HEADER, (0, s, s, 4, 4), bytes([s] * 16)))
                   for s in range(3)]
        assert [n[3] for n in notices] == [0, 1, 0]
        with open(ring.path, "rb") as f:
            mm = mmap.mmap(f.fileno(), ring.size, prot=mmap.PROT_READ)
        # slot 0 now holds frame 2: frame 0's notice no longer matches its header
        assert HEADER.unpack_from(mm, 4096 + 16)[4] == 2
        assert _read_slot(mm, ring.stride, ring.payload_offset, notices[2]) == bytes([2] * 16)
        assert notices[2][9] == __import__("zlib").crc32(bytes([2] * 16))
        (gen,) = struct.unpack_from("<Q", mm, 4096)
        assert gen == 4  # two writes, each odd while written then even
        mm.close()
    finally:
        ring.close()
    assert not ring.path.exists()
    with pytest.raises(LinkError, match="closed"):
        ring.write(HEADER, (0, 0, 0, 4, 4), bytes(16))


def test_a_frame_larger_than_a_slot_is_refused(tmp_path: Path) -> None:
    ring = FrameRing(16, tag="big", directory=tmp_path)
    try:
        with pytest.raises(LinkError, match="does not fit"):
            ring.write(HEADER, (0, 0, 0, 100, 100), bytes(ring.capacity + 1))
    finally:
        ring.close()


def test_a_dead_emulators_segment_is_removed_and_a_live_ones_kept(tmp_path: Path) -> None:
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    stale = tmp_path / f"sim_bridge-frames-{int(dead.stdout)}-5700"
    live = tmp_path / f"sim_bridge-frames-{os.getppid()}-5700"
    stale.write_bytes(b"x")
    live.write_bytes(b"x")
    ring = FrameRing(16, tag="new", directory=tmp_path)
    ring.close()
    assert not stale.exists() and live.exists()


def test_a_client_that_does_not_ask_gets_whole_records_and_no_segment() -> None:
    async def body() -> None:
        loop = asyncio.get_running_loop()
        async with FrameServer("127.0.0.1", 0) as srv:
            plain = socket.create_connection(("127.0.0.1", srv.port))
            plain.sendall(b"hello, not a request")  # ignored, as before
            while srv.n_clients < 1:
                await asyncio.sleep(0.01)
            await srv.publish(7, 70, _image(7))
            raw = await loop.run_in_executor(None, _recv_exact, plain, 32 + 48 * 64)
            assert raw == encode_frame(7, 70, _image(7))
            assert srv._ring is None  # nobody asked: no segment
            plain.close()

    asyncio.run(asyncio.wait_for(body(), 20.0))
