"""One MAVLink 2 frame per UDP datagram, read without pymavlink's parser (the receive fast path).

An autopilot sends one frame per datagram. For such a datagram the header is read at its fixed
offsets (magic 0xFD, payload length, incompat flags, seq, sysid, compid, a 24-bit msgid), so a
message the companion does not use is counted from its header alone, and a used one is checked
(CRC-16/MCRF4XX with the message's CRC_EXTRA, as pymavlink computes it) and unpacked with the
message's precompiled ``struct`` unpacker straight into the fields dict that
:func:`companion.link.messages.message_fields` gives for pymavlink's decoding of the same bytes
(same values, same order: a replay re-decoding the logged bytes with pymavlink sees the same).

Anything else (several frames in a datagram, MAVLink 1, unknown incompat flags, an unknown
msgid, a bad CRC, a length that does not add up) is left to the robust pymavlink parser, which
rejects it with the reason it always gave. Why bother: pymavlink's parser costs ~17 us a frame
here (a byte-wise state machine in Python, then the decode); this ~4 us.
"""

from __future__ import annotations

import math
import operator
import re
import struct
from collections.abc import Callable
from typing import Any, NamedTuple

import fastcrc
from pymavlink.dialects.v20 import common as mavlink2

MAGIC_V2 = 0xFD
HEADER_LEN = 10  # magic, len, incompat, compat, seq, sysid, compid, msgid (3 bytes)
CRC_LEN = 2
SIGNATURE_LEN = 13
IFLAG_SIGNED = 0x01
_CRC = struct.Struct("<H")
_mcrf4xx = fastcrc.crc16.mcrf4xx


class Header(NamedTuple):
    """What a single-frame datagram's header says (``payload_end``: where the CRC starts)."""

    seq: int
    sysid: int
    compid: int
    msgid: int
    signed: bool
    payload_end: int


def single_frame_header(data: bytes) -> Header | None:
    """The header of ``data`` when it is exactly one MAVLink 2 frame (length, flags and
    signature block add up), else None (the robust parser then reads it)."""
    n = len(data)
    if n < HEADER_LEN + CRC_LEN or data[0] != MAGIC_V2:
        return None
    flags = data[2]
    if flags & ~IFLAG_SIGNED:
        return None  # an incompat flag we do not know: the parser decides
    signed = bool(flags & IFLAG_SIGNED)
    end = HEADER_LEN + data[1]
    if n != end + CRC_LEN + (SIGNATURE_LEN if signed else 0):
        return None
    return Header(data[4], data[5], data[6], data[7] | data[8] << 8 | data[9] << 16, signed, end)


class _Spec:
    """A message type's decoding plan, built once from pymavlink's generated class."""

    __slots__ = ("crc_extra", "fields", "floats", "name", "plan", "size", "unpacker")

    def __init__(self, cls: Any) -> None:
        self.name: str = cls.msgname
        self.crc_extra = bytes([cls.crc_extra])
        self.unpacker: struct.Struct = cls.unpacker
        self.size: int = cls.unpacker.size
        lengths, orders = list(cls.lengths), list(cls.orders)
        # pymavlink's decode: field i (definition order) is wire field orders[i], which starts
        # at tuple index sum(lengths[:order]) and spans lengths[order] items
        self.plan: list[tuple[str, int, int]] = []
        for i, fname in enumerate(cls.fieldnames):
            order = orders[i]
            self.plan.append((fname, sum(lengths[:order]), lengths[order]))
        #: the unpacked tuple's float items (as a tuple), None when there are none
        self.floats: Callable[[tuple[Any, ...]], tuple[float, ...]] | None = _float_items(
            cls.unpacker.format)
        #: the unpacked tuple -> the fields dict (:func:`_fields`'s result, built by one dict
        #: display compiled for this message: ~2x the loop's speed)
        self.fields: Callable[[tuple[Any, ...]], dict[str, Any]] = _fields_builder(
            self.plan, _item_codes(cls.unpacker.format))


def _item_codes(fmt: str) -> list[str]:
    """The ``struct`` code of each item that format ``fmt`` unpacks (a ``16s`` is one item)."""
    codes: list[str] = []
    for count, code in re.findall(r"(\d*)([a-zA-Z?])", fmt):
        codes.extend([code] * (1 if code == "s" or not count else int(count)))
    return codes


def _fields_builder(plan: list[tuple[str, int, int]],
                    codes: list[str]) -> Callable[[tuple[Any, ...]], dict[str, Any]]:
    """A function of the unpacked tuple giving what :func:`_fields` gives (same keys, order,
    values and types): one dict display generated from the plan, as ``dataclasses`` and
    ``namedtuple`` generate their methods. The names are pymavlink's field names (identifiers
    of the dialect, checked here); a char array (``s``) is decoded as :func:`_fields` does."""
    items = []
    for fname, tip, n in plan:
        if not fname.isidentifier():
            raise ValueError(f"unexpected MAVLink field name {fname!r}")
        if codes[tip] == "s":
            value = f"t[{tip}].rstrip(b'\\x00').decode('utf-8', errors='replace')"
        elif n != 1:
            value = "[" + ", ".join(f"t[{tip + k}]" for k in range(n)) + "]"
        else:
            value = f"t[{tip}]"
        items.append(f"{fname!r}: {value}")
    namespace: dict[str, Any] = {}
    exec(f"def build(t):\n    return {{{', '.join(items)}}}\n", namespace)
    return namespace["build"]  # type: ignore[no-any-return]


def _float_items(fmt: str) -> Callable[[tuple[Any, ...]], tuple[float, ...]] | None:
    """A getter of the float items (``f``, ``d``) of what ``struct`` format ``fmt`` unpacks
    (a ``16s`` is one item, a ``4f`` four)."""
    idx: list[int] = []
    pos = 0
    for count, code in re.findall(r"(\d*)([a-zA-Z?])", fmt):
        n = 1 if code == "s" or not count else int(count)
        if code in "fd":
            idx.extend(range(pos, pos + n))
        pos += n
    if not idx:
        return None
    if len(idx) == 1:
        i = idx[0]
        return lambda t: (t[i],)
    return operator.itemgetter(*idx)


_SPECS: dict[int, _Spec | None] = {}


def spec(msgid: int) -> _Spec | None:
    """The decoding plan of ``msgid`` (None: not in the common dialect)."""
    s = _SPECS.get(msgid, False)
    if s is False:
        cls = mavlink2.mavlink_map.get(msgid)
        s = _SPECS[msgid] = None if cls is None else _Spec(cls)
    return s  # type: ignore[return-value]


def crc_ok(data: bytes, h: Header, s: _Spec) -> bool:
    """The frame's CRC-16/MCRF4XX over bytes 1..payload end and the CRC_EXTRA matches."""
    crc = _mcrf4xx(s.crc_extra, _mcrf4xx(data[1:h.payload_end], 0xFFFF))
    return bool(crc == _CRC.unpack_from(data, h.payload_end)[0])


def decode_fields(data: bytes, h: Header, s: _Spec) -> dict[str, Any]:
    """The fields of a CRC-checked frame as :func:`message_fields` gives them for pymavlink's
    decoding (MAVLink 2 drops trailing zero bytes of the payload: they are put back)."""
    return s.fields(_unpacked(data, h, s))


def decode_checked(data: bytes, h: Header, s: _Spec) -> tuple[dict[str, Any], bool]:
    """:func:`decode_fields` and whether every float of the frame is finite (one sum of its
    floats: NaN and inf survive a sum; a False may also be finite values whose sum
    overflows, which the caller's value-by-value check then clears)."""
    t = _unpacked(data, h, s)
    get = s.floats
    return s.fields(t), get is None or math.isfinite(sum(get(t)))


def _unpacked(data: bytes, h: Header, s: _Spec) -> tuple[Any, ...]:
    payload = data[HEADER_LEN:h.payload_end]
    if len(payload) < s.size:
        payload += bytes(s.size - len(payload))
    return s.unpacker.unpack_from(payload)


def _fields(t: tuple[Any, ...], s: _Spec) -> dict[str, Any]:
    """The reference form of ``s.fields(t)`` (:func:`_fields_builder`), kept for the test."""
    out: dict[str, Any] = {}
    for fname, tip, n in s.plan:
        v = t[tip]
        if isinstance(v, bytes):
            v = v.rstrip(b"\x00").decode("utf-8", errors="replace")
        elif n != 1:
            v = list(t[tip:tip + n])
        out[fname] = v
    return out


_HEADER_V2 = struct.Struct("<BBBBBBBHB")

#: SET_ATTITUDE_TARGET's payload in wire order (pymavlink's ``unpacker`` format): time_boot_ms,
#: q[4], body roll/pitch/yaw rates, thrust, target system, target component, type mask
SETPOINT_PAYLOAD = struct.Struct(mavlink2.MAVLink_set_attitude_target_message.unpacker.format)
#: TIMESYNC's payload: tc1, ts1
TIMESYNC_PAYLOAD = struct.Struct(mavlink2.MAVLink_timesync_message.unpacker.format)
SETPOINT_CRC_EXTRA = bytes([mavlink2.MAVLink_set_attitude_target_message.crc_extra])
TIMESYNC_CRC_EXTRA = bytes([mavlink2.MAVLink_timesync_message.crc_extra])


def frame(payload: bytes, seq: int, sysid: int, compid: int, msgid: int,
          crc_extra: bytes) -> bytes:
    """An unsigned MAVLink 2 frame of ``payload`` (its full wire-order bytes): the trailing
    zero bytes dropped as MAVLink 2 does (at least one byte stays), the header, the
    CRC-16/MCRF4XX with ``crc_extra``; byte for byte pymavlink's ``pack``."""
    payload = payload.rstrip(b"\x00") or payload[:1]
    body = _HEADER_V2.pack(MAGIC_V2, len(payload), 0, 0, seq, sysid, compid, msgid & 0xFFFF,
                           msgid >> 16) + payload
    return body + _CRC.pack(_mcrf4xx(crc_extra, _mcrf4xx(body[1:], 0xFFFF)))


def _attitude_target_payload(msg: Any) -> bytes:
    q = msg.q
    return SETPOINT_PAYLOAD.pack(
        msg.time_boot_ms, q[0], q[1], q[2], q[3], msg.body_roll_rate, msg.body_pitch_rate,
        msg.body_yaw_rate, msg.thrust, msg.target_system, msg.target_component, msg.type_mask)


def _timesync_payload(msg: Any) -> bytes:
    return TIMESYNC_PAYLOAD.pack(msg.tc1, msg.ts1)


# what the step sends (the setpoint, the TIMESYNC probe before it): the wire field order of
# the message's generated ``pack``, its CRC_EXTRA byte and msgid
_PACKERS: dict[type, tuple[Callable[[Any], bytes], bytes, int]] = {
    cls: (payload, bytes([cls.crc_extra]), cls.id) for cls, payload in (
        (mavlink2.MAVLink_set_attitude_target_message, _attitude_target_payload),
        (mavlink2.MAVLink_timesync_message, _timesync_payload))}


def pack(msg: Any, mav: Any) -> bytes:
    """``msg``'s MAVLink 2 frame from ``mav`` (seq, source ids, signing), byte for byte what
    ``msg.pack(mav)`` gives. SET_ATTITUDE_TARGET and TIMESYNC, unsigned (sent every step), are
    framed here with the message's precompiled struct (~3 us instead of pymavlink's ~11 us: its
    header object, bytearray copies and CRC object); anything else (a signed link too) by
    pymavlink."""
    packer = _PACKERS.get(type(msg))
    if packer is None or mav.signing.sign_outgoing:
        return bytes(msg.pack(mav))
    payload_of, crc_extra, msgid = packer
    return frame(payload_of(msg), mav.seq, mav.srcSystem, mav.srcComponent, msgid, crc_extra)


class LazyMessage:
    """``Received.msg`` of a fast-path frame: the pymavlink message, decoded from the frame's
    bytes only when someone asks for one of its attributes (the flight never does; tests and
    tools may)."""

    __slots__ = ("_msg", "_raw")

    def __init__(self, raw: bytes) -> None:
        self._raw = raw
        self._msg: Any = None

    def _decoded(self) -> Any:
        if self._msg is None:
            self._msg = mavlink2.MAVLink(None).decode(bytearray(self._raw))
        return self._msg

    def __getattr__(self, name: str) -> Any:
        return getattr(self._decoded(), name)

    def __repr__(self) -> str:
        return repr(self._decoded())


__all__ = ["SETPOINT_CRC_EXTRA", "SETPOINT_PAYLOAD", "TIMESYNC_CRC_EXTRA", "TIMESYNC_PAYLOAD",
           "Header", "LazyMessage", "crc_ok", "decode_checked", "decode_fields", "frame", "pack",
           "single_frame_header", "spec"]
