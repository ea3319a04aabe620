"""How the link sends: a pymavlink message (:meth:`LinkSender.send`) or a payload packed by the
caller (:meth:`LinkSender.send_payload`: the setpoint and TIMESYNC of every step, framed by
:func:`companion.link.wire.frame` without a pymavlink object), on the link's transport.

A mixin of :class:`~companion.link.link.MavlinkLink`, which owns the state declared here.
"""

from __future__ import annotations

import errno
import os
import socket
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from companion.link import wire
from companion.link.endpoints import Endpoint
from companion.link.errors import LinkError, NoPeerError
from companion.link.messages import Sent, sent
from companion.link.signing import SignatureVerifier, signing_timestamp_now


class LinkSender:
    """The send path of :class:`~companion.link.link.MavlinkLink` (see the module docstring)."""

    endpoint: Endpoint
    counters: Counter[str]
    last_tx_ns: int | None
    _enc: Any
    _verifier: SignatureVerifier | None
    _on_tx: Callable[[Sent], None] | None
    _clock_ns: Callable[[], int]
    _closed: bool
    _transport: Any
    _serial_fd: int | None
    _sock: socket.socket | None
    _peer: tuple[str, int] | None

    def _count(self, reason: str, n: int = 1) -> None:
        self.counters[reason] += n

    def send(self, msg: Any) -> bytes:
        """Encode ``msg`` (MAVLink 2, our source ids, signed if configured), send it to the peer
        and return the bytes sent. Raises :class:`NoPeerError` (udpin before the autopilot was
        heard) or :class:`LinkError`."""
        self._may_send()
        if self._verifier is not None:
            self._enc.signing.timestamp = max(self._enc.signing.timestamp, signing_timestamp_now())
        try:
            raw = wire.pack(msg, self._enc)
        except Exception as e:  # struct.error / MAVError on out-of-range fields
            raise LinkError(f"cannot encode {msg.get_type()}: {e}") from e
        self._enc.seq = (self._enc.seq + 1) % 256
        name = msg.get_type()
        self._write(raw, name)
        if self._on_tx is not None:
            self._on_tx(sent(msg, raw, self._clock_ns(), msg.get_msgId(), name))
        return raw

    def send_payload(self, msgid: int, name: str, crc_extra: bytes, payload: bytes,
                     fields: dict[str, Any]) -> bytes | None:
        """Send a message given as its packed wire-order ``payload`` (the setpoint and TIMESYNC
        of every step: no pymavlink object, :func:`wire.frame`, the same bytes as
        :meth:`send` of the message with these ``fields``); ``fields`` go to ``on_tx`` as the
        :class:`Sent`'s. Returns None, sending nothing, on a signed link (the caller then uses
        :meth:`send`). Raises as :meth:`send`."""
        enc = self._enc
        if enc.signing.sign_outgoing:
            return None
        self._may_send()
        raw = wire.frame(payload, enc.seq, enc.srcSystem, enc.srcComponent, msgid, crc_extra)
        enc.seq = (enc.seq + 1) % 256
        self._write(raw, name)
        if self._on_tx is not None:
            self._on_tx(sent(wire.LazyMessage(raw), raw, self._clock_ns(), msgid, name, fields))
        return raw

    def _may_send(self) -> None:
        if self._closed or (self._transport is None and self._serial_fd is None
                            and self._sock is None):
            raise LinkError("MAVLink link is not open")
        if self._peer is None and self.endpoint.kind in ("udpin", "udpout"):
            self._count("tx_no_peer")
            raise NoPeerError(f"no autopilot heard yet on {self.endpoint}: nothing sent")

    def _write(self, raw: bytes, name: str) -> None:
        """``raw`` out on the transport; ``last_tx_ns`` is when it left."""
        kind = self.endpoint.kind
        try:
            if kind in ("udpin", "udpout"):
                assert self._sock is not None and self._peer is not None
                self._sock.sendto(raw, self._peer)
            elif kind == "tcp":
                self._transport.write(raw)
            else:
                assert self._serial_fd is not None
                n = os.write(self._serial_fd, raw)
                if n != len(raw):
                    raise OSError(errno.EAGAIN, "short write")
        except OSError as e:
            self._count("tx_errors")
            raise LinkError(f"send {name} on {self.endpoint}: {e}") from e
        self.last_tx_ns = time.monotonic_ns()  # the frame left (its log record is made after)
        self.counters["tx_frames"] += 1
