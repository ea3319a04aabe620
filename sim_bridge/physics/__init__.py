"""Pure models of the emulated world: numpy only (no sockets, clocks, asyncio or pymavlink)."""

from __future__ import annotations
