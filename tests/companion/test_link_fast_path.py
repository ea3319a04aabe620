"""The receive fast path (companion/link/wire.py): one frame per datagram read at its header
offsets and unpacked with precompiled structs, against pymavlink's own decoding, over real UDP."""

from __future__ import annotations

import asyncio
import math
import socket
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.link import MavlinkLink, Received, default_allow_rules, message_fields, wire
from companion.link.filters import ValueLimits, check_fields
from companion.link.receive import new_parser, reset_parser

AP_SYS, AP_COMP, AGV_SYS, AGV_COMP = 1, 1, 42, 1
NAN = math.nan


def _frames(sysid: int = AP_SYS, compid: int = AP_COMP) -> list[bytes]:
    """One frame of each kind the companion reads, with NaN, strings, arrays, signed and
    unsigned ints at their extremes and trailing zero bytes (MAVLink 2 truncates them)."""
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    msgs = [
        mav.heartbeat_encode(2, 12, 157, 0x060000, 4, 3),
        mav.attitude_quaternion_encode(123, 0.5, 0.5, 0.5, 0.5, 0.1, -0.2, 0.3, [0, 0, 0, 0]),
        mav.attitude_quaternion_encode(124, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                       [NAN, NAN, NAN, NAN]),
        mav.attitude_encode(4_000_000_000, 0.1, -0.2, 3.1, 0.0, 0.0, 0.0),
        mav.local_position_ned_encode(77, 1.5, -2.5, -3.0, 0.1, 0.2, -0.3),
        mav.attitude_target_encode(88, 7, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.5),
        mav.global_position_int_encode(99, 473_977_418, -85_455_939, 500_000, -1000, 1, -2,
                                       3, 65535),
        mav.extended_sys_state_encode(0, 2),
        mav.sys_status_encode(1, 2, 3, 500, 12000, -1, 50, 0, 0, 0, 0, 0, 0),
        mav.statustext_encode(4, b"Takeoff detected", 0, 0),
        mav.statustext_encode(6, b"x" * 50, 7, 1),  # a full char[50]: no terminator
        mav.timesync_encode(0, 123_456_789_012),
        mav.command_ack_encode(176, 0, 0, 0, 0, 0),
        mav.param_value_encode(b"MPC_XY_VEL_MAX", 12.0, 9, 900, 17),
        mav.system_time_encode(1_700_000_000_000_000, 1234),
        mav.home_position_encode(1, 2, 3, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], NAN, NAN, NAN,
                                 0),
        mav.altitude_encode(10, NAN, 1.0, NAN, 2.0, NAN, NAN),
    ]
    out = []
    for m in msgs:
        out.append(bytes(m.pack(mav)))
        mav.seq = (mav.seq + 1) % 256
    return out


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


def _pymavlink_fields(frame: bytes) -> tuple[str, dict[str, Any]]:
    p = reset_parser(new_parser())
    (m,) = p.parse_buffer(frame)
    return m.get_type(), message_fields(m)


def test_fields_equal_pymavlink_decoding() -> None:
    """Same values, same types, same order as message_fields of pymavlink's decode: a replay
    re-decoding the logged bytes with pymavlink sees exactly what the flight saw."""
    for frame in _frames():
        h = wire.single_frame_header(frame)
        assert h is not None
        s = wire.spec(h.msgid)
        assert s is not None and wire.crc_ok(frame, h, s)
        name, want = _pymavlink_fields(frame)
        got = wire.decode_fields(frame, h, s)
        assert s.name == name
        assert list(got) == list(want), name
        assert all(_same(got[k], want[k]) for k in want), (name, got, want)


def _floats_finite(fields: dict[str, Any]) -> bool:
    vals = [v for v in fields.values() if isinstance(v, float)]
    vals += [x for v in fields.values() if isinstance(v, list) for x in v if isinstance(x, float)]
    return all(math.isfinite(x) for x in vals)


def test_decode_checked_knows_when_every_float_is_finite() -> None:
    """The fast path's one-sum finiteness flag is the value-by-value answer, and the value
    check given it answers as the full check (NaN where allowed, inf, NaN in an array)."""
    mav = mavlink2.MAVLink(None, srcSystem=AP_SYS, srcComponent=AP_COMP)
    extra = [mav.attitude_encode(4, 0, 0, 0, 0, 0, math.inf),
             mav.attitude_target_encode(5, 7, [1.0, NAN, 0, 0], 0, 0, 0, 0.5),
             mav.local_position_ned_encode(6, 1e38, 1e38, 0, 0, 0, -math.inf),
             mav.follow_target_encode(7, 1, 1, 2, 3.0, [0, 0, 0], [NAN, 0, 0],
                                      [1, 0, 0, 0], [0, 0, 0], [0, 0, 0], 0)]
    frames = _frames() + [bytes(m.pack(mav)) for m in extra]
    limits = ValueLimits()
    flags = []
    for frame in frames:
        h = wire.single_frame_header(frame)
        assert h is not None
        s = wire.spec(h.msgid)
        assert s is not None
        fields, finite = wire.decode_checked(frame, h, s)
        assert fields == wire.decode_fields(frame, h, s) or not finite
        assert finite == _floats_finite(fields), s.name
        assert check_fields(s.name, fields, limits, finite) == check_fields(s.name, fields,
                                                                            limits), s.name
        flags.append(finite)
    assert flags.count(False) >= 6 and flags.count(True) >= 10


def test_header_refuses_what_is_not_one_frame() -> None:
    f = _frames()[1]
    h = wire.single_frame_header(f)
    assert h is not None and (h.sysid, h.compid, h.msgid) == (AP_SYS, AP_COMP, 31)
    assert wire.single_frame_header(f + f) is None  # two frames
    assert wire.single_frame_header(f[:-1]) is None  # truncated
    assert wire.single_frame_header(b"\xfd") is None
    assert wire.single_frame_header(bytes([0xFE]) + f[1:]) is None  # MAVLink 1 magic
    assert wire.single_frame_header(f[:2] + b"\x02" + f[3:]) is None  # unknown incompat flag
    bad = bytearray(f)
    bad[12] ^= 0x40  # a payload bit: the header still adds up, the CRC does not
    hb = wire.single_frame_header(bytes(bad))
    s = wire.spec(31)
    assert hb is not None and s is not None and not wire.crc_ok(bytes(bad), hb, s)


async def _fly(datagrams: list[bytes]) -> tuple[list[Received], dict[str, int]]:
    got: list[Received] = []
    rules = default_allow_rules(AP_SYS, AP_COMP, AGV_SYS, AGV_COMP)
    link = MavlinkLink("udpin:127.0.0.1:0", source_system=255, source_component=190,
                       target_system=AP_SYS, target_component=AP_COMP, allow=rules,
                       on_rx=got.append)
    async with link:
        addr = link.local_address
        assert addr is not None
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            tx.bind(("127.0.0.1", 0))
            for d in datagrams:
                tx.sendto(d, addr)
            for _ in range(400):
                if link.counters["rx_datagrams"] >= len(datagrams):
                    break
                await asyncio.sleep(0.005)
        finally:
            tx.close()
        return got, dict(link.counters)


def test_link_over_udp_accepts_and_rejects_like_the_parser() -> None:
    frames = _frames()
    mav = mavlink2.MAVLink(None, srcSystem=AP_SYS, srcComponent=AP_COMP)
    mav.seq = 200
    imu = bytes(mav.highres_imu_encode(1, *([0.0] * 12), 0x1FFF, 0).pack(mav))
    bad_crc = bytearray(frames[4])
    bad_crc[-1] ^= 0xFF
    pair = [bytes(m.pack(mav)) for m in (mav.attitude_encode(5, 0, 0, 0, 0, 0, 0),
                                         mav.local_position_ned_encode(6, 0, 0, 0, 0, 0, 0))]
    two = pair[0] + pair[1]  # two frames in one datagram: the parser reads both
    got, counters = asyncio.run(_fly(
        [*frames, imu, bytes(bad_crc), frames[4][:-3], two, frames[3]]))
    names = [rx.name for rx in got]
    # every good frame once (NaN where the message may carry it: repr_offset_q), the pair
    # too, never the corrupted, the truncated or the repeated one; HIGHRES_IMU is unused
    assert names.count("ATTITUDE_QUATERNION") == 2
    assert names.count("ATTITUDE") == 2 and names.count("EXTENDED_SYS_STATE") == 1
    assert names.count("LOCAL_POSITION_NED") == 2
    assert "HIGHRES_IMU" not in names
    assert counters["unused"] == 1
    assert counters["bad_data"] >= 1  # the bad CRC: the parser's reason, as before
    assert counters["duplicate"] == 1  # the last datagram
    assert counters.get("non_finite", 0) == 0
    for rx in got:
        name, want = _pymavlink_fields(rx.raw)
        assert rx.name == name and rx.fields is not None
        assert all(_same(rx.fields[k], want[k]) for k in want)
        assert rx.msg.get_type() == name  # the pymavlink message, decoded on demand
    att = next(rx for rx in got if rx.name == "ATTITUDE")
    assert att.msg.time_boot_ms == 4_000_000_000 and att.seq == 3


def test_bad_values_refused_on_the_fast_path() -> None:
    mav = mavlink2.MAVLink(None, srcSystem=AP_SYS, srcComponent=AP_COMP)
    frames = []
    for m in (mav.local_position_ned_encode(1, NAN, 0, 0, 0, 0, 0),
              mav.local_position_ned_encode(2, 0, 0, 0, 300.0, 0, 0),
              mav.attitude_quaternion_encode(3, 0.9, 0, 0, 0, 0, 0, 0, [0, 0, 0, 0]),
              mav.attitude_encode(4, 0, 0, 0, 0, 0, math.inf),
              mav.attitude_target_encode(5, 7, [3e38, 3e38, 0, 0], 0, 0, 0, 0.5),
              mav.local_position_ned_encode(6, 1e38, 1e38, 0, 0, 0, 0)):
        frames.append(bytes(m.pack(mav)))
        mav.seq += 1
    got, counters = asyncio.run(_fly(frames))
    assert [rx.fields["time_boot_ms"] for rx in got if rx.fields] == [6]  # huge but finite
    assert counters["non_finite"] == 2
    assert counters["speed"] == 1
    assert counters["quaternion_norm"] == 2
    assert counters.get("angular_rate", 0) == 0


@pytest.mark.parametrize("cut", [1, 5, 11, 20])
def test_truncated_datagram_is_rejected_not_delivered(cut: int) -> None:
    f = _frames()[4]
    got, counters = asyncio.run(_fly([f[:cut]]))
    assert got == []
    assert counters["rejected"] >= 1


def test_setpoint_packer_gives_pymavlink_bytes() -> None:
    """wire.pack (SET_ATTITUDE_TARGET's own packer) against pymavlink's pack over many values:
    every seq, ids and type masks at their extremes, zeros that MAVLink 2 truncates, NaN,
    infinities; a signed link and any other message go through pymavlink (same bytes too), and
    an out-of-range field is the same struct.error."""
    import random

    rng = random.Random(24)
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=191)
    specials = [0.0, -0.0, 1.0, -1.0, NAN, math.inf, 1e-45, 3.4e38]
    n_fast = 0
    for i in range(5000):
        mav.seq = i % 256
        mav.srcSystem, mav.srcComponent = rng.choice([(0, 0), (1, 191), (255, 255)])
        pick = (lambda: rng.choice(specials)) if i % 4 == 0 else (lambda: rng.uniform(-1, 1))
        msg = mav.set_attitude_target_encode(
            rng.choice([0, 1, 0xFFFFFFFF, rng.randrange(2**32)]), rng.randrange(256),
            rng.choice([0, 255, rng.randrange(256)]), rng.choice([0, 7, 255]),
            [pick() for _ in range(4)] if i % 9 else [0.0] * 4,
            *(0.0, 0.0, 0.0) if i % 2 else (pick(), pick(), pick()),
            rng.random() if i % 3 else 0.0)
        assert wire.pack(msg, mav) == bytes(msg.pack(mav)), i
        n_fast += 1
    assert n_fast == 5000
    for tc1, ts1 in [(0, 0), (0, 123), (2**63 - 1, -(2**63)), (1, 2**40)] + [
            (rng.randrange(2**62), rng.randrange(2**62)) for _ in range(500)]:
        msg = mav.timesync_encode(tc1, ts1)
        assert wire.pack(msg, mav) == bytes(msg.pack(mav))
    other = mav.heartbeat_encode(18, 8, 0, 0, 4)
    assert wire.pack(other, mav) == bytes(other.pack(mav))
    bad = mav.set_attitude_target_encode(2**32, 1, 1, 7, [1.0, 0, 0, 0], 0, 0, 0, 0.5)
    with pytest.raises(Exception) as fast:
        wire.pack(bad, mav)
    with pytest.raises(Exception) as slow:
        bad.pack(mav)
    assert type(fast.value) is type(slow.value)
    key = bytes(range(32))
    a, b = (mavlink2.MAVLink(None, srcSystem=1, srcComponent=191) for _ in range(2))
    for m in (a, b):
        m.signing.secret_key, m.signing.sign_outgoing, m.signing.timestamp = key, True, 1000
    msg = a.set_attitude_target_encode(5, 1, 1, 7, [1.0, 0.0, 0.0, 0.0], 0, 0, 0, 0.5)
    signed = wire.pack(msg, a)
    assert signed == bytes(msg.pack(b)) and signed[2] & 1 and len(signed) > 12 + 13


def test_fast_constructors_give_the_dataclasses() -> None:
    """``received`` / ``sent`` (no frozen ``__init__``) build what the dataclasses build:
    equal, same repr, same hash, still frozen."""
    import dataclasses

    from companion.link.messages import Sent, received, sent

    args = ("msg", b"\xfd\x01", 12, 1, 2, 30, "ATTITUDE", 7, False, {"roll": 0.5})
    fast, slow = received(*args), Received(*args)
    assert fast == slow and repr(fast) == repr(slow)
    assert dataclasses.astuple(fast) == dataclasses.astuple(slow) == args
    with pytest.raises(dataclasses.FrozenInstanceError):
        fast.seq = 8  # type: ignore[misc]
    sargs = ("msg", b"\xfd\x02", 13, 82, "SET_ATTITUDE_TARGET")
    fs, ss = sent(*sargs), Sent(*sargs)
    assert fs == ss and repr(fs) == repr(ss) and hash(fs) == hash(ss)
    assert dataclasses.astuple(fs) == (*sargs, None)


async def _sent_over_udp(signing_key: bytes | None, calls: list[tuple[str, tuple[Any, ...]]]
                         ) -> tuple[list[bytes], list[Any], list[bytes]]:
    """What ``calls`` (``("setpoint", (q, thrust, t_ms))`` or ``("timesync", (tc1, ts1))``)
    return, hand to ``on_tx`` and put on a real UDP socket, from a udpout link."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    tx_items: list[Any] = []
    link = MavlinkLink(f"udpout:127.0.0.1:{rx.getsockname()[1]}", source_system=1,
                       source_component=191, target_system=1, target_component=1,
                       signing_key=signing_key, on_tx=tx_items.append)
    returned, wire_bytes = [], []
    try:
        async with link:
            for what, args in calls:
                if what == "setpoint":
                    returned.append(link.send_attitude_target(*args))
                else:
                    returned.append(link.send_timesync(*args))
                wire_bytes.append(rx.recv(4096))
    finally:
        rx.close()
    return returned, tx_items, wire_bytes


def test_setpoint_and_timesync_packed_from_values_are_pymavlink_bytes() -> None:
    """send_attitude_target / send_timesync pack their payload straight from the values
    (no pymavlink object): over a real socket, every frame (every seq, through its wrap) is
    byte for byte pymavlink's pack of the message the slow path builds, and the ``Sent``
    handed to the log carries that message's fields (same values, types, order), so the
    /mavlink/out record is the same JSON. A signed link falls back to pymavlink (signed
    bytes); an out-of-range time_boot_ms still raises LinkError."""
    import random

    from companion.link import LinkError
    from companion.log.encode import encode_json, mavlink_payload

    rng = random.Random(7)
    calls: list[tuple[str, tuple[Any, ...]]] = []
    for i in range(300):
        if i % 5 == 0:
            calls.append(("timesync", (rng.choice([0, rng.randrange(2**62)]),
                                       rng.randrange(-(2**63), 2**63))))
            continue
        q = [rng.uniform(-1, 1) for _ in range(4)]
        n = math.sqrt(sum(x * x for x in q))
        q = [x / n * rng.uniform(0.95, 1.05) for x in q] if i % 7 else [1.0, 0.0, 0.0, 0.0]
        calls.append(("setpoint", (q, rng.choice([0.0, 1.0, rng.random()]),
                                   rng.choice([0, 0xFFFFFFFF, rng.randrange(2**32)]))))
    returned, items, on_wire = asyncio.run(_sent_over_udp(None, calls))
    ref = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    ref_link = MavlinkLink("udpout:127.0.0.1:9", source_system=1, source_component=191,
                           target_system=1, target_component=1)
    for i, ((what, args), got, item, dgram) in enumerate(
            zip(calls, returned, items, on_wire, strict=True)):
        msg = (ref_link.encode_attitude_target(*args) if what == "setpoint"
               else ref.timesync_encode(*args))
        want = bytes(msg.pack(ref))
        ref.seq = (ref.seq + 1) % 256
        assert got == dgram == item.raw == want, i
        assert item.fields is not None and list(item.fields) == list(message_fields(msg))
        assert all(_same(item.fields[k], v) for k, v in message_fields(msg).items()), i
        assert item.name == msg.get_type() and item.msgid == msg.get_msgId()
        assert item.msg.get_type() == msg.get_type()  # decoded from the bytes on demand
        slow = type(item)(msg, want, item.t_tx_ns, item.msgid, item.name)  # fields unknown
        assert encode_json(mavlink_payload("out", item)) == encode_json(
            mavlink_payload("out", slow)), i
    key = bytes(range(32))
    signed, _, _ = asyncio.run(_sent_over_udp(key, calls[:3]))
    assert all(raw[2] & 1 and len(raw) > 12 + 13 for raw in signed)
    with pytest.raises(LinkError):
        asyncio.run(_sent_over_udp(None, [("setpoint", ([1.0, 0, 0, 0], 0.5, 2**32))]))


def test_generated_field_builders_match_the_loop_for_every_message() -> None:
    """Each message's generated dict display (wire._fields_builder) gives what the plain loop
    (wire._fields) gives: same keys in the same order, same values and types (char arrays
    decoded, arrays as lists), on random payloads of every message of the dialect."""
    import random

    rng = random.Random(3)
    for msgid in mavlink2.mavlink_map:
        s = wire.spec(msgid)
        assert s is not None
        for _ in range(4):
            t = s.unpacker.unpack(bytes(rng.randrange(256) for _ in range(s.size)))
            want, got = wire._fields(t, s), s.fields(t)
            assert list(got) == list(want), s.name
            assert all(_same(got[k], v) or got[k] == v for k, v in want.items()), s.name
