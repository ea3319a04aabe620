"""What the companion sends: the attitude setpoint, commands, TIMESYNC, its HEARTBEAT.

:class:`LinkCommands` builds each message with the link's encoder (our ids, signing) and
sends it with :meth:`~companion.link.link.MavlinkLink.send`; the checks that keep a command
built from bad data off the wire are here (a non-finite or non-unit quaternion, a thrust
outside [0, 1]).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.link import wire
from companion.link.errors import LinkError
from companion.link.px4 import (
    ARM_FORCE_MAGIC,
    ATTITUDE_THRUST_TYPE_MASK,
    MAV_AUTOPILOT_INVALID,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_STATE_ACTIVE,
    MAV_TYPE_ONBOARD_CONTROLLER,
)
from companion.link.sending import LinkSender

_ATTITUDE_TARGET = mavlink2.MAVLink_set_attitude_target_message
_TIMESYNC = mavlink2.MAVLink_timesync_message
_SETPOINT_ID, _TIMESYNC_ID = _ATTITUDE_TARGET.id, _TIMESYNC.id
_SETPOINT_NAME, _TIMESYNC_NAME = _ATTITUDE_TARGET.msgname, _TIMESYNC.msgname
_pack_setpoint, _pack_timesync = wire.SETPOINT_PAYLOAD.pack, wire.TIMESYNC_PAYLOAD.pack


def _unit_setpoint(q_wxyz: Sequence[float], thrust_norm: float) -> tuple[list[float], float]:
    """The checked setpoint: ``q_wxyz`` normalised (norm within 10 % of 1, finite) and the
    thrust in [0, 1]; a LinkError names what is wrong."""
    q = [float(x) for x in q_wxyz]
    thrust = float(thrust_norm)
    if len(q) != 4 or not all(math.isfinite(x) for x in q):
        raise LinkError(f"attitude setpoint q_wxyz must be 4 finite numbers, got {q_wxyz!r}")
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)  # the sum's order of sum(x * x for x in q)
    if not 0.9 <= n <= 1.1:
        raise LinkError(f"attitude setpoint quaternion norm {n:.3f} is not ~1")
    if not (math.isfinite(thrust) and 0.0 <= thrust <= 1.0):
        raise LinkError(f"thrust_norm {thrust_norm!r} not in [0, 1]")
    return [w / n, x / n, y / n, z / n], thrust


class LinkCommands(LinkSender):
    """The messages the companion sends, on top of the link's ``send`` (a mixin of
    :class:`~companion.link.link.MavlinkLink`)."""

    target_system: int
    target_component: int

    def boot_time_ms(self) -> int:
        raise NotImplementedError

    def encode_attitude_target(
        self, q_wxyz: Sequence[float], thrust_norm: float, time_boot_ms: int | None = None
    ) -> Any:
        """SET_ATTITUDE_TARGET with type_mask 7 (attitude + thrust, body rates ignored).

        ``q_wxyz``: attitude of body FRD w.r.t. NED, w,x,y,z (normalised here; norm must be
        within 10 % of 1); ``thrust_norm`` in [0, 1] along body -z.
        """
        q, thrust = _unit_setpoint(q_wxyz, thrust_norm)
        t_ms = self.boot_time_ms() if time_boot_ms is None else time_boot_ms
        return _ATTITUDE_TARGET(t_ms, self.target_system, self.target_component,
                                ATTITUDE_THRUST_TYPE_MASK, q, 0.0, 0.0, 0.0, thrust)

    def send_attitude_target(
        self, q_wxyz: Sequence[float], thrust_norm: float, time_boot_ms: int | None = None
    ) -> bytes:
        """Send SET_ATTITUDE_TARGET (see :meth:`encode_attitude_target`); returns the bytes.

        Every step sends one: its payload is packed straight from the values
        (:meth:`send_payload`, no pymavlink object; the bytes and the logged fields are those
        of :meth:`send` of :meth:`encode_attitude_target`'s message); a signed link and a
        field out of its type's range go through :meth:`send`."""
        q, thrust = _unit_setpoint(q_wxyz, thrust_norm)
        t_ms = self.boot_time_ms() if time_boot_ms is None else time_boot_ms
        ts, tc, mask = self.target_system, self.target_component, ATTITUDE_THRUST_TYPE_MASK
        if type(t_ms) is int and 0 <= t_ms <= 0xFFFFFFFF:
            payload = _pack_setpoint(t_ms, q[0], q[1], q[2], q[3], 0.0, 0.0, 0.0, thrust,
                                     ts, tc, mask)
            raw = self.send_payload(_SETPOINT_ID, _SETPOINT_NAME, wire.SETPOINT_CRC_EXTRA,
                                    payload, {
                                        "time_boot_ms": t_ms, "target_system": ts,
                                        "target_component": tc, "type_mask": mask, "q": q,
                                        "body_roll_rate": 0.0, "body_pitch_rate": 0.0,
                                        "body_yaw_rate": 0.0, "thrust": thrust})
            if raw is not None:
                return raw
        return self.send(_ATTITUDE_TARGET(t_ms, ts, tc, mask, q, 0.0, 0.0, 0.0, thrust))

    def send_command_long(
        self, command: int, params: Sequence[float] = (), confirmation: int = 0
    ) -> bytes:
        """COMMAND_LONG to the target; ``params`` up to 7 values, the rest 0."""
        if len(params) > 7:
            raise LinkError("COMMAND_LONG takes at most 7 params")
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        return self.send(
            self._enc.command_long_encode(
                self.target_system, self.target_component, command, confirmation, *p
            )
        )

    def send_set_mode(self, main_mode: int, sub_mode: int = 0, confirmation: int = 0) -> bytes:
        """MAV_CMD_DO_SET_MODE: param1 = 1 (custom mode enabled), param2 = PX4 main mode,
        param3 = sub mode (e.g. ``send_set_mode(PX4_MAIN_OFFBOARD)``)."""
        return self.send_command_long(
            MAV_CMD_DO_SET_MODE,
            (MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main_mode, sub_mode),
            confirmation,
        )

    def send_arm(self, arm: bool = True, force: bool = False, confirmation: int = 0) -> bytes:
        """MAV_CMD_COMPONENT_ARM_DISARM: param1 1 arm / 0 disarm, param2 21196 forces."""
        return self.send_command_long(
            MAV_CMD_COMPONENT_ARM_DISARM,
            (1.0 if arm else 0.0, float(ARM_FORCE_MAGIC) if force else 0.0),
            confirmation,
        )

    def send_timesync(self, tc1: int, ts1: int) -> bytes:
        """TIMESYNC (#111): a request is ``tc1 = 0, ts1 = local ns``; a reply to the
        autopilot's request is ``tc1 = local ns, ts1`` echoed (docs/reference/wire.md)."""
        tc1, ts1 = int(tc1), int(ts1)
        if -(1 << 63) <= tc1 < 1 << 63 and -(1 << 63) <= ts1 < 1 << 63:
            raw = self.send_payload(_TIMESYNC_ID, _TIMESYNC_NAME, wire.TIMESYNC_CRC_EXTRA,
                                    _pack_timesync(tc1, ts1), {"tc1": tc1, "ts1": ts1})
            if raw is not None:
                return raw
        return self.send(self._enc.timesync_encode(tc1, ts1))

    def send_heartbeat(self) -> bytes:
        """HEARTBEAT as an onboard controller (type 18, autopilot INVALID 8, state ACTIVE)."""
        return self.send(
            self._enc.heartbeat_encode(
                MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE
            )
        )
