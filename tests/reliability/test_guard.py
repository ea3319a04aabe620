"""The receive guard on real UDP sockets: pinning, spoofed sources, allow list, re-pinning,
work bounds, and the vehicle's own socket under a flood."""

from __future__ import annotations

import asyncio
import math
import socket
import threading
from collections.abc import Awaitable
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion import ConfigError
from companion.config import load_config
from companion.link import MavlinkLink, Received
from companion.link.guard import GuardParams, claimed_sysids, parse_source

AP_SYS, AP_COMP, AGV_SYS = 1, 1, 42


class Node:
    """A MAVLink 2 sender on its own UDP socket (its own source address)."""

    def __init__(self, sysid: int = AP_SYS, compid: int = AP_COMP) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.addr = self.sock.getsockname()
        self.mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)

    def frame(self, msg: Any) -> bytes:
        b = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return b

    def heartbeat(self) -> bytes:
        return self.frame(self.mav.heartbeat_encode(2, 12, 209, 6 << 16, 4, 3))

    def att(self, t_ms: int, roll: float = 0.0) -> bytes:
        c, s = math.cos(roll / 2), math.sin(roll / 2)
        return self.frame(self.mav.attitude_quaternion_encode(t_ms, c, s, 0, 0, 0, 0, 0))

    def send(self, to: tuple[str, int], *frames: bytes) -> None:
        for f in frames:
            self.sock.sendto(f, to)

    def close(self) -> None:
        self.sock.close()


def run(coro: Awaitable[Any]) -> Any:
    return asyncio.run(asyncio.wait_for(coro, 60))  # type: ignore[arg-type]


def kwargs(**guard: Any) -> dict[str, Any]:
    return dict(source_system=1, source_component=191, target_system=AP_SYS,
                target_component=AP_COMP, guard=GuardParams(**guard))


async def until(link: MavlinkLink, pred: Any, got: list[Received]) -> None:
    while True:
        rx = await link.recv(10.0)
        got.append(rx)
        if pred(rx):
            return


def test_spoofed_autopilot_is_dropped_unparsed_and_the_setpoints_stay_with_the_vehicle() -> None:
    vehicle, attacker = Node(), Node()
    got: list[Received] = []

    async def main() -> dict[str, int]:
        async with MavlinkLink("udpin:127.0.0.1:0", **kwargs()) as link:
            to = link.local_address
            assert to is not None
            vehicle.send(to, vehicle.heartbeat())
            await until(link, lambda rx: rx.name == "HEARTBEAT", got)
            assert link.peer_address == vehicle.addr
            # a sustained spoof: plausible frames with the autopilot's identity, and a
            # HEARTBEAT, from another address; then the vehicle speaks again
            for i in range(50):
                attacker.send(to, attacker.att(900_000 + i, roll=0.7), attacker.heartbeat())
            await asyncio.sleep(0.2)
            vehicle.send(to, vehicle.att(1234))
            await until(link, lambda rx: rx.name == "ATTITUDE_QUATERNION", got)
            assert link.peer_address == vehicle.addr
            link.send_heartbeat()  # goes to the vehicle, not to the attacker
            vehicle.sock.settimeout(5)
            data, _ = vehicle.sock.recvfrom(4096)
            assert data[0] == 0xFD
            return dict(link.counters)

    c = run(main())
    assert [rx.name for rx in got] == ["HEARTBEAT", "ATTITUDE_QUATERNION"]
    assert got[-1].msg.time_boot_ms == 1234
    assert c["spoofed_source"] == 100
    assert "bad_data" not in c  # dropped before parsing: nothing of it was parsed
    for n in (vehicle, attacker):
        n.close()


def test_allowed_sources_may_speak_for_the_vehicle() -> None:
    vehicle, router = Node(), Node()
    got: list[Received] = []

    async def main() -> None:
        async with MavlinkLink("udpin:127.0.0.1:0",
                               **kwargs(allowed_sources=("127.0.0.1",))) as link:
            to = link.local_address
            assert to is not None
            vehicle.send(to, vehicle.heartbeat())
            await until(link, lambda rx: rx.name == "HEARTBEAT", got)
            router.send(to, router.att(77))
            await until(link, lambda rx: rx.name == "ATTITUDE_QUATERNION", got)
            assert link.counters["spoofed_source"] == 0

    run(main())
    assert got[-1].msg.time_boot_ms == 77
    vehicle.close()
    router.close()


def test_a_silent_pin_is_released_and_the_autopilot_found_again() -> None:
    old, new = Node(), Node()
    got: list[Received] = []

    async def main() -> None:
        async with MavlinkLink("udpin:127.0.0.1:0", **kwargs(repin_after_s=0.3)) as link:
            to = link.local_address
            assert to is not None
            old.send(to, old.heartbeat())
            await until(link, lambda rx: rx.name == "HEARTBEAT", got)
            new.send(to, new.heartbeat())  # while the old pin is live: refused
            await asyncio.sleep(0.1)
            assert link.counters["spoofed_source"] == 1
            await asyncio.sleep(0.4)
            new.send(to, new.heartbeat())
            await until(link, lambda rx: rx.name == "HEARTBEAT", got)
            assert link.peer_address == new.addr
            assert link.guard.counters["repinned"] == 1

    run(main())
    old.close()
    new.close()


def test_oversize_and_rate_limited_datagrams_are_dropped_unparsed() -> None:
    stranger = Node(sysid=7)

    async def main() -> dict[str, int]:
        async with MavlinkLink("udpin:127.0.0.1:0", **kwargs(
                max_datagram_bytes=300, untrusted_parse_per_s=1.0,
                untrusted_burst=5)) as link:
            to = link.local_address
            assert to is not None
            stranger.send(to, b"\x00" * 301)
            for i in range(50):
                stranger.send(to, bytes([i]) * 20)
            await asyncio.sleep(0.5)
            return dict(link.counters)

    c = run(main())
    assert c["oversize"] == 1
    assert c["rate_limited"] >= 40  # 5 in the burst, ~1 more per second
    stranger.close()


def test_a_flood_does_not_crowd_out_the_vehicle() -> None:
    """The pinned vehicle has its own socket: 30,000 junk datagrams from another address at
    once, while the vehicle sends 300 numbered frames: every vehicle frame arrives, in order."""
    vehicle, attacker = Node(), Node(sysid=99)
    got: list[Received] = []

    async def main() -> dict[str, int]:
        # buffers small enough (512 kB as the kernel doubles it) for the junk to overflow
        async with MavlinkLink("udpin:127.0.0.1:0",
                               **kwargs(recv_buffer_bytes=256 * 1024)) as link:
            to = link.local_address
            assert to is not None
            vehicle.send(to, vehicle.heartbeat())
            await until(link, lambda rx: rx.name == "HEARTBEAT", got)
            junk = [bytes([0xFD]) + bytes([i % 251]) * 60 for i in range(30_000)]

            def flood() -> None:
                for j in junk:
                    attacker.sock.sendto(j, to)

            th = threading.Thread(target=flood)
            th.start()
            for i in range(300):
                vehicle.send(to, vehicle.att(i + 1))
            await until(link, lambda rx: rx.name == "ATTITUDE_QUATERNION"
                        and rx.msg.time_boot_ms == 300, got)
            th.join()
            return dict(link.counters)

    c = run(main())
    t = [rx.msg.time_boot_ms for rx in got if rx.name == "ATTITUDE_QUATERNION"]
    assert t == list(range(1, 301))
    assert c["rx_datagrams"] > 301  # the junk was read too (what the kernel kept of it)
    vehicle.close()
    attacker.close()


def test_claimed_sysids_finds_every_header() -> None:
    n = Node(sysid=1)
    frame = n.att(5)
    assert claimed_sysids(frame) == {1}
    assert 1 in claimed_sysids(b"garbage" + frame + b"\xfe\x09\x00\x2a\x01\x1e")
    assert 42 in claimed_sysids(b"\xfe\x09\x00\x2a\x01\x1e")  # a MAVLink 1 header: sysid 42
    assert claimed_sysids(b"\x00" * 50) == set()
    n.close()


@pytest.mark.parametrize("text", ["1.2.3", "localhost", "1.2.3.4:0", "1.2.3.4:70000", "::1"])
def test_bad_allowed_sources_are_refused(text: str) -> None:
    with pytest.raises(ConfigError, match=r"mavlink\.allowed_sources"):
        load_config(overrides=[f'mavlink.allowed_sources=["{text}"]'])
    with pytest.raises(Exception, match="allowed source"):
        parse_source(text)


@pytest.mark.parametrize("ov, key", [
    ('logging.fsync="sometimes"', "logging.fsync"),
    ("safety.max_frame_age_s=0", "safety.max_frame_age_s"),
    ("mavlink.untrusted_parse_per_s=-1", "mavlink.untrusted_parse_per_s"),
    ("mavlink.max_datagrams_per_wakeup=0", "mavlink.max_datagrams_per_wakeup"),
])
def test_new_keys_are_validated(ov: str, key: str) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(overrides=[ov])
