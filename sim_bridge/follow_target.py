"""The AGV's FOLLOW_TARGET (#144) content (docs/reference/px4-offboard.md, section 5): its NED
state as MAVLink fields, positions as WGS84 lat/lon around a shared local origin.

The local NED frame is the tangent plane at the origin: north/east metres map to latitude and
longitude through the WGS84 meridian and prime-vertical radii of curvature at the origin's
latitude (accurate to well below a centimetre within a few hundred metres of the origin).
Altitude is AMSL: ``origin_alt_m - z``. Pure math; no pymavlink here (the fields are ready for
``mav.follow_target_send(**fields)``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sim_bridge.physics.agv import AgvState

__all__ = ["EST_CAPABILITIES", "follow_target_fields", "latlon_from_ned", "ned_from_latlon"]

# est_capabilities bits: 0 position, 1 velocity, 2 acceleration, 3 attitude + rates.
EST_CAPABILITIES = 0b1111

_WGS84_A_M = 6378137.0
_WGS84_E2 = 6.69437999014e-3


def _radii(lat_deg: float) -> tuple[float, float]:
    """Meridian (north) and prime-vertical (east) radii of curvature (m) at ``lat_deg``."""
    s = math.sin(math.radians(lat_deg))
    w = 1.0 - _WGS84_E2 * s * s
    r_n = _WGS84_A_M * (1.0 - _WGS84_E2) / w**1.5
    r_e = _WGS84_A_M / math.sqrt(w)
    return r_n, r_e


def latlon_from_ned(
    pos_ned_m: Any, origin_lat_deg: float, origin_lon_deg: float, origin_alt_m: float
) -> tuple[float, float, float]:
    """``(lat_deg, lon_deg, alt_amsl_m)`` of a local NED position (m) around the origin."""
    n, e, d = (float(v) for v in np.asarray(pos_ned_m, dtype=float).reshape(3))
    r_n, r_e = _radii(origin_lat_deg)
    lat = origin_lat_deg + math.degrees(n / r_n)
    lon = origin_lon_deg + math.degrees(e / (r_e * math.cos(math.radians(origin_lat_deg))))
    return lat, lon, origin_alt_m - d


def ned_from_latlon(
    lat_deg: float,
    lon_deg: float,
    alt_m: float,
    origin_lat_deg: float,
    origin_lon_deg: float,
    origin_alt_m: float,
) -> np.ndarray:
    """Inverse of :func:`latlon_from_ned`: local NED (3,) metres of a WGS84 position."""
    r_n, r_e = _radii(origin_lat_deg)
    n = math.radians(lat_deg - origin_lat_deg) * r_n
    e = math.radians(lon_deg - origin_lon_deg) * r_e * math.cos(math.radians(origin_lat_deg))
    return np.array([n, e, origin_alt_m - alt_m])


def follow_target_fields(
    state: AgvState,
    t_boot_ms: int,
    origin_lat_deg: float,
    origin_lon_deg: float,
    origin_alt_m: float,
    position_cov: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> dict[str, Any]:
    """FOLLOW_TARGET fields of the AGV ``state`` stamped ``t_boot_ms`` (ms since boot).

    lat/lon in degE7 (rounded), alt AMSL (m), vel/acc NED (m/s, m/s^2), ``attitude_q`` the
    yaw-only quaternion w, x, y, z, ``rates`` ``[0, 0, yaw_rate]`` (rad/s), ``position_cov``
    (eph, epv, unused), ``custom_state`` 0.
    """
    lat, lon, alt = latlon_from_ned(state.pos_ned_m, origin_lat_deg, origin_lon_deg, origin_alt_m)
    half = 0.5 * state.yaw_rad
    return {
        "timestamp": int(t_boot_ms),
        "est_capabilities": EST_CAPABILITIES,
        "lat": round(lat * 1e7),
        "lon": round(lon * 1e7),
        "alt": float(alt),
        "vel": [float(v) for v in state.vel_ned_m_s],
        "acc": [float(v) for v in state.acc_ned_m_s2],
        "attitude_q": [math.cos(half), 0.0, 0.0, math.sin(half)],
        "rates": [0.0, 0.0, float(state.yaw_rate_rad_s)],
        "position_cov": [float(v) for v in position_cov],
        "custom_state": 0,
    }
