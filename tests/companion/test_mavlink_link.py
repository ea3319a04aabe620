"""MavlinkLink against real pymavlink peers on 127.0.0.1 (UDP, TCP) and a pseudo-terminal."""

from __future__ import annotations

import asyncio
import hashlib
import math
import os
import random
import socket
import struct
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink2

from companion import CompanionError
from companion.link import (
    ATTITUDE_THRUST_TYPE_MASK,
    PX4_AUTO_SUB_MODES,
    PX4_MAIN_MODES,
    PX4_MAIN_OFFBOARD,
    PX4_POSCTL_SUB_MODES,
    ConnectionStringError,
    Endpoint,
    LinkError,
    MavlinkLink,
    NoPeerError,
    Received,
    Sent,
    decode_px4_mode,
    default_allow_rules,
    is_armed,
    load_signing_key,
    parse_connection_string,
    px4_custom_mode,
    px4_mode_by_name,
    signing_timestamp_now,
)

AP_SYS, AP_COMP, AGV_SYS, AGV_COMP = 1, 1, 42, 1
KEY = hashlib.sha256(b"test key").digest()


_OPEN: list[socket.socket] = []


@pytest.fixture(autouse=True)
def _close_sockets() -> Any:
    yield
    while _OPEN:
        _OPEN.pop().close()


def udp_socket() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    _OPEN.append(s)
    return s


class Peer:
    """A fake MAVLink endpoint: a UDP socket plus an independent pymavlink encoder."""

    def __init__(self, sysid: int = AP_SYS, compid: int = AP_COMP, key: bytes | None = None):
        self.sock = udp_socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(2.0)
        self.mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = signing_timestamp_now()

    def pack(self, msg: Any, v1: bool = False) -> bytes:
        raw = bytes(msg.pack(self.mav, force_mavlink1=v1))
        self.mav.seq = (self.mav.seq + 1) % 256
        return raw

    def att(self, t_ms: int, q: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0), rate: float = 0.0) -> Any:
        return self.mav.attitude_quaternion_encode(t_ms, *q, rate, 0.0, 0.0)

    def close(self) -> None:
        self.sock.close()


def run(coro: Awaitable[Any]) -> Any:
    return asyncio.run(asyncio.wait_for(coro, 20.0))  # type: ignore[arg-type]


async def wait_until(cond: Callable[[], bool], timeout_s: float = 3.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not cond():
        if loop.time() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.002)


async def send_paced(sock: socket.socket, addr: tuple[str, int], datagrams: list[bytes]) -> None:
    for i, d in enumerate(datagrams):
        sock.sendto(d, addr)
        await asyncio.sleep(0.001 if i % 8 == 7 else 0)


def link_kwargs(**kw: Any) -> dict[str, Any]:
    base: dict[str, Any] = dict(
        source_system=1,
        source_component=191,
        target_system=AP_SYS,
        target_component=AP_COMP,
        allow=default_allow_rules(AP_SYS, AP_COMP, AGV_SYS, AGV_COMP),
    )
    base.update(kw)
    return base


# ----------------------------------------------------------------------------------------------
# Connection strings


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("udpin:0.0.0.0:14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("udpin://0.0.0.0:14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("udp::14540", Endpoint("udpin", "0.0.0.0", 14540)),
        ("udpin:127.0.0.1:0", Endpoint("udpin", "127.0.0.1", 0)),
        ("udpout:localhost:14580", Endpoint("udpout", "localhost", 14580)),
        ("tcp:192.168.1.5:5760", Endpoint("tcp", "192.168.1.5", 5760)),
        ("/dev/ttyACM0,921600", Endpoint("serial", device="/dev/ttyACM0", baud=921600)),
        ("/dev/ttyUSB1", Endpoint("serial", device="/dev/ttyUSB1", baud=115200)),
        ("serial:/dev/ttyACM0:57600", Endpoint("serial", device="/dev/ttyACM0", baud=57600)),
        (" serial:///dev/ttyS0:921600 ", Endpoint("serial", device="/dev/ttyS0", baud=921600)),
    ],
)
def test_connection_strings_parse(text: str, expected: Endpoint) -> None:
    assert parse_connection_string(text) == expected


@pytest.mark.parametrize(
    "text",
    [
        "", "14540", "udpin:0.0.0.0", "udpin:0.0.0.0:port", "udpin:0.0.0.0:70000",
        "udpout::14540", "udpout:host:0", "tcp:host", "ftp:host:21", "serial:ttyACM0:57600",
        "/dev/ttyACM0,fast", "/dev/ttyACM0,12345", "udpin:bad host:1",
    ],
)  # fmt: skip
def test_bad_connection_strings_are_clear_errors(text: str) -> None:
    with pytest.raises(ConnectionStringError, match="bad MAVLink connection string") as ei:
        parse_connection_string(text)
    assert isinstance(ei.value, LinkError) and isinstance(ei.value, CompanionError)
    assert "udpin:HOST:PORT" in str(ei.value)


def test_port_in_use_is_a_link_error() -> None:
    async def main() -> None:
        async with MavlinkLink("udpin:127.0.0.1:0", **link_kwargs()) as a:
            assert a.local_address is not None
            port = a.local_address[1]
            with pytest.raises(LinkError, match="cannot open"):
                async with MavlinkLink(f"udpin:127.0.0.1:{port}", **link_kwargs()):
                    pass

    run(main())


# ----------------------------------------------------------------------------------------------
# Receive path against hostile input


def test_hostile_udp_input_delivers_exactly_the_good_whitelisted_frames() -> None:
    rng = random.Random(7)
    ap, agv, stranger = Peer(), Peer(AGV_SYS, AGV_COMP), Peer(sysid=7)
    rejected: list[str] = []
    observed: list[Received] = []

    datagrams: list[bytes] = []
    good_t: list[int] = []
    expect = dict(
        mavlink1=0, not_whitelisted=0, unused=0, non_finite=0, quaternion_norm=0, duplicate=0,
        incomplete=0, angular_rate=0,
    )  # fmt: skip
    t = 0
    for i in range(60):
        t += 1
        good = ap.pack(ap.att(t, q=(math.cos(0.1 * i), 0.0, 0.0, math.sin(0.1 * i))))
        datagrams.append(good)
        good_t.append(t)
        kind = i % 10
        if kind == 0:
            datagrams.append(bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 80))))
        elif kind == 1:
            datagrams.append(ap.pack(ap.att(999_000 + i))[:15])  # truncated
            expect["incomplete"] += 1
        elif kind == 2:
            datagrams.append(ap.pack(ap.att(999_000 + i), v1=True))
            expect["mavlink1"] += 1
        elif kind == 3:
            datagrams.append(stranger.pack(stranger.att(999_000 + i)))
            expect["not_whitelisted"] += 1
        elif kind == 4:
            datagrams.append(ap.pack(ap.att(999_000 + i, q=(math.nan, 0.0, 0.0, 1.0))))
            expect["non_finite"] += 1
        elif kind == 5:
            datagrams.append(good)  # a duplicated datagram
            expect["duplicate"] += 1
        elif kind == 6:
            datagrams.append(ap.pack(ap.att(999_000 + i, q=(0.5, 0.0, 0.0, 0.5))))
            expect["quaternion_norm"] += 1
        elif kind == 7:
            datagrams.append(ap.pack(ap.att(999_000 + i, rate=math.inf)))
            expect["non_finite"] += 1
        elif kind == 8:
            datagrams.append(ap.pack(ap.att(999_000 + i, rate=80.0)))
            expect["angular_rate"] += 1
        else:
            # a message of the autopilot's we do not use (not in the telemetry whitelist)
            datagrams.append(ap.pack(ap.mav.gps_raw_int_encode(0, 3, 0, 0, 0, 0, 0, 0, 0, 9)))
            expect["unused"] += 1
    # two good frames in one datagram, and garbage followed by a good frame: both still decode
    t += 1
    two = ap.pack(ap.att(t)) + ap.pack(ap.att(t + 1))
    datagrams.append(two)
    good_t += [t, t + 1]
    t += 2
    datagrams.append(b"\x01\x02\x03garbage" + ap.pack(ap.att(t)))
    good_t.append(t)
    # FOLLOW_TARGET: from the AGV it passes, from the autopilot's sysid it is not used
    ft = dict(
        timestamp=1, est_capabilities=0b0011, lat=0, lon=0, alt=1.0, vel=[1.0, 0.0, 0.0],
        acc=[math.nan] * 3, attitude_q=[math.nan] * 4, rates=[math.nan] * 3,
        position_cov=[math.nan] * 3, custom_state=0,
    )  # fmt: skip
    datagrams.append(agv.pack(agv.mav.follow_target_encode(**ft)))
    datagrams.append(ap.pack(ap.mav.follow_target_encode(**ft)))
    expect["unused"] += 1
    ft_bad = dict(ft, est_capabilities=0b0111)  # claims acc, which is NaN
    datagrams.append(agv.pack(agv.mav.follow_target_encode(**ft_bad)))
    expect["non_finite"] += 1
    end = ap.pack(ap.mav.heartbeat_encode(2, 12, 81, px4_custom_mode(3), 3))
    datagrams.append(end)

    async def main() -> list[Received]:
        got: list[Received] = []
        async with MavlinkLink(
            "udpin:127.0.0.1:0",
            on_reject=lambda reason, raw, t_ns: rejected.append(reason),
            on_rx=observed.append,
            **link_kwargs(),
        ) as link:
            addr = link.local_address
            assert addr is not None
            await send_paced(ap.sock, addr, datagrams)
            async for rx in link:
                got.append(rx)
                if rx.name == "HEARTBEAT":
                    break
            c = link.counters
            for reason, n in expect.items():
                if reason == "incomplete":  # random garbage may also end in a frame's start
                    assert c[reason] >= n
                else:
                    assert c[reason] == n, (reason, c[reason], n)
            assert c["bad_data"] >= 6  # every garbage run is reported, none delivered
            assert c["rx_accepted"] == len(got)
            assert c["rx_datagrams"] == len(datagrams)
            assert c["queue_overflow"] == 0
        return got

    got = run(main())
    att = [rx for rx in got if rx.name == "ATTITUDE_QUATERNION"]
    assert [rx.msg.time_boot_ms for rx in att] == good_t
    assert [rx.name for rx in got[len(att) :]] == ["FOLLOW_TARGET", "HEARTBEAT"]
    assert got[len(att)].src_sysid == AGV_SYS
    assert all(rx.raw[0] == 0xFD and rx.src_sysid in (AP_SYS, AGV_SYS) for rx in got)
    assert all(math.isfinite(rx.msg.q1) for rx in att)
    assert observed == got  # the observer sees exactly what the iterator yields
    assert rejected.count("duplicate") == expect["duplicate"]
    # a stranger's frames are logged as rejected; the autopilot's unused streams are not
    assert rejected.count("not_whitelisted") == expect["not_whitelisted"] > 0
    assert "unused" not in rejected
    for p in (ap, agv, stranger):
        p.close()


def test_received_frame_carries_raw_bytes_and_metadata() -> None:
    ap = Peer()
    frame = ap.pack(ap.att(1234, q=(0.0, 1.0, 0.0, 0.0)))
    ticks = iter(range(10**9, 10**10, 1000))

    async def main() -> Received:
        async with MavlinkLink(
            "udpin:127.0.0.1:0", clock_ns=lambda: next(ticks), **link_kwargs()
        ) as link:
            assert link.local_address is not None
            ap.sock.sendto(frame, link.local_address)
            return await link.recv(timeout_s=2.0)

    rx = run(main())
    assert rx.raw == frame
    assert (rx.src_sysid, rx.src_compid, rx.msgid, rx.name) == (1, 1, 31, "ATTITUDE_QUATERNION")
    assert rx.seq == 0 and not rx.signed
    assert rx.t_rx_ns >= 10**9 and rx.t_rx_ns % 1000 == 0  # stamped with OUR clock
    with pytest.raises(AttributeError):
        rx.name = "x"  # type: ignore[misc]
    ap.close()


def test_queue_drops_the_oldest_and_counts() -> None:
    ap = Peer()

    async def main() -> None:
        async with MavlinkLink("udpin:127.0.0.1:0", queue_size=5, **link_kwargs()) as link:
            assert link.local_address is not None
            await send_paced(ap.sock, link.local_address, [ap.pack(ap.att(t)) for t in range(20)])
            await wait_until(lambda: link.counters["rx_accepted"] == 20)
            assert link.counters["queue_overflow"] == 15
            assert link.pending() == 5
            got = [(await link.recv(1.0)).msg.time_boot_ms for _ in range(5)]
            assert got == [15, 16, 17, 18, 19]

    run(main())
    ap.close()


def test_close_ends_the_iteration() -> None:
    async def main() -> None:
        link = MavlinkLink("udpin:127.0.0.1:0", **link_kwargs())
        await link.open()

        async def consume() -> int:
            n = 0
            async for _ in link:
                n += 1
            return n

        task = asyncio.create_task(consume())
        await asyncio.sleep(0.01)
        link.close()
        assert await asyncio.wait_for(task, 2.0) == 0
        with pytest.raises(LinkError):
            link.send_heartbeat()

    run(main())


# ----------------------------------------------------------------------------------------------
# Send path


def _decode_all(data: bytes, key: bytes | None = None) -> list[Any]:
    parser = mavlink2.MAVLink(None)
    if key is not None:
        parser.signing.secret_key = key
    msgs = parser.parse_buffer(data) or []
    assert all(m.get_type() != "BAD_DATA" for m in msgs)
    return msgs


def test_setpoint_command_and_heartbeat_bytes_decode_independently() -> None:
    autopilot = udp_socket()
    autopilot.bind(("127.0.0.1", 0))
    autopilot.settimeout(2.0)
    port = autopilot.getsockname()[1]
    sent: list[Sent] = []
    half = math.sqrt(0.5)

    async def main() -> list[bytes]:
        async with MavlinkLink(
            f"udpout:127.0.0.1:{port}", on_tx=sent.append, **link_kwargs()
        ) as link:
            out = [
                link.send_attitude_target((half, 0.0, 0.0, half), 0.62, time_boot_ms=4321),
                link.send_attitude_target((1.05 * half, 0.0, 0.0, half), 0.0),
                link.send_set_mode(PX4_MAIN_OFFBOARD),
                link.send_arm(True),
                link.send_arm(False, force=True),
                link.send_heartbeat(),
            ]
            bad_setpoints = [
                ((math.nan, 0, 0, 1), 0.5), ((1, 0, 0, 0), 1.5), ((1, 0, 0, 0), -0.1),
                ((0.5, 0, 0, 0), 0.5), ((1, 0, 0), 0.5), ((1, 0, 0, 0), math.nan),
            ]  # fmt: skip
            for bad_q, bad_t in bad_setpoints:
                with pytest.raises(LinkError):
                    link.send_attitude_target(bad_q, bad_t)
            return out

    out = run(main())
    received = [autopilot.recvfrom(1024)[0] for _ in out]
    assert received == out
    assert [s.raw for s in sent] == out
    msgs = [_decode_all(raw)[0] for raw in out]
    for i, m in enumerate(msgs):
        assert m.get_msgbuf()[0] == 0xFD  # MAVLink 2
        assert (m.get_srcSystem(), m.get_srcComponent(), m.get_seq()) == (1, 191, i)
    sat = msgs[0]
    assert sat.get_type() == "SET_ATTITUDE_TARGET"
    assert sat.type_mask == ATTITUDE_THRUST_TYPE_MASK == 7 and not sat.type_mask & 64
    assert (sat.target_system, sat.target_component, sat.time_boot_ms) == (1, 1, 4321)
    assert sat.q == pytest.approx([half, 0.0, 0.0, half], abs=1e-7)
    assert sat.thrust == pytest.approx(0.62, abs=1e-7)
    n = math.hypot(1.05 * half, half)
    assert msgs[1].q == pytest.approx([1.05 * half / n, 0, 0, half / n], abs=1e-7)
    assert msgs[1].thrust == 0.0
    mode = msgs[2]
    assert (mode.command, mode.param1, mode.param2, mode.param3) == (176, 1.0, 6.0, 0.0)
    assert (mode.target_system, mode.target_component) == (1, 1)
    assert (msgs[3].command, msgs[3].param1, msgs[3].param2) == (400, 1.0, 0.0)
    assert (msgs[4].command, msgs[4].param1, msgs[4].param2) == (400, 0.0, 21196.0)
    hb = msgs[5]
    assert (hb.type, hb.autopilot, hb.base_mode, hb.custom_mode) == (18, 8, 0, 0)
    autopilot.close()


def test_udpin_replies_to_the_autopilot_address_it_heard() -> None:
    ap, agv = Peer(), Peer(AGV_SYS, AGV_COMP)

    async def main() -> None:
        async with MavlinkLink("udpin:127.0.0.1:0", **link_kwargs()) as link:
            addr = link.local_address
            assert addr is not None
            assert not link.has_peer
            with pytest.raises(NoPeerError):
                link.send_heartbeat()
            # the AGV is whitelisted but is not the autopilot: it must not become the peer
            agv.sock.sendto(agv.pack(agv.mav.heartbeat_encode(10, 8, 0, 0, 4)), addr)
            await link.recv(2.0)
            assert link.peer_address is None
            ap.sock.sendto(ap.pack(ap.mav.heartbeat_encode(2, 12, 81, 0, 3)), addr)
            await link.recv(2.0)
            assert link.peer_address == ap.sock.getsockname()
            raw = link.send_heartbeat()
            assert ap.sock.recvfrom(512)[0] == raw
            assert link.counters["tx_no_peer"] == 1 and link.counters["tx_frames"] == 1

    run(main())
    ap.close()
    agv.close()


# ----------------------------------------------------------------------------------------------
# Stream transports: TCP and a serial pseudo-terminal


def test_tcp_stream_with_split_frames_and_garbage() -> None:
    ap = Peer()
    frames = [ap.pack(ap.att(t)) for t in range(30)]
    stream = b"".join(f + (b"\x00\x13junk" if i % 7 == 3 else b"") for i, f in enumerate(frames))

    async def main() -> tuple[list[int], bytes]:
        got_from_link = asyncio.get_running_loop().create_future()

        async def on_client(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
            for k in range(0, len(stream), 13):  # arbitrary splits across frame boundaries
                w.write(stream[k : k + 13])
                await w.drain()
            got_from_link.set_result(await r.read(512))
            w.close()

        server = await asyncio.start_server(on_client, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        async with server, MavlinkLink(f"tcp:127.0.0.1:{port}", **link_kwargs()) as link:
            got = [(await link.recv(2.0)).msg.time_boot_ms for _ in frames]
            raw = link.send_heartbeat()
            assert await asyncio.wait_for(got_from_link, 2.0) == raw
            # the server closed the connection: the iteration ends with a LinkError
            with pytest.raises(LinkError, match="lost"):
                async for _ in link:
                    pass
            assert link.counters["bad_data"] >= 1
        return got, raw

    got, raw = run(main())
    assert got == list(range(30))
    assert _decode_all(raw)[0].get_type() == "HEARTBEAT"
    ap.close()


def test_serial_over_a_pseudo_terminal() -> None:
    ap = Peer()
    master, slave = os.openpty()
    dev = os.ttyname(slave)
    frames = [ap.pack(ap.att(t)) for t in range(10)]

    async def main() -> list[int]:
        async with MavlinkLink(f"serial:{dev}:921600", **link_kwargs()) as link:
            os.write(master, b"\xaa\xbb" + b"".join(frames))
            got = [(await link.recv(2.0)).msg.time_boot_ms for _ in frames]
            raw = link.send_arm(True)
            await asyncio.sleep(0.01)
            echoed = os.read(master, 1024)
            assert echoed == raw  # raw mode: no echo, no newline translation
            return got

    try:
        assert run(main()) == list(range(10))
    finally:
        os.close(master)
        os.close(slave)
        ap.close()


# ----------------------------------------------------------------------------------------------
# Signing


def test_key_file_formats(tmp_path: Path) -> None:
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    hexf = tmp_path / "hex.key"
    hexf.write_text(KEY.hex().upper() + "\n")
    assert load_signing_key(raw) == KEY == load_signing_key(hexf)
    for bad in (b"short", KEY + b"\n", b"zz" * 32):
        p = tmp_path / "bad.key"
        p.write_bytes(bad)
        with pytest.raises(LinkError, match="32 raw bytes or 64 hex"):
            load_signing_key(p)
    with pytest.raises(LinkError, match="signing key file"):
        load_signing_key(tmp_path / "missing.key")


def _forged(peer: Peer, t_ms: int, timestamp: int) -> bytes:
    """A frame from the autopilot's ids, signed with the WRONG key at ``timestamp``."""
    forger = mavlink2.MAVLink(None, srcSystem=AP_SYS, srcComponent=AP_COMP)
    forger.signing.secret_key = b"\x55" * 32
    forger.signing.sign_outgoing = True
    forger.signing.link_id = peer.mav.signing.link_id
    forger.signing.timestamp = timestamp
    return bytes(forger.attitude_quaternion_encode(t_ms, 1.0, 0, 0, 0, 0, 0, 0).pack(forger))


def test_signing_accepts_good_rejects_unsigned_replayed_and_forged_frames() -> None:
    ap, unsigned = Peer(key=KEY), Peer()
    g1 = ap.pack(ap.att(1))
    forged = _forged(ap, 666, 2**48 - 2)
    later = [ap.pack(ap.att(t)) for t in range(2, 12)]
    seq = [g1, unsigned.pack(unsigned.att(500)), g1, forged, *later]  # g1 again = a replay

    # The pymavlink bug this link works around: its own check stores the forged timestamp,
    # and every later legitimate frame of the stream is refused.
    victim = mavlink2.MAVLink(None)
    victim.signing.secret_key = KEY
    victim.robust_parsing = True
    plain = [m.get_type() for d in seq for m in (victim.parse_buffer(d) or [])]
    assert plain.count("ATTITUDE_QUATERNION") == 1  # only g1: the forgery blocked all of `later`

    async def main() -> tuple[list[int], Any]:
        async with MavlinkLink("udpin:127.0.0.1:0", signing_key=KEY, **link_kwargs()) as link:
            assert link.local_address is not None
            await send_paced(ap.sock, link.local_address, seq)
            got = [await link.recv(2.0) for _ in range(1 + len(later))]
            c = link.counters
            assert (c["unsigned"], c["old_timestamp"], c["bad_signature"]) == (1, 1, 1)
            assert all(rx.signed for rx in got)
            # our own frames are signed and verify with the peer's key
            ap.sock.settimeout(2.0)
            raw = link.send_heartbeat()
            return [rx.msg.time_boot_ms for rx in got], raw

    got, raw = run(main())
    assert got == [1, *range(2, 12)]
    checker = mavlink2.MAVLink(None)
    checker.signing.secret_key = KEY
    (hb,) = _decode_all(ap.sock.recvfrom(512)[0], key=KEY)
    assert hb.get_signed() and hb.get_msgbuf() == raw
    with pytest.raises(Exception, match="Invalid signature"):
        wrong = mavlink2.MAVLink(None)
        wrong.signing.secret_key = b"\x01" * 32
        wrong.parse_buffer(raw)
    ap.close()
    unsigned.close()


def test_signing_rejects_a_stale_new_stream() -> None:
    ap = Peer(key=KEY)
    ap.mav.signing.timestamp = signing_timestamp_now() - 100 * 6_000_000  # 100 minutes old

    async def main() -> None:
        async with MavlinkLink("udpin:127.0.0.1:0", signing_key=KEY, **link_kwargs()) as link:
            assert link.local_address is not None
            ap.sock.sendto(ap.pack(ap.att(1)), link.local_address)
            await wait_until(lambda: link.counters["stale_stream"] == 1)
            assert link.pending() == 0

    run(main())
    ap.close()


# ----------------------------------------------------------------------------------------------
# PX4 modes


def test_px4_modes_from_the_spec() -> None:
    assert px4_custom_mode(6) == 393216
    assert decode_px4_mode(393216).name == "OFFBOARD"
    assert decode_px4_mode(3 << 16).name == "POSCTL"
    assert decode_px4_mode(4 << 16 | 3 << 24).name == "AUTO.LOITER"
    assert decode_px4_mode(4 << 16 | 6 << 24).name == "AUTO.LAND"
    assert decode_px4_mode(77 << 16).name.startswith("UNKNOWN")
    assert is_armed(145) and not is_armed(81)  # armed OFFBOARD / disarmed POSCTL


def test_px4_mode_names_round_trip() -> None:
    pairs = [(m, 0) for m in PX4_MAIN_MODES]
    pairs += [(4, s) for s in PX4_AUTO_SUB_MODES] + [(3, s) for s in PX4_POSCTL_SUB_MODES]
    for main, sub in pairs:
        mode = decode_px4_mode(px4_custom_mode(main, sub))
        assert (mode.main, mode.sub) == (main, sub)
        assert px4_mode_by_name(mode.name) == (main, sub)
    with pytest.raises(LinkError):
        px4_mode_by_name("AUTO.NOPE")


def test_struct_layout_of_custom_mode_matches_px4_union() -> None:
    # px4_custom_mode is a union {uint16 reserved; uint8 main_mode; uint8 sub_mode} (LE)
    data = struct.pack("<HBB", 0, 4, 3)
    assert px4_custom_mode(4, 3) == struct.unpack("<I", data)[0]


# ----------------------------------------------------------------------------------------------
# Properties of the per-datagram parser (hypothesis drives the receive path directly)

_GOOD = Peer.__new__(Peer)  # an encoder only, no socket
_GOOD.mav = mavlink2.MAVLink(None, srcSystem=AP_SYS, srcComponent=AP_COMP)


@settings(max_examples=300, deadline=None)
@given(junk=st.binary(max_size=300), garbage=st.binary(max_size=40), t_ms=st.integers(0, 2**32 - 1))
def test_property_garbage_never_raises_and_never_hides_the_next_datagram(
    junk: bytes, garbage: bytes, t_ms: int
) -> None:
    link = MavlinkLink("udpin:127.0.0.1:0", **link_kwargs())
    delivered: list[Received] = []
    link._on_rx = delivered.append
    link._on_datagram(junk, ("127.0.0.1", 1))  # any bytes at all: no exception
    assert link.counters["rx_accepted"] <= 1  # (a valid frame by pure chance is possible)
    n0 = len(delivered)
    # a good frame in the NEXT datagram is always delivered, whatever came before
    good = _GOOD.pack(_GOOD.att(t_ms))
    link._on_datagram(good, ("127.0.0.1", 1))
    assert len(delivered) == n0 + 1 and delivered[-1].msg.time_boot_ms == t_ms
    # and after marker-free garbage in the same datagram as well
    clean = bytes(b for b in garbage if b not in (0xFD, 0xFE))
    good2 = _GOOD.pack(_GOOD.att((t_ms + 1) % 2**32))
    link._on_datagram(clean + good2, ("127.0.0.1", 1))
    assert len(delivered) == n0 + 2


def test_from_config_whitelists_autopilot_telemetry_and_the_agv(tmp_path: Path) -> None:
    from companion.config import load_config

    root = Path(__file__).resolve().parents[2]
    cfg = load_config(root / "config" / "paper.toml", overrides=["mavlink.url='udpin:127.0.0.1:0'"])
    ap, agv, spoof = Peer(), Peer(cfg.target.mavlink_sysid, cfg.target.mavlink_compid), Peer(99)
    ft = dict(
        timestamp=1, est_capabilities=2, lat=0, lon=0, alt=0.0, vel=[0.5, 0.0, 0.0],
        acc=[0.0] * 3, attitude_q=[1.0, 0, 0, 0], rates=[0.0] * 3, position_cov=[0.0] * 3,
        custom_state=0,
    )  # fmt: skip

    async def main() -> list[str]:
        async with MavlinkLink.from_config(cfg.mavlink, cfg.target) as link:
            assert (link.source_system, link.source_component) == (1, 191)
            addr = link.local_address
            assert addr is not None
            for p in (spoof, agv, ap):
                p.sock.sendto(p.pack(p.mav.follow_target_encode(**ft)), addr)
                await asyncio.sleep(0.005)
            ap.sock.sendto(ap.pack(ap.att(3)), addr)
            got = [(await link.recv(2.0)).name for _ in range(2)]
            assert link.counters["not_whitelisted"] == 1  # sysid 99
            assert link.counters["unused"] == 1  # FOLLOW_TARGET from PX4
            return got

    assert run(main()) == ["FOLLOW_TARGET", "ATTITUDE_QUATERNION"]


def test_udpout_receives_replies_and_third_party_errors_are_link_errors() -> None:
    autopilot = Peer()

    async def main() -> None:
        port = autopilot.sock.getsockname()[1]
        async with MavlinkLink(f"udpout:127.0.0.1:{port}", **link_kwargs()) as link:
            link.send_heartbeat()
            _, link_addr = autopilot.sock.recvfrom(512)
            autopilot.sock.sendto(autopilot.pack(autopilot.att(77)), link_addr)
            assert (await link.recv(2.0)).msg.time_boot_ms == 77
            with pytest.raises(LinkError, match="cannot encode"):
                link.send_command_long(70_000)  # does not fit the uint16 command field
            with pytest.raises(LinkError, match="at most 7"):
                link.send_command_long(176, [0.0] * 8)
        with pytest.raises(LinkError, match="cannot open"):
            async with MavlinkLink("serial:/dev/does-not-exist:57600", **link_kwargs()):
                pass

    run(main())
