"""A MAVLink 2 packer for the emulator's telemetry: the bytes pymavlink's ``MAVLink.send`` would
write (same header, payload with its trailing zeros stripped, CRC-16/MCRF4XX with the
message's CRC extra), at about a fifth of its cost (pymavlink builds a header object, a
bytearray and two CRC objects per frame). Unsigned frames of messages whose fields are all
numbers only; anything else goes through pymavlink (``MavUdpLink.pack``).
tests/sim/test_mavpack.py checks the bytes against pymavlink's over every message the emulator
streams.
"""

from __future__ import annotations

import operator
import struct
from collections.abc import Callable
from typing import Any

from fastcrc.crc16 import mcrf4xx

_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")
_MAGIC_V2 = 0xFD
_NUMERIC: dict[type, bool] = {}
# per message class: its fields' getter (a tuple in wire order), its array fields (index,
# length) last first, its payload packer, id and CRC extra byte; built once per class
_Plan = tuple[Callable[[Any], Any], tuple[tuple[int, int], ...], Any, int, bytes]
_PLANS: dict[type, _Plan] = {}
# the attribute under which a message keeps its packed payload: a message sent on several
# links (Telemetry shares one encoding) is packed once; each link adds its own header
_PAYLOAD_ATTR = "_sim_bridge_payload"


def packable(msg: Any) -> bool:
    """Whether :func:`pack` packs ``msg`` (a message with number fields only: no strings)."""
    cls = type(msg)
    ok = _NUMERIC.get(cls)
    if ok is None:
        ok = all(t != "char" for t in getattr(cls, "fieldtypes", ["char"]))
        _NUMERIC[cls] = ok
    return ok


def _plan(cls: type) -> _Plan:
    names = list(cls.ordered_fieldnames)  # type: ignore[attr-defined]
    get = operator.attrgetter(*names)
    getter: Callable[[Any], Any] = get if len(names) > 1 else (lambda m: (get(m),))
    arrays = tuple((i, n) for i, n in enumerate(cls.array_lengths) if n)  # type: ignore[attr-defined]
    plan = (getter, arrays[::-1], cls.unpacker, cls.id,  # type: ignore[attr-defined]
            bytes((cls.crc_extra,)))  # type: ignore[attr-defined]
    _PLANS[cls] = plan
    return plan


def payload(msg: Any) -> bytes:
    """``msg``'s MAVLink 2 payload (trailing zeros stripped, at least one byte); kept on the
    message, which must not change afterwards (pymavlink's ``*_encode`` builds a fresh one)."""
    p: bytes | None = getattr(msg, _PAYLOAD_ATTR, None)
    if p is not None:
        return p
    cls = type(msg)
    getter, arrays, unpacker, _, _ = _PLANS.get(cls) or _plan(cls)
    values = getter(msg)
    if arrays:
        values = list(values)
        for i, n in arrays:  # last first: the earlier indices stay put
            values[i:i + 1] = values[i][:n]
    p = unpacker.pack(*values).rstrip(b"\0") or b"\0"  # MAVLink 2: trailing zeros
    setattr(msg, _PAYLOAD_ATTR, p)
    return p


def pack(mav: Any, msg: Any) -> bytes:
    """The unsigned MAVLink 2 frame of ``msg`` from ``mav`` (pymavlink ``MAVLink``), taking its
    next sequence number and counting it as ``mav.send`` does. ``packable(msg)`` must hold and
    ``mav`` must not sign."""
    cls = type(msg)
    pl = payload(msg)
    _, _, _, mid, extra = _PLANS[cls]
    body = _HEADER.pack(_MAGIC_V2, len(pl), 0, 0, mav.seq, mav.srcSystem,
                        mav.srcComponent, mid & 0xFFFF, mid >> 16) + pl
    frame = body + _CRC.pack(mcrf4xx(extra, mcrf4xx(body[1:], 0xFFFF)))
    mav.seq = (mav.seq + 1) % 256
    mav.total_packets_sent += 1
    mav.total_bytes_sent += len(frame)
    return frame
