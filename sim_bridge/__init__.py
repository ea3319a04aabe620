"""sim_bridge: a MAVLink vehicle emulator that behaves like PX4 (plus the AGV, camera and
ground truth it serves). It never imports the companion: the two meet only on the wire
(docs/reference/wire.md).
"""

from __future__ import annotations

__all__ = ["ConfigError", "LinkError", "SimBridgeError"]


class SimBridgeError(Exception):
    """Root of every error raised by sim_bridge."""


class ConfigError(SimBridgeError):
    """A configuration value is missing or invalid; the message names the key."""


class LinkError(SimBridgeError):
    """A socket could not be opened or used (wraps OSError where it enters)."""
