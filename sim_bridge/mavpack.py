"""A MAVLink 2 packer for the emulator's telemetry: the bytes pymavlink's ``MAVLink.send`` would
write (same header, payload with its trailing zeros stripped, CRC-16/MCRF4XX with the
message's CRC extra), at about a third of its cost (pymavlink builds a header object, a
bytearray and two CRC objects per frame). Unsigned frames of messages whose fields are all
numbers only; anything else goes through pymavlink (``MavUdpLink.pack``).
tests/sim/test_mavpack.py checks the bytes against pymavlink's over every message the emulator
streams.
"""

from __future__ import annotations

import struct
from typing import Any

from fastcrc.crc16 import mcrf4xx

_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")
_MAGIC_V2 = 0xFD
_NUMERIC: dict[type, bool] = {}


def packable(msg: Any) -> bool:
    """Whether :func:`pack` packs ``msg`` (a message with number fields only: no strings)."""
    cls = type(msg)
    ok = _NUMERIC.get(cls)
    if ok is None:
        ok = all(t != "char" for t in getattr(cls, "fieldtypes", ["char"]))
        _NUMERIC[cls] = ok
    return ok


def pack(mav: Any, msg: Any) -> bytes:
    """The unsigned MAVLink 2 frame of ``msg`` from ``mav`` (pymavlink ``MAVLink``), taking its
    next sequence number and counting it as ``mav.send`` does. ``packable(msg)`` must hold and
    ``mav`` must not sign."""
    cls = type(msg)
    values: list[Any] = []
    for name, n in zip(cls.ordered_fieldnames, cls.array_lengths, strict=True):
        v = getattr(msg, name)
        if n:
            values.extend(v[:n])
        else:
            values.append(v)
    payload = cls.unpacker.pack(*values).rstrip(b"\0") or b"\0"  # MAVLink 2: trailing zeros
    mid = cls.id
    body = _HEADER.pack(_MAGIC_V2, len(payload), 0, 0, mav.seq, mav.srcSystem,
                        mav.srcComponent, mid & 0xFFFF, mid >> 16) + payload
    crc = mcrf4xx(bytes((cls.crc_extra,)), mcrf4xx(body[1:], 0xFFFF))
    frame = body + _CRC.pack(crc)
    mav.seq = (mav.seq + 1) % 256
    mav.total_packets_sent += 1
    mav.total_bytes_sent += len(frame)
    return frame
