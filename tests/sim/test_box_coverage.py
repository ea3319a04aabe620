"""The box's coverages (``target._coverages``) equal the two-polygon form they replaced:
``h = coverage(hull)``, ``t = min(coverage(top), h)``, to the bit, for boxes seen from many
poses (the top's edges shared with the silhouette are not computed twice)."""

from __future__ import annotations

import math

import cv2
import numpy as np

from sim_bridge.camera import Camera
from sim_bridge.camera.scene import coverage, edge_lines
from sim_bridge.camera.scene import roi as roi_of
from sim_bridge.camera.target import _coverages
from sim_bridge.physics.agv import AgvState
from sim_bridge.physics.vehicle import quat_from_euler


def _boxes(n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """(hull, top) in canvas pixels of the paper camera's box over ``n`` random poses."""
    cam = Camera(2.8e-3, 5.04e-6, 1000, 1000)
    rng = np.random.default_rng(3)
    out = []
    while len(out) < n:
        agv = AgvState(t_s=0.0, pos_ned_m=np.array([1.0, 2.0, -0.3]),
                       vel_ned_m_s=np.zeros(3), acc_ned_m_s2=np.zeros(3),
                       yaw_rad=float(rng.uniform(-3, 3)),
                       yaw_rate_rad_s=0.0)
        pos = agv.pos_ned_m + np.array([*rng.uniform(-0.8, 0.8, 2), -rng.uniform(1.2, 4.0)])
        q = quat_from_euler(*rng.uniform(-0.3, 0.3, 2), float(rng.uniform(-3, 3)))
        r, t = cam.pose(pos, q)
        top, bottom, _ = cam.agv_points(agv)
        px = cam.lens.project(np.vstack([top, bottom]), r, t)
        hull = px[cv2.convexHull(px.astype(np.float32), returnPoints=False).ravel()]
        if roi_of(hull, 1000, 1000) is not None:
            out.append((hull, px[:4]))
    return out


def test_coverages_equal_the_two_polygon_form() -> None:
    shared = 0
    for hull, top in _boxes(150):
        roi = roi_of(hull, 1000, 1000)
        assert roi is not None
        h_ref = coverage(hull, roi)
        t_ref = np.minimum(coverage(top, roi), h_ref)
        h, t = _coverages(hull, top, roi)
        assert t is not None
        np.testing.assert_array_equal(h, h_ref)
        np.testing.assert_array_equal(t, t_ref)
        assert h.dtype == t.dtype == np.float32
        shared += len(set(edge_lines(top)) & set(edge_lines(hull)))
        h_only, none = _coverages(hull, None, roi)
        assert none is None
        np.testing.assert_array_equal(h_only, h_ref)
    assert shared > 150  # the shortcut is taken (most top edges are silhouette edges)


def test_degenerate_top_covers_nothing() -> None:
    hull = np.array([[10.0, 10.0], [40.0, 12.0], [38.0, 35.0], [9.0, 30.0]])
    top = np.array([[20.0, 20.0]] * 4)  # all corners at one point: no edge
    roi = roi_of(hull, 100, 100)
    assert roi is not None
    h, t = _coverages(hull, top, roi)
    assert t is not None and not t.any()
    np.testing.assert_array_equal(h, coverage(hull, roi))
    assert math.isclose(float(h.max()), 1.0)
