"""The compiled box compositing (sim_bridge/camera/boxdraw.py, box_rect.c) gives the numpy
passes' pixels (target.composite) on random boxes and in rendered frames; what it declines,
a missing compiler and a wrong kernel all leave numpy in charge."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from sim_bridge.camera import Camera, boxdraw
from sim_bridge.camera.scene import edge_lines
from sim_bridge.camera.scene import roi as roi_of
from sim_bridge.camera.target import composite
from sim_bridge.physics.agv import AgvState
from sim_bridge.physics.vehicle import quat_from_euler

needs_kernel = pytest.mark.skipif(boxdraw.kernel() is None,
                                  reason="no C compiler or not x86-64: numpy composites")


def _both(fn: object, canvas: np.ndarray, hull: np.ndarray,
          top: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, bool] | None:
    roi = roi_of(hull, canvas.shape[1], canvas.shape[0])
    if roi is None:
        return None
    ref = canvas.copy()
    composite(ref, roi, hull, top, 235.0)
    out = canvas.copy()
    done = boxdraw.run(fn, out, roi, edge_lines(hull),  # type: ignore[arg-type]
                       None if top is None else edge_lines(top), 30.0, 205.0)
    return out, ref, done


@needs_kernel
def test_kernel_gives_numpy_pixels_on_random_boxes() -> None:
    fn = boxdraw.kernel()
    rng = np.random.default_rng(2025)
    n = 0
    for _ in range(1500):
        res = _both(fn, *boxdraw._random_case(rng))
        if res is None:
            continue
        out, ref, done = res
        assert done
        np.testing.assert_array_equal(out, ref)
        n += 1
    assert n > 1400


@needs_kernel
def test_rendered_frames_are_the_same_with_the_kernel(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seen from above (top and sides), from the side (top hidden below the camera's
    horizon of it), close (a large ROI) and far (a small one), clipped at the frame's edge."""
    cam = Camera(2.8e-3, 5.04e-6, 1000, 1000)
    agv = AgvState(t_s=0.0, pos_ned_m=np.array([1.0, 2.0, -0.3]), vel_ned_m_s=np.zeros(3),
                   acc_ned_m_s2=np.zeros(3), yaw_rad=0.4, yaw_rate_rad_s=0.0)
    poses = [(np.array([1.2, 2.1, -2.5]), quat_from_euler(0.05, -0.03, 0.4)),
             (np.array([0.4, 2.9, -1.2]), quat_from_euler(-0.2, 0.25, 2.0)),
             (np.array([1.0, 2.0, -6.0]), quat_from_euler(0.0, 0.0, -1.0)),
             (np.array([2.2, 2.0, -1.0]), quat_from_euler(0.0, 0.5, 3.0)),
             (np.array([1.5, 2.9, -1.4]), quat_from_euler(0.5, -0.4, 0.9))]
    with_kernel = [cam.render(p, q, agv).image for p, q in poses]
    monkeypatch.setattr(boxdraw, "kernel", lambda directory=None: None)
    without = [cam.render(p, q, agv).image for p, q in poses]
    for a, b in zip(with_kernel, without, strict=True):
        np.testing.assert_array_equal(a, b)


@needs_kernel
def test_what_it_declines_is_left_untouched() -> None:
    fn = boxdraw.kernel()
    canvas = np.full((30, 40), 90, np.uint8)
    roi = (2, 3, 20, 25)
    square = np.array([[5.0, 5.0], [15.0, 5.0], [15.0, 15.0], [5.0, 15.0]])
    lines = edge_lines(square)
    cases = [
        (canvas.copy(), [], None),  # no silhouette line
        (canvas.copy(), lines, []),  # a degenerate top
        (canvas.copy(), [(float("nan"), 0.0, 1.0), *lines], None),
    ]
    read_only = canvas.copy()
    read_only.setflags(write=False)
    cases.append((read_only, lines, None))
    for image, hull_lines, top_lines in cases:
        before = image.copy()
        assert not boxdraw.run(fn, image, roi, hull_lines, top_lines, 30.0, 205.0)
        np.testing.assert_array_equal(image, before)


def test_no_compiler_means_numpy(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert boxdraw._build(tmp_path) is None


@needs_kernel
@pytest.mark.parametrize(("old", "new"), [
    ("m[i] = m[i] < d ? m[i] : d;", "m[i] = m[i] > d ? m[i] : d;"),  # max, not min
    ("__m128 t = _mm_min_ps(_mm_max_ps(_mm_loadu_ps(tm + i), z), one);",
     "__m128 t = _mm_max_ps(_mm_loadu_ps(tm + i), z);"),  # the top's coverage not clipped
    ("_mm_cvttps_epi32(_mm_add_ps(out, half))", "_mm_cvtps_epi32(out)"),  # rounding
])
def test_a_kernel_that_differs_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                          old: str, new: str) -> None:
    text = boxdraw.SOURCE_PATH.read_text()
    assert old in text
    bad = tmp_path / "box_rect.c"
    bad.write_text(text.replace(old, new))
    monkeypatch.setattr(boxdraw, "SOURCE_PATH", bad)
    lib = boxdraw._build(tmp_path)
    assert lib is not None
    assert not boxdraw._matches(boxdraw._load(lib))
