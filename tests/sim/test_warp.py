"""The ground's compiled perspective warp (sim_bridge/camera/warp.py) gives
``cv2.warpPerspective``'s pixels (INTER_LINEAR | WARP_INVERSE_MAP) on random and adversarial
probes and on rendered ground; a view it cannot take, a missing compiler and a wrong kernel
all leave OpenCV in charge."""

from __future__ import annotations

import shutil
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pytest

from sim_bridge.camera import Camera, upsample, warp
from sim_bridge.physics.agv import AgvState
from sim_bridge.physics.vehicle import quat_from_euler

needs_kernel = pytest.mark.skipif(warp.kernel() is None,
                                  reason="no C compiler, not x86-64 or no AVX2/FMA: OpenCV warps")


def _ref(src: np.ndarray, m: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return cv2.warpPerspective(src, m, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_WRAP)


@needs_kernel
def test_kernel_gives_cv2_pixels_on_probes() -> None:
    """Six seeds of the start-up check's probes (halves, every tail length, random
    homographies over random, ground-like and extreme sources): every pixel equal."""
    fn = warp.kernel()
    assert fn is not None
    n = 0
    for seed in range(6):
        for src, m, size in warp.probes(seed):
            out = warp._run(fn, src, m, size)
            assert out is not None, (seed, size)
            np.testing.assert_array_equal(out, _ref(src, m, size), f"seed {seed} {size}")
            n += out.size
    assert n > 1_500_000


@needs_kernel
def test_strided_source_and_ground_texture() -> None:
    """A source view with a row pitch wider than its rows, and the ground texture itself with
    a view from 2.5 m, yawed: the entry point gives OpenCV's pixels."""
    rng = np.random.default_rng(5)
    big = rng.integers(0, 256, (90, 130), dtype=np.uint8)
    view = big[7:80, 3:120]
    m = warp._homography(rng, view.shape, (45, 33))
    np.testing.assert_array_equal(warp.warp_perspective(view, m, (45, 33)),
                                  _ref(np.ascontiguousarray(view), m, (45, 33)))
    tex = np.ascontiguousarray(np.pad(rng.integers(40, 151, (256, 256), dtype=np.uint8), 128,
                                      mode="wrap"))
    c, s = np.cos(2.1) * 0.31, np.sin(2.1) * 0.31
    m = np.array([[c, -s, 250.0], [s, c, 260.0], [2e-5, -3e-5, 1.0]])
    np.testing.assert_array_equal(warp.warp_perspective(tex, m, (500, 500)),
                                  _ref(tex, m, (500, 500)))


@needs_kernel
def test_views_it_cannot_take_go_to_opencv() -> None:
    """Outside the texture (the border mode matters there), a pixel beyond the last column's
    neighbour, behind the camera (w < 0), w = 0 and NaN: the kernel declines and the entry
    point returns OpenCV's pixels."""
    fn = warp.kernel()
    assert fn is not None
    src = np.random.default_rng(3).integers(0, 256, (40, 60), dtype=np.uint8)
    cases = [
        np.array([[1.0, 0, -3.0], [0, 1.0, 2.0], [0, 0, 1.0]]),  # left of column 0
        np.array([[1.0, 0, 30.0], [0, 1.0, 2.0], [0, 0, 1.0]]),  # past the right edge
        np.array([[1.0, 0, 2.0], [0, 1.0, 25.0], [0, 0, 1.0]]),  # past the bottom row
        np.array([[1.0, 0, 2.0], [0, 1.0, 2.0], [0, 0, -1.0]]),  # behind: negative w
        np.array([[1.0, 0, 2.0], [0, 1.0, 2.0], [0, 0, 0.0]]),  # w = 0 at the origin
        np.array([[np.nan, 0, 2.0], [0, 1.0, 2.0], [0, 0, 1.0]]),
    ]
    for m in cases:
        assert warp._run(fn, src, m, (33, 17)) is None, m
        np.testing.assert_array_equal(warp.warp_perspective(src, m, (33, 17)),
                                      _ref(src, m, (33, 17)))


@pytest.mark.parametrize("module", [warp, upsample], ids=["warp", "upsample"])
def test_rendered_ground_is_the_same_with_the_kernel(monkeypatch: pytest.MonkeyPatch,
                                                     module: ModuleType) -> None:
    """The camera's frames with each compiled kernel are those without it (OpenCV's)."""
    if module.kernel() is None:
        pytest.skip("no compiler or no AVX2/FMA here: the OpenCV path runs")
    cam = Camera(2.8e-3, 5.04e-6, 1000, 1000)
    agv = AgvState(t_s=0.0, pos_ned_m=np.array([1.0, 2.0, -0.3]), vel_ned_m_s=np.zeros(3),
                   acc_ned_m_s2=np.zeros(3), yaw_rad=0.4, yaw_rate_rad_s=0.0)
    poses = [(np.array([1.2, 2.1, -2.5]), quat_from_euler(0.05, -0.03, 0.4)),
             (np.array([0.4, 2.9, -1.6]), quat_from_euler(-0.2, 0.25, 2.0)),
             (np.array([-3.0, 7.5, -6.0]), quat_from_euler(0.3, 0.1, -2.8))]
    with_kernel = [cam.render(p, q, agv).image for p, q in poses]
    monkeypatch.setattr(module, "kernel", lambda directory=None: None)
    without = [cam.render(p, q, agv).image for p, q in poses]
    for a, b in zip(with_kernel, without, strict=True):
        np.testing.assert_array_equal(a, b)


def test_no_compiler_means_opencv(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert warp._build(tmp_path) is None
    monkeypatch.setattr(warp, "kernel", lambda directory=None: None)
    src = np.random.default_rng(1).integers(0, 256, (20, 30), dtype=np.uint8)
    m = np.array([[0.9, 0.1, 1.5], [-0.1, 0.8, 2.25], [1e-3, 0, 1.0]])
    np.testing.assert_array_equal(warp.warp_perspective(src, m, (17, 11)),
                                  _ref(src, m, (17, 11)))


@needs_kernel
@pytest.mark.parametrize(("old", "new"), [
    # the row constants fused (OpenCV multiplies, then adds)
    ("kx = _mm256_set1_ps(fy * m[1] + m[2])", "kx = _mm256_set1_ps(fma1(fy, m[1], m[2]))"),
    # the scalar tail's w not contracted
    ("float w = fma1(fx, m[6], fy * m[7]) + m[8];", "float w = fx * m[6] + fy * m[7] + m[8];"),
    # the scalar tail's interpolation not contracted
    ("float v0 = fma1(a, p01 - p00, p00);\n    float v1 = fma1(a, p11 - p10, p10);\n"
     "    int r = _mm_cvtss_si32(_mm_set_ss(fma1(b, v1 - v0, v0)));",
     "float v0 = p00 + a * (p01 - p00);\n    float v1 = p10 + a * (p11 - p10);\n"
     "    int r = _mm_cvtss_si32(_mm_set_ss(v0 + b * (v1 - v0)));"),
    # truncation instead of rounding to nearest
    ("__m256i r = _mm256_cvtps_epi32(", "__m256i r = _mm256_cvttps_epi32("),
])
def test_a_kernel_that_differs_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                          old: str, new: str) -> None:
    """The start-up check catches a kernel one detail away from OpenCV's formula."""
    text = warp.SOURCE_PATH.read_text()
    assert old in text
    bad = tmp_path / "warp_persp.c"
    bad.write_text(text.replace(old, new))
    monkeypatch.setattr(warp, "SOURCE_PATH", bad)
    lib = warp._build(tmp_path)
    assert lib is not None
    assert not warp._matches(warp._load(lib))
