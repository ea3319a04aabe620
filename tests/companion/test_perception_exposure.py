"""The rectangle detector under exposure changes (auto-exposure, light): a camera gain scales
every grey level of the frame (and saturates at 255).

Two independent sources of pixels: this suite's own exact-coverage renderer
(tests/companion/test_perception.py, gain applied here) and the emulator's renderer
(``sim_bridge.camera.Camera``) through the emulator's sensor model
(``sim_bridge.camera.sensor.Sensor``: gain, shot and read noise at the "harsh" camera level's
values, rounding), with the gain held fixed instead of drifting.

Measured worst corner errors (px) behind the bounds below (2026-11-26):
- own renderer, 8 poses, noise 5 + blur 1.0 px: gain 0.5: 0.28, 0.7: 0.19, 1.0: 0.20,
  1.2: 0.30, 1.4: 0.58 (the top saturates above gain 255/225 = 1.13: a clipped edge profile
  moves the mid-level crossing outwards; the fixed threshold gave the same at 1.2-1.4);
- emulator, 6 poses, harsh sensor noise: blur 0: gains 0.4-1.0: <= 0.13, 1.3: 0.35,
  1.5: 0.58; blur 1.0: 0.4-1.0: <= 0.24, 1.3: 0.88, 1.5: 1.56, 1.6: 1.79;
- the fixed threshold 175 (the detector's level before): nothing found at gains 0.5-0.75 and
  1.6, and bright ground blobs reported as rejections on empty frames from gain 1.4.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from companion import ConfigError
from companion.config import load_config
from companion.perception import Perception, RectangleDetector
from companion.perception.rectangle import RectangleSettings
from sim_bridge.camera import Camera
from sim_bridge.camera.sensor import Sensor
from sim_bridge.config import CAMERA_LEVELS, CameraModelConfig
from sim_bridge.physics.agv import AgvState
from tests.companion import test_perception as tp

CFG = load_config()
FIXED_175 = RectangleSettings(threshold=175)


def with_gain(img: np.ndarray, gain: float) -> np.ndarray:
    return np.clip(np.rint(img.astype(np.float64) * gain), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# This suite's renderer


@pytest.mark.parametrize(("gain", "bound_px"),
                         [(0.5, 0.5), (0.7, 0.5), (0.75, 0.5), (1.0, 0.5), (1.2, 0.5),
                          (1.4, 0.75)])
def test_own_frames_found_at_exposure_gains(gain: float, bound_px: float) -> None:
    det = RectangleDetector(tp.L_M, tp.W_M)
    errors = []
    for i, pose in enumerate(tp.FIXED_POSES):
        top, bottom, phi, theta, seed = tp._scene(pose)
        img, true = tp.render_box(seed, top, bottom, phi, theta)
        report = det.analyse(tp.degrade(with_gain(img, gain), 5.0, 1.0, seed=i))
        assert report.detection is not None, (i, report.reason)
        errors.append(tp.set_error_px(report.detection.corners_px, true))
    assert max(errors) < bound_px, errors


@pytest.mark.parametrize("gain", [0.5, 0.75, 1.0, 1.3, 1.6])
def test_own_empty_ground_is_lost_at_every_gain(gain: float) -> None:
    det = RectangleDetector(tp.L_M, tp.W_M)
    perception = Perception(CFG.camera, CFG.target)
    for seed in range(4):
        img = tp.degrade(with_gain(tp.ground(seed), gain), 5.0, 1.0, seed)
        report = det.analyse(img)
        assert report.detection is None and "no bright region" in report.reason, report.reason
        assert perception.process(img).status == "lost"


@pytest.mark.parametrize(("gain", "found_before"),
                         [(1.0, True), (0.8, True), (0.76, False), (0.74, False), (0.7, False),
                          (0.5, False)])
def test_the_stress_reports_reproduction(gain: float, found_before: bool) -> None:
    """A clean rectangle (grey 235 x gain) on grey 60: found at every gain; the fixed level 175
    (the detector's before) lost it from gain 0.76 down."""
    img = np.full((1000, 1000), 60, np.uint8)
    img[400:520, 400:580] = int(235 * gain)
    true = np.array([[399.5, 399.5], [579.5, 399.5], [579.5, 519.5], [399.5, 519.5]])
    report = RectangleDetector(0.6, 0.4).analyse(img)
    assert report.detection is not None, report.reason
    assert tp.set_error_px(report.detection.corners_px, true) < 0.05
    fixed = RectangleDetector(0.6, 0.4, settings=FIXED_175).analyse(img)
    assert (fixed.detection is not None) == found_before


# ---------------------------------------------------------------------------------------------
# The emulator's renderer and sensor


class FixedGainSensor(Sensor):
    """The emulator's sensor with its brightness gain held at ``gain`` (noise unchanged)."""

    def __init__(self, gain: float, cfg: CameraModelConfig, w: int, h: int, seed: int) -> None:
        super().__init__(cfg, w, h, seed)
        self.fixed_gain = gain

    def advance(self, t_s: float) -> float:
        self.gain = self.fixed_gain
        return self.gain


HARSH = CAMERA_LEVELS["harsh"]
SENSOR_CFG = CameraModelConfig(read_noise_std_dn=HARSH["read_noise_std_dn"],
                               shot_noise_dn_per_e=HARSH["shot_noise_dn_per_e"])
# camera height above the ground (m), AGV north, east (m), AGV yaw (rad)
EMU_POSES = [(2.3, 0.0, 0.0, 0.3), (2.0, 0.4, -0.3, 1.2), (3.0, -0.6, 0.5, -2.0),
             (1.9, 0.2, 0.5, 2.7), (4.0, 1.0, 1.0, 0.8), (2.6, -0.5, -0.5, -0.7)]


def _emulator_frames(blur_px: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(frame with the target, its true corners (col, row), the same view without it)."""
    c = CFG.camera
    cam = Camera(c.focal_length_m, c.pixel_size_m, c.width_px, c.height_px,
                 target_length_m=CFG.target.length_m, target_width_m=CFG.target.width_m,
                 target_height_m=CFG.target.height_m, blur_px=blur_px, seed=3)
    q = np.array([1.0, 0.0, 0.0, 0.0])
    out = []
    for h, north, east, yaw in EMU_POSES:
        uav = np.array([0.0, 0.0, -h])
        zero = [0.0, 0.0, 0.0]
        fr = cam.render(uav, q, AgvState(0.0, [north, east, 0.0], zero, zero, yaw, 0.0))
        far = cam.render(uav, q, AgvState(0.0, [north + 40.0, east, 0.0], zero, zero, yaw, 0.0))
        out.append((fr.image, fr.corners_px, far.image))
    return out


@pytest.fixture(scope="module")
def emulator_frames() -> dict[float, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    return {blur: _emulator_frames(blur) for blur in (0.0, 1.0)}


def _set_error(found: np.ndarray, true: np.ndarray) -> float:
    return min(float(np.max(np.linalg.norm(found[list(p)] - true, axis=1)))
               for p in itertools.permutations(range(4)))


@pytest.mark.parametrize(("gain", "bound_px"),
                         # blur 0 / 1 px: bounds on the worst of 6 poses (see the docstring)
                         [(0.5, (0.3, 0.35)), (0.7, (0.3, 0.35)), (0.75, (0.3, 0.35)),
                          (1.0, (0.3, 0.35)), (1.3, (0.5, 1.2)), (1.5, (0.8, 2.0))])
def test_emulator_frames_found_at_exposure_gains(emulator_frames, gain: float,
                                                 bound_px: tuple[float, float]) -> None:
    det = RectangleDetector(CFG.target.length_m, CFG.target.width_m)
    for (blur, frames), bound in zip(sorted(emulator_frames.items()), bound_px, strict=True):
        sensor = FixedGainSensor(gain, SENSOR_CFG, CFG.camera.width_px, CFG.camera.height_px, 7)
        errors = []
        for k, (img, true, _) in enumerate(frames):
            report = det.analyse(sensor.apply(img, 0.1 * k))
            assert report.detection is not None, (blur, k, report.reason)
            errors.append(_set_error(report.detection.corners_px, true))
        assert max(errors) < bound, (blur, errors)


def test_emulator_gain_1_6_mostly_found(emulator_frames) -> None:
    """At gain 1.6 the ground's brightest texels (up to ~237) nearly reach the saturated top
    (255): found in 11 of the 12 frames (one edge next to bright ground lacks contrast)."""
    det = RectangleDetector(CFG.target.length_m, CFG.target.width_m)
    found = 0
    for frames in emulator_frames.values():
        sensor = FixedGainSensor(1.6, SENSOR_CFG, CFG.camera.width_px, CFG.camera.height_px, 7)
        for k, (img, true, _) in enumerate(frames):
            report = det.analyse(sensor.apply(img, 0.1 * k))
            if report.detection is not None:
                found += 1
                assert _set_error(report.detection.corners_px, true) < 2.0
    assert found >= 11


@pytest.mark.parametrize("gain", [0.5, 0.75, 1.0, 1.3, 1.6, 1.8])
def test_emulator_empty_ground_is_lost(emulator_frames, gain: float) -> None:
    det = RectangleDetector(CFG.target.length_m, CFG.target.width_m)
    perception = Perception(CFG.camera, CFG.target)
    sensor = FixedGainSensor(gain, SENSOR_CFG, CFG.camera.width_px, CFG.camera.height_px, 7)
    for k, (_, _, empty) in enumerate(emulator_frames[1.0]):
        img = sensor.apply(empty, 0.1 * k)
        report = det.analyse(img)
        assert report.detection is None and "no bright region" in report.reason, report.reason
        assert perception.process(img).status == "lost"


@pytest.mark.parametrize("gain", [0.5, 0.7, 1.6])
def test_the_fixed_level_loses_the_emulators_target(emulator_frames, gain: float) -> None:
    """The failing cases of the stress campaign, on the emulator's pixels: the fixed grey
    level 175 loses at least 5 of the 6 targets (none found at 0.5 and 0.7; at 1.6 the ground
    merges with the top in 5) where the adaptive level finds all six (above)."""
    det = RectangleDetector(CFG.target.length_m, CFG.target.width_m, settings=FIXED_175)
    sensor = FixedGainSensor(gain, SENSOR_CFG, CFG.camera.width_px, CFG.camera.height_px, 7)
    found = sum(det.analyse(sensor.apply(img, 0.1 * k)).detection is not None
                for k, (img, _, _) in enumerate(emulator_frames[0.0]))
    assert found <= (1 if gain > 1 else 0)


# ---------------------------------------------------------------------------------------------
# Configuration


def test_perception_config_reaches_the_detector() -> None:
    cfg = load_config(overrides=["perception.rectangle_threshold=175",
                                 "perception.rectangle_level_fraction=0.6"])
    det = Perception(cfg.camera, cfg.target, perception=cfg.perception).detector
    assert isinstance(det, RectangleDetector)
    assert (det.settings.threshold, det.settings.level_fraction) == (175, 0.6)
    default = Perception(CFG.camera, CFG.target, perception=CFG.perception).detector
    assert isinstance(default, RectangleDetector) and default.settings.threshold is None


@pytest.mark.parametrize(("override", "message"), [
    ("perception.rectangle_threshold=255", "perception.rectangle_threshold: 255"),
    ("perception.rectangle_threshold=-1", "perception.rectangle_threshold: -1"),
    ("perception.rectangle_level_fraction=0.95", "perception.rectangle_level_fraction: 0.95"),
    ("perception.rectangle_level_fraction=nan", "perception.rectangle_level_fraction: must be"),
])
def test_bad_perception_config_is_a_clear_error(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace(".", r"\.", 1)):
        load_config(overrides=[override])


def test_bad_detector_settings_are_refused() -> None:
    for kw in ({"level_fraction": 1.0}, {"bright_count_px": 0.0}, {"valley_band": 0.6},
               {"min_level_contrast": 0.0}, {"threshold": 255}):
        with pytest.raises(Exception, match=next(iter(kw))):
            RectangleSettings(**kw)  # type: ignore[arg-type]
    assert math.isclose(RectangleSettings().level_fraction, 0.7)
