"""Connection strings: ``udpin:``, ``udpout:``, ``tcp:``, serial devices -> :class:`Endpoint`."""

from __future__ import annotations

import logging
import re
import termios
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from companion.link.errors import ConnectionStringError

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# Connection strings


@dataclass(frozen=True)
class Endpoint:
    """A parsed connection string. ``kind`` udpin/udpout/tcp: ``host``/``port``; serial:
    ``device``/``baud``."""

    kind: Literal["udpin", "udpout", "tcp", "serial"]
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"serial:{self.device}:{self.baud}"
        return f"{self.kind}:{self.host}:{self.port}"


_FORMS = (
    "udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, /dev/ttyX,BAUD or serial:/dev/ttyX:BAUD "
    "(a '://' after the scheme is accepted too)"
)
DEFAULT_SERIAL_BAUD = 115200


def parse_connection_string(text: str) -> Endpoint:
    """Parse a pymavlink/MAVSDK-style connection string into an :class:`Endpoint`.

    ``udp:`` means ``udpin:`` (as in pymavlink). ``udpin`` accepts an empty host (0.0.0.0) and
    port 0 (an ephemeral port, see :attr:`MavlinkLink.local_address`).
    """
    s = text.strip()

    def bad(why: str) -> ConnectionStringError:
        return ConnectionStringError(f"bad MAVLink connection string {text!r}: {why}; use {_FORMS}")

    if not s:
        raise bad("empty")
    if s.startswith("/"):  # /dev/ttyACM0,921600 or /dev/ttyACM0
        dev, _, baud_s = s.partition(",")
        return _serial(dev, baud_s, bad)
    m = re.fullmatch(r"([A-Za-z]+):(?://)?(.*)", s)
    if not m:
        raise bad("no scheme")
    scheme, rest = m.group(1).lower(), m.group(2)
    if scheme == "serial":
        dev, sep, baud_s = rest.rpartition(":")
        if not sep:
            dev, baud_s = rest, ""
        return _serial(dev, baud_s, bad)
    if scheme == "udp":
        scheme = "udpin"
    if scheme not in ("udpin", "udpout", "tcp"):
        raise bad(f"unknown scheme {scheme!r}")
    host, sep, port_s = rest.rpartition(":")
    if not sep:
        raise bad("missing ':PORT'")
    if not port_s.isdigit():
        raise bad(f"port {port_s!r} is not a number")
    port = int(port_s)
    lo = 0 if scheme == "udpin" else 1
    if not lo <= port <= 65535:
        raise bad(f"port {port} out of range {lo}..65535")
    if not host:
        if scheme != "udpin":
            raise bad("missing host")
        host = "0.0.0.0"
    if not re.fullmatch(r"[A-Za-z0-9.\-_]+", host):
        raise bad(f"host {host!r} is not a hostname or IPv4 address")
    return Endpoint(kind=scheme, host=host, port=port)  # type: ignore[arg-type]


def _serial(dev: str, baud_s: str, bad: Callable[[str], ConnectionStringError]) -> Endpoint:
    if not dev.startswith("/"):
        raise bad(f"serial device {dev!r} must be an absolute path")
    if baud_s == "":
        baud = DEFAULT_SERIAL_BAUD
    elif baud_s.isdigit():
        baud = int(baud_s)
    else:
        raise bad(f"baud rate {baud_s!r} is not a number")
    if not hasattr(termios, f"B{baud}"):
        raise bad(f"baud rate {baud} is not supported by this system")
    return Endpoint(kind="serial", device=dev, baud=baud)

