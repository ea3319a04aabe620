"""The on-vehicle process: camera + telemetry -> pipeline -> SET_ATTITUDE_TARGET, all logged.

One asyncio process. Stages are wired in one place (:meth:`CompanionApp.run`); the rooms
around the loop are their own modules:

- :mod:`~companion.control.vehicle`: the link's receive callback logs every accepted message
  and feeds the telemetry store and the offboard state machine (so the log's order is the
  order the store saw), answers TIMESYNC and carries out the state machine's actions;
- :mod:`~companion.control.timebase`: one time base for frames and messages (on receipt for
  a real vehicle, or the autopilot's own clock for the emulator);
- :mod:`~companion.control.recording`: what is logged and at which log time;
- :mod:`~companion.control.faults`: fault injection windows (tests and bench).

Here: the start-up sequence, the background tasks (a 1 Hz HEARTBEAT as an onboard controller,
link statistics, TIMESYNC requests, an optional ground-truth recorder for scoring that feeds
nothing else) and the control loop, one pipeline step per camera frame, streaming the setpoint.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import math
import resource
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import orjson

from companion.camera import CameraFrame, open_camera
from companion.config import Config
from companion.control.faults import FaultWindow, apply_faults
from companion.control.knobs import warn_ineffective_knobs
from companion.control.offboard import OffboardManager, OffboardPhase
from companion.control.outrun import OutrunMonitor
from companion.control.pipeline import ControlPipeline, StepResult
from companion.control.recording import (
    TOPIC_SAFETY,
    TOPIC_STEP,
    TOPIC_TRUTH,
    FrameRecorder,
    LogClock,
    RuntimeLog,
)
from companion.control.seams import FrameSource
from companion.control.stopping import StopEvent, StopRequested, stop_on_signals
from companion.control.telemetry import TelemetryStore
from companion.control.timebase import TimeBase
from companion.control.vehicle import Vehicle
from companion.control.vehicle_limits import VehicleLimitsStage, adopt_vehicle_limits, set_pipeline
from companion.control.wiring import allow_rules, new_pipeline
from companion.core.setpoint import AttitudeSetpoint
from companion.flight_ports import write_ready
from companion.link import MavlinkLink, NoPeerError
from companion.log import schemas as sch
from companion.log.live import start_live
from companion.log.writer import McapLogger

log = logging.getLogger(__name__)

FIRST_FRAME_TIMEOUT_S = 60.0
#: The progress file (a demo's bar) at most this often, wall time: a write and a rename cost the
#: control loop ~0.3 ms of CPU and ~1.8 ms of wall time on ext4 (every 20 steps: ~6 a second).
PROGRESS_INTERVAL_S = 1.0


@dataclass(frozen=True)
class _Sent:
    """What one step sent: the monotonic time the setpoint left (``None``: nothing sent), the
    measured actuation delay the step used (s, ``None``: the configured constant) and the
    monotonic time the step started."""

    sent_ns: int | None
    measured_delay_s: float | None
    t_start_ns: int


def _cpu_s(controller: Any = None) -> float:
    """This process's CPU time (all threads), plus that of ``controller``'s solver process
    (``rmpc.solve_isolation = "process"``), seconds."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    backend = getattr(controller, "backend", None)
    return r.ru_utime + r.ru_stime + float(getattr(backend, "child_cpu_s", 0.0))


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
        warn_ineffective_knobs(cfg)  # a knob the chosen mode ignores, by name
        self.mavlink_url = mavlink_url or cfg.mavlink.url
        self.camera_url = camera_url
        self.log_path = log_path
        self.truth_port = truth_port
        self._truth_bound_port: int | None = None  # what the kernel gave a --truth-port 0
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
        self._next_progress_s = 0.0  # monotonic time of the next progress write
        self._cpu0: tuple[float, int] | None = None  # (CPU s, steps) at the first frame
        self.cpu_ms_per_step: float | None = None
        self.timebase = TimeBase(cfg.control.time_source, cfg.safety.max_frame_age_s)
        self.clock = LogClock(cfg.logging.timestamps)
        self.recorder = FrameRecorder(cfg.logging)
        self.vehicle = Vehicle(cfg, self.timebase)
        self.vehicle.params = self.limits = VehicleLimitsStage(cfg)
        self.outrun = OutrunMonitor()
        self.pipeline: ControlPipeline  # with [vehicle_limits] from_autopilot: once they are read
        if not cfg.vehicle_limits.from_autopilot:
            set_pipeline(self, new_pipeline(cfg, timer=time.perf_counter))
        self.steps = 0
        self.sent = 0
        self._stop = StopEvent(self._wake_frame_wait)
        self._frame_wait: asyncio.Timeout | None = None  # _next_frame's, while it waits
        self._records: RuntimeLog | None = None
        self._link: MavlinkLink | None = None
        self._first_frame_s: float | None = None
        self._elapsed_s = 0.0  # since the first frame, on the frames' clock

    @property
    def store(self) -> TelemetryStore:
        return self.vehicle.store

    @property
    def offboard(self) -> OffboardManager:
        return self.vehicle.offboard

    @property
    def rx_count(self) -> int:
        return self.vehicle.rx_count

    # -- wiring -----------------------------------------------------------------------------

    async def run(self) -> int:
        """The flight, in order: open the log (and the live view), open the link and the
        camera, start the background tasks, announce readiness, run the control loop until a
        stop, write the final statistics. A start-up check on the open link goes in
        :meth:`_start_up`."""
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        # the live view (None when off) fails here on a taken port, before the flight
        # (the layout's /camera/image is the JPEG preview whatever logging.image_encoding)
        live = start_live(self.cfg.live, "jpeg")
        logger = McapLogger.from_config(self.cfg.logging, self.log_path)
        logger.observer = live  # the live view sees what the log writes
        records = RuntimeLog(logger, self.clock, self.cfg, self.config_text)
        self._records = self.vehicle.records = records
        try:
            with stop_on_signals(self._stop), logger:
                records.config()
                await self._fly(records)
        finally:
            if live is not None:
                live.close()
            close = getattr(getattr(getattr(self, "pipeline", None), "rmpc", None), "close", None)
            if callable(close):  # the solver's child process (rmpc.solve_isolation)
                close()
        self._finish(logger)
        return 0

    def _open_link(self, records: RuntimeLog) -> MavlinkLink:
        link = MavlinkLink.from_config(
            dataclasses.replace(self.cfg.mavlink, url=self.mavlink_url), self.cfg.target,
            allow=allow_rules(self.cfg), on_rx=self.vehicle.on_rx, on_tx=records.sent,
            on_reject=records.rejected)
        self._link = self.vehicle.link = link
        return link

    async def _fly(self, records: RuntimeLog) -> None:
        link = self._open_link(records)
        async with link, open_camera(self.camera_url) as camera:
            log.info("companion: mavlink %s, camera %s, log %s", self.mavlink_url,
                     self.camera_url, self.log_path)
            async with asyncio.TaskGroup() as tg:
                control = tg.create_task(self._control(camera))
                aux = await self._start_up(tg, link)
                if self.ready_file is not None:  # with the ports bound (an orchestrator's)
                    write_ready(self.ready_file, link.local_address, self._truth_bound_port)
                await control
                for t in aux:
                    t.cancel()
            self.log_stats(link)
            log.info("companion: link counters %s", dict(link.counters))
            records.flush_early(self.clock.now_ns())  # never any stamp: at time 0

    async def _start_up(self, tg: asyncio.TaskGroup, link: MavlinkLink) -> list[asyncio.Task[None]]:
        """With the link and the camera open, before the companion says it is ready: the
        background tasks (the ground-truth listener bound before readiness)."""
        aux = [tg.create_task(self._drain(link)), tg.create_task(self._heartbeat(link)),
               tg.create_task(self._stats(link))]
        if self.cfg.control.time_source == "timesync":
            aux.append(tg.create_task(self._timesync(link)))
        if self.truth_port is not None:
            ready = asyncio.Event()
            aux.append(tg.create_task(self._truth(self.truth_port, ready)))
            await ready.wait()
        return aux

    def _finish(self, logger: McapLogger) -> None:
        if self._cpu0 is not None and self.steps > self._cpu0[1]:
            self.cpu_ms_per_step = (1e3 * (_cpu_s(self.pipeline.rmpc) - self._cpu0[0])
                                    / (self.steps - self._cpu0[1]))
        log.info("companion: %d steps, %d setpoints sent, %d messages in; log %s "
                 "(%d written, %d dropped); CPU %s ms per step (getrusage, all threads and the "
                 "solver process, first frame to exit)", self.steps, self.sent, self.rx_count,
                 self.log_path, logger.stats.written, logger.stats.dropped,
                 "-" if self.cpu_ms_per_step is None else f"{self.cpu_ms_per_step:.2f}")
        self._write_progress(final=True)

    def _progress_due(self) -> None:
        """The progress file, unless written less than ``PROGRESS_INTERVAL_S`` ago."""
        now = time.monotonic()
        if now >= self._next_progress_s:
            self._next_progress_s = now + PROGRESS_INTERVAL_S
            self._write_progress()

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

    # -- background tasks -------------------------------------------------------------------

    async def _drain(self, link: MavlinkLink) -> None:
        """Wait for the link to close: the callback does the work on every frame (the link
        queues none), and a link closed by an error raises it here (ends the task group)."""
        async for _rx in link:
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
        assert self._records is not None, "the log is open"
        self._records.link_stats(link, self.stale_frames, self.timebase.stale_count)

    async def _timesync(self, link: MavlinkLink) -> None:
        """TIMESYNC requests at 10 Hz, like PX4's onboard link (the replies feed the
        vehicle's :class:`~companion.control.timesync.TimeSync`)."""
        while True:
            with contextlib.suppress(NoPeerError):
                link.send_timesync(*self.vehicle.timesync.request(time.monotonic_ns()))
            await asyncio.sleep(0.1)

    async def _truth(self, port: int, ready: asyncio.Event) -> None:
        """Ground truth from the emulator, logged for scoring only (never read by control)."""
        assert self._records is not None
        records = self._records
        logger, clock = records.logger, self.clock
        loop = asyncio.get_running_loop()

        class _Proto(asyncio.DatagramProtocol):
            def datagram_received(self, data: bytes, addr: Any) -> None:
                try:  # strict JSON is logged as received (orjson: ~10x json's speed)
                    rec = orjson.loads(data)
                    rec = bytes(data) if isinstance(rec, dict) else rec
                except orjson.JSONDecodeError:  # json's extensions (NaN) decoded as before
                    try:
                        rec = json.loads(data)
                    except ValueError:
                        return
                records.at(clock.now_ns(),
                           lambda t: logger.log(TOPIC_TRUTH, t, rec, schema=sch.JSON))

        transport, _ = await loop.create_datagram_endpoint(_Proto, local_addr=("127.0.0.1", port))
        self._truth_bound_port = int(transport.get_extra_info("sockname")[1])
        ready.set()
        try:
            await asyncio.Future()
        finally:
            transport.close()

    # -- control ----------------------------------------------------------------------------

    async def _control(self, camera: FrameSource) -> None:
        await adopt_vehicle_limits(self, new_pipeline)
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
            # before the first frame the camera may still be starting: wait longer
            wait_s = self.idle_timeout_s if self._first_frame_s is not None else max(
                self.idle_timeout_s, self.startup_timeout_s)
            if exit_deadline is not None:  # stopping: wait no longer than the exit allows
                wait_s = max(0.0, min(wait_s, exit_deadline - time.monotonic()))
            try:
                frame: CameraFrame = await self._next_frame(it, wait_s,
                                                            wake_on_stop=exit_deadline is None)
            except StopRequested:
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
        ``wake_on_stop``, raises :class:`StopRequested` as soon as a stop is requested.

        Awaited in the control task itself under one ``asyncio.timeout``: a stop request moves
        that timeout to now (:class:`StopEvent`). No task, no ``asyncio.wait`` and no extra
        loop iteration a frame (they cost ~40-60 us of CPU a step)."""
        if wake_on_stop and self._stop.is_set():
            raise StopRequested
        try:
            async with asyncio.timeout(wait_s) as deadline:
                self._frame_wait = deadline if wake_on_stop else None
                frame: CameraFrame = await it.__anext__()
        except TimeoutError:
            if wake_on_stop and self._stop.is_set():
                raise StopRequested from None
            raise
        finally:
            self._frame_wait = None
        return frame

    def _wake_frame_wait(self) -> None:
        """A stop was requested: end the control loop's frame wait now (if it waits)."""
        deadline = self._frame_wait
        if deadline is not None and not deadline.expired():
            deadline.reschedule(asyncio.get_running_loop().time())

    def _step(self, frame: CameraFrame) -> None:
        """One camera frame: admitted (fresh), computed and sent, then recorded."""
        assert self._records is not None
        t_s = self.timebase.frame_s(frame.t_us, frame.t_rx_ns)
        frame_late_s = self.timebase.last_excess_s
        t_log = self.clock.frame_ns(frame.t_us, frame.t_rx_ns)
        self._records.config()
        if not self._admit(frame, t_log, t_s):
            return
        res, sent = self._compute_and_send(frame, t_s)
        # The frame is logged after the command left: a logging backlog never delays it.
        logged_input = self.recorder.record(self._records.logger, t_log, np.asarray(frame.image),
                                            frame.t_us, res.input_region)
        before = self.offboard.phase
        self.offboard.on_controller(
            res.setpoint is not None and res.rmpc is not None and res.rmpc.mode == "recovery")
        for act in self.offboard.step(t_s):
            self.vehicle.act(act, t_s)
        self.vehicle.log_offboard(before)
        self.steps += 1
        if self._cpu0 is None:
            self._cpu0 = (_cpu_s(self.pipeline.rmpc), self.steps)
        elif self.progress_file is not None and self.steps % 20 == 0:
            self._progress_due()
        self._log_step(frame, t_s, t_log, frame_late_s, res, sent, logged_input)

    def _admit(self, frame: CameraFrame, t_log: int, t_s: float) -> bool:
        """A frame fit to control from (not from a backlog); the flight's elapsed time, the
        duration's stop and the fault windows follow from it."""
        assert self._records is not None
        if self.timebase.last_excess_s > self.cfg.safety.max_frame_age_s:
            # a frame from a backlog (the process or the link stalled): never control from it
            self.stale_frames += 1
            self.offboard.on_stream_gap()
            self._records.logger.log_text(
                TOPIC_SAFETY, t_log,
                f"stale frame {frame.seq} dropped: {self.timebase.last_excess_s:.3f}"
                f" s late (safety.max_frame_age_s {self.cfg.safety.max_frame_age_s} s)",
                level="WARNING", name="safety")
            return False
        if self._first_frame_s is None:
            self._first_frame_s = t_s
        elapsed = t_s - self._first_frame_s
        self._elapsed_s = elapsed
        if self.duration_s is not None and elapsed >= self.duration_s:
            self._stop.set()
        apply_faults(self.faults, self.pipeline, elapsed)
        return True

    def _compute_and_send(self, frame: CameraFrame, t_s: float) -> tuple[StepResult, _Sent]:
        """The pipeline's step and its setpoint on the link (or a stream gap), sent as soon
        as the command is built (the pipeline's ``send``), the step's result after."""
        assert self._records is not None
        logger, vehicle = self._records.logger, self.vehicle
        t_start_ns = time.monotonic_ns()
        # The log writer waits while the step computes and sends (McapLogger.hold): it would
        # take the GIL from the step for up to the 5 ms switch interval (send stage 1.2-1.9 ->
        # 0.4-0.6 ms median, frame -> command 6.7-7.1 -> 5.8-6.2 ms, load 6, interleaved).
        meter = vehicle.delay_meter
        measured = None if meter is None else meter.value()
        sent: list[int | None] = []  # the send's time (None: no peer yet); empty: a stream gap
        logger.hold()
        try:
            res = self.pipeline.step(np.asarray(frame.image), t_s, vehicle.store,
                                     t_now_s=vehicle.now_s(), in_control=vehicle.in_control(),
                                     actuation_delay_s=measured,
                                     send=lambda sp, t_now: self._send(sp, t_now, t_s, sent))
        finally:
            logger.release()
        if not sent:
            self.offboard.on_stream_gap()
        return res, _Sent(sent[0] if sent else None, measured, t_start_ns)

    def _send(self, setpoint: AttitudeSetpoint, t_now: float, t_s: float, sent: list[Any]) -> None:
        """The setpoint on the link unless OFFBOARD is done, a due TIMESYNC probe right before
        it (same way, same delays); ``sent`` gets when it left (None: no autopilot heard)."""
        if self.offboard.phase is OffboardPhase.DONE:
            return
        link, vehicle, meter = self._link, self.vehicle, self.vehicle.delay_meter
        assert link is not None
        try:
            if meter is not None and meter.due(t_now):
                ts1 = time.monotonic_ns()
                link.send_timesync(*vehicle.timesync.request(ts1))
                meter.sent(ts1, t_now)
            link.send_attitude_target(setpoint.q_wxyz.tolist(), setpoint.thrust_norm,
                                      time_boot_ms=int(max(t_s, 0.0) * 1e3) & 0xFFFFFFFF)
        except NoPeerError:
            sent.append(None)
            return
        sent.append(link.last_tx_ns)  # when it left, not after its log record
        self.sent += 1
        self.offboard.on_streamed(t_s)

    def _log_step(self, frame: CameraFrame, t_s: float, t_log: int, frame_late_s: float,
                  res: StepResult, sent: _Sent, logged_input: dict[str, Any] | None) -> None:
        """``/control/step`` (the pipeline's record plus the runtime's view), the poses, and
        the safety level (the initial one, then each transition)."""
        assert self._records is not None
        logger, meter, sent_ns = self._records.logger, self.vehicle.delay_meter, sent.sent_ns
        rec = res.to_record()
        rec.update({
            "frame_seq": frame.seq, "frame_t_us": frame.t_us, "t_rx_ns": frame.t_rx_ns,
            "rx_count": self.rx_count, "offboard": self.offboard.phase.value,
            "fault_injected": self.pipeline.force_solver_failure, "sent": sent_ns is not None,
            "frame_late_s": frame_late_s,
            "telemetry_age_s": age if math.isfinite(age := self.store.telemetry_age_s(t_s))
            else None,
            "latency_ms": None if sent_ns is None else (sent_ns - frame.t_rx_ns) * 1e-6,
            "actuation_delay": None if meter is None else {
                "used_s": res.actuation_delay_s, "measured": sent.measured_delay_s is not None,
                "samples": meter.samples, "spread_s": meter.spread(),
                "replies": meter.replies, "rejected": meter.rejected},
            "input": logged_input,
        })
        if sent_ns is not None:
            # decode: receipt -> step start (decoding the frame, then waiting for the loop)
            rec["timings_ms"] = {"decode": (sent.t_start_ns - frame.t_rx_ns) * 1e-6,
                                 **rec["timings_ms"],
                                 "send": (sent_ns - sent.t_start_ns) * 1e-6
                                 - sum(rec["timings_ms"].values())}
        logger.log(TOPIC_STEP, t_log, rec, schema=sch.CONTROLLER_STEP)
        self._records.poses(t_log, self.store)
        self.outrun.observe(self, res, t_s, t_log)
        if res.safety.changed or self.steps == 1:  # the initial state, then each transition
            logger.log_text(TOPIC_SAFETY, t_log,
                            f"{res.safety.level.value}: {res.safety.reason}",
                            level="WARNING", name="safety")
