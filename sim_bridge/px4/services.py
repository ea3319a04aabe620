"""The emulated PX4's answers to what a client sends on a vehicle link: setpoints to the commander,
commands (the commander's and the link layer's: REQUEST_MESSAGE, SET_MESSAGE_INTERVAL, ...),
PING, TIMESYNC, and everything else to the ground-station services (parameters, mission,
``sim_bridge.gcs``).

:attr:`Services.handlers` maps a MAVLink message type to its handler
``(link, msg, addr, t_s)``; a new service adds its types there (``services.handlers[...] = fn``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from sim_bridge.link import Address, MavUdpLink
from sim_bridge.px4.modes import ACCEPTED, DENIED, AttitudeTarget
from sim_bridge.px4.streams import (
    AUTOPILOT_VERSION,
    CMD_GET_HOME_POSITION,
    CMD_REQUEST_AUTOPILOT_CAPABILITIES,
    CMD_REQUEST_MESSAGE,
    CMD_SET_MESSAGE_INTERVAL,
    DEFAULT_RATES_HZ,
    HOME_POSITION,
)

if TYPE_CHECKING:
    from sim_bridge.app import SimBridge

log = logging.getLogger(__name__)

Handler = Callable[[MavUdpLink, Any, Address, float], None]

# PX4 parameters that change what the emulated commander does (others are only stored)
_PARAM_FIELDS = {"MPC_THR_HOVER": "hover_thrust", "COM_OF_LOSS_T": "com_of_loss_t_s",
                 "COM_OBL_RC_ACT": "com_obl_rc_act", "COM_DISARM_PRFLT": "com_disarm_prflt_s",
                 "COM_DISARM_LAND": "com_disarm_land_s", "MPC_TILTMAX_AIR": "max_tilt_rad"}


class Services:
    """Dispatches the messages ``sim``'s vehicle links receive (see the module docstring) and
    counts what it handled."""

    def __init__(self, sim: SimBridge) -> None:
        self.sim = sim
        self.setpoints = 0
        self.commands = 0
        self.acks = 0
        self.timesync_replies = 0
        self.timesync_offset_us: float | None = None
        self.timesync_rtt_us: float | None = None
        self.handlers: dict[str, Handler] = {
            "SET_ATTITUDE_TARGET": self._on_setpoint,
            "COMMAND_LONG": self._on_command,
            "COMMAND_INT": self._on_command,
            "PING": self._on_ping,
            "TIMESYNC": self._on_timesync,
        }

    def on_message(self, link: MavUdpLink, msg: Any, addr: Address) -> None:
        """A link's message handler: the registered one, else the ground-station services."""
        handler = self.handlers.get(msg.get_type())
        if handler is None:
            self.sim.gcs.handle(link, msg, addr)
        else:
            handler(link, msg, addr, self.sim.now_s())

    def _on_setpoint(self, link: MavUdpLink, msg: Any, addr: Address, t: float) -> None:
        self.setpoints += 1
        sp = AttitudeTarget(
            type_mask=int(msg.type_mask),
            q_wxyz=(float(msg.q[0]), float(msg.q[1]), float(msg.q[2]), float(msg.q[3])),
            body_rates_rad_s=(float(msg.body_roll_rate), float(msg.body_pitch_rate),
                              float(msg.body_yaw_rate)),
            thrust_norm=float(msg.thrust))
        self.sim.px4.on_attitude_target(t, sp)
        if link.name not in self.sim.raw_counted:
            self.sim.answered(int(msg.time_boot_ms))
        self.sim.note_changes(t)

    def _on_ping(self, link: MavUdpLink, msg: Any, addr: Address, t: float) -> None:
        if msg.target_system == 0 and msg.target_component == 0:
            self.sim.transport.tx(link, link.mav.ping_encode(
                msg.time_usec, msg.seq, msg.get_srcSystem(), msg.get_srcComponent()), addr,
                reply=True)

    def on_param(self, name: str, value: float) -> None:
        """A PARAM_SET changed ``name``: apply it to the commander if it models it."""
        field_name = _PARAM_FIELDS.get(name)
        if field_name is None:
            return
        v: float | int = value
        if name == "COM_OBL_RC_ACT":
            v = int(value)
        elif name == "MPC_TILTMAX_AIR":
            v = math.radians(value)
        px4 = self.sim.px4
        px4.p = dataclasses.replace(px4.p, **{field_name: v})  # type: ignore[arg-type]
        log.info("param %s = %g", name, value)

    def _on_timesync(self, link: MavUdpLink, msg: Any, addr: Address, t: float) -> None:
        """PX4 (mavlink_timesync.cpp): a request (tc1 == 0) is answered with tc1 = own boot
        time in ns and ts1 echoed; an answer to one of our requests (ts1 = our stamp) gives
        PX4's offset sample ``(ts1 + now - 2 tc1) / 2`` and the round trip ``now - ts1``."""
        now_ns = round(self.sim.boot_s(t) * 1e9)
        if msg.tc1 == 0:
            self.sim.transport.tx(link, link.mav.timesync_encode(now_ns, msg.ts1), addr,
                                  reply=True)
            return
        if msg.tc1 > 0 and int(msg.ts1) in self.sim.telemetry.timesync_sent_ns:
            self.sim.telemetry.timesync_sent_ns.pop(int(msg.ts1))
            self.timesync_replies += 1
            self.timesync_offset_us = (msg.ts1 + now_ns - 2 * msg.tc1) / 2 / 1000
            self.timesync_rtt_us = (now_ns - msg.ts1) / 1000

    def _on_command(self, link: MavUdpLink, msg: Any, addr: Address, t: float) -> None:
        self.commands += 1
        cmd = int(msg.command)
        if msg.get_type() == "COMMAND_LONG":
            params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6,
                      msg.param7)
        else:
            params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x),
                      float(msg.y), float(msg.z))
        params = tuple(float(p) for p in params)  # type: ignore[assignment]
        after: int | None = None
        if cmd == CMD_REQUEST_MESSAGE:
            mid = int(params[0]) if math.isfinite(params[0]) else -1
            result = ACCEPTED if mid in DEFAULT_RATES_HZ else DENIED
            after = mid if result == ACCEPTED else None
        elif cmd == CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            result, after = ACCEPTED, AUTOPILOT_VERSION
        elif cmd == CMD_GET_HOME_POSITION:
            result, after = ACCEPTED, HOME_POSITION
        elif cmd == CMD_SET_MESSAGE_INTERVAL:
            streams = self.sim.telemetry.streams[link.name]
            ok = math.isfinite(params[0]) and math.isfinite(params[1]) and streams.set_interval(
                int(params[0]), params[1], t)
            result = ACCEPTED if ok else DENIED
        else:
            res = self.sim.px4.handle_command(t, cmd, params)
            result = res.result
            if res.text:
                log.info("command %d from %d/%d: result %d (%s)", cmd, msg.get_srcSystem(),
                         msg.get_srcComponent(), result, res.text)
        ack = link.mav.command_ack_encode(cmd, result, 0, 0, msg.get_srcSystem(),
                                          msg.get_srcComponent())
        self.sim.transport.tx(link, ack, addr, reply=True)
        self.acks += 1
        if after is not None:
            self.sim.telemetry.send_message(link, after, t, addr, reply=True)
        self.sim.note_changes(t)

