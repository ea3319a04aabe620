"""The on-vehicle process: camera + telemetry -> pipeline -> SET_ATTITUDE_TARGET, all logged.

One asyncio process. Stages are wired in one place (:meth:`CompanionApp.run`):

- the MAVLink link's receive callback logs every accepted message and feeds the telemetry
  store and the offboard state machine (so the log's order is the order the store saw);
- the control task runs one pipeline step per camera frame and streams the setpoint;
- a heartbeat task announces the companion (MAV_TYPE_ONBOARD_CONTROLLER) at 1 Hz;
- an optional ground-truth recorder (emulator only) logs ``/truth`` for scoring: it feeds
  nothing else.

Time: :class:`TimeBase` stamps frames and messages either on receipt (real vehicle) or with
the autopilot's own clock (the emulator, where frames carry the autopilot's boot time).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import resource
import signal
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion import CompanionError
from companion.camera import CameraFrame, open_camera
from companion.config import Config
from companion.control.offboard import (
    PX4_MAIN_MODE_OFFBOARD,
    OffboardManager,
    OffboardPhase,
    VehicleStatus,
)
from companion.control.pipeline import ControlPipeline
from companion.control.recording import FrameRecorder, LogClock
from companion.control.seams import FrameSource
from companion.control.telemetry import TelemetryStore
from companion.control.timesync import ActuationDelayMeter, TimeSync
from companion.link import AllowRule, MavlinkLink, NoPeerError, Received, default_allow_rules
from companion.log import schemas as sch
from companion.log.live import start_live
from companion.log.writer import McapLogger
from companion.perception.pipeline import Perception

log = logging.getLogger(__name__)

FIRST_FRAME_TIMEOUT_S = 60.0
TOPIC_FRAME = "/camera/image"
TOPIC_STEP = "/control/step"
TOPIC_SAFETY = "/control/safety"
TOPIC_OFFBOARD = "/control/offboard"
TOPIC_TRUTH = "/truth"
TOPIC_POSE = "/vehicle/pose"
TOPIC_TARGET_POSE = "/target/pose"
TOPIC_STATS = "/mavlink/stats"

# Messages whose own timestamp field (ms) is the source time in "autopilot" mode.
_STAMP_FIELDS = {
    "ATTITUDE_QUATERNION": "time_boot_ms",
    "ATTITUDE": "time_boot_ms",
    "LOCAL_POSITION_NED": "time_boot_ms",
    "ATTITUDE_TARGET": "time_boot_ms",
    "FOLLOW_TARGET": "timestamp",
    "HIGHRES_IMU": "time_usec",
}
# the stamp's unit (s per count): ms, except HIGHRES_IMU's time_usec (us since boot)
_STAMP_SCALE = {"HIGHRES_IMU": 1e-6}
STAMPED_MESSAGES = frozenset(_STAMP_FIELDS)  # the messages TimeBase reads a time from

# records held until the source log clock has its first stamp (a few seconds of traffic)
EARLY_RECORDS_MAX = 4096


#: MAV_STATE names (HEARTBEAT system_status)
MAV_STATE_NAMES = {0: "UNINIT", 1: "BOOT", 2: "CALIBRATING", 3: "STANDBY", 4: "ACTIVE",
                   5: "CRITICAL", 6: "EMERGENCY", 7: "POWEROFF", 8: "FLIGHT_TERMINATION"}


class _StopRequested(Exception):
    """A stop was requested (signal, duration) while waiting for a camera frame."""


class DelayFloor:
    """The smallest transport delay ``t_rx - t_src`` of one stream (seconds, in whatever
    offset the two clocks have), rising by at most ``drift`` s/s (clock drift), so that
    ``excess = delay - floor`` is how late one item is compared with the stream at its best.
    After ``relearn_s`` of receipt time in which every item was late by more than
    ``stale_s`` (the source clock jumped: a reboot), the floor is learnt again."""

    def __init__(self, stale_s: float, drift: float = 1e-3, relearn_s: float = 3.0) -> None:
        self.stale_s, self.drift, self.relearn_s = stale_s, drift, relearn_s
        self.floor: float | None = None
        self._t_last: float | None = None
        self._late_since: float | None = None

    def excess(self, t_rx_s: float, t_src_s: float) -> float:
        d = t_rx_s - t_src_s
        if self.floor is None or self._t_last is None:
            self.floor, self._t_last = d, t_rx_s
            return 0.0
        self.floor += self.drift * max(t_rx_s - self._t_last, 0.0)
        self._t_last = t_rx_s
        if d <= self.floor:
            self.floor, self._late_since = d, None
            return 0.0
        ex = d - self.floor
        if ex <= self.stale_s:
            self._late_since = None
        elif self._late_since is None:
            self._late_since = t_rx_s
        elif t_rx_s - self._late_since >= self.relearn_s:
            log.warning("time base: stream delays moved by %.3f s for %.1f s: relearnt", ex,
                        self.relearn_s)
            self.floor, self._late_since = d, None
            return 0.0
        return ex


class TimeBase:
    """Assigns every input a time in seconds on one base (see ``control.time_source``).

    ``receipt``: local monotonic time. A stamped input (frame ``t_us``, a message's
    ``time_boot_ms``) gets its source stamp plus its stream's smallest delay
    (:class:`DelayFloor`), i.e. when it would have arrived at best: a backlog received late
    (after a process stall, a link hiccup) keeps its true age instead of looking fresh.
    ``last_excess_s`` is how late the last input was; unstamped messages (HEARTBEAT,
    COMMAND_ACK) get their receipt time. ``autopilot``: the source's own stamps; messages
    without a stamp get the newest source time seen so far.
    """

    def __init__(self, source: str, stale_s: float = 0.25) -> None:
        self.source = source
        self.latest_s = -math.inf
        self.stale_s = stale_s
        self.last_excess_s = 0.0
        self.stale_count = 0  # stamped inputs later than stale_s (receipt mode)
        self._floors: dict[str, DelayFloor] = {}

    def _mapped(self, stream: str, t_rx_s: float, t_src_s: float) -> float:
        fl = self._floors.get(stream)
        if fl is None:
            fl = self._floors[stream] = DelayFloor(self.stale_s)
        ex = fl.excess(t_rx_s, t_src_s)
        self.last_excess_s = ex
        if ex > self.stale_s:
            self.stale_count += 1
        return t_rx_s - ex

    def message_s(self, name: str, fields: Mapping[str, Any], t_rx_ns: int) -> float:
        if self.source == "receipt":
            key = _STAMP_FIELDS.get(name)
            if key is None or key not in fields:
                self.last_excess_s = 0.0
                return t_rx_ns * 1e-9
            return self._mapped(name, t_rx_ns * 1e-9,
                                float(fields[key]) * _STAMP_SCALE.get(name, 1e-3))
        key = _STAMP_FIELDS.get(name)
        if key is not None and key in fields:
            t = float(fields[key]) * _STAMP_SCALE.get(name, 1e-3)
            self.latest_s = max(self.latest_s, t)
            return t
        return self.latest_s if math.isfinite(self.latest_s) else 0.0

    def frame_s(self, t_us: int, t_rx_ns: int) -> float:
        if self.source == "receipt":
            return self._mapped("camera", t_rx_ns * 1e-9, t_us * 1e-6)
        t = t_us * 1e-6
        self.latest_s = max(self.latest_s, t)
        return t


FAULT_KINDS = ("solver", "solver-hang")


@dataclass(frozen=True)
class FaultWindow:
    """Fault injection for tests and bench (like PX4's failure injection) during ``[t0_s,
    t1_s)`` after the first frame: ``kind`` is ``solver`` (every solve reported failed) or
    ``solver-hang`` (each step's solve never returns: the solver process's test hook, cut by
    ``rmpc.max_solve_time_s``; needs ``rmpc.solve_isolation = "process"``)."""

    kind: str
    t0_s: float
    t1_s: float

    @classmethod
    def parse(cls, text: str) -> FaultWindow:
        try:
            kind, t0, t1 = text.split(":")
            w = cls(kind, float(t0), float(t1))
        except ValueError:
            raise CompanionError(f"--inject-fault {text!r}: expected KIND:T0:T1") from None
        if w.kind not in FAULT_KINDS or not w.t1_s > w.t0_s:
            raise CompanionError(f"--inject-fault {text!r}: kind one of {FAULT_KINDS} and "
                                 "T1 > T0 only")
        return w


def _finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _cpu_s(controller: Any = None) -> float:
    """This process's CPU time (all threads), plus that of ``controller``'s solver process
    (``rmpc.solve_isolation = "process"``), seconds."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    backend = getattr(controller, "backend", None)
    return r.ru_utime + r.ru_stime + float(getattr(backend, "child_cpu_s", 0.0))


def new_pipeline(cfg: Config, timer: Any = None) -> ControlPipeline:
    """The pipeline a flight (live or replayed) uses for this config."""
    perception = Perception(cfg.camera, cfg.target, perception=cfg.perception)
    return ControlPipeline(cfg, perception, timer=timer)


def new_store(cfg: Config) -> TelemetryStore:
    t = cfg.target
    return TelemetryStore(t.mavlink_sysid, t.origin_lat_deg, t.origin_lon_deg, t.origin_alt_m,
                          autopilot_sysid=cfg.mavlink.target_system)


def allow_rules(cfg: Config) -> tuple[AllowRule, ...]:
    """What the link delivers: the autopilot's telemetry the companion uses (plus HIGHRES_IMU
    when the estimator fuses the accelerometer) and FOLLOW_TARGET from the AGV."""
    extra = ("HIGHRES_IMU",) if cfg.control.estimator.accelerometer else ()
    return default_allow_rules(cfg.mavlink.target_system, cfg.mavlink.target_component,
                               cfg.target.mavlink_sysid, cfg.target.mavlink_compid, extra)


def is_autopilot(cfg: Config, sysid: int, compid: int) -> bool:
    return sysid == cfg.mavlink.target_system and (
        cfg.mavlink.target_component in (0, compid)
    )


class CompanionApp:
    def __init__(
        self,
        cfg: Config,
        *,
        mavlink_url: str | None = None,
        camera_url: str,
        log_path: Path,
        truth_port: int | None = None,
        duration_s: float | None = None,
        idle_timeout_s: float = 5.0,
        startup_timeout_s: float = FIRST_FRAME_TIMEOUT_S,
        faults: tuple[FaultWindow, ...] = (),
        config_text: str = "",
        ready_file: Path | None = None,
        progress_file: Path | None = None,
    ) -> None:
        self.cfg = cfg
        self.mavlink_url = mavlink_url or cfg.mavlink.url
        self.camera_url = camera_url
        self.log_path = log_path
        self.truth_port = truth_port
        self.duration_s = duration_s
        self.idle_timeout_s = idle_timeout_s
        # before the first frame nothing is under our control: wait longer for the camera
        # (an emulator starting on a loaded machine takes seconds)
        self.startup_timeout_s = startup_timeout_s
        self.faults = faults
        self.config_text = config_text
        self.ready_file = ready_file
        self.stale_frames = 0  # frames refused as stale (no command built from them)
        self.progress_file = progress_file
        self._cpu0: tuple[float, int] | None = None  # (CPU s, steps) at the first frame
        self.cpu_ms_per_step: float | None = None
        self.timebase = TimeBase(cfg.control.time_source, cfg.safety.max_frame_age_s)
        self.clock = LogClock(cfg.logging.timestamps)
        self.recorder = FrameRecorder(cfg.logging)
        self.timesync = TimeSync()
        lat = cfg.control.latency
        # the actuation delay measured from TIMESYNC probes (None: the configured constant)
        self.delay_meter = ActuationDelayMeter(
            cfg.control.time_source, lat.auto_delay_window, lat.auto_delay_min_samples,
            lat.auto_delay_max_s, 1.0 / lat.auto_delay_probe_hz) if lat.auto_delay else None
        self.store = new_store(cfg)
        self.pipeline = new_pipeline(cfg, timer=time.perf_counter)
        if any(f.kind == "solver-hang" for f in faults) and not hasattr(
                getattr(self.pipeline.rmpc, "backend", None), "hang_next_solve"):
            raise CompanionError("--inject-fault solver-hang: needs controller.kind an RMPC "
                                 "with rmpc.solve_isolation = \"process\"")
        self.offboard = OffboardManager(cfg.offboard, reengage=cfg.offboard.reengage)
        #: the autopilot's HEARTBEAT system_status (MAV_STATE) last seen; None before the first
        self.autopilot_state: int | None = None
        self.rx_count = 0
        self.steps = 0
        self.sent = 0
        self._stop = asyncio.Event()
        self._logger: McapLogger | None = None
        self._link: MavlinkLink | None = None
        self._first_frame_s: float | None = None
        self._elapsed_s = 0.0  # since the first frame, on the frames' clock
        self._config_logged = False
        self._streaming = True
        # source log times: records made before the first autopilot stamp have no time yet;
        # they wait here and are written at that first stamp (see _log_at)
        self._early: deque[Callable[[int], object]] = deque(maxlen=EARLY_RECORDS_MAX)
        self.early_dropped = 0

    # -- wiring -----------------------------------------------------------------------------

    async def run(self) -> int:
        cfg = self.cfg
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        # the live view (None when off) fails here on a taken port, before the flight
        # (the layout's /camera/image is the JPEG preview whatever logging.image_encoding)
        live = start_live(cfg.live, "jpeg")
        logger = McapLogger.from_config(cfg.logging, self.log_path)
        logger.observer = live  # the live view sees what the log writes
        self._logger = logger
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, self._stop.set)
        try:
            with logger:
                self._log_config()
                link = MavlinkLink.from_config(
                    dataclasses.replace(cfg.mavlink, url=self.mavlink_url), cfg.target,
                    allow=allow_rules(cfg),
                    on_rx=self._on_rx,
                    on_tx=lambda s: self._log_at(
                        self._tx_log_ns(s), lambda t: logger.log_mavlink("out", s, t)),
                    on_reject=self._on_reject,
                )
                self._link = link
                async with link, open_camera(self.camera_url) as camera:
                    log.info("companion: mavlink %s, camera %s, log %s", self.mavlink_url,
                             self.camera_url, self.log_path)
                    async with asyncio.TaskGroup() as tg:
                        control = tg.create_task(self._control(camera))
                        aux = [tg.create_task(self._drain(link)),
                               tg.create_task(self._heartbeat(link)),
                               tg.create_task(self._stats(link))]
                        if cfg.control.time_source == "timesync":
                            aux.append(tg.create_task(self._timesync(link)))
                        if self.truth_port is not None:
                            ready = asyncio.Event()
                            aux.append(tg.create_task(self._truth(self.truth_port, ready)))
                            await ready.wait()
                        if self.ready_file is not None:
                            self.ready_file.write_text("ready\n")
                        await control
                        for t in aux:
                            t.cancel()
                    self.log_stats(link)
                    log.info("companion: link counters %s", dict(link.counters))
                    self._flush_early(self.clock.now_ns())  # never any stamp: at time 0
        finally:
            for sig in (signal.SIGINT, signal.SIGTERM):
                with contextlib.suppress(NotImplementedError, RuntimeError):
                    loop.remove_signal_handler(sig)
            if live is not None:
                live.close()
            close = getattr(self.pipeline.rmpc, "close", None)
            if callable(close):  # the solver's child process (rmpc.solve_isolation)
                close()
        if self._cpu0 is not None and self.steps > self._cpu0[1]:
            self.cpu_ms_per_step = (1e3 * (_cpu_s(self.pipeline.rmpc) - self._cpu0[0])
                                    / (self.steps - self._cpu0[1]))
        log.info("companion: %d steps, %d setpoints sent, %d messages in; log %s "
                 "(%d written, %d dropped); CPU %s ms per step (getrusage, all threads and the "
                 "solver process, first frame to exit)", self.steps, self.sent, self.rx_count,
                 self.log_path,
                 logger.stats.written, logger.stats.dropped,
                 "-" if self.cpu_ms_per_step is None else f"{self.cpu_ms_per_step:.2f}")
        self._write_progress(final=True)
        return 0

    def _write_progress(self, final: bool = False) -> None:
        """``elapsed_s steps [cpu_ms_per_step]`` for an orchestrator (``companion demo``)."""
        if self.progress_file is None:
            return
        elapsed = self._elapsed_s
        cpu = f" {self.cpu_ms_per_step:.4f}" if final and self.cpu_ms_per_step else ""
        with contextlib.suppress(OSError):
            tmp = self.progress_file.with_suffix(".tmp")
            tmp.write_text(f"{elapsed:.3f} {self.steps}{cpu}\n")
            tmp.replace(self.progress_file)

    def _log_config(self) -> None:
        """``/config``, once: at start, or (source log times) at the first stamp seen, followed
        by the records that waited for that stamp."""
        if self._config_logged or not self.clock.started or self._logger is None:
            return
        self._config_logged = True
        self._logger.log_config(self.clock.now_ns(), self.config_text, dict(self.cfg.raw),
                                self.cfg.source)
        self._flush_early(self.clock.now_ns())

    def _log_at(self, t_ns: int, write: Callable[[int], object]) -> None:
        """``write(t_ns)`` now, or (source log times, no autopilot stamp seen yet: the time
        base is unknown, and a 0 would put the record hours before the flight in Foxglove)
        at the first stamp. At most ``EARLY_RECORDS_MAX`` wait; beyond, the oldest are
        dropped and counted in ``early_dropped``."""
        if self.clock.started and self._config_logged:
            write(t_ns)
            return
        if len(self._early) == self._early.maxlen:
            self.early_dropped += 1
        self._early.append(write)

    def _flush_early(self, t_ns: int) -> None:
        while self._early:
            self._early.popleft()(t_ns)

    def _on_reject(self, reason: str, raw: bytes, t_rx_ns: int) -> None:
        """A rejected frame, on the log's time base (receipt time, or the source clock)."""
        assert self._logger is not None
        logger = self._logger
        t_log = int(t_rx_ns) if self.clock.mode == "receipt" else self.clock.now_ns()
        self._log_at(t_log, lambda t: logger.log_rejected(reason, raw, t_rx_ns, log_time_ns=t))

    def _tx_log_ns(self, sent: Any) -> int:
        return int(sent.t_tx_ns) if self.clock.mode == "receipt" else self.clock.now_ns()

    # -- receive ----------------------------------------------------------------------------

    def _on_rx(self, rx: Received) -> None:
        assert self._logger is not None
        logger = self._logger
        fields = rx.msg.to_dict()
        t_log = self.clock.message_ns(rx.name, fields, rx.t_rx_ns)
        self._log_config()
        self._log_at(t_log, lambda t: logger.log_mavlink("in", rx, t))
        t_s = self.timebase.message_s(rx.name, fields, rx.t_rx_ns)
        self.store.ingest(rx.name, fields, t_s, rx.src_sysid)
        self.rx_count += 1
        if rx.name == "HEARTBEAT" and is_autopilot(self.cfg, rx.src_sysid, rx.src_compid):
            m = self.store.mode
            if m is not None:
                before = self.offboard.phase
                self.offboard.on_heartbeat(VehicleStatus(m.armed, m.main_mode, m.sub_mode, t_s))
                self._log_offboard(before, t_s)
            self._on_autopilot_state(fields.get("system_status"))
        elif rx.name == "TIMESYNC" and is_autopilot(self.cfg, rx.src_sysid, rx.src_compid):
            answer = self.timesync.on_timesync(int(fields["tc1"]), int(fields["ts1"]),
                                               time.monotonic_ns())
            if answer is None and self.delay_meter is not None:
                self.delay_meter.on_reply(int(fields["tc1"]), int(fields["ts1"]), rx.t_rx_ns)
            if answer is not None and self._link is not None:
                with contextlib.suppress(NoPeerError):
                    self._link.send_timesync(*answer)
        elif rx.name == "COMMAND_ACK":
            log.info("COMMAND_ACK command %s result %s", fields.get("command"),
                     fields.get("result"))
            if is_autopilot(self.cfg, rx.src_sysid, rx.src_compid):
                refused = self.offboard.request_rejected
                self.offboard.on_command_ack(int(fields.get("command", -1)),
                                             int(fields.get("result", -1)), t_s)
                if self.offboard.request_rejected and not refused:
                    text = (f"OFFBOARD request refused (result {fields.get('result')}): "
                            f"retried in {self.cfg.offboard.mode_retry_s} s")
                    self._log_at(self.clock.now_ns(), lambda t: logger.log_text(
                        TOPIC_OFFBOARD, t, text, level="WARNING", name="offboard"))

    async def _drain(self, link: MavlinkLink) -> None:
        async for _rx in link:  # the callback did the work; keep the queue empty
            pass

    async def _heartbeat(self, link: MavlinkLink) -> None:
        while True:
            with contextlib.suppress(NoPeerError):
                link.send_heartbeat()
            await asyncio.sleep(1.0)

    async def _stats(self, link: MavlinkLink) -> None:
        """The link's counters on /mavlink/stats (a flood or a spoofer shows up here)."""
        while True:
            await asyncio.sleep(self.cfg.mavlink.stats_interval_s)
            self.log_stats(link)

    def log_stats(self, link: MavlinkLink) -> None:
        assert self._logger is not None
        pinned = {str(s): f"{a[0]}:{a[1]}" for s in (self.cfg.mavlink.target_system,
                                                    self.cfg.target.mavlink_sysid)
                  if (a := link.guard.pinned(s)) is not None}
        counters = dict(link.counters)
        counters.update({f"guard_{k}": v for k, v in link.guard.counters.items()})
        t_ns = time.monotonic_ns() if self.clock.mode == "receipt" else self.clock.now_ns()
        logger = self._logger
        payload = {
            "counters": counters, "pinned": pinned,
            "stale_dropped": self.stale_frames, "stale_inputs": self.timebase.stale_count,
            "log_dropped": logger.stats.dropped + self.early_dropped,
        }
        self._log_at(t_ns, lambda t: logger.log(TOPIC_STATS, t, payload,
                                                schema=sch.MAVLINK_STATS))

    async def _timesync(self, link: MavlinkLink) -> None:
        """TIMESYNC requests at 10 Hz, like PX4's onboard link (the replies feed
        :attr:`timesync` in :meth:`_on_rx`)."""
        while True:
            with contextlib.suppress(NoPeerError):
                link.send_timesync(*self.timesync.request(time.monotonic_ns()))
            await asyncio.sleep(0.1)

    def _in_control(self) -> bool:
        """Our setpoints fly the vehicle: armed, and OFFBOARD confirmed (HEARTBEAT) or just
        requested and not refused (PX4 switches at once; the 1 Hz HEARTBEAT confirms up to
        1 s later; a COMMAND_ACK refusing the request ends it until the next request)."""
        m = self.store.mode
        if m is None or not m.armed:
            return False
        if self.offboard.phase is OffboardPhase.REQUESTING:
            return self.offboard.awaiting_switch
        return m.main_mode == PX4_MAIN_MODE_OFFBOARD and self.offboard.phase in (
            OffboardPhase.ACTIVE, OffboardPhase.LOST, OffboardPhase.EXITING)

    def now_s(self) -> float | None:
        """"Now" on the frames' time base, for the latency compensation: ``None`` with
        receipt stamps (a frame's age is unknown); else the newest attitude/position stamp,
        or later by the TIMESYNC-mapped local clock (``control.time_source = "timesync"``).
        In lockstep the autopilot's clock stands still while it waits for our setpoint, so
        the wall-clock mapping runs ahead there: the demo uses ``"autopilot"``."""
        if self.timebase.source == "receipt":
            return None
        now = self.store.newest_autopilot_s()
        if self.timebase.source == "timesync":
            mapped = self.timesync.autopilot_s(time.monotonic_ns())
            if mapped is not None and math.isfinite(mapped):
                now = max(now, mapped)
        return now if math.isfinite(now) else None

    async def _truth(self, port: int, ready: asyncio.Event) -> None:
        """Ground truth from the emulator, logged for scoring only (never read by control)."""
        assert self._logger is not None
        logger = self._logger
        clock = self.clock
        log_at = self._log_at
        loop = asyncio.get_running_loop()

        class _Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: Any) -> None:
                try:
                    rec = json.loads(data)
                except ValueError:
                    return
                log_at(clock.now_ns(), lambda t: logger.log(TOPIC_TRUTH, t, rec, schema=sch.JSON))

        transport, _ = await loop.create_datagram_endpoint(
            _Proto, local_addr=("127.0.0.1", port))
        ready.set()
        try:
            await asyncio.Future()
        finally:
            transport.close()

    # -- control ----------------------------------------------------------------------------

    async def _control(self, camera: FrameSource) -> None:
        it = camera.__aiter__()
        exit_deadline: float | None = None
        while True:
            if self._stop.is_set() and exit_deadline is None:
                exit_deadline = time.monotonic() + 2.0
                self.offboard.request_exit(self.timebase.latest_s)
            if exit_deadline is not None and (
                time.monotonic() > exit_deadline or self.offboard.phase is OffboardPhase.DONE
            ):
                break
            # before the first frame the camera may still be starting (a loaded machine takes
            # seconds to start the emulator): wait longer than between frames
            wait_s = self.idle_timeout_s if self._first_frame_s is not None else max(
                self.idle_timeout_s, self.startup_timeout_s)
            if exit_deadline is not None:  # stopping: wait no longer than the exit allows
                wait_s = max(0.0, min(wait_s, exit_deadline - time.monotonic()))
            try:
                frame: CameraFrame = await self._next_frame(it, wait_s,
                                                            wake_on_stop=exit_deadline is None)
            except _StopRequested:
                continue  # SIGTERM/SIGINT while waiting: start the exit now
            except (TimeoutError, StopAsyncIteration):
                if exit_deadline is None:
                    log.info("companion: no camera frame for %.1f s, stopping", wait_s)
                    self._stop.set()
                    continue
                break
            self._step(frame)

    async def _next_frame(self, it: Any, wait_s: float, wake_on_stop: bool) -> CameraFrame:
        """The camera's next frame within ``wait_s`` (``TimeoutError``); with
        ``wake_on_stop``, raises :class:`_StopRequested` as soon as a stop is requested."""
        if not wake_on_stop:
            frame: CameraFrame = await asyncio.wait_for(it.__anext__(), wait_s)
            return frame
        nxt = asyncio.ensure_future(it.__anext__())
        stop = asyncio.ensure_future(self._stop.wait())
        try:
            done, _ = await asyncio.wait({nxt, stop}, timeout=wait_s,
                                         return_when=asyncio.FIRST_COMPLETED)
        finally:
            stop.cancel()
        if nxt in done:
            frame = nxt.result()
            return frame
        nxt.cancel()
        with contextlib.suppress(asyncio.CancelledError, StopAsyncIteration):
            await nxt
        if stop in done:
            raise _StopRequested
        raise TimeoutError

    def _step(self, frame: CameraFrame) -> None:
        assert self._logger is not None and self._link is not None
        logger, link = self._logger, self._link
        t_s = self.timebase.frame_s(frame.t_us, frame.t_rx_ns)
        frame_late_s = self.timebase.last_excess_s
        t_log = self.clock.frame_ns(frame.t_us, frame.t_rx_ns)
        self._log_config()
        if self.timebase.last_excess_s > self.cfg.safety.max_frame_age_s:
            # a frame from a backlog (the process or the link stalled): never control from it
            self.stale_frames += 1
            self.offboard.on_stream_gap()
            logger.log_text(TOPIC_SAFETY, t_log,
                            f"stale frame {frame.seq} dropped: {self.timebase.last_excess_s:.3f}"
                            f" s late (safety.max_frame_age_s "
                            f"{self.cfg.safety.max_frame_age_s} s)",
                            level="WARNING", name="safety")
            return
        if self._first_frame_s is None:
            self._first_frame_s = t_s
        elapsed = t_s - self._first_frame_s
        self._elapsed_s = elapsed
        if self.duration_s is not None and elapsed >= self.duration_s:
            self._stop.set()
        self.pipeline.force_solver_failure = any(
            f.t0_s <= elapsed < f.t1_s for f in self.faults if f.kind == "solver")
        hang = [f.t0_s <= elapsed < f.t1_s for f in self.faults if f.kind == "solver-hang"]
        if hang:  # the solver process's test hook, withdrawn after the window
            self.pipeline.rmpc.backend.hang_next_solve(any(hang))  # type: ignore[attr-defined]
        t_start_ns = time.monotonic_ns()
        # The log writer waits while the step computes and sends (McapLogger.hold): its Python
        # serialisation otherwise takes the GIL from the step for up to CPython's 5 ms switch
        # interval (measured: send stage 1.2-1.9 -> 0.4-0.6 ms median, frame -> command
        # 6.7-7.1 -> 5.8-6.2 ms median at load 6, interleaved).
        meter = self.delay_meter
        measured = None if meter is None else meter.value()
        logger.hold()
        try:
            res = self.pipeline.step(np.asarray(frame.image), t_s, self.store,
                                     t_now_s=self.now_s(), in_control=self._in_control(),
                                     actuation_delay_s=measured)
            sent_ns = None
            if res.setpoint is not None and self.offboard.phase is not OffboardPhase.DONE:
                try:
                    t_now = res.t_now_s if res.t_now_s is not None else t_s
                    if meter is not None and meter.due(t_now):
                        # right before the setpoint: the same way, the same delays
                        ts1 = time.monotonic_ns()
                        link.send_timesync(*self.timesync.request(ts1))
                        meter.sent(ts1, t_now)
                    link.send_attitude_target(res.setpoint.q_wxyz.tolist(),
                                              res.setpoint.thrust_norm,
                                              time_boot_ms=int(max(t_s, 0.0) * 1e3) & 0xFFFFFFFF)
                    sent_ns = time.monotonic_ns()
                    self.sent += 1
                    self.offboard.on_streamed(t_s)
                except NoPeerError:
                    pass
            else:
                self.offboard.on_stream_gap()
        finally:
            logger.release()
        # The frame is logged after the command left: a logging backlog never delays it.
        logged_input = self.recorder.record(logger, t_log, np.asarray(frame.image), frame.t_us,
                                            res.input_region)
        before = self.offboard.phase
        self.offboard.on_controller(
            res.setpoint is not None and res.rmpc is not None and res.rmpc.mode == "recovery")
        for act in self.offboard.step(t_s):
            self._act(act, t_s)
        self._log_offboard(before, t_s)
        self.steps += 1
        if self._cpu0 is None:
            self._cpu0 = (_cpu_s(self.pipeline.rmpc), self.steps)
        elif self.progress_file is not None and self.steps % 20 == 0:
            self._write_progress()
        rec = res.to_record()
        rec.update({
            "frame_seq": frame.seq, "frame_t_us": frame.t_us, "t_rx_ns": frame.t_rx_ns,
            "rx_count": self.rx_count, "offboard": self.offboard.phase.value,
            "fault_injected": self.pipeline.force_solver_failure, "sent": sent_ns is not None,
            "frame_late_s": frame_late_s,
            "telemetry_age_s": _finite_or_none(self.store.telemetry_age_s(t_s)),
            "latency_ms": None if sent_ns is None else (sent_ns - frame.t_rx_ns) * 1e-6,
            "actuation_delay": None if meter is None else {
                "used_s": res.actuation_delay_s, "measured": measured is not None,
                "samples": meter.samples, "spread_s": meter.spread(),
                "replies": meter.replies, "rejected": meter.rejected},
            "input": logged_input,
        })
        if sent_ns is not None:
            # decode: receipt -> step start (decoding the frame, then waiting for the loop)
            rec["timings_ms"] = {"decode": (t_start_ns - frame.t_rx_ns) * 1e-6,
                                 **rec["timings_ms"],
                                 "send": (sent_ns - t_start_ns) * 1e-6
                                 - sum(rec["timings_ms"].values())}
        logger.log(TOPIC_STEP, t_log, rec, schema=sch.CONTROLLER_STEP)
        self._log_poses(t_log)
        if res.safety.changed or self.steps == 1:  # the initial state, then each transition
            logger.log_text(TOPIC_SAFETY, t_log,
                            f"{res.safety.level.value}: {res.safety.reason}",
                            level="WARNING", name="safety")

    def _log_poses(self, t_ns: int) -> None:
        """The vehicle and the target as the companion knows them (Foxglove 3-D panel, NED)."""
        assert self._logger is not None
        kin, tgt = self.store.kinematics, self.store.target
        if kin is not None and self.store.attitude:
            self._logger.log_pose(TOPIC_POSE, t_ns, "ned", kin.pos_ned_m,
                                  self.store.attitude[-1].q_wxyz)
        if tgt is not None:
            half = 0.5 * tgt.yaw_rad
            self._logger.log_pose(TOPIC_TARGET_POSE, t_ns, "ned", tgt.pos_ned_m,
                                  (math.cos(half), 0.0, 0.0, math.sin(half)))

    def _act(self, act: Any, t_s: float) -> None:
        assert self._link is not None
        try:
            if act.kind == "arm":
                self._link.send_arm(True)
            elif act.kind == "set_mode":
                self._link.send_set_mode(act.main_mode, act.sub_mode)
            elif act.kind == "stop_stream":
                return
        except NoPeerError:
            return
        log.info("offboard: %s (%s) at t=%.2f s", act.kind, act.reason, t_s)

    def _on_autopilot_state(self, state: object) -> None:
        """Log a change of the autopilot's MAV_STATE: PX4 reports CRITICAL while a failsafe
        action is in force (e.g. after an offboard loss, until a mode is asked for),
        EMERGENCY / FLIGHT_TERMINATION beyond it (HEARTBEAT.hpp)."""
        if not isinstance(state, int) or state == self.autopilot_state:
            return
        before, self.autopilot_state = self.autopilot_state, state
        if self._logger is None or (before is None and state in (3, 4)):
            return  # the first STANDBY / ACTIVE is no news
        name = MAV_STATE_NAMES.get(state, f"MAV_STATE {state}")
        alarm = state in (5, 6, 8)
        was = "none" if before is None else MAV_STATE_NAMES.get(before, f"MAV_STATE {before}")
        text = (f"autopilot system status {was} -> {name}"
                + (": a failsafe is in force on the autopilot" if alarm else ""))
        (log.warning if alarm else log.info)(text)
        logger = self._logger
        self._log_at(self.clock.now_ns(), lambda t: logger.log_text(
            TOPIC_SAFETY, t, text, level="WARNING" if alarm else "INFO", name="autopilot"))

    def _log_offboard(self, before: OffboardPhase, t_s: float) -> None:
        if self.offboard.phase is not before and self._logger is not None:
            _, phase, reason = self.offboard.transitions[-1]
            log.info("offboard %s -> %s: %s", before.value, phase.value, reason)
            logger = self._logger
            text = f"{before.value} -> {phase.value}: {reason}"
            self._log_at(self.clock.now_ns(), lambda t: logger.log_text(
                TOPIC_OFFBOARD, t, text, level="INFO", name="offboard"))

