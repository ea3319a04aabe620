"""The companion's side of the vehicle: what it knows of the autopilot and how it answers it.

:class:`Vehicle` owns the telemetry store, the offboard state machine, TIMESYNC (clock offset
and the measured actuation delay) and the autopilot's MAV_STATE. The link's receive callback
(:meth:`Vehicle.on_rx`) logs every accepted message and feeds the store and the state machine,
so the log's order is the order the store saw; :meth:`Vehicle.act` carries out the state
machine's actions on the link.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from typing import Any

from companion.config import Config
from companion.control.offboard import (
    PX4_MAIN_MODE_OFFBOARD,
    Action,
    OffboardManager,
    OffboardPhase,
    VehicleStatus,
)
from companion.control.recording import TOPIC_OFFBOARD, TOPIC_SAFETY, RuntimeLog
from companion.control.timebase import TimeBase
from companion.control.timesync import ActuationDelayMeter, TimeSync
from companion.control.wiring import is_autopilot, new_store
from companion.link import MavlinkLink, NoPeerError, Received, message_fields

log = logging.getLogger(__name__)

#: MAV_STATE names (HEARTBEAT system_status)
MAV_STATE_NAMES = {0: "UNINIT", 1: "BOOT", 2: "CALIBRATING", 3: "STANDBY", 4: "ACTIVE",
                   5: "CRITICAL", 6: "EMERGENCY", 7: "POWEROFF", 8: "FLIGHT_TERMINATION"}


class Vehicle:
    """The autopilot as the companion sees it (see the module docstring). ``link`` and
    ``records`` are attached once the flight's link and log are open."""

    def __init__(self, cfg: Config, timebase: TimeBase) -> None:
        self.cfg = cfg
        self.timebase = timebase
        self.store = new_store(cfg)
        self.offboard = OffboardManager(cfg.offboard, reengage=cfg.offboard.reengage)
        self.timesync = TimeSync()
        lat = cfg.control.latency
        # the actuation delay measured from TIMESYNC probes (None: the configured constant)
        self.delay_meter = ActuationDelayMeter(
            cfg.control.time_source, lat.auto_delay_window, lat.auto_delay_min_samples,
            lat.auto_delay_max_s, 1.0 / lat.auto_delay_probe_hz) if lat.auto_delay else None
        #: the autopilot's HEARTBEAT system_status (MAV_STATE) last seen; None before the first
        self.autopilot_state: int | None = None
        self.rx_count = 0
        self.link: MavlinkLink | None = None
        self.records: RuntimeLog | None = None
        #: where PARAM_VALUEs go (companion/control/vehicle_limits.py), attached by the runtime
        self.params: Any = None
        #: the offboard manager's held-back reason last logged (log_offboard)
        self._held_logged: str | None = None

    # -- receive ----------------------------------------------------------------------------

    def on_rx(self, rx: Received) -> None:
        """The link's callback for every accepted message."""
        assert self.records is not None
        # decoded once by the link (message_fields), shared with the log writer
        fields = rx.fields if rx.fields is not None else message_fields(rx.msg)
        self.records.received(rx, fields)
        t_s = self.timebase.message_s(rx.name, fields, rx.t_rx_ns)
        self.store.ingest(rx.name, fields, t_s, rx.src_sysid)
        self.rx_count += 1
        from_autopilot = is_autopilot(self.cfg, rx.src_sysid, rx.src_compid)
        if rx.name == "HEARTBEAT" and from_autopilot:
            m = self.store.mode
            if m is not None:
                before = self.offboard.phase
                self.offboard.on_heartbeat(VehicleStatus(m.armed, m.main_mode, m.sub_mode, t_s))
                self.log_offboard(before)
            self._on_autopilot_state(fields.get("system_status"))
        elif rx.name == "EXTENDED_SYS_STATE" and from_autopilot:
            if "landed_state" in fields:
                self.offboard.on_landed_state(int(fields["landed_state"]))
        elif rx.name == "TIMESYNC" and from_autopilot:
            self._on_timesync(fields, rx.t_rx_ns)
        elif rx.name == "PARAM_VALUE" and self.params is not None:
            self.params.on_param_value(fields, rx.src_sysid, rx.src_compid)
        elif rx.name == "COMMAND_ACK":
            log.info("COMMAND_ACK command %s result %s", fields.get("command"),
                     fields.get("result"))
            if from_autopilot:
                self._on_command_ack(fields, t_s)

    def _on_timesync(self, fields: dict[str, Any], t_rx_ns: int) -> None:
        answer = self.timesync.on_timesync(int(fields["tc1"]), int(fields["ts1"]),
                                           time.monotonic_ns())
        if answer is None and self.delay_meter is not None:
            self.delay_meter.on_reply(int(fields["tc1"]), int(fields["ts1"]), t_rx_ns)
        if answer is not None and self.link is not None:
            with contextlib.suppress(NoPeerError):
                self.link.send_timesync(*answer)

    def _on_command_ack(self, fields: dict[str, Any], t_s: float) -> None:
        assert self.records is not None
        refused = self.offboard.request_rejected
        self.offboard.on_command_ack(int(fields.get("command", -1)),
                                     int(fields.get("result", -1)), t_s)
        if self.offboard.request_rejected and not refused:
            self.records.text(TOPIC_OFFBOARD,
                              f"OFFBOARD request refused (result {fields.get('result')}): "
                              f"retried in {self.cfg.offboard.mode_retry_s} s",
                              level="WARNING", name="offboard")

    def _on_autopilot_state(self, state: object) -> None:
        """Log a change of the autopilot's MAV_STATE: PX4 reports CRITICAL while a failsafe
        action is in force (e.g. after an offboard loss, until a mode is asked for),
        EMERGENCY / FLIGHT_TERMINATION beyond it (HEARTBEAT.hpp)."""
        if not isinstance(state, int) or state == self.autopilot_state:
            return
        before, self.autopilot_state = self.autopilot_state, state
        if self.records is None or (before is None and state in (3, 4)):
            return  # the first STANDBY / ACTIVE is no news
        name = MAV_STATE_NAMES.get(state, f"MAV_STATE {state}")
        alarm = state in (5, 6, 8)
        was = "none" if before is None else MAV_STATE_NAMES.get(before, f"MAV_STATE {before}")
        text = (f"autopilot system status {was} -> {name}"
                + (": a failsafe is in force on the autopilot" if alarm else ""))
        (log.warning if alarm else log.info)(text)
        self.records.text(TOPIC_SAFETY, text, level="WARNING" if alarm else "INFO",
                          name="autopilot")

    # -- the vehicle's state ----------------------------------------------------------------

    def in_control(self) -> bool:
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

    # -- acting -----------------------------------------------------------------------------

    def act(self, act: Action, t_s: float) -> None:
        """Carry out one of the offboard state machine's actions on the link."""
        assert self.link is not None
        try:
            if act.kind == "arm":
                self.link.send_arm(True)
            elif act.kind == "set_mode":
                self.link.send_set_mode(act.main_mode, act.sub_mode)
            elif act.kind == "stop_stream":
                return
        except NoPeerError:
            return
        log.info("offboard: %s (%s) at t=%.2f s", act.kind, act.reason, t_s)

    def log_offboard(self, before: OffboardPhase) -> None:
        """Log the offboard phase's change since ``before``, if any, and a newly held-back
        request (its reason once, as a WARNING)."""
        held = self.offboard.held
        if held != self._held_logged:
            self._held_logged = held
            if held is not None:
                log.warning("%s", held)
                if self.records is not None:
                    self.records.text(TOPIC_OFFBOARD, held, level="WARNING", name="offboard")
        if self.offboard.phase is not before and self.records is not None:
            _, phase, reason = self.offboard.transitions[-1]
            log.info("offboard %s -> %s: %s", before.value, phase.value, reason)
            self.records.text(TOPIC_OFFBOARD, f"{before.value} -> {phase.value}: {reason}",
                              level="INFO", name="offboard")
