"""A MAVLink 2 packer for the emulator's telemetry: the bytes pymavlink's ``MAVLink.send`` would
write (same header, payload with its trailing zeros stripped, CRC-16/MCRF4XX with the
message's CRC extra), at about a fifth of its cost (pymavlink builds a header object, a
bytearray and two CRC objects per frame). Unsigned frames of messages whose fields are all
numbers only; anything else goes through pymavlink (``MavUdpLink.pack``).
tests/sim/test_mavpack.py checks the bytes against pymavlink's over every message the emulator
streams.
"""

from __future__ import annotations

import inspect
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
    """Whether :func:`pack` packs ``msg`` (an :class:`Encoded`, or a message with number fields
    only: no strings)."""
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


class Encoded:
    """A message whose payload was packed when it was encoded (:func:`encoder`): no pymavlink
    message object on the way (its ``__init__`` and the field reads cost about as much as
    the packing). :meth:`message` builds pymavlink's, for a link that signs."""

    __slots__ = ("args", "cls", "extra", "mid", "payload")

    def __init__(self, cls: type, args: tuple[Any, ...], payload: bytes, mid: int,
                 extra: bytes) -> None:
        self.cls, self.args, self.payload, self.mid, self.extra = cls, args, payload, mid, extra

    def message(self) -> Any:
        """pymavlink's message of the same fields (``cls(*args)``, as ``*_encode`` builds it)."""
        return self.cls(*self.args)


_NUMERIC[Encoded] = True


def encoder(cls: type) -> Callable[..., Encoded]:
    """The encoder of pymavlink message class ``cls`` (number fields only): called with the
    arguments of pymavlink's ``MAVLink.<name>_encode`` (positional, in its order; omitted
    extension fields take its defaults), it returns an :class:`Encoded` whose payload is the
    one :func:`payload` packs from pymavlink's message (tests/sim/test_mavpack.py)."""
    if not all(t != "char" for t in cls.fieldtypes):  # type: ignore[attr-defined]
        raise ValueError(f"{cls.__name__}: string fields are packed by pymavlink")
    names = list(cls.fieldnames)  # type: ignore[attr-defined]
    defaults = tuple(p.default for p in inspect.signature(cls).parameters.values())
    # the payload's values in wire order, an array field's first n elements spliced in (as
    # pymavlink's pack reads them): one tuple display compiled from the field indices
    items = []
    for name, n in zip(cls.ordered_fieldnames, cls.array_lengths, strict=True):  # type: ignore[attr-defined]
        i = names.index(name)
        items += [f"a[{i}][{k}]" for k in range(n)] if n else [f"a[{i}]"]
    values: Callable[[tuple[Any, ...]], tuple[Any, ...]] = eval(  # built from indices only
        f"lambda a: ({', '.join(items)},)")
    st, mid, extra = cls.unpacker, cls.id, bytes((cls.crc_extra,))  # type: ignore[attr-defined]
    n_fields = len(names)

    def encode(*args: Any) -> Encoded:
        if len(args) < n_fields:
            args = args + defaults[len(args):]
        return Encoded(cls, args, st.pack(*values(args)).rstrip(b"\0") or b"\0", mid, extra)

    return encode


def pack(mav: Any, msg: Any) -> bytes:
    """The unsigned MAVLink 2 frame of ``msg`` (an :class:`Encoded` or a pymavlink message)
    from ``mav`` (pymavlink ``MAVLink``), taking its next sequence number and counting it as
    ``mav.send`` does. ``packable(msg)`` must hold and ``mav`` must not sign."""
    if type(msg) is Encoded:
        pl, mid, extra = msg.payload, msg.mid, msg.extra
    else:
        pl = payload(msg)
        _, _, _, mid, extra = _PLANS[type(msg)]
    body = _HEADER.pack(_MAGIC_V2, len(pl), 0, 0, mav.seq, mav.srcSystem,
                        mav.srcComponent, mid & 0xFFFF, mid >> 16) + pl
    frame = body + _CRC.pack(mcrf4xx(extra, mcrf4xx(body[1:], 0xFFFF)))
    mav.seq = (mav.seq + 1) % 256
    mav.total_packets_sent += 1
    mav.total_bytes_sent += len(frame)
    return frame


# ---------------------------------------------------------------------------------- receiving
# per message id: its class, payload size and unpacker, CRC extra byte and where each field
# sits in the unpacked tuple ((index, length): length 0 for a scalar); None: not unpacked here
_RxPlan = tuple[type, int, Any, bytes, tuple[tuple[int, int], ...]]
_RX_PLANS: dict[int, _RxPlan | None] = {}


def _rx_plan(mid: int, dialect: Any) -> _RxPlan | None:
    cls = dialect.mavlink_map.get(mid)
    plan: _RxPlan | None = None
    if cls is not None and all(t != "char" for t in cls.fieldtypes):
        lens, order = cls.lengths, cls.orders
        arrays = sum(lens) != len(lens)
        # pymavlink's decode: without arrays field i is t[order[i]]; with them it starts at
        # sum(lengths[:order[i]]) and spans lengths[order[i]] values (a list unless 1)
        fields = tuple((sum(lens[:o]), lens[o] if lens[o] > 1 else 0) if arrays else (o, 0)
                       for o in order)
        plan = (cls, cls.unpacker.size, cls.unpacker, bytes((cls.crc_extra,)), fields)
    _RX_PLANS[mid] = plan
    return plan


def unpack(data: bytes, dialect: Any) -> Any | None:
    """The message of a datagram that is exactly one unsigned MAVLink 2 frame with a good CRC
    of a message of ``dialect`` (a pymavlink dialect module) whose fields are all numbers,
    built as a fresh pymavlink parser with robust parsing builds it (the same fields, buffer,
    payload, CRC and header; tests/sim/test_mavpack.py) at a fraction of its cost (~80 us a
    SET_ATTITUDE_TARGET: a parser per datagram, byte-wise framing). ``None`` for anything
    else (MAVLink 1, signed, several frames, bad CRC, strings): pymavlink parses those."""
    n = len(data)
    if n < 12 or data[0] != _MAGIC_V2 or data[2] != 0 or n != data[1] + 12:
        return None
    mid = data[7] | data[8] << 8 | data[9] << 16
    plan = _RX_PLANS[mid] if mid in _RX_PLANS else _rx_plan(mid, dialect)
    if plan is None:
        return None
    cls, size, unpacker, extra, fields = plan
    crc = data[-2] | data[-1] << 8
    if crc != mcrf4xx(extra, mcrf4xx(data[1:-2], 0xFFFF)):
        return None
    body = data[10:-2]
    if len(body) < size:  # MAVLink 2 strips trailing zeros; extensions may be left out
        body += bytes(size - len(body))
    t = unpacker.unpack(body[:size])
    m = cls(*[t[i] if k == 0 else list(t[i:i + k]) for i, k in fields])
    m._signed = False
    m._msgbuf = bytearray(data)
    m._payload = m._msgbuf[6:-2]  # pymavlink's slice (a v1 header's length)
    m._crc = crc
    m._header = dialect.MAVLink_header(mid, 0, data[3], data[1], data[4], data[5], data[6])
    return m
