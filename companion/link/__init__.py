"""The MAVLink link to the autopilot (PX4 or the emulator).

- :mod:`~companion.link.endpoints`: connection strings (UDP, TCP, serial) -> :class:`Endpoint`
- :mod:`~companion.link.px4`: PX4 custom-mode encoding and the MAVLink constants used
- :mod:`~companion.link.filters`: whitelist per source and value limits (receive path)
- :mod:`~companion.link.signing`: MAVLink 2 signing keys and signature verification
- :mod:`~companion.link.messages`: accepted and sent frames as values
- :mod:`~companion.link.transport`: UDP sockets (batched reads, per-source sockets), TCP, serial
- :mod:`~companion.link.receive`: the receive path (what is accepted, what is rejected and why)
- :mod:`~companion.link.commands`: what the companion sends (setpoint, commands, heartbeat)
- :mod:`~companion.link.link`: :class:`MavlinkLink`, the asyncio link tying them together
"""

from __future__ import annotations

from companion.link.endpoints import DEFAULT_SERIAL_BAUD, Endpoint, parse_connection_string
from companion.link.errors import ConnectionStringError, LinkError, NoPeerError
from companion.link.filters import (
    AUTOPILOT_TELEMETRY,
    DEFAULT_NAN_ALLOWED,
    AllowRule,
    ValueLimits,
    check_values,
    default_allow_rules,
    msgid_of,
)
from companion.link.link import MavlinkLink
from companion.link.messages import Received, Sent, message_fields
from companion.link.px4 import (
    ARM_FORCE_MAGIC,
    ATTITUDE_THRUST_TYPE_MASK,
    MAV_AUTOPILOT_INVALID,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    MAV_STATE_ACTIVE,
    MAV_TYPE_ONBOARD_CONTROLLER,
    MAVLINK2_MAGIC,
    PX4_AUTO_SUB_MODES,
    PX4_MAIN_AUTO,
    PX4_MAIN_MODES,
    PX4_MAIN_OFFBOARD,
    PX4_MAIN_POSCTL,
    PX4_POSCTL_SUB_MODES,
    PX4_SUB_AUTO_LOITER,
    Px4Mode,
    decode_px4_mode,
    is_armed,
    px4_custom_mode,
    px4_mode_by_name,
)
from companion.link.signing import SignatureVerifier, load_signing_key, signing_timestamp_now

__all__ = [
    "ARM_FORCE_MAGIC",
    "ATTITUDE_THRUST_TYPE_MASK",
    "AUTOPILOT_TELEMETRY",
    "DEFAULT_NAN_ALLOWED",
    "DEFAULT_SERIAL_BAUD",
    "MAVLINK2_MAGIC",
    "MAV_AUTOPILOT_INVALID",
    "MAV_CMD_COMPONENT_ARM_DISARM",
    "MAV_CMD_DO_SET_MODE",
    "MAV_MODE_FLAG_CUSTOM_MODE_ENABLED",
    "MAV_MODE_FLAG_SAFETY_ARMED",
    "MAV_STATE_ACTIVE",
    "MAV_TYPE_ONBOARD_CONTROLLER",
    "PX4_AUTO_SUB_MODES",
    "PX4_MAIN_AUTO",
    "PX4_MAIN_MODES",
    "PX4_MAIN_OFFBOARD",
    "PX4_MAIN_POSCTL",
    "PX4_POSCTL_SUB_MODES",
    "PX4_SUB_AUTO_LOITER",
    "AllowRule",
    "ConnectionStringError",
    "Endpoint",
    "LinkError",
    "MavlinkLink",
    "NoPeerError",
    "Px4Mode",
    "Received",
    "Sent",
    "SignatureVerifier",
    "ValueLimits",
    "check_values",
    "decode_px4_mode",
    "default_allow_rules",
    "is_armed",
    "load_signing_key",
    "message_fields",
    "msgid_of",
    "parse_connection_string",
    "px4_custom_mode",
    "px4_mode_by_name",
    "signing_timestamp_now",
]
