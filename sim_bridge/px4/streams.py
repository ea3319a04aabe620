"""The MAVLink messages the emulated PX4 streams, their default rates (the emulator's own and
PX4's "onboard" / "normal" link modes) and the per-link schedule that ``SET_MESSAGE_INTERVAL``
changes."""

from __future__ import annotations

import math

# MAVLink message ids the emulator streams or answers
HEARTBEAT = 0
SYS_STATUS = 1
SYSTEM_TIME = 2
ATTITUDE = 30
ATTITUDE_QUATERNION = 31
LOCAL_POSITION_NED = 32
HIGHRES_IMU = 105
SET_ATTITUDE_TARGET = 82
ATTITUDE_TARGET = 83
# ATTITUDE, ATTITUDE_QUATERNION, LOCAL_POSITION_NED, HIGHRES_IMU: what a telemetry fault hits
STATE_STREAMS = frozenset({30, 31, 32, 105})
GLOBAL_POSITION_INT = 33
TIMESYNC = 111
AUTOPILOT_VERSION = 148
HOME_POSITION = 242
EXTENDED_SYS_STATE = 245

# MAV_CMD answered by the link layer (not the commander)
CMD_REQUEST_MESSAGE = 512
CMD_SET_MESSAGE_INTERVAL = 511
CMD_REQUEST_AUTOPILOT_CAPABILITIES = 520
CMD_GET_HOME_POSITION = 410

# Default stream rates (Hz), like a PX4 "onboard" MAVLink instance; 0 = only on request
DEFAULT_RATES_HZ: dict[int, float] = {
    HEARTBEAT: 1.0,
    SYS_STATUS: 2.0,
    ATTITUDE_QUATERNION: 50.0,
    ATTITUDE: 25.0,
    LOCAL_POSITION_NED: 30.0,
    HIGHRES_IMU: 50.0,
    ATTITUDE_TARGET: 10.0,
    GLOBAL_POSITION_INT: 10.0,
    EXTENDED_SYS_STATE: 5.0,
    HOME_POSITION: 0.0,
    AUTOPILOT_VERSION: 0.0,
    SYSTEM_TIME: 0.0,
    TIMESYNC: 0.0,
}

# PX4's own defaults (src/modules/mavlink/mavlink_main.cpp, configure_streams_to_default) for
# the messages the emulator implements: mode "onboard" (the offboard API link, SITL -m onboard)
# and mode "normal" (the GCS link). HEARTBEAT is always 1 Hz.
PX4_ONBOARD_RATES_HZ: dict[int, float] = {
    HEARTBEAT: 1.0,
    TIMESYNC: 10.0,
    HIGHRES_IMU: 50.0,
    LOCAL_POSITION_NED: 30.0,
    ATTITUDE: 100.0,
    ATTITUDE_QUATERNION: 50.0,
    ATTITUDE_TARGET: 10.0,
    EXTENDED_SYS_STATE: 5.0,
    GLOBAL_POSITION_INT: 50.0,
    HOME_POSITION: 0.5,
    SYS_STATUS: 5.0,
    SYSTEM_TIME: 1.0,
    AUTOPILOT_VERSION: 0.0,
}
PX4_NORMAL_RATES_HZ: dict[int, float] = {
    HEARTBEAT: 1.0,
    ATTITUDE: 15.0,
    ATTITUDE_TARGET: 2.0,
    EXTENDED_SYS_STATE: 1.0,
    GLOBAL_POSITION_INT: 5.0,
    HOME_POSITION: 0.5,
    LOCAL_POSITION_NED: 1.0,
    SYS_STATUS: 1.0,
    ATTITUDE_QUATERNION: 0.0,
    HIGHRES_IMU: 0.0,
    TIMESYNC: 0.0,
    SYSTEM_TIME: 0.0,
    AUTOPILOT_VERSION: 0.0,
}
FLIGHT_SW_VERSION = (1 << 24) | (16 << 16) | (0 << 8) | 255  # v1.16.0 official
# MAVLINK2, COMMAND_INT, SET_ATTITUDE_TARGET, SET_POSITION_TARGET_LOCAL_NED, MISSION_INT,
# PARAM_ENCODE_BYTEWISE (integer parameters travel byte-wise, as PX4's do)
CAPABILITIES = 8192 | 8 | 64 | 128 | 4 | 16


class Streams:
    """Per-link stream schedule in boot time (s)."""

    def __init__(self, rates_hz: dict[int, float] | None = None) -> None:
        self.rates_hz = DEFAULT_RATES_HZ if rates_hz is None else rates_hz
        self.interval_s: dict[int, float | None] = {
            mid: (1.0 / hz if hz > 0 else None) for mid, hz in self.rates_hz.items()}
        self.next_s: dict[int, float] = dict.fromkeys(self.rates_hz, 0.0)

    def set_interval(self, msgid: int, interval_us: float, now_s: float) -> bool:
        if msgid not in self.rates_hz:
            return False
        if interval_us == 0:  # default rate
            hz = self.rates_hz[msgid]
            self.interval_s[msgid] = 1.0 / hz if hz > 0 else None
        elif interval_us < 0:
            self.interval_s[msgid] = None
        else:
            self.interval_s[msgid] = interval_us * 1e-6
        self.next_s[msgid] = now_s
        return True

    def next_due_s(self) -> float:
        """Boot time of the next message due on this link (``inf``: none streams)."""
        return min((self.next_s[mid] for mid, iv in self.interval_s.items() if iv is not None),
                   default=math.inf)

    def due(self, now_s: float) -> list[int]:
        out = []
        for mid, iv in self.interval_s.items():
            if iv is None or now_s + 1e-9 < self.next_s[mid]:
                continue
            out.append(mid)
            # no catch-up bursts: the next one is one interval after now (or the schedule)
            self.next_s[mid] = max(self.next_s[mid] + iv, now_s + 0.5 * iv)
        return out

