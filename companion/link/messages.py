"""What the link hands out and logs: accepted frames (:class:`Received`), sent frames
(:class:`Sent`) and a message's fields as plain values."""


from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# ----------------------------------------------------------------------------------------------
# Received frames


@dataclass(frozen=True)
class Received:
    """One accepted MAVLink 2 frame. ``msg`` is the pymavlink message object (treat as
    read-only), ``raw`` the exact bytes received, ``t_rx_ns`` the link clock at receipt,
    ``fields`` the message's fields as :func:`message_fields` gives them, decoded once by the
    link and shared read-only by the telemetry store, the log clock and the log payload
    (``None`` when built elsewhere: the users then decode ``msg`` themselves)."""

    msg: Any
    raw: bytes
    t_rx_ns: int
    src_sysid: int
    src_compid: int
    msgid: int
    name: str
    seq: int
    signed: bool
    fields: dict[str, Any] | None = None


_new = object.__new__


def received(msg: Any, raw: bytes, t_rx_ns: int, src_sysid: int, src_compid: int, msgid: int,
             name: str, seq: int, signed: bool, fields: dict[str, Any] | None) -> Received:
    """A :class:`Received` equal to ``Received(...)`` of the same values, built without the
    frozen dataclass's ``__init__`` (one ``object.__setattr__`` a field: ~2 us of the ~6
    datagrams a step)."""
    r = _new(Received)
    r.__dict__.update(msg=msg, raw=raw, t_rx_ns=t_rx_ns, src_sysid=src_sysid,
                      src_compid=src_compid, msgid=msgid, name=name, seq=seq, signed=signed,
                      fields=fields)
    return r


@dataclass(frozen=True)
class Sent:
    """One frame the link sent: ``raw`` bytes as written, ``t_tx_ns`` the link clock,
    ``fields`` the message's fields as :func:`message_fields` gives them for the message object
    the frame was packed from (``None``: the log decodes ``msg`` itself). A setpoint or
    TIMESYNC packed straight from its values (:meth:`LinkCommands.send_attitude_target`) has
    ``fields`` and a ``msg`` decoded from ``raw`` on first use."""

    msg: Any
    raw: bytes
    t_tx_ns: int
    msgid: int
    name: str
    fields: dict[str, Any] | None = None


def message_fields(msg: Any) -> dict[str, Any]:
    """JSON-friendly decoded fields of a pymavlink message (bytes -> str, NaN kept as float)."""
    out: dict[str, Any] = {}
    for fname in msg.get_fieldnames():
        v = getattr(msg, fname)
        if isinstance(v, bytes | bytearray):
            v = bytes(v).decode("utf-8", errors="replace")
        elif isinstance(v, tuple):
            v = list(v)
        out[fname] = v
    return out


def sent(msg: Any, raw: bytes, t_tx_ns: int, msgid: int, name: str,
         fields: dict[str, Any] | None = None) -> Sent:
    """A :class:`Sent` equal to ``Sent(...)`` of the same values (see :func:`received`)."""
    r = _new(Sent)
    r.__dict__.update(msg=msg, raw=raw, t_tx_ns=t_tx_ns, msgid=msgid, name=name, fields=fields)
    return r
