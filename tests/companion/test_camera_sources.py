"""Camera sources against real peers: a TCP frame server on 127.0.0.1 speaking
docs/reference/wire.md, and real video files written with cv2.VideoWriter."""

from __future__ import annotations

import asyncio
import itertools
import struct
import zlib
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from companion import CompanionError
from companion.camera import (
    FRAME_HEADER,
    CameraError,
    CameraFrame,
    FrameHeader,
    FrameSocketSource,
    VideoCaptureSource,
    open_camera,
    pack_frame,
)


def run(coro: Awaitable[Any], timeout_s: float = 20.0) -> Any:
    return asyncio.run(asyncio.wait_for(coro, timeout_s))  # type: ignore[arg-type]


def _image(seq: int, w: int = 64, h: int = 48, color: bool = False) -> np.ndarray:
    """A frame whose pixels encode its seq (checked after the round trip)."""
    rng = np.random.default_rng(seq)
    img = rng.integers(0, 256, (h, w, 3) if color else (h, w), dtype=np.uint8)
    return img


class FrameServer:
    """A real asyncio TCP server; ``script(conn_index, writer)`` decides what each
    connection receives."""

    def __init__(
        self, script: Callable[[int, asyncio.StreamWriter], Awaitable[None]], port: int = 0
    ) -> None:
        self.script = script
        self.connections = 0
        self.server: asyncio.Server | None = None
        self.port = port

    async def __aenter__(self) -> FrameServer:
        self.server = await asyncio.start_server(self._handle, "127.0.0.1", self.port)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self.server is not None
        self.server.close()
        await self.server.wait_closed()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        index = self.connections
        self.connections += 1
        try:
            await self.script(index, writer)
            await reader.read()  # hold the connection until the client closes it
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass  # the client went away or the test ended
        finally:
            writer.close()


def test_header_layout_matches_wire_doc() -> None:
    assert FRAME_HEADER.size == 32
    rec = pack_frame(7, 123456789, _image(7))
    h = FrameHeader.unpack(rec[:32])
    assert (h.magic, h.version, h.encoding, h.seq, h.t_us) == (b"IBVF", 1, 0, 7, 123456789)
    assert (h.width_px, h.height_px, h.payload_len) == (64, 48, 64 * 48)
    assert h.crc32 == zlib.crc32(rec[32:])
    # field offsets of docs/reference/wire.md
    assert struct.unpack_from("<I", rec, 8)[0] == 7
    assert struct.unpack_from("<Q", rec, 12)[0] == 123456789
    assert struct.unpack_from("<HH", rec, 20) == (64, 48)


@pytest.mark.parametrize("encoding", ["mono8", "bgr8", "png", "jpeg"])
def test_frames_arrive_with_seq_time_and_pixels(encoding: str) -> None:
    color = encoding in ("bgr8", "jpeg")
    sent = {seq: _image(seq, color=color) for seq in range(5)}

    async def script(i: int, w: asyncio.StreamWriter) -> None:
        for seq, img in sent.items():
            w.write(pack_frame(seq, 1000 + 50_000 * seq, img, encoding if encoding else ""))
            await w.drain()
            await asyncio.sleep(0.02)

    async def main() -> list[CameraFrame]:
        async with FrameServer(script) as srv:
            got: list[CameraFrame] = []
            async with FrameSocketSource("127.0.0.1", srv.port, queue_size=8) as cam:
                async for frame in cam:
                    got.append(frame)
                    if frame.seq == 4:
                        break
            return got

    got = run(main())
    assert [f.seq for f in got] == [0, 1, 2, 3, 4]
    for f in got:
        assert f.t_us == 1000 + 50_000 * f.seq
        assert f.encoding == ("bgr8" if color else "mono8")
        assert f.wire_encoding == encoding
        assert f.t_rx_ns > 0
        if encoding == "jpeg":  # lossy: equal to OpenCV's own round trip of the same image
            _, buf = cv2.imencode(".jpg", sent[f.seq])
            np.testing.assert_array_equal(f.image, cv2.imdecode(buf, cv2.IMREAD_UNCHANGED))
        else:
            np.testing.assert_array_equal(f.image, sent[f.seq])
    assert all(b.t_rx_ns >= a.t_rx_ns for a, b in itertools.pairwise(got))


@pytest.mark.parametrize(
    "corrupt",
    ["crc", "magic", "version", "payload_len"],
)
def test_bad_record_resyncs_and_next_good_frame_arrives(corrupt: str) -> None:
    async def script(i: int, w: asyncio.StreamWriter) -> None:
        if i == 0:
            w.write(pack_frame(0, 0, _image(0)))
            bad = bytearray(pack_frame(1, 50_000, _image(1)))
            if corrupt == "crc":
                bad[40] ^= 0x01  # one payload bit
            elif corrupt == "magic":
                bad[0:4] = b"XBVF"
            elif corrupt == "version":
                bad[4] = 2
            else:
                struct.pack_into("<I", bad, 24, 5)  # raw payload shorter than w*h
            w.write(bytes(bad))
            w.write(pack_frame(2, 100_000, _image(2)))  # lost with the bad connection
        else:
            w.write(pack_frame(3, 150_000, _image(3)))
        await w.drain()

    async def main() -> tuple[list[int], Any, int]:
        async with FrameServer(script) as srv:
            seqs: list[int] = []
            async with FrameSocketSource("127.0.0.1", srv.port, queue_size=8) as cam:
                async for frame in cam:
                    seqs.append(frame.seq)
                    np.testing.assert_array_equal(frame.image, _image(frame.seq))
                    if frame.seq == 3:
                        break
                return seqs, cam.stats, srv.connections

    seqs, stats, connections = run(main())
    assert seqs == [0, 3]
    assert stats.bad_records == 1 and stats.resyncs == 1
    assert stats.connects == 2 and connections == 2


def test_slow_consumer_gets_the_newest_frame_and_drops_are_counted() -> None:
    n = 20

    async def script(i: int, w: asyncio.StreamWriter) -> None:
        for seq in range(n):
            w.write(pack_frame(seq, seq * 50_000, _image(seq, 320, 240)))
        await w.drain()

    async def main() -> tuple[CameraFrame, Any]:
        async with (
            FrameServer(script) as srv,
            FrameSocketSource("127.0.0.1", srv.port, queue_size=1) as cam,
        ):
            while cam.stats.frames_received < n:  # the consumer is busy elsewhere
                await asyncio.sleep(0.01)
            frame = await anext(cam)
            return frame, cam.stats

    frame, stats = run(main())
    assert frame.seq == n - 1
    np.testing.assert_array_equal(frame.image, _image(n - 1, 320, 240))
    assert stats.frames_dropped == n - 1
    assert stats.frames_delivered == 1


@pytest.mark.parametrize(("encoding", "frames"),
                         [("mono8", "newest"), ("jpeg", "newest"), ("mono8", "all")])
def test_a_busy_consumer_takes_the_newest_frame_the_kernel_holds_not_the_first(
        encoding: str, frames: str) -> None:
    """The loop was blocked (a step that overran) while frames arrived: they sit unread in the
    socket's receive buffer. The next frame handed out is the newest of them, and only it is
    decoded: not the first record to complete once the loop reads again. (JPEG: the older
    records carry a payload that does not decode, with a good CRC; decoding any of them would
    count a decode error.) With ``?frames=all`` (the lockstep emulator's client, which must
    answer every frame delivered) nothing is read ahead: the first record comes first."""
    import socket
    import threading
    import time

    n = 12
    if encoding == "jpeg":
        records = [pack_frame(seq, seq * 50_000, _image(seq), "jpeg", payload=b"not a jpeg")
                   for seq in range(n - 1)]
        records.append(pack_frame(n - 1, (n - 1) * 50_000, _image(n - 1), "jpeg"))
    else:
        records = [pack_frame(seq, seq * 50_000, _image(seq)) for seq in range(n)]
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    go, sent = threading.Event(), threading.Event()
    conns: list[socket.socket] = []

    def serve() -> None:
        conn, _ = listener.accept()
        conns.append(conn)
        go.wait(20.0)
        conn.sendall(b"".join(records))  # ~37 kB: fits the kernel's buffers at once
        sent.set()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()

    async def main() -> tuple[CameraFrame, Any]:
        async with open_camera(f"tcp://127.0.0.1:{port}?frames={frames}", queue_size=1) as cam:
            await asyncio.wait_for(cam.connected.wait(), 10.0)
            go.set()
            assert sent.wait(10.0)  # blocks the event loop: nothing is read meanwhile
            time.sleep(0.1)  # (loopback delivery)
            frame = await anext(cam)
            return frame, cam.stats

    try:
        frame, stats = run(main())
    finally:
        for c in conns:
            c.close()
        listener.close()
        thread.join(5.0)
    if frames == "all":
        assert frame.seq == 0 and stats.frames_delivered == 1
        return
    assert frame.seq == n - 1
    if encoding == "mono8":
        np.testing.assert_array_equal(frame.image, _image(n - 1))
    assert stats.frames_received == n and stats.frames_dropped == n - 1
    assert stats.frames_delivered == 1 and stats.decode_errors == 0


def test_seq_gaps_upstream_are_counted() -> None:
    async def script(i: int, w: asyncio.StreamWriter) -> None:
        for seq in (10, 11, 15, 16):
            w.write(pack_frame(seq, seq, _image(seq)))
        await w.drain()

    async def main() -> Any:
        async with (
            FrameServer(script) as srv,
            FrameSocketSource("127.0.0.1", srv.port, queue_size=8) as cam,
        ):
            async for frame in cam:
                if frame.seq == 16:
                    return cam.stats

    assert run(main()).seq_gaps == 3


def test_reconnects_with_backoff_when_the_server_appears_late_and_after_it_drops() -> None:
    async def main() -> tuple[list[int], Any]:
        # reserve a port, then start the server on it only after the client has failed a few times
        probe = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
        port = probe.sockets[0].getsockname()[1]
        probe.close()
        await probe.wait_closed()

        async def script(i: int, w: asyncio.StreamWriter) -> None:
            w.write(pack_frame(i, i, _image(i)))
            await w.drain()
            if i == 0:
                w.close()  # the emulator restarts

        seqs: list[int] = []
        async with FrameSocketSource(
            "127.0.0.1", port, backoff_initial_s=0.02, backoff_max_s=0.1, queue_size=4
        ) as cam:
            await asyncio.sleep(0.2)
            assert cam.stats.connect_failures >= 2
            async with FrameServer(script, port):
                async for frame in cam:
                    seqs.append(frame.seq)
                    if len(seqs) == 2:
                        break
            return seqs, cam.stats

    seqs, stats = run(main())
    assert seqs == [0, 1]
    assert stats.connects == 2 and stats.disconnects == 1


def test_iteration_ends_when_closed() -> None:
    async def script(i: int, w: asyncio.StreamWriter) -> None:
        return None

    async def main() -> None:
        async with FrameServer(script) as srv:
            cam = FrameSocketSource("127.0.0.1", srv.port)
            await cam.start()

            async def consume() -> list[CameraFrame]:
                return [f async for f in cam]

            task = asyncio.create_task(consume())
            await asyncio.sleep(0.05)
            await cam.aclose()
            assert await task == []

    run(main())


def test_a_crashed_reader_surfaces_as_camera_error() -> None:
    """Fault injection: the reader task dies on an unexpected error; the consumer must not
    wait forever but get a CameraError."""

    class Faulty(FrameSocketSource):
        async def _read_records(self, reader: asyncio.StreamReader) -> bool:
            raise RuntimeError("injected")

    async def script(i: int, w: asyncio.StreamWriter) -> None:
        return None

    async def main() -> None:
        async with FrameServer(script) as srv, Faulty("127.0.0.1", srv.port) as cam:
            with pytest.raises(CameraError, match="injected"):
                await anext(cam)

    run(main())


def _write_video(path: Path, n: int, fps: float = 10.0) -> list[np.ndarray]:
    fourcc = cv2.VideoWriter.fourcc(*"MJPG")
    writer = cv2.VideoWriter(str(path), fourcc, fps, (64, 48))
    assert writer.isOpened(), "this OpenCV build cannot write MJPG/AVI"
    frames = []
    for i in range(n):
        img = np.full((48, 64, 3), 8 * i, np.uint8)
        frames.append(img)
        writer.write(img)
    writer.release()
    return frames


def test_video_file_source_reads_every_frame_with_stream_times(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    sent = _write_video(path, 8, fps=10.0)

    async def main() -> list[CameraFrame]:
        async with open_camera(str(path)) as cam:
            assert isinstance(cam, VideoCaptureSource) and not cam.live
            return [f async for f in cam]

    got = run(main())
    assert [f.seq for f in got] == list(range(8))
    assert [f.t_us for f in got] == [100_000 * i for i in range(8)]
    for f, img in zip(got, sent, strict=True):
        assert f.encoding == "bgr8" and f.image.shape == (48, 64, 3)
        assert abs(float(f.image.mean()) - float(img.mean())) < 3.0  # MJPG is lossy


def test_video_file_as_live_source_keeps_only_the_newest(tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    _write_video(path, 30)

    async def main() -> tuple[CameraFrame, Any]:
        async with VideoCaptureSource(str(path), live=True, gray=True) as cam:
            while cam.stats.frames_received < 30:
                await asyncio.sleep(0.01)
            frame = await anext(cam)
            return frame, cam.stats

    frame, stats = run(main())
    assert frame.seq == 29 and frame.encoding == "mono8"
    assert abs(float(frame.image.mean()) - 8 * 29) < 3.0
    assert stats.frames_dropped == 29


def test_open_camera_dispatch(tmp_path: Path) -> None:
    cam = open_camera("tcp://127.0.0.1:5700")
    assert isinstance(cam, FrameSocketSource) and (cam.host, cam.port) == ("127.0.0.1", 5700)
    dev = open_camera("0")
    assert isinstance(dev, VideoCaptureSource) and dev.source == 0 and dev.live
    assert isinstance(open_camera("/dev/video0"), VideoCaptureSource)
    rtsp = open_camera("rtsp://192.168.1.10:8554/cam")
    assert isinstance(rtsp, VideoCaptureSource) and rtsp.live
    f = tmp_path / "clip.avi"
    _write_video(f, 2)
    for url in (str(f), f"file://{f}"):
        src = open_camera(url)
        assert isinstance(src, VideoCaptureSource) and not src.live
    for bad in ("", "tcp://host", "tcp://h:99999", "tcp://h:1?frames=some",
                str(tmp_path / "missing.avi"), "foo://x"):
        with pytest.raises(CameraError):
            open_camera(bad)
    with pytest.raises(CameraError, match="no such file"):
        open_camera(str(tmp_path / "run.mcap"))
    (tmp_path / "run.mcap").write_bytes(b"")  # opened lazily: a bad file fails on entry
    from companion.camera import McapSource

    for url in (str(tmp_path / "run.mcap"), f"mcap://{tmp_path / 'run.mcap'}"):
        assert isinstance(open_camera(url), McapSource)
    assert issubclass(CameraError, CompanionError)


def test_unopenable_device_is_a_clear_error(tmp_path: Path) -> None:
    async def main() -> None:
        async with VideoCaptureSource(str(tmp_path / "nothing.avi"), live=False):
            pass

    with pytest.raises(CameraError, match="cannot open"):
        run(main())


@pytest.mark.parametrize("encoding", ["png", "raw"])
def test_mcap_source_gives_back_the_logged_frames(tmp_path: Path, encoding: str) -> None:
    """Frames written by the companion's logger (protobuf, mono and colour) come back from an
    MCAP camera URL in log-time order, pixel-exact, with their capture stamps; a frame that
    does not decode is counted and skipped."""
    from companion.camera import McapSource
    from companion.log import schemas as sch
    from companion.log.writer import McapLogger

    rng = np.random.default_rng(5)
    imgs = [rng.integers(0, 255, (40, 60), dtype=np.uint8) for _ in range(4)]
    imgs.append(rng.integers(0, 255, (40, 60, 3), dtype=np.uint8))
    path = tmp_path / "cam.mcap"
    schema = sch.RAW_IMAGE if encoding == "raw" else sch.COMPRESSED_IMAGE
    with McapLogger(path, chunk_size=2048) as lg:
        for k, img in enumerate(imgs):
            # logged out of order on purpose: the source delivers in log-time order
            t = [3, 1, 4, 2, 5][k] * 1_000_000
            assert lg.log_image("/camera/image", t, img, encoding, stamp_ns=t // 2)
        assert lg.log("/camera/image", 6_000_000, b"\x00garbage", schema=schema)

    async def collect(p: Path) -> tuple[list[Any], Any]:
        async with open_camera(f"mcap://{p}") as cam:
            assert isinstance(cam, McapSource)
            return [f async for f in cam], cam.stats

    frames, stats = run(collect(path))
    order = [1, 3, 0, 2, 4]  # log times 1, 2, 3, 4, 5 ms
    assert [f.t_rx_ns for f in frames] == [1_000_000 * (i + 1) for i in range(5)]
    for f, k in zip(frames, order, strict=True):
        assert np.array_equal(f.image, imgs[k]) and f.t_us == f.t_rx_ns // 2000
        assert f.encoding == ("bgr8" if imgs[k].ndim == 3 else "mono8")
    assert [f.seq for f in frames] == [1, 2, 3, 4, 5]
    assert stats.decode_errors == 1 and stats.frames_delivered == 5
