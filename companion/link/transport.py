"""The link's transports: UDP sockets read in batches, a TCP stream, a raw serial device.

Only the operating system's side lives here (sockets, termios); what arrives is handed to the
link's receive path (:mod:`companion.link.receive`) by :class:`~companion.link.link.MavlinkLink`.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import termios
from collections.abc import Callable

from companion.link.endpoints import Endpoint
from companion.link.errors import LinkError


class StreamProtocol(asyncio.Protocol):
    """A TCP stream's bytes and its end, passed to the link's callbacks."""

    def __init__(self, on_data: Callable[[bytes], None],
                 on_lost: Callable[[Exception | None], None]) -> None:
        self._on_data, self._on_lost = on_data, on_lost

    def data_received(self, data: bytes) -> None:
        self._on_data(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self._on_lost(exc)


def udp_socket(recv_buffer_bytes: int) -> socket.socket:
    """A non-blocking UDP socket sharing its port with our other sockets (SO_REUSEADDR: the
    per-source sockets of a pinned source share the bound port), with a large receive
    buffer when the system allows it."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, recv_buffer_bytes)
        sock.setblocking(False)
    except OSError:
        sock.close()
        raise
    return sock


def bound_udp_socket(local: tuple[str, int], recv_buffer_bytes: int) -> socket.socket:
    """:func:`udp_socket` bound to ``local``. Our sockets share the port (SO_REUSEADDR) with
    each other only: a port another program (or another link) holds is refused, as a plain
    bind would."""
    if local[1] != 0:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.bind(local)
    sock = udp_socket(recv_buffer_bytes)
    try:
        sock.bind(local)
    except OSError:
        sock.close()
        raise
    return sock


def connected_udp_socket(bound: socket.socket, addr: tuple[str, int],
                         recv_buffer_bytes: int) -> socket.socket:
    """A socket bound to ``bound``'s port and connected to ``addr``: the kernel then delivers
    that source's datagrams there (a connected socket matches better than the bound one), in
    a buffer a flood from other addresses cannot fill. Raises ``OSError``."""
    sock = udp_socket(recv_buffer_bytes)
    try:
        sock.bind(bound.getsockname())
        sock.connect(addr)
    except OSError:
        sock.close()
        raise
    return sock


def open_serial(ep: Endpoint) -> int:
    """The serial device of ``ep`` opened non-blocking in raw mode (cfmakeraw), 8N1, no flow
    control, at ``ep.baud``; returns its file descriptor."""
    fd = os.open(ep.device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        attrs = termios.tcgetattr(fd)
        speed = getattr(termios, f"B{ep.baud}")
        attrs[0] &= ~(
            termios.IGNBRK
            | termios.BRKINT
            | termios.PARMRK
            | termios.ISTRIP
            | termios.INLCR
            | termios.IGNCR
            | termios.ICRNL
            | termios.IXON
            | termios.IXOFF
        )
        attrs[1] &= ~termios.OPOST
        attrs[2] &= ~(termios.CSIZE | termios.PARENB | termios.CSTOPB | termios.CRTSCTS)
        attrs[2] |= termios.CS8 | termios.CREAD | termios.CLOCAL
        attrs[3] &= ~(
            termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN
        )
        attrs[4] = attrs[5] = speed
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except (termios.error, OSError) as e:
        os.close(fd)
        raise LinkError(f"cannot configure serial device {ep.device}: {e}") from e
    return fd
