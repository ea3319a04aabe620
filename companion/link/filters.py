"""What the receive path accepts: the message whitelist per source and the value limits
(non-finite values, quaternion norm, speeds, rates) checked before a frame is used."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.link.errors import LinkError

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# Whitelist and value checks


def msgid_of(name: str) -> int:
    """MAVLink message id for a message name of the common dialect (``ATTITUDE`` -> 30)."""
    mid = getattr(mavlink2, f"MAVLINK_MSG_ID_{name.upper()}", None)
    if mid is None:
        raise LinkError(f"unknown MAVLink message name {name!r}")
    return int(mid)


@dataclass(frozen=True)
class AllowRule:
    """Frames from ``sysid`` (and ``compid``, None = any) with a message in ``msg_names``
    (None = any) are accepted."""

    sysid: int
    compid: int | None = None
    msg_names: frozenset[str] | None = None

    def __post_init__(self) -> None:
        if not 1 <= self.sysid <= 255:
            raise LinkError(f"AllowRule.sysid {self.sysid} not in 1..255")
        if self.msg_names is not None:
            for n in self.msg_names:
                msgid_of(n)

    def msgids(self) -> frozenset[int] | None:
        return None if self.msg_names is None else frozenset(msgid_of(n) for n in self.msg_names)


#: What the companion needs from the autopilot (plus a few harmless status messages).
AUTOPILOT_TELEMETRY: frozenset[str] = frozenset(
    {
        "HEARTBEAT",
        "SYS_STATUS",
        "ATTITUDE",
        "ATTITUDE_QUATERNION",
        "LOCAL_POSITION_NED",
        "EXTENDED_SYS_STATE",
        "COMMAND_ACK",
        "STATUSTEXT",
        "ATTITUDE_TARGET",
        "ALTITUDE",
        "GLOBAL_POSITION_INT",
        "HOME_POSITION",
        "AUTOPILOT_VERSION",
        "TIMESYNC",
        "SYSTEM_TIME",  # its Unix time anchors `companion log export --tlog`
        "PARAM_VALUE",  # the vehicle's limits (companion/link/params.py)
    }
)


def default_allow_rules(
    autopilot_sysid: int, autopilot_compid: int, agv_sysid: int, agv_compid: int | None,
    extra_autopilot: Sequence[str] = (),
) -> tuple[AllowRule, ...]:
    """Autopilot telemetry from (sysid, compid) plus FOLLOW_TARGET (and HEARTBEAT) from the AGV.
    ``autopilot_compid`` 0 means any component of the autopilot's system. ``extra_autopilot``:
    more autopilot messages to deliver (HIGHRES_IMU when the estimator uses the
    accelerometer; otherwise PX4's 50 Hz stream is counted as unused and dropped)."""
    return (
        AllowRule(autopilot_sysid, autopilot_compid or None,
                  AUTOPILOT_TELEMETRY | frozenset(extra_autopilot)),
        AllowRule(agv_sysid, agv_compid or None, frozenset({"FOLLOW_TARGET", "HEARTBEAT"})),
    )


#: Fields that legitimately carry NaN ("unset") per message.
DEFAULT_NAN_ALLOWED: Mapping[str, frozenset[str]] = {
    "COMMAND_LONG": frozenset(f"param{i}" for i in range(1, 8)),
    "COMMAND_INT": frozenset(f"param{i}" for i in range(1, 5)),
    "FOLLOW_TARGET": frozenset({"position_cov"}),  # others: see est_capabilities below
    "ATTITUDE_QUATERNION": frozenset({"repr_offset_q"}),
    "ALTITUDE": frozenset(
        {
            "altitude_monotonic",
            "altitude_amsl",
            "altitude_local",
            "altitude_relative",
            "altitude_terrain",
            "bottom_clearance",
        }
    ),
    "HOME_POSITION": frozenset({"q", "approach_x", "approach_y", "approach_z"}),
    # an INT32 travels byte-wise in the float: some bit patterns are NaN (params.py decodes)
    "PARAM_VALUE": frozenset({"param_value"}),
}
_FT_CAP_FIELDS = {0: ("alt",), 1: ("vel",), 2: ("acc",), 3: ("attitude_q", "rates")}


@dataclass(frozen=True)
class ValueLimits:
    """Plausibility bounds on received values. A frame outside them is dropped and counted."""

    quat_norm_tol: float = 1e-2
    max_speed_m_s: float = 100.0
    max_rate_rad_s: float = 50.0
    nan_allowed: Mapping[str, frozenset[str]] = field(
        default_factory=lambda: dict(DEFAULT_NAN_ALLOWED)
    )


def _all_finite(fields: Mapping[str, Any], skip: frozenset[str] | set[str]) -> bool:
    # one sum per field: NaN and inf survive a sum, so a finite sum clears every float in it
    # (the rare non-finite sum of finite huge values is then checked value by value)
    for fname, v in fields.items():
        if fname in skip:
            continue
        if isinstance(v, float):
            if not math.isfinite(v):
                return False
        elif isinstance(v, list):
            xs = [x for x in v if isinstance(x, float)]
            if xs and not math.isfinite(sum(xs)) and not all(math.isfinite(x) for x in xs):
                return False
    return True


def check_values(msg: Any, limits: ValueLimits) -> str | None:
    """:func:`check_fields` of a pymavlink message."""
    from companion.link.messages import message_fields

    return check_fields(msg.get_type(), message_fields(msg), limits)


def check_fields(name: str, fields: Mapping[str, Any], limits: ValueLimits,
                 all_finite: bool = False) -> str | None:
    """Reason a decoded message (``fields`` as :func:`~companion.link.messages.message_fields`
    gives them) is implausible (``non_finite``, ``quaternion_norm``, ``speed``,
    ``angular_rate``), or None when it is fine. ``all_finite``: the caller already knows
    every float of it is finite (:func:`companion.link.wire.decode_checked`)."""
    if all_finite:
        return _plausible(name, fields, limits)
    allowed: frozenset[str] | set[str] = limits.nan_allowed.get(name, frozenset())
    if name == "FOLLOW_TARGET":
        caps = int(fields["est_capabilities"])
        allowed = set(allowed)
        for bit, names in _FT_CAP_FIELDS.items():
            if not caps & (1 << bit):
                allowed.update(names)
    if not _all_finite(fields, allowed):
        return "non_finite"
    return _plausible(name, fields, limits)


def _plausible(name: str, f: Mapping[str, Any], limits: ValueLimits) -> str | None:
    def qbad(q: Sequence[float]) -> bool:
        return abs(math.sqrt(sum(x * x for x in q)) - 1.0) > limits.quat_norm_tol

    def too_fast(v: Sequence[float], lim: float) -> bool:
        return math.sqrt(sum(x * x for x in v)) > lim

    if name == "ATTITUDE_QUATERNION":
        if qbad((f["q1"], f["q2"], f["q3"], f["q4"])):
            return "quaternion_norm"
        if too_fast((f["rollspeed"], f["pitchspeed"], f["yawspeed"]), limits.max_rate_rad_s):
            return "angular_rate"
    elif name == "ATTITUDE":
        if too_fast((f["rollspeed"], f["pitchspeed"], f["yawspeed"]), limits.max_rate_rad_s):
            return "angular_rate"
    elif name == "ATTITUDE_TARGET" and qbad(f["q"]):
        return "quaternion_norm"
    elif name == "LOCAL_POSITION_NED":
        if too_fast((f["vx"], f["vy"], f["vz"]), limits.max_speed_m_s):
            return "speed"
    elif name == "FOLLOW_TARGET":
        caps = int(f["est_capabilities"])
        if caps & 2 and too_fast(f["vel"], limits.max_speed_m_s):
            return "speed"
        if caps & 8:
            if qbad(f["attitude_q"]):
                return "quaternion_norm"
            if too_fast(f["rates"], limits.max_rate_rad_s):
                return "angular_rate"
    return None
