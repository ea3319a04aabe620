"""A camera turned about its optical axis (``camera.mount_rpy_rad = [0, 0, yaw]``).

Real drones often carry the downward camera turned by 90 degrees (image "up" to the side) or
by some other angle. The emulator renders the mount with its own geometry (``cv2.projectPoints``
through its own camera pose); the companion detects the target in those pixels and re-projects
the points into body axes with its own rotation. Scored against the true features of the scene
(the AGV's top centre in the vehicle's virtual frame, computed from the poses alone): the
companion configured with the mount measures them; configured without it, it does not (the
check can fail). A tilted or offset camera is refused with a clear error.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.config import load_config
from companion.core.errors import ParamError
from companion.core.geometry import (
    camera_to_body_rotation,
    quat_from_euler_zyx,
    rectangle_corners_m,
)
from companion.core.moments import a_star
from companion.core.state import build_error_state
from companion.perception import Perception
from companion.report.figures import true_features
from sim_bridge.camera import Camera
from sim_bridge.physics.agv import AgvState

CFG = load_config()
CAM = CFG.camera
Z_STAR = CFG.rmpc.desired_depth_m


def _scene(mount_yaw: float, roll: float, pitch: float, yaw: float,
           rel_ned: tuple[float, float], agv_yaw: float) -> tuple[np.ndarray, dict]:
    """The emulator's frame of the AGV seen from a vehicle at ``rel_ned`` (m) from its top
    centre, 2 m above it, and the truth record of the same instant."""
    cam = Camera(CAM.focal_length_m, CAM.pixel_size_m, CAM.width_px, CAM.height_px,
                 mount_rpy_rad=(0.0, 0.0, mount_yaw), target_length_m=CFG.target.length_m,
                 target_width_m=CFG.target.width_m, target_height_m=CFG.target.height_m)
    agv = AgvState(0.0, np.array([3.0, -1.0, 0.0]), np.zeros(3), np.zeros(3), agv_yaw, 0.0)
    uav = np.array([3.0 + rel_ned[0], -1.0 + rel_ned[1], -Z_STAR])
    q = quat_from_euler_zyx(roll, pitch, yaw)
    frame = cam.render(uav, q, agv)
    assert frame.target_in_image
    truth = {"uav": {"pos_ned_m": uav.tolist(), "q_wxyz": q.tolist()},
             "agv": {"pos_ned_m": agv.pos_ned_m.tolist(), "yaw_rad": agv_yaw}}
    return frame.image, truth


def _measured(image: np.ndarray, mount_yaw: float, roll: float, pitch: float,
              yaw: float) -> np.ndarray:
    """The companion's ``s_e`` from the pixels, configured with ``mount_yaw``."""
    cam = dataclasses.replace(CAM, mount_rpy_rad=(0.0, 0.0, mount_yaw))
    pr = Perception(cam, CFG.target).process(image)
    assert pr.status == "ok", pr.reason
    a_ref = a_star(rectangle_corners_m(CFG.target.length_m, CFG.target.width_m), Z_STAR,
                   CAM.focal_length_m)
    es = build_error_state(
        pr.points_m, roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw, yaw_rate_rad_s=0.0,
        v_q_ned_m_s=np.zeros(3), v_a_ned_m_s=np.zeros(3), a_a_ned_m_s2=np.zeros(3),
        psidot_a_rad_s=0.0, a_star=a_ref, lam=CAM.focal_length_m,
        cam_to_body=None if mount_yaw == 0.0 else camera_to_body_rotation(cam.mount_rpy_rad))
    return np.asarray(es.eta_e[:4])


def _s4_gap(a: float, b: float) -> float:
    """|a - b| for the rectangle's heading (period pi)."""
    return abs((a - b + math.pi / 2) % math.pi - math.pi / 2)


@pytest.mark.parametrize("mount_yaw", [math.pi / 2, -math.pi / 2, math.pi, 0.6])
def test_a_turned_camera_measures_the_true_features(mount_yaw: float) -> None:
    roll, pitch, yaw = 0.08, -0.05, 0.4
    image, truth = _scene(mount_yaw, roll, pitch, yaw, (-0.25, 0.15), agv_yaw=0.9)
    want = true_features(truth, Z_STAR)
    assert want is not None
    got = _measured(image, mount_yaw, roll, pitch, yaw)
    # detection on rendered pixels: measured within 1e-4 here; 1e-3 is 2 mm at 2 m
    np.testing.assert_allclose(got[:3], want[:3], atol=1e-3)
    assert _s4_gap(got[3], want[3]) < 0.005
    # the same frame taken for the paper's mount is a different (wrong) state
    wrong = _measured(image, 0.0, roll, pitch, yaw)
    assert np.linalg.norm(wrong[:2] - want[:2]) > 0.05 or _s4_gap(wrong[3], want[3]) > 0.3


def test_the_paper_mount_is_unchanged() -> None:
    roll, pitch, yaw = -0.06, 0.07, -1.1
    image, truth = _scene(0.0, roll, pitch, yaw, (0.2, 0.3), agv_yaw=-0.4)
    want = true_features(truth, Z_STAR)
    assert want is not None
    got = _measured(image, 0.0, roll, pitch, yaw)
    np.testing.assert_allclose(got[:3], want[:3], atol=1e-3)
    assert _s4_gap(got[3], want[3]) < 0.005


@pytest.mark.parametrize(("field", "value", "words"), [
    ("mount_rpy_rad", (0.1, 0.0, 0.0), "tilted camera"),
    ("mount_rpy_rad", (0.0, -0.2, 1.57), "tilted camera"),
    ("mount_offset_m", (0.05, 0.0, 0.0), "optical centre"),
    ("mount_rpy_rad", (0.0, 0.0, float("nan")), "finite"),
])
def test_an_unsupported_mount_is_refused_with_a_reason(field: str, value: tuple,
                                                       words: str) -> None:
    with pytest.raises(ParamError, match=words):
        dataclasses.replace(CAM, **{field: value})
