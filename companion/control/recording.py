"""What the live process records of each frame, and on which clock (``[logging]``).

- :class:`LogClock` gives every logged item its log time: the companion's monotonic receipt
  time (``logging.timestamps = "receipt"``, a real vehicle) or the autopilot's clock carried by
  frames and telemetry (``"source"``: a lockstep simulation then plays at its simulated speed
  in Foxglove and ``companion log info`` shows its real rates). Source log times never go
  backwards, so log-time order stays the order of arrival that replay relies on.
- :class:`FrameRecorder` logs, per step, what perception read losslessly on
  ``/perception/input`` (the region of interest, or the whole frame when the detector
  searched) and, decimated and downscaled, a JPEG preview for people on ``/camera/image``.

docs/reference/logging.md says what replay keeps under each setting.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from companion.config import LoggingConfig
from companion.log.writer import McapLogger

TOPIC_INPUT = "/perception/input"
TOPIC_PREVIEW = "/camera/image"

#: autopilot messages whose ``time_boot_ms`` advances a source log clock (other senders, e.g.
#: the target's FOLLOW_TARGET, keep their own clocks and never move it)
_CLOCK_FIELDS = {
    "ATTITUDE_QUATERNION": "time_boot_ms",
    "ATTITUDE": "time_boot_ms",
    "LOCAL_POSITION_NED": "time_boot_ms",
}


class LogClock:
    """Log times in ns. ``source`` mode: the newest autopilot time seen (frames' ``t_us``,
    autopilot messages' ``time_boot_ms``), never decreasing; 0 before any."""

    def __init__(self, mode: str) -> None:
        if mode not in ("receipt", "source"):
            raise ValueError(f"log clock mode {mode!r} is not 'receipt' or 'source'")
        self.mode = mode
        self._now_ns = 0
        self.started = mode == "receipt"  # a source clock starts with its first stamp

    def _advance(self, t_ns: int) -> int:
        if t_ns > self._now_ns:
            self._now_ns = t_ns
        self.started = True
        return self._now_ns

    def message_ns(self, name: str, fields: Mapping[str, Any], t_rx_ns: int) -> int:
        """Log time of a received MAVLink message (its receipt time ``t_rx_ns`` in receipt
        mode)."""
        if self.mode == "receipt":
            return int(t_rx_ns)
        key = _CLOCK_FIELDS.get(name)
        if key is not None:
            v = fields.get(key)
            if isinstance(v, int | float) and math.isfinite(v) and v >= 0:
                return self._advance(int(v) * 1_000_000)
        return self._now_ns

    def frame_ns(self, t_us: int, t_rx_ns: int) -> int:
        """Log time of a camera frame captured at ``t_us`` and received at ``t_rx_ns``."""
        if self.mode == "receipt":
            return int(t_rx_ns)
        return self._advance(max(int(t_us), 0) * 1000)

    def now_ns(self) -> int:
        """Log time of anything else (monotonic clock in receipt mode)."""
        return time.monotonic_ns() if self.mode == "receipt" else self._now_ns


class FrameRecorder:
    """Logs one step's frame: the lossless perception input and the decimated preview."""

    def __init__(self, cfg: LoggingConfig) -> None:
        self.cfg = cfg
        self._next_preview_us: int | None = None
        self._period_us = (
            round(1e6 / cfg.preview_rate_hz) if cfg.preview_rate_hz > 0 else None
        )

    def record(self, logger: McapLogger, log_time_ns: int, image: np.ndarray, t_us: int,
               region: tuple[int, int, int, int] | None) -> dict[str, Any] | None:
        """Log ``image`` (captured at ``t_us``) of which perception read ``region``
        (``(x0, y0, x1, y1)`` pixels, end exclusive; None: unknown, the whole frame). Returns
        the step record's ``input`` entry (where the crop sits in the frame and its log time),
        or None when the input is not logged (or was dropped by the logger)."""
        cfg = self.cfg
        entry: dict[str, Any] | None = None
        h, w = image.shape[:2]
        if cfg.perception_input != "none":
            x0, y0, x1, y1 = (0, 0, w, h) if region is None or cfg.perception_input == "full" \
                else region
            crop = image[y0:y1, x0:x1]
            if logger.log_image(TOPIC_INPUT, log_time_ns, crop, cfg.image_encoding,
                                stamp_ns=t_us * 1000):
                entry = {"log_time_ns": log_time_ns, "x0": x0, "y0": y0, "x1": x1, "y1": y1,
                         "width": w, "height": h}
        if self._period_us is not None and (
            self._next_preview_us is None or t_us >= self._next_preview_us
        ):
            # scheduled on the camera's clock, so a replayed or lockstep flight gets the same
            # preview frames whatever the speed it ran at
            base = t_us if self._next_preview_us is None else self._next_preview_us
            self._next_preview_us = max(base + self._period_us, t_us + self._period_us // 2)
            logger.log_image(TOPIC_PREVIEW, log_time_ns, image, "jpeg", stamp_ns=t_us * 1000,
                             scale=cfg.preview_scale, jpeg_quality=cfg.preview_jpeg_quality)
        return entry
