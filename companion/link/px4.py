"""PX4 on the wire: MAVLink constants the companion uses and PX4's custom-mode encoding
(docs/reference/px4-offboard.md; PX4 ``src/modules/commander/px4_custom_mode.h``)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass

from companion.link.errors import LinkError

log = logging.getLogger(__name__)


MAVLINK2_MAGIC = 0xFD
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_CMD_DO_SET_MODE = 176
MAV_CMD_COMPONENT_ARM_DISARM = 400
ARM_FORCE_MAGIC = 21196
#: SET_ATTITUDE_TARGET type_mask: ignore roll/pitch/yaw body rates, use attitude + thrust.
#: Never bit 64 (throttle ignore): PX4 then drops the message (px4-offboard.md).
ATTITUDE_THRUST_TYPE_MASK = 7

# ----------------------------------------------------------------------------------------------
# PX4 modes (px4-offboard.md "HEARTBEAT and mode encoding", commander/px4_custom_mode.h)

PX4_MAIN_MODES: Mapping[int, str] = {
    1: "MANUAL",
    2: "ALTCTL",
    3: "POSCTL",
    4: "AUTO",
    5: "ACRO",
    6: "OFFBOARD",
    7: "STABILIZED",
    8: "RATTITUDE",
    9: "SIMPLE",
    10: "TERMINATION",
    11: "ALTITUDE_CRUISE",
}
PX4_AUTO_SUB_MODES: Mapping[int, str] = {
    1: "READY",
    2: "TAKEOFF",
    3: "LOITER",
    4: "MISSION",
    5: "RTL",
    6: "LAND",
    8: "FOLLOW_TARGET",
    9: "PRECLAND",
    10: "VTOL_TAKEOFF",
    **{10 + i: f"EXTERNAL{i}" for i in range(1, 9)},
}
PX4_POSCTL_SUB_MODES: Mapping[int, str] = {1: "ORBIT", 2: "SLOW"}
PX4_MAIN_OFFBOARD = 6
PX4_MAIN_POSCTL = 3
PX4_MAIN_AUTO = 4
PX4_SUB_AUTO_LOITER = 3


@dataclass(frozen=True)
class Px4Mode:
    """A PX4 custom mode: ``main`` and ``sub`` mode numbers and a name like ``AUTO.LOITER``."""

    main: int
    sub: int
    name: str


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """HEARTBEAT ``custom_mode`` for a PX4 main/sub mode: ``main << 16 | sub << 24``."""
    return (main & 0xFF) << 16 | (sub & 0xFF) << 24


def decode_px4_mode(custom_mode: int) -> Px4Mode:
    """Decode HEARTBEAT ``custom_mode`` (PX4) into main/sub/name; unknown values are named
    ``UNKNOWN(main.sub)``."""
    main = (custom_mode >> 16) & 0xFF
    sub = (custom_mode >> 24) & 0xFF
    base = PX4_MAIN_MODES.get(main)
    if base is None:
        return Px4Mode(main, sub, f"UNKNOWN({main}.{sub})")
    subs = {PX4_MAIN_AUTO: PX4_AUTO_SUB_MODES, PX4_MAIN_POSCTL: PX4_POSCTL_SUB_MODES}.get(main)
    if sub == 0 or subs is None:
        name = base if sub == 0 else f"{base}.{sub}"
    else:
        name = f"{base}.{subs.get(sub, str(sub))}"
    return Px4Mode(main, sub, name)


def px4_mode_by_name(name: str) -> tuple[int, int]:
    """(main, sub) for a name like ``OFFBOARD``, ``POSCTL`` or ``AUTO.LOITER``."""
    base, _, sub_name = name.upper().partition(".")
    mains = {v: k for k, v in PX4_MAIN_MODES.items()}
    if base not in mains:
        raise LinkError(f"unknown PX4 mode {name!r}")
    main = mains[base]
    if not sub_name:
        return main, 0
    subs = {PX4_MAIN_AUTO: PX4_AUTO_SUB_MODES, PX4_MAIN_POSCTL: PX4_POSCTL_SUB_MODES}.get(main, {})
    inv = {v: k for k, v in subs.items()}
    if sub_name not in inv:
        raise LinkError(f"unknown PX4 sub mode {name!r}")
    return main, inv[sub_name]


def is_armed(base_mode: int) -> bool:
    """HEARTBEAT ``base_mode`` armed bit (MAV_MODE_FLAG_SAFETY_ARMED = 128)."""
    return bool(base_mode & MAV_MODE_FLAG_SAFETY_ARMED)

