"""The value checks of the emulator's config fields (each names what it wants) and ``HOST:PORT``
parsing. A field declares its check as ``field(metadata=checked(fn))``."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

Check = Callable[[Any], str | None]

def positive(x: float) -> str | None:
    return None if x > 0 else "must be > 0"


def nonneg(x: float) -> str | None:
    return None if x >= 0 else "must be >= 0"


def open_unit(x: float) -> str | None:
    return None if 0 < x < 1 else "must be in (0, 1)"


def unit(x: float) -> str | None:
    return None if 0 < x <= 1 else "must be in (0, 1]"


def valid_port(x: int) -> str | None:
    return None if 0 <= x <= 65535 else "must be a port number in 0..65535 (0 = any free port)"


def valid_sysid(x: int) -> str | None:
    return None if 1 <= x <= 255 else "must be in 1..255"


def one_of(*choices: Any) -> Check:
    def check(x: Any) -> str | None:
        return None if x in choices else f"must be one of {', '.join(map(repr, choices))}"

    return check


def address(x: str) -> str | None:
    try:
        parse_address(x)
    except ValueError as e:
        return str(e)
    return None


def checked(fn: Check) -> dict[str, Any]:
    return {"check": fn}


def parse_address(text: str) -> tuple[str, int]:
    """``"HOST:PORT"`` -> ``(host, port)``; raises ``ValueError`` on anything else."""
    host, sep, port_s = text.rpartition(":")
    if not sep or not host:
        raise ValueError(f"must be 'HOST:PORT', got {text!r}")
    try:
        port = int(port_s)
    except ValueError:
        raise ValueError(f"port of {text!r} is not an integer") from None
    if not 1 <= port <= 65535:
        raise ValueError(f"port of {text!r} must be in 1..65535")
    return host, port

