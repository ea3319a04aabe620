"""MCAP flight logs: the writer (every MAVLink message, frame and control step), the reader
(salvages a log cut short, CRC-checks chunks) and the Foxglove schemas both use."""

from __future__ import annotations

from companion import CompanionError


class McapLogError(CompanionError):
    """The logger was misused (unknown schema, topic re-registered) or its writer failed."""
