"""``cv2.VideoCapture`` sources: devices, video files and network streams."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from companion.camera.base import CameraError, CameraFrame, CameraSource, _Newest, _stop

_log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# cv2.VideoCapture (devices, files, network streams)


_R = TypeVar("_R")


class VideoCaptureSource(CameraSource):
    """Frames from ``cv2.VideoCapture(source)``: a device index, a device path, a file or a
    stream URL. Every OpenCV call runs on one dedicated worker thread (VideoCapture is not
    thread-safe and its calls block).

    ``live``: a live source is grabbed continuously and the consumer gets the newest frame
    (the driver's own queue would otherwise hand out stale frames); a file is read at the
    consumer's pace, nothing dropped. ``None`` = live unless ``source`` is a file path.
    ``t_us``: the stream position (``CAP_PROP_POS_MSEC``) for files; for live sources the
    receipt time since opening (cameras' positions are not reliable across backends).
    ``gray``: convert to mono8 on the worker thread.
    """

    def __init__(
        self,
        source: str | int,
        *,
        live: bool | None = None,
        queue_size: int = 1,
        api_preference: int = cv2.CAP_ANY,
        gray: bool = False,
        reopen_after_failures: int = 10,
        reopen_backoff_s: float = 1.0,
    ) -> None:
        super().__init__()
        self.source = source
        is_file = isinstance(source, str) and Path(source).is_file()
        self.live = (not is_file) if live is None else live
        self._queue_size = queue_size
        self._api = api_preference
        self._gray = gray
        self._reopen_after = reopen_after_failures
        self._reopen_backoff_s = reopen_backoff_s
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="videocapture")
        self._cap: cv2.VideoCapture | None = None
        self._buffer: _Newest[CameraFrame] | None = None
        self._task: asyncio.Task[None] | None = None
        self._seq = 0
        self._t0_ns = 0
        self._eof = False

    def __repr__(self) -> str:
        return f"VideoCaptureSource({self.source!r}, live={self.live})"

    async def _call(self, fn: Callable[..., _R], *args: Any) -> _R:
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(self.source, self._api)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"cv2.VideoCapture cannot open {self.source!r}")
        return cap

    async def _start(self) -> None:
        try:
            self._cap = await self._call(self._open)
        except BaseException:
            self._pool.shutdown(wait=False)
            raise
        self._t0_ns = time.monotonic_ns()
        if self.live:
            self._buffer = _Newest(self._queue_size)
            self._task = asyncio.create_task(self._grab_loop(), name=f"capture {self.source!r}")
            self._watch(self._task, self._buffer)

    async def _close(self) -> None:
        if self._task is not None:
            await _stop(self._task)
        if self._buffer is not None:
            self._buffer.close()
        if self._cap is not None:
            cap = self._cap
            self._cap = None
            await self._call(cap.release)
        self._pool.shutdown(wait=False)

    def _read(self) -> tuple[npt.NDArray[np.uint8], float, int] | None:
        """On the worker thread: one frame, its stream position (ms) and receipt time."""
        cap = self._cap
        if cap is None:
            return None
        ok, img = cap.read()
        t_rx_ns = time.monotonic_ns()
        if not ok or img is None:
            return None
        pos_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
        if img.dtype != np.uint8:
            img = cv2.convertScaleAbs(img)
        if self._gray and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        elif img.ndim == 3 and img.shape[2] == 1:
            img = img[:, :, 0]
        out = np.asarray(img, dtype=np.uint8)
        out.setflags(write=False)
        return out, pos_ms, t_rx_ns

    def _frame(self, got: tuple[npt.NDArray[np.uint8], float, int]) -> CameraFrame:
        img, pos_ms, t_rx_ns = got
        t_us = (t_rx_ns - self._t0_ns) // 1000 if self.live else round(pos_ms * 1000.0)
        frame = CameraFrame(
            self._seq, t_us, t_rx_ns, img, "mono8" if img.ndim == 2 else "bgr8", "capture"
        )
        self._seq += 1
        self._count("frames_received")
        return frame

    async def _next_frame(self) -> CameraFrame | None:
        if self.live:
            assert self._buffer is not None
            frame = await self._buffer.get()
            if frame is None:
                self._raise_if_failed()
            return frame
        if self._eof:
            return None
        got = await self._call(self._read)
        if got is None:
            self._eof = True
            return None
        return self._frame(got)

    async def _grab_loop(self) -> None:
        assert self._buffer is not None
        failures = 0
        while True:
            got = await self._call(self._read)
            if got is None:
                failures += 1
                self._count("decode_errors")
                if failures >= self._reopen_after:
                    _log.warning("%r: %d failed reads, reopening", self, failures)
                    await self._reopen()
                    failures = 0
                else:
                    await asyncio.sleep(0.01)
                continue
            failures = 0
            if self._buffer.put(self._frame(got)):
                self._count("frames_dropped")

    async def _reopen(self) -> None:
        old, self._cap = self._cap, None
        if old is not None:
            await self._call(old.release)
        self._count("disconnects")
        while True:
            await asyncio.sleep(self._reopen_backoff_s)
            try:
                self._cap = await self._call(self._open)
            except CameraError as exc:
                self._count("connect_failures")
                _log.warning("%s", exc)
                continue
            self._count("connects")
            return


