"""Both of PX4's attitude messages feed one attitude history.

PX4's onboard MAVLink mode streams the same attitude estimate as ATTITUDE (100 Hz, Euler angles)
and ATTITUDE_QUATERNION (50 Hz). Using both halves the interpolation interval for the attitude
at a frame's capture time and makes the "now" of the latency compensation (the newest attitude
or position stamp) up to 10 ms fresher. Checked against the real pymavlink wire format: the
fields are taken from decoded MAVLink messages.
"""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from companion.control.telemetry import TelemetryStore
from companion.core.geometry import euler_zyx_from_quat, quat_from_euler_zyx

AUTOPILOT = 1


def _store() -> TelemetryStore:
    return TelemetryStore(target_sysid=2, origin_lat_deg=47.0, origin_lon_deg=8.0,
                          origin_alt_m=400.0, autopilot_sysid=AUTOPILOT)


def _wire(msg: mavlink2.MAVLink_message) -> dict[str, object]:
    """Encode and decode ``msg`` with pymavlink; the fields as the link hands them over."""
    mav = mavlink2.MAVLink(None, srcSystem=AUTOPILOT, srcComponent=1)
    out = mav.parse_char(msg.pack(mav))
    assert out is not None
    return out.to_dict()


def _attitude(t_ms: int, roll: float, pitch: float, yaw: float, yawspeed: float) -> dict:
    return _wire(mavlink2.MAVLink_attitude_message(t_ms, roll, pitch, yaw, 0.0, 0.0, yawspeed))


def _attitude_q(t_ms: int, roll: float, pitch: float, yaw: float, yawspeed: float) -> dict:
    q = quat_from_euler_zyx(roll, pitch, yaw)
    return _wire(mavlink2.MAVLink_attitude_quaternion_message(
        t_ms, *(float(x) for x in q), 0.0, 0.0, yawspeed))


def test_attitude_euler_lands_in_the_history_as_the_same_rotation() -> None:
    store = _store()
    assert store.ingest("ATTITUDE", _attitude(10, 0.1, -0.2, 2.5, 0.3), 0.01, AUTOPILOT)
    s = store.attitude[-1]
    rpy = euler_zyx_from_quat(s.q_wxyz)
    assert np.allclose(rpy, (0.1, -0.2, 2.5), atol=1e-6)  # float32 on the wire
    assert math.isclose(s.yaw_rate_rad_s, 0.3, rel_tol=1e-6)
    assert store.newest_autopilot_s() == 0.01


def test_both_messages_interleave_and_the_newest_stamp_is_now() -> None:
    """100 Hz ATTITUDE between 50 Hz ATTITUDE_QUATERNION: one history, ordered, no duplicate
    instants, and the interpolation between two ATTITUDE samples is exact for a steady turn."""
    store = _store()
    for k in range(11):  # 0.00 .. 0.10 s, yaw turning at 1 rad/s
        t = 0.01 * k
        if k % 2 == 0:
            assert store.ingest("ATTITUDE_QUATERNION", _attitude_q(10 * k, 0.0, 0.0, t, 1.0), t,
                                AUTOPILOT)
        assert store.ingest("ATTITUDE", _attitude(10 * k, 0.0, 0.0, t, 1.0), t, AUTOPILOT)
    stamps = [s.t_s for s in store.attitude]
    assert stamps == sorted(stamps) and len(stamps) == len(set(stamps)) == 11
    assert store.newest_autopilot_s() == stamps[-1]
    mid = store.attitude_at(0.095)
    assert mid is not None
    assert math.isclose(euler_zyx_from_quat(mid.q_wxyz)[2], 0.095, abs_tol=1e-6)
    assert not store.rejected


def test_an_older_attitude_sample_is_counted_and_not_used() -> None:
    store = _store()
    assert store.ingest("ATTITUDE", _attitude(20, 0.0, 0.0, 0.2, 0.0), 0.02, AUTOPILOT)
    assert not store.ingest("ATTITUDE_QUATERNION", _attitude_q(10, 0.0, 0.0, 0.1, 0.0), 0.01,
                            AUTOPILOT)
    assert store.rejected == {"ATTITUDE_QUATERNION out of order": 1}
    assert [s.t_s for s in store.attitude] == [0.02]


def test_bad_attitude_is_refused_with_a_reason_and_loses_nothing() -> None:
    store = _store()
    assert store.ingest("ATTITUDE", _attitude(10, 0.0, 0.1, 0.0, 0.0), 0.01, AUTOPILOT)
    assert not store.ingest("ATTITUDE", _attitude(20, float("nan"), 0.0, 0.0, 0.0), 0.02,
                            AUTOPILOT)
    assert not store.ingest("ATTITUDE", {"roll": 0.0, "pitch": 0.0}, 0.03, AUTOPILOT)
    assert store.rejected == {"ATTITUDE non-finite": 1, "ATTITUDE malformed": 1}
    assert [s.t_s for s in store.attitude] == [0.01]
