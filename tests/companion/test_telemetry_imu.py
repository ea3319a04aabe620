"""HIGHRES_IMU into the telemetry store: the accelerometer sample on the autopilot clock
(``time_usec``, microseconds, where the other streams carry ``time_boot_ms``), only from the
autopilot, in order, finite and plausible; the link delivers it only when the estimator fuses
the accelerometer. Fields as pymavlink decodes them from the wire."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.config import load_config
from companion.control.telemetry import TelemetryStore
from companion.control.timebase import TimeBase
from companion.control.wiring import allow_rules
from companion.link.filters import msgid_of

AUTOPILOT = 1


def _store() -> TelemetryStore:
    return TelemetryStore(target_sysid=2, origin_lat_deg=47.0, origin_lon_deg=8.0,
                          origin_alt_m=400.0, autopilot_sysid=AUTOPILOT)


def _imu(t_us: int, acc: tuple[float, float, float], updated: int = 0b111111,
         sysid: int = AUTOPILOT) -> dict[str, object]:
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
    msg = mavlink2.MAVLink_highres_imu_message(t_us, *acc, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                               0.0, 0.0, 0.0, updated, 0)
    out = mav.parse_char(msg.pack(mav))
    assert out is not None
    return out.to_dict()


def test_samples_are_kept_on_the_autopilot_clock() -> None:
    s, tb = _store(), TimeBase("autopilot")
    for k in range(3):
        f = _imu(37_250_000 + 20_000 * k, (0.1 * k, -0.2, -9.81))
        assert s.ingest("HIGHRES_IMU", f, tb.message_s("HIGHRES_IMU", f, 0), AUTOPILOT)
    assert [a.t_s for a in s.accel] == pytest.approx([37.25, 37.27, 37.29])
    assert s.accel[-1].f_frd_m_s2 == pytest.approx((0.2, -0.2, -9.81))
    # ATTITUDE's time_boot_ms of the same instant maps to the same time
    att = {"time_boot_ms": 37_290}
    assert tb.message_s("ATTITUDE", att, 0) == pytest.approx(37.29)


@pytest.mark.parametrize("case", ["nan", "huge", "order", "sysid", "no_accel"])
def test_bad_samples_are_refused(case: str) -> None:
    s = _store()
    assert s.ingest("HIGHRES_IMU", _imu(1_000_000, (0.0, 0.0, -9.81)), 1.0, AUTOPILOT)
    f, t, sysid = _imu(1_020_000, (0.0, 0.0, -9.81)), 1.02, AUTOPILOT
    if case == "nan":
        f = {**f, "xacc": math.nan}
    elif case == "huge":
        f = {**f, "yacc": 500.0}
    elif case == "order":
        t = 1.0
    elif case == "sysid":
        sysid = 7
    else:
        f = _imu(1_020_000, (0.0, 0.0, -9.81), updated=0b111000)
    assert not s.ingest("HIGHRES_IMU", f, t, sysid)
    assert len(s.accel) == 1 and sum(s.rejected.values()) == 1


def test_the_link_delivers_highres_imu_only_for_the_accelerometer() -> None:
    cfg = load_config()
    mid = msgid_of("HIGHRES_IMU")
    off = allow_rules(cfg)
    on = allow_rules(load_config(overrides=["control.estimator.accelerometer=true"]))
    ap = cfg.mavlink.target_system
    assert not any(r.sysid == ap and mid in (r.msgids() or ()) for r in off)
    assert any(r.sysid == ap and mid in (r.msgids() or ()) for r in on)
