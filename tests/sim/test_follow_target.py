"""FOLLOW_TARGET (#144) content: a round trip through pymavlink's MAVLink 2 encoder/decoder,
and the lat/lon <-> local NED conversion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink2

from sim_bridge.follow_target import follow_target_fields, latlon_from_ned, ned_from_latlon
from sim_bridge.physics.agv import AgvState, AgvTrajectory

ORIGIN = (47.397742, 8.545594, 488.0)


def _codec(sysid: int = 42) -> mavlink2.MAVLink:
    mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=1)
    mav.robust_parsing = True
    return mav


@settings(max_examples=100, deadline=None)
@given(t=st.floats(0.0, 251.0), kind=st.sampled_from(["paper", "circle", "figure8", "ramp"]))
def test_round_trip_through_pymavlink(t: float, kind: str) -> None:
    s = AgvTrajectory(kind, speed_scale=10.0 if kind == "ramp" else 1.0, top_z_m=-0.2).state(t)
    fields = follow_target_fields(s, int(t * 1000), *ORIGIN)
    tx, rx = _codec(), _codec(1)
    buf = tx.follow_target_encode(**fields).pack(tx)
    assert buf[0] == 0xFD  # MAVLink 2
    msgs = rx.parse_buffer(buf)
    assert msgs is not None and len(msgs) == 1
    m = msgs[0]
    assert m.get_type() == "FOLLOW_TARGET" and m.get_srcSystem() == 42
    assert m.timestamp == int(t * 1000) and m.est_capabilities == 0b1111
    assert m.custom_state == 0
    np.testing.assert_allclose(m.vel, s.vel_ned_m_s, atol=1e-6)
    np.testing.assert_allclose(m.acc, s.acc_ned_m_s2, atol=1e-6)
    np.testing.assert_allclose(m.rates, [0.0, 0.0, s.yaw_rate_rad_s], atol=1e-6)
    w, x, y, z = m.attitude_q
    assert x == 0.0 and y == 0.0 and w * w + z * z == pytest.approx(1.0, abs=1e-6)
    assert math.atan2(2 * w * z, 1 - 2 * z * z) == pytest.approx(s.yaw_rad, abs=1e-6)
    ned = ned_from_latlon(m.lat * 1e-7, m.lon * 1e-7, m.alt, *ORIGIN)
    np.testing.assert_allclose(ned, s.pos_ned_m, atol=0.01)  # degE7 quantisation: < 1 cm


@settings(max_examples=200, deadline=None)
@given(n=st.floats(-500, 500), e=st.floats(-500, 500), d=st.floats(-50, 5))
def test_latlon_inverse(n: float, e: float, d: float) -> None:
    lat, lon, alt = latlon_from_ned([n, e, d], *ORIGIN)
    np.testing.assert_allclose(ned_from_latlon(lat, lon, alt, *ORIGIN), [n, e, d], atol=1e-9)


def test_latlon_scale_matches_wgs84() -> None:
    # 1 m north / east at the origin: independent check against the ellipsoid's radii.
    a, e2 = 6378137.0, 6.69437999014e-3
    phi = math.radians(ORIGIN[0])
    m_per_deg_lat = math.pi * a * (1 - e2) / (180 * (1 - e2 * math.sin(phi) ** 2) ** 1.5)
    m_per_deg_lon = math.pi * a * math.cos(phi) / (180 * math.sqrt(1 - e2 * math.sin(phi) ** 2))
    lat, lon, alt = latlon_from_ned([100.0, 200.0, -3.0], *ORIGIN)
    assert (lat - ORIGIN[0]) * m_per_deg_lat == pytest.approx(100.0, rel=1e-9)
    assert (lon - ORIGIN[1]) * m_per_deg_lon == pytest.approx(200.0, rel=1e-9)
    assert alt == pytest.approx(491.0)
    # ~111 km per degree of latitude, ~75 km per degree of longitude at 47.4 deg
    assert 111_000 < m_per_deg_lat < 111_300 and 75_000 < m_per_deg_lon < 75_500


def test_fields_of_the_paper_start() -> None:
    s = AgvState(0.0, [0.0, 0.0, 0.0], [0.1, 0.1, 0.0], [0.0, 0.0, 0.0], math.pi / 4, 0.0)
    f = follow_target_fields(s, 1234, *ORIGIN, position_cov=(0.05, 0.1, 0.0))
    assert f["lat"] == round(ORIGIN[0] * 1e7) and f["lon"] == round(ORIGIN[1] * 1e7)
    assert f["alt"] == 488.0 and f["timestamp"] == 1234
    np.testing.assert_allclose(
        f["attitude_q"], [math.cos(math.pi / 8), 0, 0, math.sin(math.pi / 8)], atol=1e-15
    )
    assert f["position_cov"] == [0.05, 0.1, 0.0]
