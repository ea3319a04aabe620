"""A camera like a real one (sim_bridge.camera_model and the renderer's lens and motion blur),
against independent oracles: OpenCV's own undistortion, hand projections, binomial bounds, the
noise model's analytic standard deviation."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from sim_bridge import ConfigError
from sim_bridge.camera import Camera, read_calibration
from sim_bridge.camera_model import CameraTiming, DelayLine, Sensor, line_kernel
from sim_bridge.config import CameraModelConfig, load_config
from sim_bridge.physics.agv import AgvState
from tests.sim.test_camera import (
    LAM,
    PIX,
    _sample,
    agv_state,
    detect_bright_quad,
    match_error,
    quat_wxyz,
)

ROOT = Path(__file__).resolve().parents[2]
CALIB = ROOT / "config" / "camera-distorted.yaml"
W = H = 1000


@pytest.fixture(scope="module")
def lens() -> tuple[np.ndarray, np.ndarray]:
    return read_calibration(CALIB, W, H)


@pytest.fixture(scope="module")
def dcam(lens: tuple[np.ndarray, np.ndarray]) -> Camera:
    k, d = lens
    return Camera(LAM, PIX, W, H, camera_matrix=k, dist_coeffs=d)


def pinhole(k: np.ndarray, p_world: np.ndarray, uav: np.ndarray) -> np.ndarray:
    """Ideal pixels of a level, yaw-0 camera at ``uav`` (body = camera: x fwd, y right,
    z down): col = cx + fx y/z, row = cy - fy x/z (docs/reference/wire.md)."""
    rel = np.atleast_2d(p_world) - uav
    return np.column_stack([k[0, 2] + k[0, 0] * rel[:, 1] / rel[:, 2],
                            k[1, 2] - k[1, 1] * rel[:, 0] / rel[:, 2]])


# ---------------------------------------------------------------- lens distortion
def test_calibration_file_is_opencv_filestorage(lens: tuple[np.ndarray, np.ndarray]) -> None:
    k, d = lens
    assert k.shape == (3, 3) and d.shape == (5,)
    assert d[0] < 0  # barrel
    with pytest.raises(ConfigError, match=r"calibrated at 1000 x 1000"):
        read_calibration(CALIB, 640, 480)
    with pytest.raises(ConfigError, match=r"camera\.calibration_file"):
        read_calibration("nope.yaml", W, H)


def test_distorted_corners_match_projectpoints_and_the_ideal_pinhole(
        dcam: Camera, lens: tuple[np.ndarray, np.ndarray]) -> None:
    """Truth corners = cv2.projectPoints with the distortion; undistorting them gives the hand
    pinhole projection (independent oracle); and the rendered image, undistorted with OpenCV's
    own map (initUndistortRectifyMap, not the renderer's inverse), shows a straight-edged quad
    whose corners are the pinhole projection within 0.5 px."""
    k, d = lens
    uav = np.array([0.0, 0.0, -2.3])
    for ax, ay, yaw in ((1.3, 1.5, 0.3), (-1.2, -1.4, 2.0), (1.2, -1.3, -0.7)):
        agv = agv_state(ax, ay, yaw)
        fr = dcam.render(uav, quat_wxyz(0, 0, 0), agv)
        assert fr.target_in_image
        top = dcam.agv_points(agv)[0]
        ideal = pinhole(k, top, uav)
        # strongly distorted where we look: > 10 px from the pinhole position
        assert np.linalg.norm(fr.corners_px - ideal, axis=1).min() > 10
        np.testing.assert_allclose(dcam.ideal_px(fr.corners_px), ideal, atol=1e-6)
        und = cv2.undistortPoints(fr.corners_px.reshape(-1, 1, 2), k, d, P=k,
                                  criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS,
                                            100, 1e-12)).reshape(-1, 2)
        np.testing.assert_allclose(und, ideal, atol=1e-6)
        m1, m2 = cv2.initUndistortRectifyMap(k, d, None, k, (W, H), cv2.CV_32FC1)
        straight = cv2.remap(fr.image, m1, m2, cv2.INTER_CUBIC)
        assert match_error(detect_bright_quad(straight), ideal) < 0.5


def test_distorted_edges_cross_mid_level_where_projectpoints_puts_them(
        dcam: Camera, lens: tuple[np.ndarray, np.ndarray]) -> None:
    """In the distorted image itself: along each top edge, the profile across the (curved)
    edge crosses the mid level within 0.5 px of cv2.projectPoints' position."""
    k, d = lens
    uav = np.array([0.0, 0.0, -2.3])
    agv = agv_state(1.3, 1.5, 0.3)
    fr = dcam.render(uav, quat_wxyz(0, 0, 0), agv)
    top = dcam.agv_points(agv)[0]
    rvec, _ = cv2.Rodrigues(np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]))
    tvec = -np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]) @ uav
    offs = np.arange(-3.0, 3.0001, 0.05)
    errors = []
    centre = top.mean(axis=0)
    for i in range(4):
        a, b = top[i], top[(i + 1) % 4]
        s = np.linspace(0.15, 0.85, 15)[:, None]
        pts = a + s * (b - a)
        px, _ = cv2.projectPoints(np.vstack([pts, pts + 1e-3 * (b - a)]), rvec, tvec, k, d)
        px = px.reshape(-1, 2)
        p, q = px[:15], px[15:]
        tang = (q - p) / np.linalg.norm(q - p, axis=1, keepdims=True)
        nrm = np.column_stack([-tang[:, 1], tang[:, 0]])
        c_px, _ = cv2.projectPoints(centre[None], rvec, tvec, k, d)
        flip = np.sign(np.sum(nrm * (p - c_px.reshape(2)), axis=1))[:, None]
        nrm = nrm * flip  # outward
        for j in range(15):
            prof = _sample(fr.image, p[j] + offs[:, None] * nrm[j])
            inside = _sample(fr.image, (p[j] - 2.5 * nrm[j])[None])[0]
            beyond = prof[offs >= -0.5]
            outside = beyond.min()
            level = (inside + outside) / 2
            kk = np.nonzero((prof[:-1] >= level) & (prof[1:] < level))[0]
            assert len(kk) >= 1
            k0 = kk[0]
            t = offs[k0] + (prof[k0] - level) / (prof[k0] - prof[k0 + 1]) * 0.05
            errors.append(abs(t))
    assert np.median(errors) < 0.25 and max(errors) < 0.5, (np.median(errors), max(errors))


def test_ideal_camera_without_calibration_is_unchanged() -> None:
    a = Camera(LAM, PIX, 400, 400)
    b = Camera(LAM, PIX, 400, 400, camera_matrix=a.camera_matrix, dist_coeffs=np.zeros(5))
    agv, uav, q = agv_state(0.1, 0.0, 0.3), np.array([0.0, 0.1, -2.0]), quat_wxyz(0, 0, 0.2)
    np.testing.assert_array_equal(a.render(uav, q, agv).image, b.render(uav, q, agv).image)
    assert not a.distorted and not b.distorted


# ---------------------------------------------------------------- motion blur
def test_image_motion_matches_hand_translation() -> None:
    """Level camera 2.3 m above the top: the UAV flying north at 2 m/s for 10 ms moves the
    target 0.02 f / 2.3 px down the image; the AGV driving east at 1 m/s moves it right."""
    cam = Camera(LAM, PIX, W, H)
    f = cam.f_px
    uav, q = np.array([0.0, 0.0, -2.3]), quat_wxyz(0, 0, 0)
    still = AgvState(0.0, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], 0.0, 0.0)
    m = cam.image_motion_px(uav, q, np.array([2.0, 0, 0]), np.zeros(3), still, 0.01)
    np.testing.assert_allclose(m, [0.0, f * 0.02 / 2.3], atol=1e-6)
    east = AgvState(0.0, [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0], 0.0, 0.0)
    m = cam.image_motion_px(uav, q, np.zeros(3), np.zeros(3), east, 0.01)
    np.testing.assert_allclose(m, [f * 0.01 / 2.3, 0.0], atol=1e-6)
    # a pure yaw rate turns the image about the optical axis: the target on the axis stays
    m = cam.image_motion_px(uav, q, np.zeros(3), np.array([0, 0, 1.0]), still, 0.01)
    np.testing.assert_allclose(m, [0.0, 0.0], atol=1e-6)


def test_line_kernel_is_centred_and_normalised() -> None:
    assert line_kernel(0.2, 0.1) is None
    for dx, dy in ((5.0, 0.0), (3.0, 4.0), (-7.0, 2.5), (20.0, -9.0)):
        k = line_kernel(dx, dy)
        assert k is not None
        assert k.sum() == pytest.approx(1.0, abs=1e-5)
        n = k.shape[0]
        rows, cols = np.mgrid[0:n, 0:n] - n // 2
        assert abs(float((k * cols).sum())) < 0.1 and abs(float((k * rows).sum())) < 0.1
        # second moment along the motion: a uniform segment of length L has L^2 / 12
        u = (cols * dx + rows * dy) / math.hypot(dx, dy)
        var = float((k * u * u).sum())
        assert var == pytest.approx(math.hypot(dx, dy) ** 2 / 12, rel=0.35, abs=0.3)


@pytest.mark.parametrize("speed_m_s", [2.0, 8.0])  # 4.8 px (full-frame kernel), 19 px (halves)
def test_motion_blur_spreads_edges_but_keeps_their_mid_level(speed_m_s: float) -> None:
    cam = Camera(LAM, PIX, W, H)
    uav, q = np.array([0.05, -0.1, -2.3]), quat_wxyz(0, 0, 0.4)
    agv = agv_state(0.0, 0.0, 0.4)
    vel = np.array([speed_m_s * math.cos(0.4), speed_m_s * math.sin(0.4), 0.0])  # forward
    sharp = cam.render(uav, q, agv)
    blur = cam.render(uav, q, agv, uav_vel_ned_m_s=vel, uav_rates_frd_rad_s=np.zeros(3),
                      exposure_s=0.01)
    np.testing.assert_array_equal(blur.corners_px, sharp.corners_px)
    length = cam.f_px * speed_m_s * 0.01 / 2.3
    if length < 8:  # the plain detector looks 3 px out: only for a short blur
        assert match_error(detect_bright_quad(blur.image), blur.corners_px) < 0.5
    # front and rear edges (across the motion): the 50 % crossing between levels taken beyond
    # the blur stays on the projected edge; the 10-90 % width grows by about the motion length
    reach = int(length / 2) + 4
    for a, b, outward in ((0, 1, -1), (3, 2, 1)):
        row_edge = (blur.corners_px[a][1] + blur.corners_px[b][1]) / 2
        cols = np.linspace(blur.corners_px[a][0], blur.corners_px[b][0], 9)[2:-2]
        found, widths = [], []
        for c in cols:
            c = round(c)
            r0 = round(row_edge)
            rows = np.arange(r0 - reach - 3, r0 + reach + 4)
            for img, out in ((blur.image, found), (sharp.image, None)):
                prof = img[rows, c].astype(float)
                inside = float(img[r0 - outward * (reach + 2), c])
                outside = float(img[r0 + outward * (reach + 2), c])
                lv = (inside + outside) / 2
                seg = prof if outward > 0 else prof[::-1]
                rr = rows if outward > 0 else rows[::-1]
                k = np.nonzero((seg[:-1] >= lv) & (seg[1:] < lv))[0]
                assert len(k) >= 1
                k0 = k[0]
                cross = rr[k0] + outward * (seg[k0] - lv) / (seg[k0] - seg[k0 + 1])
                lo, hi = min(inside, outside), max(inside, outside)
                w = int(np.sum((prof > lo + 0.1 * (hi - lo)) & (prof < lo + 0.9 * (hi - lo))))
                if out is not None:
                    out.append(cross)
                    widths.append(w)
                else:
                    widths[-1] -= w
        assert abs(float(np.median(found)) - row_edge) < 0.5, (found, row_edge)
        assert float(np.median(widths)) >= 0.6 * length - 1, (widths, length)


# ---------------------------------------------------------------- sensor
def test_noise_on_a_flat_region_matches_read_plus_shot_noise() -> None:
    cfg = CameraModelConfig(read_noise_std_dn=2.0, shot_noise_dn_per_e=0.05)
    sensor = Sensor(cfg, 400, 300, seed=3)
    for level in (30, 120, 235):
        flat = np.full((300, 400), level, np.uint8)
        out = sensor.apply(flat, 0.0).astype(float)
        expect = math.sqrt(4.0 + 0.05 * level + 1 / 12)  # + 8-bit rounding
        assert out.mean() == pytest.approx(level, abs=0.1)
        assert out.std() == pytest.approx(expect, rel=0.05)
    # seeded: same seed, same frames
    again = Sensor(cfg, 400, 300, seed=3)
    a = again.apply(np.full((300, 400), 100, np.uint8), 0.0)
    b = Sensor(cfg, 400, 300, seed=3).apply(np.full((300, 400), 100, np.uint8), 0.0)
    np.testing.assert_array_equal(a, b)


def test_brightness_drift_is_slow_seeded_and_saturates() -> None:
    cfg = CameraModelConfig(brightness_drift_std=0.1, brightness_drift_tau_s=5.0)
    s = Sensor(cfg, 8, 8, seed=1)
    gains = np.array([s.advance(0.05 * i) for i in range(20000)])
    logs = np.log(gains)
    assert np.std(logs) == pytest.approx(0.1, rel=0.3)
    step_sd = 0.1 * math.sqrt(1 - math.exp(-2 * 0.05 / 5.0))  # OU increment over 50 ms
    assert np.std(np.diff(logs)) == pytest.approx(step_sd, rel=0.1)  # slow: no flicker
    assert np.max(np.abs(np.diff(logs))) < 6 * step_sd
    lag = int(5.0 / 0.05)
    rho = np.corrcoef(logs[:-lag], logs[lag:])[0, 1]
    assert rho == pytest.approx(math.exp(-1), abs=0.15)  # time constant 5 s
    s2 = Sensor(cfg, 8, 8, seed=1)
    assert [s2.advance(0.05 * i) for i in range(5)] == list(gains[:5])
    bright = Sensor(CameraModelConfig(brightness_drift_std=1.0), 8, 8, seed=2)
    while bright.advance((bright._t_s or 0.0) + 1.0) < 1.2:
        pass
    assert bright.apply(np.full((8, 8), 235, np.uint8), bright._t_s or 0.0).max() == 255


# ---------------------------------------------------------------- timing
def test_drop_rate_within_binomial_bounds_and_latency_in_its_band() -> None:
    cfg = CameraModelConfig(latency_ms=60.0, latency_jitter_ms=15.0, drop_probability=0.05)
    n = 4000
    timing = CameraTiming(cfg, seed=11)
    caps = [timing.capture(0.05 * i) for i in range(n)]
    drops = sum(c.dropped for c in caps)
    sd = math.sqrt(n * 0.05 * 0.95)
    assert abs(drops - n * 0.05) < 4 * sd
    lat = np.array([c.latency_s for c in caps if not c.dropped])
    assert lat.min() >= 0.045 - 1e-9 and lat.max() <= 0.075 + 1e-9
    assert lat.mean() == pytest.approx(0.060, abs=0.001)
    assert np.std(lat) == pytest.approx(0.015 / math.sqrt(3), rel=0.1)  # uniform +-15 ms
    delivered = [c.deliver_s for c in caps if not c.dropped]
    assert delivered == sorted(delivered)
    assert [c.stamp_us for c in caps[:3]] == [0, 50_000, 100_000]
    again = CameraTiming(cfg, seed=11)
    assert [again.capture(0.05 * i) for i in range(50)] == caps[:50]


def test_frames_stay_in_order_with_jitter_larger_than_the_period() -> None:
    cfg = CameraModelConfig(latency_ms=100.0, latency_jitter_ms=80.0)
    timing = CameraTiming(cfg, seed=2)
    d = [timing.capture(0.01 * i).deliver_s for i in range(500)]
    assert d == sorted(d)


def test_camera_clock_stamps() -> None:
    cfg = CameraModelConfig(timestamp_clock="camera", clock_offset_ms=1500.0,
                            clock_drift_ppm=100.0)
    t = CameraTiming(cfg, seed=0, clock_offset_s=10.0)
    # autopilot clock 10 + 20 s; camera clock = that * (1 + 1e-4) + 1.5 s
    assert t.stamp_us(20.0) == round((30.0 * (1 + 1e-4) + 1.5) * 1e6)
    synced = CameraTiming(CameraModelConfig(), seed=0, clock_offset_s=10.0)
    assert synced.stamp_us(20.0) == 30_000_000


def test_delay_line_is_fifo() -> None:
    line: DelayLine[int] = DelayLine()
    assert line.push(0.3, 1) == 0.3
    assert line.push(0.1, 2) == 0.3  # never overtakes
    line.push(0.5, 3)
    assert list(line.pop_due(0.2)) == []
    assert list(line.pop_due(0.3)) == [1, 2]
    assert line.next_due_s == 0.5 and len(line) == 1


# ---------------------------------------------------------------- config
def test_levels_fill_knobs_and_explicit_keys_win(tmp_path: Path) -> None:
    base = load_config()
    assert base.sim.camera_model.ideal and base.sim.telemetry.delay_ms == 0.0
    p = tmp_path / "v.toml"
    p.write_text(f'base = "{ROOT / "config" / "paper.toml"}"\n'
                 '[sim.camera_model]\nlevel = "realistic"\nlatency_ms = 70.0\n'
                 '[sim.telemetry]\nlevel = "harsh"\n')
    c = load_config(p)
    assert c.sim.camera_model.latency_ms == 70.0
    assert c.sim.camera_model.latency_jitter_ms == 15.0 and c.sim.camera_model.exposure_ms > 0
    assert not c.sim.camera_model.ideal
    assert c.sim.telemetry.rates == "px4" and c.sim.telemetry.delay_ms == 20.0
    p.write_text(f'base = "{ROOT / "config" / "paper.toml"}"\n'
                 '[sim.camera_model]\nlevel = "awful"\n')
    with pytest.raises(ConfigError, match=r"sim\.camera_model\.level"):
        load_config(p)
    p.write_text(f'base = "{ROOT / "config" / "paper.toml"}"\n'
                 '[sim.camera_model]\nlatency_ms = 10.0\nlatency_jitter_ms = 20.0\n')
    with pytest.raises(ConfigError, match=r"latency_jitter_ms"):
        load_config(p)


def test_realistic_sensors_file() -> None:
    c = load_config(ROOT / "config" / "realistic-sensors.toml")
    assert c.sim.camera_model.level == "realistic" and c.sim.camera_model.latency_ms == 60.0
    assert c.sim.telemetry.level == "realistic" and c.sim.telemetry.rates == "px4"
    assert c.camera.calibration_file.endswith("camera-distorted.yaml")
    _, d = read_calibration(c.camera.calibration_file, c.camera.width_px, c.camera.height_px,
                            relative_to=c.source)
    assert d.size == 5


def test_distorted_frame_equals_a_full_resolution_remap_of_the_ideal_canvas(
        dcam: Camera, lens: tuple[np.ndarray, np.ndarray]) -> None:
    """The fast path (ground distorted at half resolution, only the box's region at full
    resolution, motion blur included) against the plain definition: an ideal pinhole camera
    with the canvas's matrix renders the scene, every output pixel samples it at its
    undistorted position."""
    k, d = lens
    rk, (rw, rh) = dcam._rk, (dcam._rw, dcam._rh)
    ref_cam = Camera(LAM, PIX, rw, rh, camera_matrix=rk, dist_coeffs=np.zeros(5))
    cols, rows = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pts = np.stack([cols.ravel(), rows.ravel()], axis=-1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, k, d, P=k, criteria=(
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(H, W, 2)
    mx = (und[..., 0] + rk[0, 2] - k[0, 2]).astype(np.float32)
    my = (und[..., 1] + rk[1, 2] - k[1, 2]).astype(np.float32)
    for uav, eul, agv, vel in (
        (np.array([1.1, 1.2, -2.3]), (0.05, -0.04, 0.3), agv_state(1.3, 1.5, 0.3), None),
        (np.array([0.2, -0.3, -3.0]), (0.1, 0.2, -1.0), agv_state(0.0, 0.0, 1.0),
         np.array([3.0, 0.0, 0.0])),
    ):
        q = quat_wxyz(*eul)
        kw = {} if vel is None else {"uav_vel_ned_m_s": vel,
                                     "uav_rates_frd_rad_s": np.zeros(3), "exposure_s": 0.01}
        fast = dcam.render(uav, q, agv, **kw).image.astype(float)
        canvas = ref_cam.render(uav, q, agv, **kw).image
        ref = cv2.remap(canvas, mx, my, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE).astype(float)
        diff = np.abs(fast - ref)
        assert diff.mean() < 1.0 and np.percentile(diff, 99.9) < 12, (diff.mean(),
                                                                      np.percentile(diff, 99.9))
        bright = ref > 200  # the AGV top: exactly the full-resolution path
        assert bright.sum() > 500
        assert diff[cv2.erode(bright.astype(np.uint8), np.ones((3, 3))) > 0].max() <= 2
