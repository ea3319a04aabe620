"""Recorded frames from a companion log (the replay source)."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion import CompanionError
from companion.camera.base import CameraError, CameraFrame, CameraSource

_log = logging.getLogger(__name__)


class McapSource(CameraSource):
    """Frames recorded in a companion log (``/camera/image``: foxglove.CompressedImage or
    RawImage), in log order, with their original capture time (``t_us`` from the image
    stamp) and receipt time (``t_rx_ns`` = the log time). ``pace``: deliver at the recorded
    rate instead of as fast as the consumer reads. A log cut short ends where its recovered
    part ends."""

    def __init__(self, path: Path, topic: str = "/camera/image", pace: bool = False) -> None:
        super().__init__()
        self.path = Path(path)
        self.topic = topic
        self._pace = pace
        self._reader: Any = None
        self._it: Any = None
        self._seq = 0
        self._t0: tuple[int, float] | None = None

    def __repr__(self) -> str:
        return f"McapSource({str(self.path)!r})"

    async def _start(self) -> None:
        from companion.log.reader import LogReader  # the reader is only needed here

        try:
            self._reader = LogReader(self.path)
        except CompanionError as exc:
            raise CameraError(f"{self!r}: {exc}") from exc
        self._it = self._reader.messages(topics=[self.topic])

    async def _close(self) -> None:
        if self._reader is not None:
            self._reader.close()

    async def _next_frame(self) -> CameraFrame | None:
        while True:
            m = await asyncio.get_running_loop().run_in_executor(None, next, self._it, None)
            if m is None:
                return None
            if m.image is None:
                self._count("decode_errors")
                continue
            break
        self._count("frames_received")
        stamp = (m.data or {}).get("timestamp") or {}
        t_ns = int(stamp.get("sec", 0)) * 1_000_000_000 + int(stamp.get("nsec", 0))
        if self._pace:
            now = time.monotonic()
            if self._t0 is None:
                self._t0 = (m.log_time_ns, now)
            due = self._t0[1] + (m.log_time_ns - self._t0[0]) * 1e-9
            if due > now:
                await asyncio.sleep(due - now)
        img = np.ascontiguousarray(m.image)
        img.setflags(write=False)
        self._seq += 1
        enc = "mono8" if img.ndim == 2 else "bgr8"
        return CameraFrame(self._seq, t_ns // 1000, m.log_time_ns, img, enc, "mcap")

