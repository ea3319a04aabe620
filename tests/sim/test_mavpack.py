"""The emulator's MAVLink 2 packer (sim_bridge/mavpack.py) writes pymavlink's bytes: every message
of the dialect with number fields, random values (zeros included: MAVLink 2 strips trailing
zero bytes), and the link's sequence numbers and counters advance the same way."""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from sim_bridge import mavpack
from sim_bridge.link import MavUdpLink

_INT_RANGES = {"int8_t": (-128, 127), "uint8_t": (0, 255), "int16_t": (-32768, 32767),
               "uint16_t": (0, 65535), "int32_t": (-2**31, 2**31 - 1), "uint32_t": (0, 2**32 - 1),
               "int64_t": (-2**63, 2**63 - 1), "uint64_t": (0, 2**64 - 1)}


def _value(rng: np.random.Generator, ftype: str, zero: bool) -> Any:
    if zero:
        return 0.0 if ftype in ("float", "double") else 0
    if ftype in ("float", "double"):
        return float(np.float32(rng.normal() * 10.0 ** int(rng.integers(-3, 4))))
    lo, hi = _INT_RANGES[ftype]
    return int(rng.integers(lo, hi, endpoint=True, dtype=np.int64)) if hi < 2**63 else int(
        rng.integers(0, 2**62))


def _random_message(cls: type, rng: np.random.Generator) -> Any:
    args = []
    tail_zero = rng.random() < 0.3  # the last fields zero: stripped on the wire
    for i, (name, ftype) in enumerate(zip(cls.fieldnames, cls.fieldtypes, strict=True)):
        zero = tail_zero and i >= len(cls.fieldnames) // 2
        n = cls.array_lengths[cls.ordered_fieldnames.index(name)]
        args.append([_value(rng, ftype, zero) for _ in range(n)] if n else
                    _value(rng, ftype, zero))
    return cls(*args)


def _ours_and_pymavlinks() -> tuple[Any, Any, list[bytes]]:
    """A sender for mavpack (no output) and a pymavlink one whose frames land in the list."""
    frames: list[bytes] = []

    class Sink:
        def write(self, b: bytes) -> None:
            frames.append(bytes(b))

    return (mavlink2.MAVLink(None, srcSystem=1, srcComponent=1),
            mavlink2.MAVLink(Sink(), srcSystem=1, srcComponent=1), frames)


def test_packer_writes_pymavlinks_bytes_for_every_numeric_message() -> None:
    rng = np.random.default_rng(4)
    ours, ref, frames = _ours_and_pymavlinks()
    checked = 0
    for cls in mavlink2.mavlink_map.values():
        if "char" in cls.fieldtypes:  # strings: pymavlink packs them (MavUdpLink.pack)
            assert not mavpack.packable(cls.__new__(cls))
            continue
        msg0 = _random_message(cls, rng)
        assert mavpack.packable(msg0)
        for k in range(6):
            msg = msg0 if k == 0 else _random_message(cls, rng)
            ref.send(msg)
            assert mavpack.pack(ours, msg) == frames.pop(), cls.__name__
            checked += 1
    assert checked > 600
    assert (ours.seq, ours.total_packets_sent, ours.total_bytes_sent) == (
        ref.seq, ref.total_packets_sent, ref.total_bytes_sent)


def _random_args(cls: type, rng: np.random.Generator) -> list[Any]:
    """Arguments of pymavlink's ``*_encode`` (declaration order), as _random_message draws."""
    msg = _random_message(cls, rng)
    return [getattr(msg, f) for f in cls.fieldnames]


def test_encoder_writes_pymavlinks_bytes_for_every_numeric_message() -> None:
    """mavpack.encoder (the telemetry's encoding: no pymavlink message object) packs the
    frame pymavlink's ``*_encode`` + ``send`` writes, for every number-only message, with the
    extension fields given or left to their defaults; its message() is pymavlink's."""
    rng = np.random.default_rng(6)
    ours, ref, frames = _ours_and_pymavlinks()
    checked = 0
    for cls in mavlink2.mavlink_map.values():
        if "char" in cls.fieldtypes:
            try:
                mavpack.encoder(cls)
            except ValueError:
                continue
            raise AssertionError(f"{cls.__name__}: strings must go through pymavlink")
        encode = mavpack.encoder(cls)
        method = getattr(ref, cls.msgname.lower() + "_encode")
        n_ext = sum(p.default is not inspect.Parameter.empty
                    for p in inspect.signature(cls).parameters.values())
        for k in range(6):
            args = _random_args(cls, rng)
            if k % 2 and n_ext:  # the extensions left out: pymavlink's defaults
                args = args[:len(args) - n_ext]
            enc = encode(*args)
            assert mavpack.packable(enc)
            ref.send(method(*args))
            assert mavpack.pack(ours, enc) == frames.pop(), cls.__name__
            pm = enc.message()
            assert type(pm) is cls and pm.pack(mavlink2.MAVLink(None)) == method(
                *args).pack(mavlink2.MAVLink(None)), cls.__name__
            checked += 1
    assert checked > 600
    assert (ours.seq, ours.total_packets_sent, ours.total_bytes_sent) == (
        ref.seq, ref.total_packets_sent, ref.total_bytes_sent)


def test_every_telemetry_encoding_is_pymavlinks() -> None:
    """Each message the telemetry encodes with mavpack.encoder, fed the same arguments,
    gives pymavlink's frame (HIGHRES_IMU with the fields_updated bitmask, arrays, ints)."""
    from sim_bridge.px4 import telemetry

    rng = np.random.default_rng(7)
    assert len(telemetry._ENC) == 13
    for mid, encode in telemetry._ENC.items():
        cls = mavlink2.mavlink_map[mid]
        a, b = (mavlink2.MAVLink(None, srcSystem=1, srcComponent=1) for _ in range(2))
        for _ in range(20):
            args = _random_args(cls, rng)
            ref = getattr(a, cls.msgname.lower() + "_encode")(*args).pack(a)
            a.seq = (a.seq + 1) % 256  # as a.send() would count it
            assert mavpack.pack(b, encode(*args)) == ref, cls.__name__


def test_link_packs_numbers_fast_and_strings_through_pymavlink() -> None:
    link = MavUdpLink("t", "127.0.0.1", 0, None, 1, 1)
    ref = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    for msg in (link.mav.attitude_quaternion_encode(1000, 1.0, 0.0, 0.0, 0.0, 0.1, 0.2, 0.3),
                link.mav.statustext_encode(6, b"hello", 0, 0),
                link.mav.heartbeat_encode(2, 12, 0, 0, 0, 3)):
        assert link.pack(msg) == [msg.pack(ref)]
        ref.seq = (ref.seq + 1) % 256


def _pymavlink_parse(data: bytes) -> list[Any]:
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    return parser.parse_buffer(data) or []


def _same_message(a: Any, b: Any) -> bool:
    """Type, every field (NaN equal to NaN: the bytes of its float), buffer, payload, CRC,
    header and signing flags."""
    def fields(m: Any) -> list[Any]:
        return [repr(getattr(m, f)) for f in m.get_fieldnames()]
    ha, hb = a.get_header(), b.get_header()
    return (type(a) is type(b) and fields(a) == fields(b) and a._msgbuf == b._msgbuf
            and type(a._msgbuf) is type(b._msgbuf) and a._payload == b._payload
            and a._crc == b._crc and a._signed == b._signed and a._link_id == b._link_id
            and vars(ha) == vars(hb))


def test_unpacker_builds_pymavlinks_message_for_every_numeric_message() -> None:
    rng = np.random.default_rng(5)
    sender = mavlink2.MAVLink(None, srcSystem=7, srcComponent=190)
    checked = 0
    for cls in mavlink2.mavlink_map.values():
        if "char" in cls.fieldtypes:
            continue
        for _ in range(4):
            sender.seq = int(rng.integers(256))
            data = mavpack.pack(sender, _random_message(cls, rng))
            (ref,) = _pymavlink_parse(data)
            ours = mavpack.unpack(data, mavlink2)
            assert ours is not None and _same_message(ours, ref), cls.__name__
            checked += 1
    assert checked > 400


def test_unpacker_leaves_everything_else_to_pymavlink() -> None:
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    sp = mavpack.pack(mav, mav.set_attitude_target_encode(
        1234, 1, 1, 7, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0.55))
    assert mavpack.unpack(sp, mavlink2) is not None
    bad_crc = sp[:-1] + bytes([sp[-1] ^ 1])
    text = mav.statustext_encode(6, b"hello", 0, 0).pack(mav)
    v1 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    hb_v1 = v1.heartbeat_encode(2, 12, 0, 0, 0, 3).pack(v1, force_mavlink1=True)
    unknown = bytearray(sp)
    unknown[7:10] = (60000).to_bytes(3, "little")  # no such message id
    for data in (bad_crc, sp + sp, sp[:-3], sp + b"\0", text, hb_v1, b"", bytes(unknown),
                 b"\xfd" + sp[1:2] + b"\x01" + sp[3:]):  # incompat flags (signed)
        assert mavpack.unpack(bytes(data), mavlink2) is None
    assert [m.get_type() for m in _pymavlink_parse(bad_crc)] == ["BAD_DATA"]
