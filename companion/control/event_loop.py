"""The control process's event loop: uvloop's (libuv, the loop in C) when it is installed, a
pinned dependency; asyncio's own otherwise.

The loop turns several times a step (the frame, ~6 telemetry datagrams, the control task), and
asyncio's pure-Python loop costs CPU at each turn. On a lockstep frame and its answer
(``bench/frame_transport.py --transport shm``, four interleaved pairs at load 6-7) the client's
CPU a frame was 0.45, 0.41, 0.34, 0.33 ms with asyncio's loop against 0.33, 0.33, 0.30,
0.31 ms with uvloop (docs/guides/sizing.md)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Coroutine
from typing import Any

log = logging.getLogger(__name__)


def run_loop(main: Coroutine[Any, Any, int]) -> int:
    """Run ``main`` to its end on a new event loop (uvloop's when installed) and return its
    result."""
    try:
        import uvloop
    except ImportError:
        log.info("uvloop is not installed: asyncio's own event loop")
        return asyncio.run(main)
    return int(uvloop.run(main))
