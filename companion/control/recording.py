"""What the live process records of each frame, and on which clock (``[logging]``).

- :class:`LogClock` gives every logged item its log time: the companion's monotonic receipt
  time (``logging.timestamps = "receipt"``, a real vehicle) or the autopilot's clock carried by
  frames and telemetry (``"source"``: a lockstep simulation then plays at its simulated speed
  in Foxglove and ``companion log info`` shows its real rates). Source log times never go
  backwards, so log-time order stays the order of arrival that replay relies on.
- :class:`FrameRecorder` logs, per step, what perception read losslessly on
  ``/perception/input`` (the region of interest, or the whole frame when the detector
  searched) and, decimated and downscaled, a JPEG preview for people on ``/camera/image``.
- :class:`RuntimeLog` is the live process's other writes (``/config``, MAVLink in and out,
  rejections, text events, poses, link statistics), each at its log time; with source log
  times, the records made before the first autopilot stamp wait for it.

docs/reference/logging.md says what replay keeps under each setting.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from companion.config import Config, LoggingConfig
from companion.log import schemas as sch
from companion.log.writer import McapLogger

TOPIC_INPUT = "/perception/input"
TOPIC_PREVIEW = "/camera/image"
TOPIC_FRAME = TOPIC_PREVIEW  # an old log's full frames (replay_inputs reads them)
TOPIC_STEP = "/control/step"
TOPIC_SAFETY = "/control/safety"
TOPIC_OFFBOARD = "/control/offboard"
TOPIC_TRUTH = "/truth"
TOPIC_POSE = "/vehicle/pose"
TOPIC_TARGET_POSE = "/target/pose"
TOPIC_STATS = "/mavlink/stats"

# records held until the source log clock has its first stamp (a few seconds of traffic)
EARLY_RECORDS_MAX = 4096

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


class RuntimeLog:
    """The live process's writes besides the frames, each at its log time.

    With source log times, a record made before the first autopilot stamp has no time yet (the
    time base is unknown, and a 0 would put the record hours before the flight in Foxglove):
    it waits and is written at that first stamp, right after ``/config``. At most
    ``EARLY_RECORDS_MAX`` wait; beyond, the oldest are dropped and counted in
    ``early_dropped``."""

    def __init__(self, logger: McapLogger, clock: LogClock, cfg: Config,
                 config_text: str) -> None:
        self.logger, self.clock, self.cfg, self.config_text = logger, clock, cfg, config_text
        self._early: deque[Callable[[int], object]] = deque(maxlen=EARLY_RECORDS_MAX)
        self.early_dropped = 0
        self._config_logged = False

    def config(self) -> None:
        """``/config``, once: at start, or (source log times) at the first stamp seen,
        followed by the records that waited for that stamp."""
        if self._config_logged or not self.clock.started:
            return
        self._config_logged = True
        self.logger.log_config(self.clock.now_ns(), self.config_text, dict(self.cfg.raw),
                               self.cfg.source)
        self.flush_early(self.clock.now_ns())

    def at(self, t_ns: int, write: Callable[[int], object]) -> None:
        """``write(t_ns)`` now, or at the first stamp (see the class docstring)."""
        if self.clock.started and self._config_logged:
            write(t_ns)
            return
        if len(self._early) == self._early.maxlen:
            self.early_dropped += 1
        self._early.append(write)

    def flush_early(self, t_ns: int) -> None:
        while self._early:
            self._early.popleft()(t_ns)

    def text(self, topic: str, text: str, level: str, name: str) -> None:
        """A text event at the current log time."""
        logger = self.logger
        self.at(self.clock.now_ns(), lambda t: logger.log_text(topic, t, text, level=level,
                                                               name=name))

    def received(self, rx: Any, fields: Mapping[str, Any]) -> None:
        """An accepted MAVLink message (the order of the log is the order the store saw)."""
        t_log = self.clock.message_ns(rx.name, fields, rx.t_rx_ns)
        if self._config_logged and self.clock.started:  # the flight's case: written now
            self.logger.log_mavlink("in", rx, t_log)
            return
        self.config()
        logger = self.logger
        self.at(t_log, lambda t: logger.log_mavlink("in", rx, t))

    def sent(self, sent: Any) -> None:
        """A sent MAVLink frame."""
        t_log = int(sent.t_tx_ns) if self.clock.mode == "receipt" else self.clock.now_ns()
        logger = self.logger
        if self._config_logged and self.clock.started:  # the flight's case: written now
            logger.log_mavlink("out", sent, t_log)
            return
        self.at(t_log, lambda t: logger.log_mavlink("out", sent, t))

    def rejected(self, reason: str, raw: bytes, t_rx_ns: int) -> None:
        """A rejected frame, on the log's time base (receipt time, or the source clock)."""
        t_log = int(t_rx_ns) if self.clock.mode == "receipt" else self.clock.now_ns()
        logger = self.logger
        self.at(t_log, lambda t: logger.log_rejected(reason, raw, t_rx_ns, log_time_ns=t))

    def poses(self, t_ns: int, store: Any) -> None:
        """The vehicle and the target as the companion knows them (Foxglove 3-D panel, NED)."""
        kin, tgt = store.kinematics, store.target
        if kin is not None and store.attitude:
            self.logger.log_pose(TOPIC_POSE, t_ns, "ned", kin.pos_ned_m, store.attitude[-1].q_wxyz)
        if tgt is not None:
            half = 0.5 * tgt.yaw_rad
            self.logger.log_pose(TOPIC_TARGET_POSE, t_ns, "ned", tgt.pos_ned_m,
                                 (math.cos(half), 0.0, 0.0, math.sin(half)))

    def link_stats(self, link: Any, stale_dropped: int, stale_inputs: int) -> None:
        """The link's counters on /mavlink/stats (a flood or a spoofer shows up here)."""
        cfg = self.cfg
        pinned = {str(s): f"{a[0]}:{a[1]}" for s in (cfg.mavlink.target_system,
                                                    cfg.target.mavlink_sysid)
                  if (a := link.guard.pinned(s)) is not None}
        counters = dict(link.counters)
        counters.update({f"guard_{k}": v for k, v in link.guard.counters.items()})
        t_ns = time.monotonic_ns() if self.clock.mode == "receipt" else self.clock.now_ns()
        logger = self.logger
        payload = {
            "counters": counters, "pinned": pinned,
            "stale_dropped": stale_dropped, "stale_inputs": stale_inputs,
            "log_dropped": logger.stats.dropped + self.early_dropped,
        }
        self.at(t_ns, lambda t: logger.log(TOPIC_STATS, t, payload, schema=sch.MAVLINK_STATS))
