"""Camera frames over a real TCP socket on 127.0.0.1 (docs/reference/wire.md): round trip,
corruption, slow clients getting the newest frame, clients coming and going."""

from __future__ import annotations

import asyncio
import socket
import struct
import zlib
from collections.abc import Awaitable, Callable

import numpy as np
import pytest

from sim_bridge.frames import (
    FrameError,
    FrameServer,
    decode_header,
    decode_payload,
    encode_frame,
    read_frame,
)


def run(coro_fn: Callable[[], Awaitable[None]], timeout_s: float = 20.0) -> None:
    async def main() -> None:
        await asyncio.wait_for(coro_fn(), timeout_s)

    asyncio.run(main())


def test_record_layout_is_the_documented_one() -> None:
    img = np.arange(12 * 7, dtype=np.uint8).reshape(7, 12)
    rec = encode_frame(42, 1_250_000, img)
    magic, ver, enc, res, seq, t_us, w, h, n, crc = struct.unpack_from("<4sBBHIQHHII", rec)
    assert (magic, ver, enc, res, seq, t_us, w, h, n) == (
        b"IBVF",
        1,
        0,
        0,
        42,
        1_250_000,
        12,
        7,
        84,
    )
    assert len(rec) == 32 + 84 and crc == zlib.crc32(rec[32:])
    np.testing.assert_array_equal(np.frombuffer(rec[32:], np.uint8).reshape(7, 12), img)


@pytest.mark.parametrize("encoding", ["mono8", "bgr8", "png", "jpeg"])
def test_encodings_round_trip(encoding: str) -> None:
    rng = np.random.default_rng(0)
    shape = (48, 64, 3) if encoding == "bgr8" else (48, 64)
    img = (rng.integers(0, 40, shape) + 100).astype(np.uint8)
    rec = encode_frame(3, 9, img, encoding)
    hdr = decode_header(rec)
    out = decode_payload(hdr, rec[32:])
    assert hdr.encoding_name == encoding and out.shape == img.shape
    if encoding == "jpeg":
        assert np.abs(out.astype(int) - img).mean() < 10
    else:
        np.testing.assert_array_equal(out, img)


def test_corruption_is_detected() -> None:
    img = np.full((20, 30), 77, np.uint8)
    rec = bytearray(encode_frame(1, 2, img))
    hdr = decode_header(bytes(rec))
    for i in (32, 32 + 299, len(rec) - 1):
        bad = bytearray(rec)
        bad[i] ^= 0x10
        with pytest.raises(FrameError, match="CRC"):
            decode_payload(hdr, bytes(bad[32:]))
    with pytest.raises(FrameError, match="magic"):
        decode_header(b"XBVF" + bytes(rec[4:32]))
    with pytest.raises(FrameError, match="version"):
        decode_header(bytes(rec[:4]) + b"\x02" + bytes(rec[5:32]))
    with pytest.raises(FrameError, match="inconsistent"):
        decode_header(bytes(rec[:24]) + struct.pack("<I", 5) + bytes(rec[28:32]))
    with pytest.raises(FrameError):
        encode_frame(2**32, 0, img)


def test_frames_over_tcp_decode_to_the_same_image() -> None:
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, (1000, 1000), dtype=np.uint8) for _ in range(3)]

    async def body() -> None:
        async with FrameServer("127.0.0.1", 0) as srv:
            assert srv.port != 0
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.port)
            while srv.n_clients < 1:
                await asyncio.sleep(0.001)
            for k, img in enumerate(images):
                await srv.publish(100 + k, 50_000 * k, img)
                hdr, out = await read_frame(reader)
                assert (hdr.seq, hdr.t_us, hdr.width, hdr.height) == (
                    100 + k,
                    50_000 * k,
                    1000,
                    1000,
                )
                np.testing.assert_array_equal(out, img)
            writer.close()
            await writer.wait_closed()
            assert srv.sent == 3 and srv.dropped == 0

    run(body)


def test_slow_client_gets_the_newest_frame_and_drops_are_counted() -> None:
    n_frames = 60

    async def body() -> None:
        async with FrameServer("127.0.0.1", 0) as srv:
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 64 * 1024)
            sock.connect(("127.0.0.1", srv.port))
            sock.setblocking(False)
            reader, writer = await asyncio.open_connection(sock=sock)
            while srv.n_clients < 1:
                await asyncio.sleep(0.001)
            img = np.zeros((1000, 1000), np.uint8)
            for k in range(n_frames):  # the client reads nothing meanwhile
                img[:] = k
                await srv.publish(k, k * 50_000, img)
                await asyncio.sleep(0.002)
            seqs = []
            while not seqs or seqs[-1] != n_frames - 1:
                hdr, out = await read_frame(reader)
                assert out[0, 0] == hdr.seq and out[-1, -1] == hdr.seq  # not torn
                seqs.append(hdr.seq)
            assert seqs == sorted(set(seqs))  # in order, no repeats
            assert len(seqs) < n_frames / 2  # most were dropped, not buffered
            assert srv.sent == len(seqs) and srv.sent + srv.dropped == n_frames
            writer.close()
            await writer.wait_closed()

    run(body)


def test_clients_come_and_go() -> None:
    img = np.full((100, 120), 9, np.uint8)

    async def body() -> None:
        async with FrameServer("127.0.0.1", 0) as srv:
            await srv.publish(0, 0, img)  # nobody listening: fine
            ra, wa = await asyncio.open_connection("127.0.0.1", srv.port)
            while srv.n_clients < 1:
                await asyncio.sleep(0.001)
            await srv.publish(1, 10, img)
            assert (await read_frame(ra))[0].seq == 1
            rb, wb = await asyncio.open_connection("127.0.0.1", srv.port)
            while srv.n_clients < 2:
                await asyncio.sleep(0.001)
            await srv.publish(2, 20, img)
            assert (await read_frame(ra))[0].seq == 2
            assert (await read_frame(rb))[0].seq == 2
            wa.close()
            await wa.wait_closed()
            while srv.n_clients > 1:
                await asyncio.sleep(0.001)
            for k in (3, 4):
                await srv.publish(k, 10 * k, img)
                assert (await read_frame(rb))[0].seq == k
            wb.close()
            await wb.wait_closed()
            while srv.n_clients:
                await asyncio.sleep(0.001)
            await srv.publish(5, 50, img)
            assert srv.published == 6 and srv.sent == 5

    run(body)


def test_a_taken_port_is_a_link_error() -> None:
    from sim_bridge import LinkError

    async def body() -> None:
        async with FrameServer("127.0.0.1", 0) as srv:
            with pytest.raises(LinkError, match="cannot listen"):
                async with FrameServer("127.0.0.1", srv.port):
                    pass

    run(body)


# ------------------------------------------------------------------ ground truth (UDP JSON)
def test_truth_record_over_udp() -> None:
    import json

    from sim_bridge.camera import Camera
    from sim_bridge.physics.agv import AgvTrajectory
    from sim_bridge.truth import TruthPublisher, truth_record

    agv = AgvTrajectory("paper").state(12.5)
    cam = Camera(2.8e-3, 5.04e-6, 200, 200)
    q = [1.0, 0.0, 0.0, 0.0]
    uav = agv.pos_ned_m + np.array([0.0, 0.0, -2.0])
    frame = cam.render(uav, q, agv)
    rec = truth_record(
        12_500_000,
        250,
        uav,
        [0.1, 0.0, float("nan")],
        q,
        [0.0, 0.0, 0.01],
        agv,
        frame,
        mode="OFFBOARD",
        armed=True,
        setpoint_age_s=0.02,
    )
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    try:
        with TruthPublisher("127.0.0.1", rx.getsockname()[1]) as pub:
            assert pub.publish(rec)
            got = json.loads(rx.recv(65536).decode())
            assert pub.sent == 1 and pub.errors == 0
            # not JSON-serialisable: counted, not raised
            assert not pub.publish({"bad": object()})
            assert pub.errors == 1
    finally:
        rx.close()
    assert got["t_us"] == 12_500_000 and got["frame_seq"] == 250
    assert got["uav"]["vel_ned_m_s"] == [0.1, 0.0, None]  # NaN -> null, valid JSON
    np.testing.assert_allclose(got["agv"]["pos_ned_m"], agv.pos_ned_m)
    assert got["agv"]["yaw_rad"] == pytest.approx(agv.yaw_rad)
    np.testing.assert_allclose(got["corners_px"], frame.corners_px)
    assert got["target_in_image"] is True and got["mode"] == "OFFBOARD" and got["armed"] is True
    assert set(got) >= {"disturbance_accel_ned_m_s2", "setpoint_age_s", "top_corners_px"}


def test_truth_to_nobody_never_raises() -> None:
    from sim_bridge.truth import TruthPublisher

    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nobody listens there now
    with TruthPublisher("127.0.0.1", port) as pub:
        for k in range(20):
            pub.publish({"t_us": k})
        assert pub.sent + pub.errors == 20


def test_record_parts_are_the_record_without_copying_the_image() -> None:
    """The frame server writes (header, payload) as they are: the raw payload is the image's
    own memory, read-only, and the two parts are exactly encode_frame's record."""
    from sim_bridge.frames import encode_frame_parts

    img = np.arange(48 * 64, dtype=np.uint8).reshape(48, 64)
    header, payload = encode_frame_parts(7, 123, img)
    assert header + bytes(payload) == encode_frame(7, 123, img)
    view = np.frombuffer(payload, np.uint8)
    assert np.shares_memory(view, img) and not view.flags.writeable
