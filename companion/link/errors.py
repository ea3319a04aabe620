"""Errors of the MAVLink link."""

from __future__ import annotations

import logging

from companion import CompanionError

log = logging.getLogger(__name__)


class LinkError(CompanionError):
    """The MAVLink link failed or was misused (bad connection string, closed, no peer...)."""


class ConnectionStringError(LinkError):
    """A connection string could not be parsed."""


class NoPeerError(LinkError):
    """``udpin``: nothing was sent because no whitelisted autopilot frame has arrived yet."""

